"""``grip-mixing``: LTI observer on the redefined output y(t) - y(t - T) (periodic output disturbance).

Paper: H. F. Grip, "Observer design in the presence of periodic output disturbances by
mixing of past and present output data" (the year is not recorded here: the copy this was
built from does not print it).

That copy drops minus signs; every equation below was rebuilt from the surrounding text and
checked numerically (``tests/test_grip_mixing.py``).

Plant and disturbance (1)::

    x'(t) = A x(t) + B u(t)                        (1a)   x in R^n, u in R^m (known input)
    y(t)  = C x(t) + D u(t) + d(t)                 (1b)   y, d in R^p (here p = 1)
    d(t)  = d(t - T)                                      d unknown, bounded, period T known

Solving (1a) backwards over one period (4)::

    x(t - T) = e^{-AT} x(t) + int_t^{t-T} e^{A(t-T-s)} B u(s) ds                      (4)
    u_Delta(t) = C int_t^{t-T} e^{A(t-T-s)} B u(s) ds + D u(t - T)

so that, for t >= T, the system with the redefined output is the LTI system (5)::

    x'(t)  = A x(t) + B u(t)                                                          (5a)
    ybar(t) = y(t) - y(t - T) = C (I - e^{-AT}) x(t) + D u(t) - u_Delta(t)            (5b)

Theorem 1: (C (I - e^{-AT}), A) is observable iff (C, A) is observable and A has no
eigenvalue at +-j 2 pi k / T, k = 0, 1, 2, ...  (a DC state, k = 0, is never observable:
a constant is periodic with every period, see Remark 2).

Observer (7), with y_d and u_Delta_d the outputs of the implemented delays (equal to
y(t - T) and u_Delta(t) once t >= t0 + T)::

    xhat' = A xhat + B u + L ( y(t) - y_d(t - T) - C (I - e^{-AT}) xhat - D u(t) + u_Delta_d(t) )   (7)
    dhat(t) = y(t) - C xhat(t) - D u(t)                          (disturbance estimate, Sec. III-A)

with L placed so that A - L C (I - e^{-AT}) is Hurwitz (Theorem 2). Section III-B computes
u_Delta_d from an internal copy of the plant driven by u::

    z' = A z + B u,     u_Delta_d(t) = C ( z_d(t - T) - e^{-AT} z(t) ) + D u_d(t - T)  (III-B)
    z(t - T) = e^{-AT} z(t) + int_t^{t-T} e^{A(t-T-s)} B u(s) ds                     (8)

(8) holds for any z(t0), so z may be reset; it is invalid for one period after a reset, hence
two copies of z whose resets are staggered by half the reset interval: at every sample the
copy reset longer ago (at least one period ago) supplies u_Delta_d. This keeps z finite when A
is unstable (or marginally stable and driven at resonance).

Section V (rebuilt): A = [[0, 1], [-1, 0]], B = [0, 1]^T, C = [1, 0], D = 0 (the observability
matrix [C; CA] is the identity and the eigenvalues are +-j, as the text says), u = 2 + 3 sin(0.3 t),
T = 4.5 s, poles -1 and -2: L = (1.9037, -0.7110) (the paper prints |L| = (1.90, 0.71), its
minus sign lost); with T = 4 s, L = (1.7288, -0.1865) (paper: (1.73, 0.19)).

Discretisation (this module's choice, documented)
-------------------------------------------------
Samples arrive every Ts = 1/fs; the period is T = M Ts with M a whole number of samples
(otherwise ``fractional_delay=True``, below). Sample k carries y_k and, when the plant has
inputs, u_k. The continuous design is kept verbatim: ``gain_L`` is the gain of (7) placed
with ``scipy.signal.place_poles`` on (A, C (I - e^{-AT})). The kernel runs the sampled-data
version of (7):

* (5a) is discretised exactly for inputs linear between samples (first-order hold)::

      x_{k+1} = Ad x_k + Bd0 u_k + Bd1 u_{k+1},   Ad = e^{A Ts},
      [Ad, G1, G2] = top row of expm([[A, B, 0], [0, 0, I/Ts], [0, 0, 0]] Ts),
      Bd0 = G1 - G2, Bd1 = G2

  (z of III-B uses the same recursion, so (8) holds exactly between samples of the model);
* the correction uses the innovation of (7) at the sample, in "current estimator" form::

      xhat^-_k = Ad xhat_{k-1} + Bd0 u_{k-1} + Bd1 u_k                          (5a) sampled
      eps_k    = y_k - y_d(k - M) - C (I - e^{-AT}) xhat^-_k - D u_k + u_Delta_d(k)     (7)
      xhat_k   = xhat^-_k + Ld eps_k

  with Ld placed by ``place_poles`` on (Ad, C (I - e^{-AT}) Ad) at the mapped poles
  e^{p_i Ts}: the sampled error x_k - xhat_k then obeys e_k = (I - Ld Cbar) Ad e_{k-1}, whose
  eigenvalues are exactly the samples e^{p_i Ts} of the continuous error modes of Theorem 2,
  and Ld / Ts -> L as Ts -> 0 (checked in the tests). Unlike integrating (7) with the
  measured output held or interpolated between samples, this has no bias on sampled data.

Fractional period (``fractional_delay=True``): with T fs = D not a whole number, every delayed
read (y_d, u_d, z_d and the periodic prediction of dhat) is a 4-tap Lagrange (cubic)
interpolation at delay D from the taps floor(D)-1 .. floor(D)+2; e^{-AT} keeps the exact T.
The cancellation of d is then approximate (error ~ (2 pi f Ts)^4 / 24 relative, per harmonic f
of d); without the option a fractional T fs is a ParameterError.

Delay buffers (Sec. III-A: "initialised with a bounded initial function on [t0 - T, t0)"):
y_d, u_d and z_d start at zero; z starts at zero at t0; xhat starts at ``x0`` (default 0).
During the first period the estimate is bounded but not exact (Theorem 2).

Outputs
-------
* ``extras["x_hat"]`` (N, n): the state estimate; ``extras["d_hat"]`` (N,): dhat (p = 1).
* Sinusoids: one component per oscillatory mode of A (eigenvalue pair lambda, conj(lambda)
  with Im lambda > 0), sorted by frequency: frequency = Im lambda / (2 pi) (the model's, not
  estimated), and the instantaneous amplitude and phase of that mode's contribution to C xhat:
  with v, w the right and left eigenvectors (w^H v = 1), q = 2 (C v)(w^H xhat) is the analytic
  value of the contribution Re(q) = amplitude sin(phase), so amplitude = |q|,
  phase = atan2(Re q, -Im q). A plant without oscillatory modes, or with a repeated eigenvalue
  (no modal basis), reports one component with NaN frequency/amplitude/phase and
  ``converged`` False; x_hat and d_hat are still valid.
* offset = C xhat + D u - sum_k Re(q_k) + mean of dhat over the last period, i.e. everything the
  model explains that is not an oscillatory mode, plus the DC part of the periodic
  disturbance (the DC part is unobservable from ybar, Theorem 1 with k = 0, so it is read from
  dhat). The zero-mean part of d is only in ``d_hat``.
* converged: the sample index is at least M (delays filled) + the settling time of the
  Theorem 2 bound, ln(1/convergence_tolerance) / min_i |Re p_i|, + one period for the mean of
  dhat. It is a schedule derived from the placed poles, not a test on the data.
* residual: one-step prediction error of y, y_k - C xhat^-_k - D u_k - dhat_d(k - M) (the
  disturbance predicted by its value one period earlier).

Presets
-------
* ``preset="harmonics"`` (default): the plant is a bank of undamped oscillators at the known
  ``frequencies_hz`` (default 50, 150, 250 Hz), block i = [[0, w_i], [-w_i, 0]] on the state
  (a_i sin theta_i, a_i cos theta_i), C = [1, 0, 1, 0, ...], no input; poles default to
  -decay_rate +- j w_i (each line's observer decays at ``decay_rate`` 1/s). Theorem 1 then
  requires f_i T not an integer: the oscillators must not sit on a harmonic of the
  disturbance. It estimates amplitude and phase of each line while cancelling any periodic
  disturbance of period T (its DC part goes to ``offset``).
* ``preset="plant"``: any (A, B, C, D) given as nested lists; ``poles`` default to the
  spectrum of A shifted left, -|Re lambda_i| - decay_rate + j Im lambda_i. With m = columns of
  B > 0, the known input travels with the samples: the block is (N, 1 + m), column 0 = y,
  columns 1..m = u (``n_inputs`` = 1 + m). Without B the block is (N,).

``GripMixing.params_for`` (the accuracy bench's hook) configures the ``harmonics`` preset for
a scenario's nominal frequencies with a mixing period T (whole samples, <= 0.1 s) that
maximises min_k |sin(pi f_k T)|, the conditioning of I - e^{-AT}.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from sinewatch.estimators import register
from sinewatch.estimators.bank import register_bank
from sinewatch.estimators.base import Estimator, EstimatorParams, Track
from sinewatch.estimators.grip_mixing_kernels import grip_mixing_bank_kernel, grip_mixing_kernel
from sinewatch.schemas.errors import ParameterError

DEFAULT_FREQUENCIES_HZ = (50.0, 150.0, 250.0)
_THEOREM1_TOL = 1e-6  # |1 - e^{-lambda T}| below this: lambda sits on +-j 2 pi k / T
_PBH_TOL = 1e-7  # relative smallest singular value of [lambda I - A; C] below this: unobservable
_MAX_Z_GROWTH = 20.0  # z may grow by e^20 between resets: (8) then cancels to ~1e-8 relative
_MAX_EXP_NORM = 1e10  # ||e^{-AT}|| above this: C (I - e^{-AT}) loses every significant digit


class GripMixingParams(EstimatorParams):
    preset: Literal["harmonics", "plant"] = Field(
        "harmonics",
        description="'harmonics': oscillator bank at frequencies_hz; 'plant': matrices A, B, C, D",
    )
    period_s: float = Field(0.05, gt=0, description="Known period T of the output disturbance, seconds")
    fractional_delay: bool = Field(
        False, description="Allow T fs not a whole number (4-tap Lagrange interpolated delays)"
    )
    frequencies_hz: list[float] | None = Field(
        None, description="harmonics preset: oscillator frequencies (default 50, 150, 250 Hz)"
    )
    decay_rate: float = Field(20.0, gt=0, description="Default poles: each mode's observer decays at this rate, 1/s")
    A: list[list[float]] | None = Field(None, description="plant preset: n x n system matrix")
    B: list[list[float]] | None = Field(None, description="plant preset: n x m input matrix (omit: no input)")
    C: list[list[float]] | list[float] | None = Field(None, description="plant preset: 1 x n output matrix")
    D: list[list[float]] | list[float] | None = Field(None, description="plant preset: 1 x m feedthrough")
    poles: list[float | tuple[float, float]] | None = Field(
        None, description="Poles of A - L C (I - e^{-AT}): n reals or [re, im] pairs (conjugates included)"
    )
    x0: list[float] | None = Field(None, description="Initial state estimate xhat(t0) (default 0)")
    z_reset_periods: int = Field(
        4, ge=2, description="Each internal state z of Sec. III-B is reset every this many periods"
    )
    convergence_tolerance: float = Field(
        0.01, gt=0, lt=1, description="converged once the Theorem 2 bound has decayed to this fraction"
    )


@dataclass(frozen=True)
class GripDesign:
    """Everything derived from the parameters and the sample rate (computed once)."""

    A: np.ndarray  # (n, n)
    B: np.ndarray  # (n, m)
    C: np.ndarray  # (n,) the single output row
    D: np.ndarray  # (m,)
    E: np.ndarray  # e^{-AT}
    Cbar: np.ndarray  # C (I - e^{-AT}), (5b)
    poles: np.ndarray  # continuous poles p_i of A - L Cbar
    L: np.ndarray  # (n,) continuous gain of (7)
    Ad: np.ndarray  # e^{A Ts}
    Bd0: np.ndarray  # FOH input matrices
    Bd1: np.ndarray
    Ld: np.ndarray  # (n,) sampled-data gain, eig((I - Ld Cbar) Ad) = e^{p Ts}
    delay_samples: float  # T fs
    tap_h: np.ndarray  # delay-line weights
    tap_o: np.ndarray  # delay-line offsets (samples)
    window: int  # samples in the mean of dhat (offset)
    reset_half: int  # H: stagger of the two z copies; reset interval 2 H
    warm: int  # samples before converged may be True
    frequencies_hz: np.ndarray  # (K,)
    Wre: np.ndarray  # (K, n) real / imaginary parts of the modal analytic rows
    Wim: np.ndarray
    modal_ok: bool


def _matrix(name: str, value: object, rows: int | None, cols: int | None) -> np.ndarray:
    try:
        a = np.array(value, dtype=np.float64)
    except ValueError:
        raise ParameterError(f"{name}: expected a rectangular matrix, got ragged rows") from None
    if a.ndim == 1:
        a = a[None, :]
    if a.ndim != 2 or a.size == 0:
        raise ParameterError(f"{name}: expected a non-empty matrix, got shape {a.shape}")
    want = (rows if rows is not None else a.shape[0], cols if cols is not None else a.shape[1])
    if a.shape != want:
        raise ParameterError(f"{name}: expected shape {want}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ParameterError(f"{name}: expected finite values, got {value}")
    return a


def _fmt(lam: complex) -> str:
    return f"{lam.real:.6g}{lam.imag:+.6g}j"


def check_theorem1(A: np.ndarray, C: np.ndarray, T: float) -> None:
    """Theorem 1: raise ParameterError naming the eigenvalue that breaks observability of
    (C (I - e^{-AT}), A)."""
    n = A.shape[0]
    scale = max(1.0, float(np.linalg.norm(A, 2)), float(np.linalg.norm(C)))
    for lam in np.linalg.eigvals(A):
        pbh = np.vstack([lam * np.eye(n) - A, C.reshape(1, n).astype(complex)])
        smin = np.linalg.svd(pbh, compute_uv=False)[-1]
        if smin < _PBH_TOL * scale:
            raise ParameterError(
                f"A, C: expected an observable pair (C, A) (Theorem 1), got eigenvalue {_fmt(lam)} unobservable from C"
            )
        k = lam.imag * T / (2.0 * np.pi)
        if abs(1.0 - np.exp(-lam * T)) < _THEOREM1_TOL:
            raise ParameterError(
                f"period_s: expected no eigenvalue of A at +-j 2 pi k / T (Theorem 1), got eigenvalue "
                f"{_fmt(lam)} = j 2 pi {abs(round(k))} / T with T = {T} s: that mode is periodic with "
                f"period T and cancels in y(t) - y(t - T) like the disturbance"
            )


def _place(Amat: np.ndarray, c: np.ndarray, poles: np.ndarray, what: str) -> np.ndarray:
    """Observer gain l with eig(Amat - l c) = poles, by scipy.signal.place_poles on the dual."""
    import scipy.signal  # here, not with the module: listing the estimators need not import it (~1 s CPU)

    n = Amat.shape[0]
    try:
        res = scipy.signal.place_poles(Amat.T, c.reshape(n, 1), poles)
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise ParameterError(f"poles: expected placeable poles for {what}, got an error: {exc}") from None
    l_gain = np.real_if_close(res.gain_matrix.T[:, 0]).astype(np.float64)
    got = np.linalg.eigvals(Amat - np.outer(l_gain, c))
    err = max(min(abs(g - p) for p in poles) for g in got)
    if not np.all(np.isfinite(l_gain)) or err > 1e-6 * max(1.0, np.max(np.abs(poles))):
        raise ParameterError(
            f"poles: expected an accurate placement for {what}, got eigenvalues {np.sort_complex(got)} "
            f"(ill-conditioned: is T close to a multiple of a mode's period?)"
        )
    return l_gain


def _parse_poles(poles: list[float | tuple[float, float]], n: int) -> np.ndarray:
    p = np.array([complex(v[0], v[1]) if isinstance(v, (tuple, list)) else complex(v) for v in poles])
    if p.size != n:
        raise ParameterError(f"poles: expected {n} poles (one per state), got {p.size}")
    if not np.all(np.isfinite(p)) or np.any(p.real >= 0):
        raise ParameterError(f"poles: expected finite poles with negative real part, got {poles}")
    if not np.allclose(np.sort_complex(p), np.sort_complex(p.conj()), rtol=0, atol=1e-9):
        raise ParameterError(f"poles: expected complex poles in conjugate pairs, got {poles}")
    d = np.abs(p[:, None] - p[None, :]) + np.eye(n)
    if np.any(d < 1e-9):
        raise ParameterError(f"poles: expected distinct poles (one output: multiplicity 1), got {poles}")
    return p


def _foh(A: np.ndarray, B: np.ndarray, Ts: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ad, Bd0, Bd1 of x_{k+1} = Ad x_k + Bd0 u_k + Bd1 u_{k+1} (exact for u linear between samples)."""
    n, m = B.shape
    big = np.zeros((n + 2 * m, n + 2 * m))
    big[:n, :n] = A * Ts
    big[:n, n : n + m] = B * Ts
    big[n : n + m, n + m :] = np.eye(m)
    import scipy.linalg  # here, not with the module (see _place)

    ex = scipy.linalg.expm(big)
    Ad, G1, G2 = ex[:n, :n], ex[:n, n : n + m], ex[:n, n + m :]
    return Ad, G1 - G2, G2


def _delay_taps(delay: float) -> tuple[np.ndarray, np.ndarray]:
    """Weights and offsets reading a delay line at ``delay`` samples (1 tap if whole)."""
    if delay == round(delay):
        return np.ones(1), np.array([round(delay)], dtype=np.int64)
    base = math.floor(delay) - 1
    d = delay - base  # in [1, 2): cubic Lagrange on taps base .. base + 3
    h = np.ones(4)
    for j in range(4):
        for i in range(4):
            if i != j:
                h[j] *= (d - i) / (j - i)
    return h, base + np.arange(4, dtype=np.int64)


def design(params: GripMixingParams, fs: float) -> GripDesign:
    """Validate the parameters against the sample rate and derive every constant."""
    p = params
    Ts = 1.0 / fs
    T = p.period_s
    # ---- the plant -----------------------------------------------------------------------
    if p.preset == "harmonics":
        for key in ("A", "B", "C", "D"):
            if getattr(p, key) is not None:
                raise ParameterError(f"{key}: expected no matrix with preset 'harmonics', got {getattr(p, key)}")
        f = np.array(p.frequencies_hz if p.frequencies_hz is not None else DEFAULT_FREQUENCIES_HZ, float)
        if f.size == 0 or not np.all(np.isfinite(f)) or np.any(f <= 0) or np.any(f >= fs / 2):
            raise ParameterError(
                f"frequencies_hz: expected at least one value in (0, fs/2 = {fs / 2:g}) Hz, got {f.tolist()}"
            )
        if np.unique(f).size != f.size:
            raise ParameterError(f"frequencies_hz: expected distinct values, got {f.tolist()}")
        f = np.sort(f)
        K = f.size
        n = 2 * K
        A = np.zeros((n, n))
        E = np.zeros((n, n))
        Ad = np.zeros((n, n))
        C = np.zeros(n)
        Wre = np.zeros((K, n))
        Wim = np.zeros((K, n))
        for i, w in enumerate(2 * np.pi * f):
            s = slice(2 * i, 2 * i + 2)
            A[s, s] = [[0.0, w], [-w, 0.0]]  # state (a sin theta, a cos theta), theta' = w
            cT, sT = math.cos(w * T), math.sin(w * T)
            E[s, s] = [[cT, -sT], [sT, cT]]  # e^{-AT}: rotation by -w T
            cs, ss = math.cos(w * Ts), math.sin(w * Ts)
            Ad[s, s] = [[cs, ss], [-ss, cs]]  # e^{A Ts}
            C[2 * i] = 1.0
            Wre[i, 2 * i] = 1.0  # q = a sin theta - j a cos theta = a e^{j(theta - pi/2)}
            Wim[i, 2 * i + 1] = -1.0
        B = np.zeros((n, 0))
        D = np.zeros(0)
        Bd0 = Bd1 = B
        freqs, modal_ok = f, True
        if p.x0 is not None and len(p.x0) != n:
            raise ParameterError(f"x0: expected {n} values (2 per frequency), got {len(p.x0)}")
        default_poles = np.concatenate([-p.decay_rate + 2j * np.pi * f, -p.decay_rate - 2j * np.pi * f])
    else:
        if p.frequencies_hz is not None:
            raise ParameterError(f"frequencies_hz: expected none with preset 'plant', got {p.frequencies_hz}")
        if p.A is None or p.C is None:
            raise ParameterError("A, C: expected both matrices with preset 'plant', got none")
        A = _matrix("A", p.A, None, None)
        n = A.shape[0]
        if A.shape[1] != n:
            raise ParameterError(f"A: expected a square matrix, got shape {A.shape}")
        C = _matrix("C", p.C, 1, n)[0]
        if p.B is not None:
            B = _matrix("B", p.B, n, None)
        else:
            B = np.zeros((n, 0))
        m = B.shape[1]
        if p.D is not None:
            if m == 0:
                raise ParameterError(f"D: expected none without an input matrix B, got {p.D}")
            D = _matrix("D", p.D, 1, m)[0]
        else:
            D = np.zeros(m)
        if p.x0 is not None and len(p.x0) != n:
            raise ParameterError(f"x0: expected {n} values, got {len(p.x0)}")
        import scipy.linalg  # here, not with the module (see _place)

        E = scipy.linalg.expm(-A * T)
        Ad, Bd0, Bd1 = _foh(A, B, Ts)
        lam = np.linalg.eigvals(A)
        default_poles = -np.abs(lam.real) - p.decay_rate + 1j * lam.imag
        freqs, Wre, Wim, modal_ok = _modes(A, C)
    if p.x0 is not None and not all(math.isfinite(v) for v in p.x0):
        raise ParameterError(f"x0: expected finite values, got {p.x0}")

    # ---- the delay T ---------------------------------------------------------------------
    delay = T * fs
    whole = abs(delay - round(delay)) <= 1e-9 * max(1.0, delay)
    if whole:
        delay = float(round(delay))
    elif not p.fractional_delay:
        raise ParameterError(
            f"period_s: expected a whole number of sample periods (T fs = {T} * {fs:g}), got "
            f"{T * fs:.6g} samples; set fractional_delay=true for an interpolated delay"
        )
    if delay < 2:
        raise ParameterError(f"period_s: expected at least 2 sample periods, got {T * fs:.6g} samples")
    tap_h, tap_o = _delay_taps(delay)

    # ---- Theorem 1, then the gains ------------------------------------------------------------
    check_theorem1(A, C, T)
    if np.linalg.norm(E, 2) > _MAX_EXP_NORM:
        raise ParameterError(
            f"period_s: expected ||e^{{-AT}}|| <= {_MAX_EXP_NORM:g}, got {np.linalg.norm(E, 2):.3g} "
            f"(stable modes decay too much over T; with A Hurwitz the paper's answer is L = 0)"
        )
    poles = _parse_poles(p.poles, n) if p.poles is not None else default_poles
    if p.poles is None:
        _parse_poles([(z.real, z.imag) for z in poles], n)  # default poles must be distinct too
    if np.any(np.abs(poles.imag) >= np.pi * fs):
        raise ParameterError(f"poles: expected |Im p| < pi fs = {np.pi * fs:.6g} rad/s, got {poles}")
    Cbar = C @ (np.eye(n) - E)  # (5b)
    L = _place(A, Cbar, poles, "A - L C (I - e^{-AT}) (continuous, Theorem 2)")
    # sampled-data pair (Ad, Cbar Ad): a repeated e^{lambda Ts} (aliasing) is caught by the PBH test
    for mu in np.linalg.eigvals(Ad):
        pbh = np.vstack([mu * np.eye(n) - Ad, (Cbar @ Ad).reshape(1, n).astype(complex)])
        if np.linalg.svd(pbh, compute_uv=False)[-1] < _PBH_TOL * max(1.0, float(np.linalg.norm(Cbar))):
            raise ParameterError(
                f"A: expected a sampled pair that stays observable at fs = {fs:g} Hz, got eigenvalue "
                f"e^(lambda Ts) = {_fmt(mu)} shared by two modes (aliasing)"
            )
    Ld = _place(Ad, Cbar @ Ad, np.exp(poles * Ts), "(I - Ld Cbar) Ad (sampled)")

    # ---- staggered resets of z and the convergence schedule --------------------------------------
    max_off = int(tap_o.max())
    reset_half = max(max_off, math.ceil(p.z_reset_periods * max_off / 2))
    growth = max(0.0, float(np.max(np.linalg.eigvals(A).real))) * 2 * reset_half / fs
    if B.shape[1] > 0 and growth > _MAX_Z_GROWTH:
        raise ParameterError(
            f"z_reset_periods: expected the internal states of Sec. III-B to grow by at most "
            f"e^{_MAX_Z_GROWTH:g} between resets, got e^{growth:.3g} (max Re lambda x reset interval); "
            f"lower z_reset_periods (minimum 2) or shorten T"
        )
    window = round(delay)
    settle = math.ceil(math.log(1.0 / p.convergence_tolerance) / float(np.min(-poles.real)) * fs)
    warm = max_off + settle + window
    return GripDesign(
        A=A, B=B, C=C, D=D, E=E, Cbar=Cbar, poles=poles, L=L, Ad=Ad, Bd0=Bd0, Bd1=Bd1, Ld=Ld,
        delay_samples=delay, tap_h=tap_h, tap_o=tap_o, window=window, reset_half=reset_half,
        warm=warm, frequencies_hz=np.asarray(freqs, float), Wre=Wre, Wim=Wim, modal_ok=modal_ok,
    )  # fmt: skip


def _modes(A: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """Oscillatory modes of A: frequencies (Hz) and the rows q_k = (Wre + j Wim) x with
    Re q_k the mode's contribution to C x (see module docstring)."""
    n = A.shape[0]
    lam, V = np.linalg.eig(A)
    scale = max(1.0, np.max(np.abs(lam)))
    idx = [i for i in range(n) if lam[i].imag > 1e-9 * scale]
    if not idx or np.linalg.cond(V) > 1e8:
        return np.full(1, np.nan), np.zeros((1, n)), np.zeros((1, n)), False
    Vinv = np.linalg.inv(V)
    idx.sort(key=lambda i: lam[i].imag)
    W = np.array([2.0 * (C @ V[:, i]) * Vinv[i, :] for i in idx])
    return np.array([lam[i].imag / (2 * np.pi) for i in idx]), W.real.copy(), W.imag.copy(), True


def _pairs(Ad: np.ndarray) -> bool:
    """True if Ad is block-diagonal with 2 x 2 blocks (the kernel then skips the zeros)."""
    n = Ad.shape[0]
    if n % 2:
        return False
    mask = np.kron(np.eye(n // 2), np.ones((2, 2))) == 0
    return not np.any(Ad[mask])


def state_layout(n: int, m: int, lz: int, lb: int) -> dict[str, tuple[int, ...]]:
    """Shapes of the parts of the flat kernel state, in order (documentation and tests)."""
    return {"x_hat": (n,), "u_prev": (m,), "z": (2, n), "z_buf": (2, lz, n), "y_buf": (lb,),
            "u_buf": (lb, m), "d_buf": (lb,), "d_sum": (1,)}  # fmt: skip


@register
class GripMixing(Estimator[GripMixingParams], kernel=grip_mixing_kernel, name="grip-mixing"):
    """LTI observer on y(t) - y(t-T) that cancels a periodic output disturbance of known period; preset 'harmonics' tracks known-frequency lines"""

    paper = 'H. F. Grip, "Observer design in the presence of periodic output disturbances by mixing of past and present output data"'
    example_sample_rate_hz = 4000.0
    # Printed by ``sinewatch bench kernels`` under its table. Its ratio and ns/sample: ``sinewatch bench kernels --block 1024 --estimators grip-mixing``
    # (the kernel alone: that ns/sample less the per-block call, ~5-7 us / 1024).
    bench_note: ClassVar[str] = (
        "grip-mixing is just below the streaming FFT (about 0.8x at 1024-sample blocks): the "
        "observer (7) is a recursion, xhat -> xhat^- (5a) -> the innovation, a sum over the n "
        "states in a fixed order -> xhat, that no two samples can share; at the example's n = 6 "
        "(three lines) with its two delay lines the kernel takes ~32 ns/sample and the call "
        "(validation, the state copy, four returned arrays) ~7 us a block, another ~7 ns/sample "
        "at 1024."
    )
    # Printed by ``sinewatch bench kernels --bank N`` when the bank is below twice the streaming FFT.
    bank_note: ClassVar[str] = (
        "grip-mixing's bank runs a bank of oscillators (Ad of 2 x 2 blocks, at most 8 states: the "
        "harmonics preset up to 4 lines) as 8 vector lanes of one work array, each lane the single "
        "kernel's operations in order (bit for bit), the delay lines' taps copied in and out as "
        "one vector each: 2.25x the streaming FFT and 2.63x one channel at bank 8 (`sinewatch "
        "bench kernels --block 1024 --bank 8 --estimators grip-mixing`, load 15-16). Below 8 "
        "channels the lanes are padded (3 channels cost what 8 do), and the Python around the "
        "call (gathering and scattering 421 state values a channel, the Tracks, ~80 us a frame) "
        "is a larger share of a shorter block; other plants (more states, Ad not of 2 x 2 "
        "blocks) run each channel through the single kernel in one compiled call, at about the "
        "single channel's rate"
    )
    # its memory is already a settling bound (the delays filled and the Theorem 2 bound settled): one is
    # enough, every valid estimate of the validity bench within 0.04 of its target (validity rules 5)
    REFILL_MEMORIES: ClassVar[int] = 1
    example_params: ClassVar[dict[str, Any]] = {
        "preset": "harmonics",
        "frequencies_hz": [50.0, 150.0, 250.0],
        "period_s": 0.05,
    }

    @classmethod
    def example_signal(cls, n: int, seed: int = 0) -> np.ndarray:
        """0.5 + lines at 50/150/250 Hz + a 20 Hz (T = 0.05 s) periodic disturbance + 1 % noise."""
        rng = np.random.default_rng(seed)
        t = np.arange(n) / cls.example_sample_rate_hz
        lines = (
            np.sin(2 * np.pi * 50 * t + 0.3)
            + 0.2 * np.sin(2 * np.pi * 150 * t - 1.0)
            + 0.1 * np.sin(2 * np.pi * 250 * t + 2.0)
        )
        dist = 0.4 * np.sin(2 * np.pi * 20 * t) + 0.3 * np.sin(2 * np.pi * 60 * t + 0.5)
        return 0.5 + lines + dist + 0.01 * rng.standard_normal(n)

    @classmethod
    def params_for(cls, sample_rate_hz: float, hints: dict[str, Any]) -> dict[str, Any]:
        """Parameters for a scenario described by ``hints`` (the accuracy bench's hook).

        One input column: the ``harmonics`` preset at the scenario's nominal frequencies, with
        a period T (whole samples, at most 0.1 s) chosen to maximise min_k |sin(pi f_k T)|,
        i.e. the conditioning of I - e^{-AT} (Theorem 1), the longest of the near-best (the
        offset is a mean over T). Such a scenario has no periodic disturbance; T is only the
        mixing delay. Known inputs: nothing here, the scenario's
        suggested plant decides.
        """
        if int(hints.get("n_inputs", 1)) > 1:
            return {}
        f = np.asarray(hints["nominal_frequency_hz"], dtype=np.float64)
        if f.size == 0 or np.any(f <= 0) or np.any(f >= sample_rate_hz / 2) or np.unique(f).size != f.size:
            raise ParameterError(f"nominal_frequency_hz: expected distinct values in (0, fs/2), got {f.tolist()}")
        m = np.arange(2, max(3, int(0.1 * sample_rate_hz) + 1))
        score = np.min(np.abs(np.sin(np.pi * np.outer(m / sample_rate_hz, f))), axis=1)
        best = int(m[np.flatnonzero(score >= score.max() - 1e-3)[-1]])  # longest: offset = mean over T
        return {
            "preset": "harmonics",
            "frequencies_hz": f.tolist(),
            "period_s": best / sample_rate_hz,
            "fractional_delay": False,
        }

    @property
    def memory_samples(self) -> int:
        """The samples before converged may be True: the delays filled and the Theorem 2
        bound settled (``GripDesign.warm``)."""
        return int(self._design.warm)

    def _check_params(self) -> None:
        self._design = design(self.params, self.sample_rate_hz)

    def _setup(self) -> None:
        g = self._design
        n, m = g.B.shape
        self._lb = int(g.tap_o.max()) + 1  # delay lines: the longest tap must still be there
        self._lz = self._lb if m > 0 else 0  # no input: z and its delay line are never used
        self._fconst = np.concatenate([
            g.Ad.ravel(), g.Bd0.ravel(), g.Bd1.ravel(), g.C, g.Cbar, g.C @ g.E, g.Ld, g.D, g.tap_h,
            g.Wre.ravel(), g.Wim.ravel(), g.frequencies_hz if g.modal_ok else np.full(1, np.nan),
        ])  # fmt: skip
        self._n, self._K = n, int(g.Wre.shape[0])
        K, every = self._K, slice(None)
        # the index of each output column group of the kernel's ``out``, built once
        self._columns = (
            (every, slice(0, K)), (every, slice(K, 2 * K)), (every, slice(2 * K, 3 * K)), (every, 3 * K),
            (every, 3 * K + 1), (every, 3 * K + 2), (every, slice(3 * K + 3, 3 * K + 3 + n)),
        )  # fmt: skip
        self._iconst = np.array(
            [n, m, g.Wre.shape[0], g.tap_h.size, self._lb, self._lz, g.window, g.reset_half, g.warm,
             int(g.modal_ok), *g.tap_o, int(_pairs(g.Ad))],
            dtype=np.int64,
        )  # fmt: skip
        self._constants = (self._fconst, self._iconst)

    # ---- design read-outs (for docs and tests) ----------------------------------------------
    @property
    def design(self) -> GripDesign:
        return self._design

    @property
    def gain_L(self) -> np.ndarray:
        """The continuous gain L of (7): eig(A - L C (I - e^{-AT})) = poles."""
        return self._design.L.copy()

    @property
    def n_components(self) -> int:
        return int(self._design.Wre.shape[0])

    @property
    def n_inputs(self) -> int:
        return 1 + int(self._design.B.shape[1])

    def _initial_state(self) -> dict[str, np.ndarray]:
        """``state``: flat, the parts of :func:`state_layout` in order: xhat, the previous
        u, the two internal states z (2, n) of Sec. III-B, the delay lines of z (2, Lz, n),
        y (Lb,), u (Lb, m) and dhat (Lb,), and the running sum of dhat over the last
        ``window`` samples; ``count`` (1,) int64: the sample count."""
        n, m = self._design.B.shape
        parts = state_layout(n, m, self._lz, self._lb)
        flat = np.zeros(sum(int(np.prod(shape)) for shape in parts.values()))
        if self.params.x0 is not None:
            flat[:n] = self.params.x0  # xhat(t0); every delay line starts at 0 (Sec. III-A)
        return {"state": flat, "count": np.zeros(1, dtype=np.int64)}

    def _kernel_input(self, samples: np.ndarray) -> np.ndarray:
        return samples if samples.ndim == 2 else samples.reshape(-1, 1)

    @staticmethod
    def _bank_tracks(first: GripMixing, outputs: tuple[Any, ...], samples: np.ndarray) -> list[Track]:
        """:meth:`_track` of every channel of a bank (``out`` (C, rows, columns), ``sse`` (C,)),
        one numpy call a field for the whole bank: each channel's fields are views of its slice,
        as the single path's are of its ``out``, and its residual the same correctly rounded
        sqrt(sse / N)."""
        out, sse = outputs
        K, n = first._K, first._n
        freq, amp, phase = list(out[:, :, 0:K]), list(out[:, :, K : 2 * K]), list(out[:, :, 2 * K : 3 * K])
        offset, conv = list(out[:, :, 3 * K]), list(out[:, :, 3 * K + 1].astype(np.bool_))
        dh, xh = list(out[:, :, 3 * K + 2]), list(out[:, :, 3 * K + 3 : 3 * K + 3 + n])
        rms = np.sqrt(sse / samples.shape[0]).tolist()
        return [
            Track(freq[c], amp[c], phase[c], offset[c], conv[c], rms[c], {"x_hat": xh[c], "d_hat": dh[c]})
            for c in range(out.shape[0])
        ]

    def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
        out, sse = outputs
        f, a, p, off, conv, dh, xh = self._columns
        return Track(
            out[f],  # frequency_hz
            out[a],  # amplitude
            out[p],  # phase_rad
            out[off],  # offset
            out[conv].astype(np.bool_),  # converged: != 0 (NaN counts as True either way), one call
            math.sqrt(sse / block.shape[0]),  # residual_rms
            {"x_hat": out[xh], "d_hat": out[dh]},
        )


# one-input channels of a frame advance together, each channel's chain beside the others'
register_bank(GripMixing, grip_mixing_bank_kernel, n_outputs=2, tracks=GripMixing._bank_tracks)
