"""What the lane-major banks share: channels as the lanes of one work array, 8 a row.

A lane-major bank (:mod:`sinewatch.estimators.bank`) keeps each quantity of its channels in one
row of ``LANES`` doubles, lane ``l`` of row ``r`` at ``W[r * LANES + l]``, and runs each sample's
step as a loop of literal trip count ``LANES`` over that row, which LLVM vectorises (one 512-bit
vector on AVX-512, two 256-bit ones on AVX2). :func:`copy_lanes` moves a whole row between
arrays (a delay line's ring, the samples, the work array) as one vector; :func:`host_vector_bits`
says which of those widths the kernels are compiled for on this machine; :func:`aligned_lanes`
allocates a lane-major array whose rows each lie in one cache line.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, cast

import numba
import numpy as np
from llvmlite import binding as llvm
from llvmlite import ir as llvm_ir
from numba.extending import intrinsic

from sinewatch.estimators.base import kernel

LANES = 8  # channels advanced together: 8 doubles, one AVX-512 register


def host_vector_bits() -> tuple[str, int]:
    """The CPU the kernels are compiled for (LLVM's name of it, or numba's NUMBA_CPU_NAME) and the
    widest vector of doubles they can use on it, in bits: 512 with AVX-512F, 256 with AVX, else
    128. A bank's step over its LANES lanes is one vector at 512 bits and two at 256, so the same
    bank's speed against one channel and against the streaming FFT differs between such hosts
    (a virtual machine may also hide AVX-512 from a CPU that has it)."""
    config: Any = numba.config  # (its settings are set at import, absent from its type stubs)
    if config.CPU_FEATURES:  # numba's own override (NUMBA_CPU_FEATURES) is what it compiles for
        features = {f[1:]: f[0] == "+" for f in str(config.CPU_FEATURES).split(",") if f}
    else:
        features = dict(llvm.get_host_cpu_features())
    name = str(config.CPU_NAME or llvm.get_host_cpu_name())
    return name, 512 if features.get("avx512f") else 256 if features.get("avx") else 128


@intrinsic
def _copy_lanes_intrinsic(typingctx: Any, dst: Any, dst_at: Any, src: Any, src_at: Any) -> Any:
    sig = numba.types.void(dst, numba.types.int64, src, numba.types.int64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        d = context.make_array(signature.args[0])(context, builder, args[0])
        s = context.make_array(signature.args[2])(context, builder, args[2])
        vec = llvm_ir.VectorType(llvm_ir.DoubleType(), LANES).as_pointer()
        v = builder.load(builder.bitcast(builder.gep(s.data, [args[3]]), vec), align=8)
        builder.store(v, builder.bitcast(builder.gep(d.data, [args[1]]), vec), align=8)
        return context.get_dummy_value()

    return sig, codegen


@kernel(inline="always")
def copy_lanes(dst: np.ndarray, dst_at: int, src: np.ndarray, src_at: int) -> None:
    """``dst.flat[dst_at : dst_at + LANES] = src.flat[src_at : src_at + LANES]`` (flat indices of
    C-contiguous arrays of float64) as one vector load and one vector store, no bounds check: the
    callers' offsets are rows of their own arrays. Why: a row the lanes' loop reads as one vector
    must be written as one, not by LANES scalar stores, or the load waits for the stores to reach
    the cache (store forwarding fails); and a loop of LANES copies between two arrays stays scalar
    (LLVM adds no overlap check to a loop that short). The values are moved, not computed: no bit
    changes."""
    _copy_lanes_intrinsic(dst, dst_at, src, src_at)  # type: ignore[call-arg]  # numba passes the typing context


@intrinsic
def _select_intrinsic(typingctx: Any, cond: Any, a: Any, b: Any) -> Any:
    sig = numba.types.float64(numba.types.boolean, numba.types.float64, numba.types.float64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return builder.select(args[0], args[1], args[2])

    return sig, codegen


#: ``a if cond else b`` for floats as one LLVM ``select``, no branch; the value chosen is the
#: same, bit for bit (both sides are computed: callers pass values, not calls that could fail).
#: Why: a Python conditional is a branch in numba's IR, and a lane loop of several branches on
#: the same lane's flag is threaded by LLVM (each path's code copied), whose stores the
#: vectoriser then predicates: masked stores (``vmaskmovpd``, microcoded on AMD's cores) and
#: masked loads where a select is one ``vblendvpd``. Also a Python conditional is three
#: blocks of numba's IR, which numba copies with the whole function's scope when it inlines
#: the function (compile time).
select = cast(Callable[[bool, float, float], float], _select_intrinsic)


@intrinsic
def _frozen_intrinsic(typingctx: Any, x: Any) -> Any:
    sig = numba.types.float64(numba.types.float64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        frozen = llvm_ir.Instruction(builder.block, args[0].type, "freeze", [args[0]])
        builder._insert(frozen)  # (llvmlite's builder has no freeze)
        return frozen

    return sig, codegen


#: ``x`` itself, through LLVM's ``freeze`` (which returns a value that is not poison as it is: no
#: bit changes). Why: a lane loop's ``S[r] = select(c, v, S[r])``, a row kept where a lane's flag
#: is off, is recognised by LLVM as a conditional store of ``v`` and vectorised as a masked store
#: (``vmaskmovpd``, microcoded on AMD's cores: ~6 of kkl-biased's sample); ``select(c, v,
#: frozen(S[r]))`` is not the row's own value to LLVM, so it stays a blend and a plain store.
frozen = cast(Callable[[float], float], _frozen_intrinsic)


#: a cache line, in doubles: a row of LANES doubles that starts on one lies in one line
_LINE_DOUBLES = 64 // 8


@kernel
def aligned_lanes(size: int) -> np.ndarray:
    """``np.empty(size)`` of float64 whose element 0 is on a 64-byte boundary, so that every row of
    ``LANES`` doubles at a multiple of ``LANES`` lies in one cache line. Why: numba's own arrays
    start on 32-byte boundaries (its preferred alignment), so a row may straddle two lines, and
    which rows do changes with where the allocator puts the array, from process to process;
    ges-kalman's bank, whose work array was first allocated that way, ran ~30 % slower in one
    process of seven. The lane-major banks take their work arrays (and lane-major sample rows)
    from here; the values, hence every output bit, are unchanged."""
    buf = np.empty(size + _LINE_DOUBLES)
    at = (_LINE_DOUBLES - (buf.ctypes.data // 8) % _LINE_DOUBLES) % _LINE_DOUBLES
    return buf[at : at + size]


_HOST_CPU, HOST_VECTOR_BITS = host_vector_bits()
#: the vectors of doubles a bank's LANES lanes take on this host: 1 with AVX-512, 2 with AVX2
VECTORS = max(1, LANES * 64 // HOST_VECTOR_BITS)
#: the lanes of one vector: a lane loop runs ``range(HALF)`` and steps lanes ``lane`` and
#: ``lane + HALF`` in each iteration when VECTORS == 2 (see the banks' ``_bank_lanes``)
HALF = LANES // 2
