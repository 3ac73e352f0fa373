"""A recording replays bit for bit on any x86-64 host: adaptive-multisine's design constants and
outputs do not depend on which kernels OpenBLAS or numpy pick for the CPU.

OpenBLAS chooses its kernels by CPU when it loads; ``OPENBLAS_CORETYPE`` forces a choice, so one
host can run the kernels of several (Haswell: AVX2 and FMA, as on AMD Zen; SandyBridge: AVX;
Prescott: SSE3). numpy's own loops dispatch by CPU the same way; ``NPY_DISABLE_CPU_FEATURES``
turns its AVX2/AVX-512 loops off. Each configuration runs in its own process (both are read
when the libraries load), on the same input bytes, and must give the same output bytes.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sinewatch.estimators import get

# A child: the design constants of both modes and the outputs on the input, as one hex digest.
CHILD = r"""
import hashlib, sys
import numpy as np
from sinewatch.estimators import get
from sinewatch.estimators import _adaptive_multisine_explicit as explicit

cls = get("adaptive-multisine")
x = np.load(sys.argv[1])
digest = hashlib.sha256()
for params in (dict(cls.example_params), {"n_sinusoids": 2}):
    design = explicit.setup(cls.Params(**params), cls.example_sample_rate_hz)
    for key in ("cf", "ci", "L_x", "theta0"):
        digest.update(np.ascontiguousarray(design[key]).tobytes())
    track = cls(cls.example_sample_rate_hz, params).update(x)
    for a in (track.frequency_hz, track.amplitude, track.phase_rad, track.offset, track.converged):
        digest.update(np.ascontiguousarray(a).tobytes())
    digest.update(np.float64(track.residual_rms).tobytes())
    for key in sorted(track.extras):
        digest.update(np.ascontiguousarray(track.extras[key]).tobytes())
print(digest.hexdigest())
"""

CONFIGURATIONS = {
    "OpenBLAS Haswell": {"OPENBLAS_CORETYPE": "Haswell"},
    "OpenBLAS SandyBridge": {"OPENBLAS_CORETYPE": "SandyBridge"},
    "OpenBLAS Prescott": {"OPENBLAS_CORETYPE": "Prescott"},
    "numpy without AVX2 or AVX-512 loops": {"NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR"},
}


def _digest(env: dict[str, str], signal: Path) -> str:
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(signal)],
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def signal(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The example signal, made once here so that every child reads the same input bytes."""
    path = tmp_path_factory.mktemp("host") / "x.npy"
    np.save(path, get("adaptive-multisine").example_signal(1500, seed=3))
    return path


def test_adaptive_multisine_gives_the_same_bytes_whatever_kernels_the_host_picks(signal: Path) -> None:
    digests = {name: _digest(env, signal) for name, env in CONFIGURATIONS.items()}
    assert len(set(digests.values())) == 1, digests


# ---- detlinalg: the pole placement against scipy's, and the solve ---------------------------------
def _observer(a: list[float], bias: bool) -> tuple[np.ndarray, np.ndarray]:
    from sinewatch.estimators._adaptive_multisine_explicit import observer_matrices

    return observer_matrices(np.asarray(a), bias)


@pytest.mark.parametrize(
    ("a", "bias", "poles"),
    [
        ([-1.0, -4.0], True, [-0.6, -0.5, -0.3, -1.0, -10.0]),  # the paper's Example 2 (defaults)
        ([-9.0, -16.0], False, [-2.0, -0.7, -0.5, -0.2]),  # Example 1
        ([-1.0, -4.0, -9.0], True, [-0.3, -0.4, -0.5, -0.6, -0.7, -0.8, -2.0]),
    ],
)
def test_ackermann_places_the_poles_as_closely_as_scipy(a: list[float], bias: bool, poles: list[float]) -> None:
    from scipy.signal import place_poles

    from sinewatch.estimators import detlinalg

    fx, cx = _observer(a, bias)
    mine = np.array(detlinalg.observer_gain(fx.tolist(), cx.tolist(), poles))
    ref = place_poles(fx.T, cx[:, None], poles).gain_matrix.T[:, 0]
    np.testing.assert_allclose(mine, ref, rtol=1e-9)
    placed = np.sort(np.linalg.eigvals(fx - np.outer(mine, cx)).real)
    np.testing.assert_allclose(placed, np.sort(poles), rtol=1e-9)


def test_unobservable_pair_is_a_typed_error() -> None:
    from sinewatch.estimators import detlinalg

    fx, cx = _observer([-4.0, -4.0], False)  # two oscillators on one line: C cannot tell them apart
    with pytest.raises(detlinalg.SingularMatrixError, match="pivot"):
        detlinalg.observer_gain(fx.tolist(), cx.tolist(), [-1.0, -2.0, -3.0, -4.0])


def test_solve_pivots_and_matches_numpy() -> None:
    from sinewatch.estimators import detlinalg

    rng = np.random.default_rng(5)
    m = rng.standard_normal((6, 6))
    m[0, 0] = 0.0  # a zero on the diagonal: only pivoting gets past it
    b = rng.standard_normal(6)
    np.testing.assert_allclose(detlinalg.solve(m.tolist(), b.tolist()), np.linalg.solve(m, b), rtol=1e-12)


# A child that imports sinewatch first, as the daemon, replay and the command line do.
PINNED_CHILD = r"""
import os
import sinewatch.estimators
import numpy
from numpy._core._multiarray_umath import __cpu_features__
from sinewatch import host_arithmetic
print(host_arithmetic.PINNED, os.environ.get("OPENBLAS_CORETYPE"), host_arithmetic.openblas_core(),
      __cpu_features__.get("X86_V4", False), __cpu_features__.get("AVX512F", False))
"""


def _child(code: str, env: dict[str, str]) -> list[str]:
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return done.stdout.split()


def _env_without_choices() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES")}


def test_sinewatch_imported_first_runs_openblas_haswell_kernels_and_no_avx512_numpy_loops() -> None:
    """What makes kkl's, kkl-biased's, grip-mixing's and differential-rls's designs (solves,
    eigenvalues, matrix exponentials through OpenBLAS) the same bits on an AVX-512 host as on an
    AVX2 one: sinewatch chooses the kernels before numpy loads them."""
    if not {"avx2", "fma"} <= __import__("sinewatch.host_arithmetic").host_arithmetic._cpu_flags():
        pytest.skip("a CPU without AVX2 and FMA keeps OpenBLAS's own choice")
    pinned, coretype, core, v4, avx512f = _child(PINNED_CHILD, _env_without_choices())
    assert (pinned, coretype, core) == ("True", "Haswell", "Haswell")
    assert (v4, avx512f) == ("False", "False")  # numpy's AVX-512 loops off, on a host that has them too


def test_a_users_choice_is_kept_and_numpy_loaded_first_is_left_alone() -> None:
    env = _env_without_choices() | {"OPENBLAS_CORETYPE": "SandyBridge"}
    assert _child(PINNED_CHILD, env)[1:3] == ["SandyBridge", "Sandybridge"]
    late = "import numpy, os\nfrom sinewatch import host_arithmetic\nprint(host_arithmetic.PINNED, os.environ.get('OPENBLAS_CORETYPE'))"
    assert _child(late, _env_without_choices()) == ["False", "None"]
