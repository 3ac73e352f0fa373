"""The same arithmetic on every x86-64 host: which kernels OpenBLAS and numpy run.

OpenBLAS (numpy's and scipy's BLAS and LAPACK) chooses its kernels by CPU when it loads, and numpy
chooses its own loops (sin, cos, exp, log, ...) the same way; kernels written for different
instruction sets sum and round in another order, so their results differ in the last bits.
Several estimators' designs go through them (kkl's and kkl-biased's observer gains through a
solve and a matrix exponential, grip-mixing's through eigenvalues and an SVD, differential-rls's
filter design through scipy.signal), and their constants feed every estimate: a recording made on
an Intel host with AVX-512 (OpenBLAS's SkylakeX kernels) did not replay bit for bit on an AMD
host without it (its Haswell kernels), in the last digits of kkl's, kkl-biased's, grip-mixing's,
differential-rls's and adaptive-multisine's estimates (tests/test_host_independence.py runs the
designs under each kernel choice).

Both libraries read an environment variable when they load, once. Imported before numpy (every
package of sinewatch's service imports this module first), this sets them to what every x86-64
CPU with AVX2 and FMA runs alike: OpenBLAS's Haswell kernels (``OPENBLAS_CORETYPE``) and numpy
without its AVX-512 loops (``NPY_DISABLE_CPU_FEATURES``). The subprocesses sinewatch starts
inherit them. Left as they are: a value the user set (theirs wins), a CPU without AVX2 and FMA,
another architecture, and a process that imported numpy before sinewatch (too late to choose:
``PINNED`` is then False and replay's bit-for-bit promise holds only against recordings made on
a host that chose the same kernels).
"""

from __future__ import annotations

import os
import platform
import sys

KERNELS = {
    "OPENBLAS_CORETYPE": "Haswell",  # AVX2 + FMA kernels, the default on such AMD hosts
    "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",  # numpy's AVX-512 loops off
}


def _cpu_flags() -> set[str]:
    """The CPU's feature flags as Linux lists them (empty where /proc/cpuinfo is not)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            lines = f.readlines()
    except OSError:  # not Linux: nothing known, so nothing is pinned
        return set()
    flags = next((line for line in lines if line.startswith("flags")), "")
    return set(flags.partition(":")[2].split())


def pin_kernels() -> bool:
    """Set ``KERNELS`` in the environment (keeping any value already there) if numpy has not
    loaded yet and the CPU is an x86-64 with AVX2 and FMA; whether they now apply."""
    if "numpy" in sys.modules or platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    if not {"avx2", "fma"} <= _cpu_flags():
        return False
    for name, value in KERNELS.items():
        os.environ.setdefault(name, value)
    return True


PINNED = pin_kernels()


def openblas_core() -> str | None:
    """The name of the kernels the loaded OpenBLAS runs (``Haswell`` when pinned), or None when
    no OpenBLAS is loaded in this process or it names none (call it after numpy is imported)."""
    import ctypes  # here: only the callers that ask load it

    try:
        with open("/proc/self/maps", encoding="ascii", errors="replace") as f:
            paths = sorted({line.split()[-1] for line in f if "openblas" in line and line.rstrip().endswith(".so")})
    except OSError:  # not Linux: no maps to read the library's path from
        return None
    for path in paths:
        lib = ctypes.CDLL(path)
        for symbol in ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename", "openblas_get_corename"):
            corename = getattr(lib, symbol, None)
            if corename is not None:
                corename.restype = ctypes.c_char_p
                return bytes(corename()).decode("ascii")
    return None
