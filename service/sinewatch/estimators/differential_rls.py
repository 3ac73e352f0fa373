"""``differential-rls``: differential signal model + recursive (extended) least squares for
the frequency, its rate of change (ROCOF), phase and amplitude of one sinusoid.

Paper: "Differential signal model and sampling techniques for recursive (extended)
least-squares estimation of frequency, frequency derivatives, phase and amplitude" (the
authors and the year are not recorded here: the copy this was built from does not print
them). Most equations are missing from that copy; those used here were rebuilt from the
text and each is checked numerically in ``tests/test_differential_rls.py``.

Rebuilt equations
-----------------
Measurements, eqs. (1)-(2): in-phase and quadrature components relative to a reference
oscillator, taken at t_k = t_{k-1} + dt_k, written as one complex sample::

    y(k) = A sin(w t_k + phi) + n_i(k),  z(k) = A cos(w t_k + phi) + n_q(k)
    c(k) = z(k) + j y(k) = A e^{j(w t_k + phi)} + n(k),   n = n_q + j n_i      (1)-(2)

(w = omega_d, the offset between the signal and the reference.) Taylor expansion around
t_{k-1}, eq. (3): ``sin(w t_{k-1} + phi + w dt_k) = sum_m (w dt_k)^m / m! sin(w t_{k-1} + phi
+ m pi/2)``, and the same for cos, give the differential model, eqs. (4)-(7)::

    v(k) = c(k) - c(k-1) = (e^{j w dt_k} - 1) c(k-1) + xi(k)                      (4)
    xi(k) = n(k) - e^{j w dt_k} n(k-1)                                           (5)
    v(k) = x(k)' theta + xi(k) + O((w dt_k)^{n+1} / (n+1)!)                      (6)
    theta = (w, w^2, ..., w^n),  x_m(k) = (j dt_k)^m / m! c(k-1)                 (7)

i.e. two real equations per sample, in-phase ``y(k)-y(k-1) = dt z w - dt^2/2 y w^2 - dt^3/6
z w^3 + ...`` and quadrature ``z(k)-z(k-1) = -dt y w - dt^2/2 z w^2 + dt^3/6 y w^3 + ...``
(y, z at k-1). With dt_k constant the columns of w and w^3 (and of w^2 and w^4) are
proportional: the information matrix has rank 2 (Section 4). Nonuniform cyclic sampling
(Section 5) cycles dt_k through ceil(n/2) distinct values (here dt (1 - j s), j = 0, 1, ...,
s = ``cycle_spacing``, the paper's T, 0.9 T, 0.8 T).

Frequency derivative, eqs. (24)-(25): with ``w(t) = w0 + lam0 t`` the phase increment is
``alpha_k = w0 dt_k + lam0 g_k``, ``g_k = (t_k^2 - t_{k-1}^2) / 2``, and ``c(k) = e^{j alpha_k}
c(k-1) + ...``, so::

    v(k) = sum_{m=1..n} (j alpha_k)^m / m! c(k-1) + xi(k)
         = sum_{a+b=m<=n} [j^m C(m,b)/m! dt_k^a g_k^b c(k-1)] w0^a lam0^b + xi(k)  (25)

theta holds every monomial ``w0^a lam0^b`` (n = 2: w0, lam0, w0^2, w0 lam0, lam0^2: the
paper's "(w dt)^3 and higher negligible"). Times are counted from a time origin that is
moved to the present at every re-centring (below).

Least squares with exponential data weighting lam, eq. (8), in recursive form (12)::

    P(k) = [P(k-1) - P x x' P / (lam + x' P x)] / lam,  theta^(k) = theta^(k-1) + P(k) x e(k)

(each complex sample is two real updates; lam applied once per sample).

Extended least squares, eqs. (11)-(13). The coloured noise is a moving average of n,
``xi(k) = D(k, z^-1) n(k)`` with ``D = 1 - e^{j w dt_k} z^-1`` (11) (as 2x2 real:
D11 = D22 = 1 - cos(w dt) z^-1, D12 = -D21 = -sin(w dt) z^-1). With E^_k = 1 + sum_p r_p
theta^_p (the estimated ``e^{j w dt_k}``, normalised to |E^| = 1)::

    v_bar(k) = v(k) + (E^_k - r1) n^(k-1),   e(k) = v_bar(k) - x(k)' theta^(k-1)     (12)
    n^(k) = v(k) + rho E^_k n^(k-1) - x(k)' theta^(k)                               (13)

r1 = 0 is the paper's white-noise case (v_bar = v + E^ n^). r1 = lag-1 correlation of the
(oversampled, hence coloured) noise removes only the part of xi correlated with the
regressor c(k-1), as the paper's Section 5 does ("the remaining measurements are only used
for the estimate of the n(k-1) term ... so as to eliminate it"); with the demodulator's
low-pass r1 is computed from its impulse response. rho < 1 is the paper's passivity
artifice (an independent noise added for estimating n^ turns, by spectral factorisation,
the unit-circle root of D into rho): (13) is then ``n^ = c - s^``, ``s^(k) = E^ [rho s^(k-1) +
(1 - rho) c(k-1)]``. The first ``ls_start`` samples are plain least squares (Section 3).

Oversampling, eq. (14): ideal low-pass noise of bandwidth B_N has ``R(tau) = sigma^2
sin(2 pi B_N tau) / (2 pi B_N tau)``; at dt = T_sN / M (T_sN = 1 / (2 B_N)),
``E[(n(k) - n(k-1))^2] = 2 sigma^2 (1 - sinc(1/M))``: 0.033 sigma^2 at M = 10 as the paper
says; at M = 5 it is 0.129 sigma^2 (the paper's 0.065 is 1 - sinc(1/5), without the 2).

Error covariance, eq. (19): ``Cov(theta~) = sigma^2 P``; with weighting, sigma^2 P / (1 + lam).
The reported ``frequency_std_hz`` is that, with sigma^2 the weighted a-priori error power.

Phase and amplitude, eqs. (21)-(23): referred to the end of the data, ``c(j) =
e^{-j w (t_k - t_j)} a(k) + n(j)`` with ``a(k) = A e^{j phi(t_k)} = q + j p`` (21)-(22),
estimated by exponentially weighted least squares with w replaced by w^; recursively
``a^(k) = e^{j alpha^_k} a^(k-1) + (c(k) - e^{j alpha^_k} a^(k-1)) / S(k)``,
``S(k) = lam_a S(k-1) + 1``; then ``A^ = |a^| = sqrt(p^2 + q^2)``, ``phi^ = atan2(p, q)`` (23).

Re-centring (Sections 7 and 10: "a periodic adjustment of the reference oscillator
frequency by the estimate", so that the truncation error of (6) vanishes): every
``recenter_every`` decimated samples, once confident (std below the threshold), the
reference moves by ``dw = w^(t_k)`` (and its ramp by ``dl = lam0^`` when lam0^ stands 3 sigma
out of its noise) and the time origin to t_k. theta is
re-expressed exactly: ``w' = w + lam0 Delta - dw``, ``lam0' = lam0 - dl`` make every monomial
``w'^a lam0'^b`` an affine function of the old ones, ``theta' = T theta + b0``, ``P' = T P T'``.

Real input (this module's front end)
------------------------------------
A real channel ``x = B + A sin(psi + phi_d)`` is mixed with the reference oscillator
(phase psi, frequency w_ref, ramp lam_ref), ``m = 2j (x - B^) e^{-j psi}``, and low-passed
(4th-order Butterworth, bandwidth B_N = ``bandwidth_hz`` = Omega_d / 2 pi), so that
``LPF(m) = A e^{j phi_d} = c``; B^ is the same low-pass applied to x. c is decimated every
``round(fs / (2 B_N M))`` input samples (M = ``oversampling``, Section 5), cycled as above
when n > 2. When the reference is re-centred, the low-pass state is moved to the new
frequency (the steady state of a DF2T biquad for ``X z^n`` is ``z1 = (H - b0) X z``,
``z2 = (b2 - a2 H) X``), so that the filter output continues as if the reference had always
been there. Outputs are compensated for the low-pass response H at the estimated offset
and held between decimated samples with the phase advanced at the estimated frequency:
at every input sample ``frequency = (w_ref + w^ + lam0^ s) / 2 pi``, ``phase = psi + arg(a^ / H)
+ w^ s + lam0^ s^2 / 2`` (s = time since the last decimated sample), ``rocof_hz_per_s =
(lam_ref + lam0^) / 2 pi`` (NaN without ``rocof_model``).

I/Q input (``input = "iq"``: the paper's own setting)
---------------------------------------------------
A channel whose blocks carry two columns, the in-phase ``y`` (column 0) and the quadrature
``z`` (column 1) of eqs. (1)-(2), measured against an external oscillator at
``nominal_frequency_hz`` (0 for a baseband signal, as in Section 10), skips the demodulator:
``c = z + j y`` is taken every ``round(fs / (2 B_N M))`` input samples (cycled as above when
n > 2: the paper's T, 0.9 T come from decimating a uniform stream) and rotated by a digital
reference oscillator, which re-centring moves exactly as the analogue one (within
``tracking_range_hz`` of the external one). ``bandwidth_hz`` is B_N, the bound on the offset
(the I/Q front end's bandwidth, Omega_d / 2 pi); r1 defaults to ``sinc(1/M)``, the ideal
low-pass noise of eq. (14) (``noise_correlation = 0`` for white noise, eq. 11's model). Outputs:
``frequency_hz = nominal + (w_ref + w^ + lam0^ s) / 2 pi``, ``phase_rad`` the phase of the pair
(``y = A sin(phase)``, relative to the external oscillator), ``offset`` 0 (the model has none),
``rocof_hz_per_s`` as above; ``residual_rms`` is the in-phase column's one-step prediction error.
The column count must match ``input`` (InputError ``shape_mismatch`` otherwise). Through the
registry this reproduces the offline Section 10 runs (tests/test_differential_rls.py,
``test_served_*``).

Internally times are in units of T0 (the longest decimated interval) and every equation
is divided by the RMS amplitude of c (weighted with lam^4, taken before c(k-1) so that the
weight is independent of the equation's own noise, and never below |c(k-1)| / 2), so that P
is scale-free. Safeguards (not in the paper): no forgetting while c carries no information
(zero input); a signal 60 dB below its mean power is absent (NaN, no learning; back at 40 dB,
hysteresis against the low-pass ringing); when it comes back, or jumps 20 dB, the core waits
for the low-pass to settle and restarts with theta^ as prior; theta^ is reset if it leaves
|w dt| < pi or goes non-finite; ELS runs only while the offset estimate is within the
band (beyond it the residual is truncation error and the whitening feedback ran away).
sigma^2 for eq. (19) is the a-priori error power weighted with lam^4, so that a transient
is forgotten 4x faster than theta. ``converged`` = at least 2p updates,
``frequency_std_hz < convergence_rel_std * bandwidth_hz`` and |offset| within the bandwidth.

Deviations: the block-Hankel fast solution (9)-(10) is not needed by the recursive form;
the subsequence algorithm (15)-(18) is replaced by the r1-weighted whitening above; the
frequency smoother of Section 10 is replaced by re-centring. docs/estimators/differential-rls.md
has the measured figures beside the paper's.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator
from scipy import signal as _sig

from sinewatch.estimators import register
from sinewatch.estimators.bank import register_bank
from sinewatch.estimators.base import Estimator, EstimatorParams, Track, kernel, track_from_columns
from sinewatch.schemas.errors import InputError, ParameterError

TWO_PI = 2.0 * math.pi

# ---- layout of the state vectors (module constants are compile-time constants in numba) ----
# core: the baseband estimator (shared by the real-input kernel and the I/Q kernel)
C_PREV_RE, C_PREV_IM = 0, 1  # c(k-1)
NH_RE, NH_IM = 2, 3  # white-noise estimate n^(k-1), eq. (13)
A_RE, A_IM = 4, 5  # complex amplitude a^(k) = A e^{j phi(t_k)}, eqs. (21)-(23)
S_A = 6  # sum of the phase-stage weights
PW, PW_N = 7, 8  # exponentially weighted power of c (normaliser)
SIG2, SIG2_N = 9, 10  # exponentially weighted a-priori error power (normalised units)
TAU = 11  # time since the time origin of the derivative model, in units of T0
COUNT = 12  # decimated steps taken
SINCE_REBASE = 13  # decimated steps since the last re-centring / time rebase
HAS_PREV = 14  # c(k-1) exists
HOLD = 15  # decimated samples still to skip after a restart (the low-pass is settling)
ABSENT = 16  # 1 while the signal is 60 dB below its mean power (it stopped)
INBAND = 17  # 1 while the estimate is valid and within the low-pass band (enables ELS)
CORE_SIZE = 18

# consts (float64), shared by both kernels
K_FS, K_T0, K_LAM, K_LAM_A, K_RHO, K_LS_START, K_P0, K_TRACE_MAX = 0, 1, 2, 3, 4, 5, 6, 7
K_W_NOM, K_W_RANGE, K_MIN_AMP, K_CONV_STD, K_W_BB_MAX = 8, 9, 10, 11, 12
K_REBASE_EVERY, K_ELS, K_DERIV, K_RECENTER, K_WARM, K_R1, K_HOLD = 13, 14, 15, 16, 17, 18, 19
N_CONSTS = 20

# front end (real-input kernel)
F_PSI, F_WREF, F_LREF, F_B = 0, 1, 2, 3  # reference phase (rad), frequency (rad/s), ramp (rad/s^2), offset
F_ZI = 4  # 3 channels x 2 biquads x 2 delays = 12 values: offset, in-phase-mix re, im
F_SNAP_W, F_SNAP_L, F_SNAP_PH, F_SNAP_A = 16, 17, 18, 19  # snapshot at the last decimated step
F_SNAP_VALID, F_SNAP_CONV, F_SNAP_STD, F_SINCE = 20, 21, 22, 23
F_LO_RE, F_LO_IM, F_LS_RE, F_LS_IM = 24, 25, 26, 27  # e^{j psi} and its per-sample step
F_BB_RE, F_BB_IM, F_BS_RE, F_BS_IM = 28, 29, 30, 31  # predicted baseband phasor and its step
FE_SIZE = 32


def monomial_table(n: int, derivative: bool) -> np.ndarray:
    """Rows (m, b, C(m, b) / m!) of the parameter vector: theta_p = w^(m-b) lam^b."""
    rows = [(1, 0, 1.0)]
    if derivative:
        rows.append((1, 1, 1.0))
    for m in range(2, n + 1):
        for b in range((m if derivative else 0) + 1):
            rows.append((m, b, math.comb(m, b) / math.factorial(m)))
    return np.array(rows, dtype=np.float64)


def _multinomials(nmax: int) -> np.ndarray:
    """M[a, j, l] = a! / (i! j! l!), i = a - j - l, as the float expression computes it (exact
    integers here); M[b, s, 0] is C(b, s). A table, so that re-centring divides nothing."""
    f = [float(math.factorial(k)) for k in range(nmax + 1)]
    m = np.zeros((nmax + 1, nmax + 1, nmax + 1))
    for a in range(nmax + 1):
        for j in range(a + 1):
            for ll in range(a - j + 1):
                m[a, j, ll] = f[a] / (f[a - j - ll] * f[j] * f[ll])
    return m


_MULTINOMIAL = _multinomials(6)  # n_terms <= 6


@kernel(refcount=False)
def regressor_coefficients(u: float, g: float, tab: np.ndarray, rr: np.ndarray, ri: np.ndarray) -> None:
    """r_p such that e^{j alpha} - 1 = sum_p r_p theta_p + O(alpha^(n+1)), alpha = w u + lam g.

    Eq. (7) (and (25) with the derivative): r_p = j^m C(m, b) / m! * u^(m-b) * g^b.
    """
    for q in range(tab.shape[0]):
        m = int(tab[q, 0])
        b = int(tab[q, 1])
        mag = tab[q, 2]
        for _ in range(m - b):  # integer powers by products (pow() is slow)
            mag *= u
        for _ in range(b):
            mag *= g
        mm = m & 3
        if mm == 0:
            rr[q] = mag
            ri[q] = 0.0
        elif mm == 1:
            rr[q] = 0.0
            ri[q] = mag
        elif mm == 2:
            rr[q] = -mag
            ri[q] = 0.0
        else:
            rr[q] = 0.0
            ri[q] = -mag


@kernel(refcount=False)
def _rls_scalar(P: np.ndarray, theta: np.ndarray, x: np.ndarray, y: float, f: float, px: np.ndarray) -> None:
    """One scalar RLS update with forgetting f (eq. 12): P <- (P - P x x' P / (f + x' P x)) / f."""
    p = theta.shape[0]
    den = f
    e = y
    for a in range(p):
        s = 0.0
        for b in range(p):
            s += P[a, b] * x[b]
        px[a] = s
        den += x[a] * s
        e -= x[a] * theta[a]
    if not (den > 0.0):
        return
    ge = e / den
    inv_f = 1.0 / f
    for a in range(p):
        theta[a] += px[a] * ge
        pa = px[a] / den
        for b in range(a, p):
            v = (P[a, b] - pa * px[b]) * inv_f
            P[a, b] = v
            P[b, a] = v


@kernel(inline="always")
def _rls_pair5(
    P: np.ndarray, theta: np.ndarray, xr: np.ndarray, yr: float, f: float, xi: np.ndarray, yi: float
) -> None:
    """The two scalar updates of :func:`core_step` (xr with forgetting f, then xi without),
    as :func:`_rls_scalar` computes them, for p = 5 (n = 2 with the derivative model, the
    default): P (symmetric: its upper triangle), theta and x in registers; the same
    operations in the same order, hence the same bits."""
    p00, p01, p02, p03, p04, p11, p12, p13, p14, p22, p23, p24, p33, p34, p44 = (
        P[0, 0], P[0, 1], P[0, 2], P[0, 3], P[0, 4], P[1, 1], P[1, 2], P[1, 3], P[1, 4], P[2, 2], P[2, 3], P[2, 4], P[3, 3], P[3, 4], P[4, 4],
    )  # fmt: skip
    t0, t1, t2, t3, t4 = theta[0], theta[1], theta[2], theta[3], theta[4]
    x0, x1, x2, x3, x4 = xr[0], xr[1], xr[2], xr[3], xr[4]
    den = f
    e = yr
    s = 0.0
    s += p00 * x0
    s += p01 * x1
    s += p02 * x2
    s += p03 * x3
    s += p04 * x4
    q0 = s
    den += x0 * s
    e -= x0 * t0
    s = 0.0
    s += p01 * x0
    s += p11 * x1
    s += p12 * x2
    s += p13 * x3
    s += p14 * x4
    q1 = s
    den += x1 * s
    e -= x1 * t1
    s = 0.0
    s += p02 * x0
    s += p12 * x1
    s += p22 * x2
    s += p23 * x3
    s += p24 * x4
    q2 = s
    den += x2 * s
    e -= x2 * t2
    s = 0.0
    s += p03 * x0
    s += p13 * x1
    s += p23 * x2
    s += p33 * x3
    s += p34 * x4
    q3 = s
    den += x3 * s
    e -= x3 * t3
    s = 0.0
    s += p04 * x0
    s += p14 * x1
    s += p24 * x2
    s += p34 * x3
    s += p44 * x4
    q4 = s
    den += x4 * s
    e -= x4 * t4
    if den > 0.0:
        ge = e / den
        inv_f = 1.0 / f
        t0 += q0 * ge
        pa = q0 / den
        p00 = (p00 - pa * q0) * inv_f
        p01 = (p01 - pa * q1) * inv_f
        p02 = (p02 - pa * q2) * inv_f
        p03 = (p03 - pa * q3) * inv_f
        p04 = (p04 - pa * q4) * inv_f
        t1 += q1 * ge
        pa = q1 / den
        p11 = (p11 - pa * q1) * inv_f
        p12 = (p12 - pa * q2) * inv_f
        p13 = (p13 - pa * q3) * inv_f
        p14 = (p14 - pa * q4) * inv_f
        t2 += q2 * ge
        pa = q2 / den
        p22 = (p22 - pa * q2) * inv_f
        p23 = (p23 - pa * q3) * inv_f
        p24 = (p24 - pa * q4) * inv_f
        t3 += q3 * ge
        pa = q3 / den
        p33 = (p33 - pa * q3) * inv_f
        p34 = (p34 - pa * q4) * inv_f
        t4 += q4 * ge
        pa = q4 / den
        p44 = (p44 - pa * q4) * inv_f
    x0, x1, x2, x3, x4 = xi[0], xi[1], xi[2], xi[3], xi[4]
    den = 1.0
    e = yi
    s = 0.0
    s += p00 * x0
    s += p01 * x1
    s += p02 * x2
    s += p03 * x3
    s += p04 * x4
    q0 = s
    den += x0 * s
    e -= x0 * t0
    s = 0.0
    s += p01 * x0
    s += p11 * x1
    s += p12 * x2
    s += p13 * x3
    s += p14 * x4
    q1 = s
    den += x1 * s
    e -= x1 * t1
    s = 0.0
    s += p02 * x0
    s += p12 * x1
    s += p22 * x2
    s += p23 * x3
    s += p24 * x4
    q2 = s
    den += x2 * s
    e -= x2 * t2
    s = 0.0
    s += p03 * x0
    s += p13 * x1
    s += p23 * x2
    s += p33 * x3
    s += p34 * x4
    q3 = s
    den += x3 * s
    e -= x3 * t3
    s = 0.0
    s += p04 * x0
    s += p14 * x1
    s += p24 * x2
    s += p34 * x3
    s += p44 * x4
    q4 = s
    den += x4 * s
    e -= x4 * t4
    if den > 0.0:
        ge = e / den
        inv_f = 1.0 / 1.0
        t0 += q0 * ge
        pa = q0 / den
        p00 = (p00 - pa * q0) * inv_f
        p01 = (p01 - pa * q1) * inv_f
        p02 = (p02 - pa * q2) * inv_f
        p03 = (p03 - pa * q3) * inv_f
        p04 = (p04 - pa * q4) * inv_f
        t1 += q1 * ge
        pa = q1 / den
        p11 = (p11 - pa * q1) * inv_f
        p12 = (p12 - pa * q2) * inv_f
        p13 = (p13 - pa * q3) * inv_f
        p14 = (p14 - pa * q4) * inv_f
        t2 += q2 * ge
        pa = q2 / den
        p22 = (p22 - pa * q2) * inv_f
        p23 = (p23 - pa * q3) * inv_f
        p24 = (p24 - pa * q4) * inv_f
        t3 += q3 * ge
        pa = q3 / den
        p33 = (p33 - pa * q3) * inv_f
        p34 = (p34 - pa * q4) * inv_f
        t4 += q4 * ge
        pa = q4 / den
        p44 = (p44 - pa * q4) * inv_f
    P[0, 0] = p00
    P[0, 1] = p01
    P[1, 0] = p01
    P[0, 2] = p02
    P[2, 0] = p02
    P[0, 3] = p03
    P[3, 0] = p03
    P[0, 4] = p04
    P[4, 0] = p04
    P[1, 1] = p11
    P[1, 2] = p12
    P[2, 1] = p12
    P[1, 3] = p13
    P[3, 1] = p13
    P[1, 4] = p14
    P[4, 1] = p14
    P[2, 2] = p22
    P[2, 3] = p23
    P[3, 2] = p23
    P[2, 4] = p24
    P[4, 2] = p24
    P[3, 3] = p33
    P[3, 4] = p34
    P[4, 3] = p34
    P[4, 4] = p44
    theta[0], theta[1], theta[2], theta[3], theta[4] = t0, t1, t2, t3, t4


@kernel(inline="always")
def _all_finite_sum(theta: np.ndarray, P: np.ndarray) -> bool:
    """Whether sum(theta) + sum(P), added in row order, is finite. Every entry finite and below
    1e300 in magnitude cannot overflow (checked row by row, independent chains); otherwise the
    sum itself decides, in the original order (NaN, Inf or an overflow: not finite)."""
    p = theta.shape[0]
    small = True
    for q in range(p):
        row = abs(theta[q]) < 1e300
        for r in range(p):
            row = row and abs(P[q, r]) < 1e300
        small = small and row
    if small:
        return True
    acc = 0.0
    for q in range(p):
        acc += theta[q]
        for r in range(p):
            acc += P[q, r]
    return math.isfinite(acc)


@kernel(refcount=False)
def core_step(
    cr: float,
    ci: float,
    u: float,
    core: np.ndarray,
    theta: np.ndarray,
    P: np.ndarray,
    tab: np.ndarray,
    consts: np.ndarray,
    rr: np.ndarray,
    ri: np.ndarray,
    xr: np.ndarray,
    xi: np.ndarray,
    px: np.ndarray,
) -> None:
    """One decimated step of the baseband estimator on c(k) = cr + j ci, dt_k = u T0.

    Differential model (4)-(7)/(25), extended least squares (12)-(13), phase/amplitude
    stage (21)-(23). Updates core, theta, P in place (the kernels pass copies).
    rr, ri, xr, xi, px are scratch vectors of length p.
    """
    p = theta.shape[0]
    lam = consts[K_LAM]
    lam4 = lam * lam * lam * lam
    c2 = cr * cr + ci * ci
    mean2 = core[PW] / core[PW_N] if core[PW_N] > 0.0 else 0.0
    if c2 < (1e-4 if core[ABSENT] != 0.0 else 1e-6) * mean2:
        # the signal stopped (60 dB below its mean power; it is back once 40 dB below the
        # decaying mean, a hysteresis against the low-pass ringing): nothing to learn, the
        # outputs are undefined until it comes back
        core[ABSENT] = 1.0
        core[PW] = lam4 * core[PW] + c2
        core[PW_N] = lam4 * core[PW_N] + 1.0
        core[C_PREV_RE] = cr
        core[C_PREV_IM] = ci
        return
    restart = core[ABSENT] != 0.0 or (core[PW_N] > 0.0 and c2 > 100.0 * mean2)
    if restart:
        # the signal comes back (or jumps 20 dB above its mean power): skip the low-pass
        # rise, then start afresh from there, keeping theta^ as the prior
        core[HOLD] = consts[K_HOLD]
        core[ABSENT] = 0.0
    if core[HAS_PREV] == 0.0 or restart or core[HOLD] > 0.0:
        if core[HOLD] > 0.0:
            core[HOLD] -= 1.0
        core[C_PREV_RE] = cr
        core[C_PREV_IM] = ci
        core[A_RE] = cr
        core[A_IM] = ci
        core[S_A] = 1.0
        core[NH_RE] = 0.0
        core[NH_IM] = 0.0
        core[PW] = c2
        core[PW_N] = 1.0
        core[SIG2] = 0.0
        core[SIG2_N] = 0.0
        core[COUNT] = 0.0
        core[HAS_PREV] = 1.0
        p0 = consts[K_P0]
        for q in range(p):
            for r in range(p):
                P[q, r] = p0 if q == r else 0.0
        return
    rho = consts[K_RHO]
    deriv = consts[K_DERIV] != 0.0
    tau = core[TAU]
    g = u * (tau + 0.5 * u) if deriv else 0.0  # (tau_k^2 - tau_{k-1}^2) / 2, eq. (25)
    if p == 5 and deriv:  # n = 2 with the derivative model (the default), as the loop computes it
        rr[0], ri[0] = 0.0, 1.0 * u  # j w dt
        rr[1], ri[1] = 0.0, 1.0 * g  # j lam g
        rr[2], ri[2] = -(0.5 * u * u), 0.0  # -(w dt)^2 / 2
        rr[3], ri[3] = -(1.0 * u * g), 0.0  # -w lam dt g
        rr[4], ri[4] = -(0.5 * g * g), 0.0  # -(lam g)^2 / 2
    else:
        regressor_coefficients(u, g, tab, rr, ri)
    # E^_k = 1 + sum r_p theta^_p(k-1): the estimated one-step rotation e^{j w dt}, eqs. (4), (11)
    er = 1.0
    ei = 0.0
    for q in range(p):
        er += rr[q] * theta[q]
        ei += ri[q] * theta[q]
    cpr = core[C_PREV_RE]
    cpi = core[C_PREV_IM]
    vr = cr - cpr  # v(k) = c(k) - c(k-1), eq. (4)
    vi = ci - cpi
    nr = core[NH_RE]
    ni = core[NH_IM]
    # E^ normalised to |E^| = 1 (it estimates e^{j w dt}): keeps the recursion (13) stable
    emag = math.hypot(er, ei)
    if emag > 0.0 and math.isfinite(emag):
        eur = er / emag
        eui = ei / emag
    else:
        eur = 1.0
        eui = 0.0
    # rho E^ n^(k-1): the damped noise recursion of eq. (13)
    tr_ = rho * (eur * nr - eui * ni)
    ti_ = rho * (eur * ni + eui * nr)
    # (E^ - r1) n^(k-1): the part of xi(k) = n(k) - E n(k-1) (eq. 11) correlated with the
    # regressor c(k-1); r1 = lag-1 correlation of n (0: white noise, the paper's eq. 12)
    r1 = consts[K_R1]
    # ELS after a plain least-squares start, and only while that estimate lies in the band:
    # the whitening feeds the residual back, which ran away on an offset beyond the low-pass
    # (where the truncation error of (6), not noise, dominates the residual)
    use_els = consts[K_ELS] != 0.0 and core[COUNT] >= consts[K_LS_START] and core[INBAND] != 0.0
    if use_els:
        vbr = vr + (eur - r1) * nr - eui * ni  # modified measurement, eq. (12)
        vbi = vi + (eur - r1) * ni + eui * nr
    else:
        vbr = vr
        vbi = vi
    # normaliser: the mean power of c before c(k-1) (so that the weight does not depend on
    # the noise in this equation), never below |c(k-1)|^2 / 4 so that no equation (a rising
    # signal) weighs more than 4 steady ones (|x| <= 2 |r|)
    cp2 = cpr * cpr + cpi * cpi
    m2 = max(core[PW] / core[PW_N], 0.25 * cp2) if core[PW_N] > 0.0 else cp2
    core[PW] = lam4 * core[PW] + cp2  # mean power, lam^4: follows amplitude steps
    core[PW_N] = lam4 * core[PW_N] + 1.0
    if m2 > 1e-300 and math.isfinite(m2):
        sc = 1.0 / math.sqrt(m2)  # equations divided by the RMS amplitude: scale-free P
        for q in range(p):
            xr[q] = (rr[q] * cpr - ri[q] * cpi) * sc  # x(k): regressor of eq. (6)-(7)
            xi[q] = (rr[q] * cpi + ri[q] * cpr) * sc
        yr = vbr * sc
        yi = vbi * sc
        e0r = yr
        e0i = yi
        for q in range(p):
            e0r -= xr[q] * theta[q]
            e0i -= xi[q] * theta[q]
        # a-priori error power, weighted with lam^4 (4x shorter memory than theta^): the
        # noise level for eq. (19), quick to forget a transient (a step, a restart)
        core[SIG2] = lam4 * core[SIG2] + 0.5 * (e0r * e0r + e0i * e0i)
        core[SIG2_N] = lam4 * core[SIG2_N] + 1.0
        tr = 0.0
        for q in range(p):
            tr += P[q, q]
        # forget only while the regressor carries information (|c(k-1)|^2 / mean power)
        # and P is sane: P stays finite on zero input and on a signal that stops
        excited = cp2 > 1e-4 * m2
        f = lam if (excited and tr < consts[K_TRACE_MAX]) else 1.0
        if p == 5:  # the default model, unrolled (the same arithmetic)
            _rls_pair5(P, theta, xr, yr, f, xi, yi)
        else:
            _rls_scalar(P, theta, xr, yr, f, px)
            _rls_scalar(P, theta, xi, yi, 1.0, px)
        # never let the state go non-finite or the estimate leave the decimated band
        # (|w dt| < pi): restart the parameter estimate
        if not (abs(theta[0]) < math.pi and _all_finite_sum(theta, P)):
            p0 = consts[K_P0]
            for q in range(p):
                theta[q] = 0.0
                for r in range(p):
                    P[q, r] = p0 if q == r else 0.0
            core[SIG2] = 0.0
            core[SIG2_N] = 0.0
            core[NH_RE] = 0.0
            core[NH_IM] = 0.0
            tr_ = 0.0
            ti_ = 0.0
    # n^(k) = v(k) + rho E^ n^(k-1) - x(k)' theta^(k): noise estimate, eq. (13) damped by rho,
    # i.e. n^(k) = c(k) - s^(k) with s^(k) = E^ [rho s^(k-1) + (1 - rho) c(k-1)]
    e1r = 0.0
    e1i = 0.0
    for q in range(p):
        e1r += rr[q] * theta[q]
        e1i += ri[q] * theta[q]
    core[NH_RE] = vr + tr_ - (e1r * cpr - e1i * cpi)
    core[NH_IM] = vi + ti_ - (e1r * cpi + e1i * cpr)
    # phase / amplitude stage, eqs. (21)-(23): exponentially weighted LS of a = A e^{j phi(t_k)},
    # past samples rotated to t_k by the estimated phase increment alpha^ = w^ u + lam^ g
    alpha = theta[0] * u + (theta[1] * g if deriv else 0.0)
    car = math.cos(alpha)
    sar = math.sin(alpha)
    ar = core[A_RE]
    ai = core[A_IM]
    par = car * ar - sar * ai
    pai = car * ai + sar * ar
    sa = consts[K_LAM_A] * core[S_A] + 1.0
    core[S_A] = sa
    core[A_RE] = par + (cr - par) / sa
    core[A_IM] = pai + (ci - pai) / sa
    core[TAU] = tau + u
    core[COUNT] += 1.0
    core[SINCE_REBASE] += 1.0
    core[C_PREV_RE] = cr
    core[C_PREV_IM] = ci


@kernel(inline="always")
def _hypot_positive(a: float, b: float) -> bool:
    """``math.hypot(a, b) > 0.0`` without the hypot (~25 ns): infinite if either is, else NaN if
    either is, else positive iff either is non-zero (hypot of subnormals is not 0)."""
    if math.isinf(a) or math.isinf(b):
        return True
    if math.isnan(a) or math.isnan(b):
        return False
    return a != 0.0 or b != 0.0


@kernel(refcount=False)
def core_status(
    core: np.ndarray, theta: np.ndarray, P: np.ndarray, consts: np.ndarray
) -> tuple[float, float, float, bool, bool, bool, float]:
    """(w_bb rad/T0, lam_bb rad/T0^2, std of w_bb rad/T0, valid, confident, converged,
    lam_bb if significant else 0).

    confident: enough updates and std < the threshold (allows re-centring); converged:
    confident and the offset within the low-pass band (valid and in band is recorded in
    core[INBAND]: it allows ELS)."""
    deriv = consts[K_DERIV] != 0.0
    tau = core[TAU]
    w = theta[0] + (theta[1] * tau if deriv else 0.0)
    lam_bb = theta[1] if deriv else 0.0
    pww = P[0, 0]
    if deriv:
        pww += 2.0 * tau * P[0, 1] + tau * tau * P[1, 1]
    s2 = core[SIG2] / core[SIG2_N] if core[SIG2_N] > 0.0 else math.inf
    var = s2 * max(pww, 0.0) / (1.0 + consts[K_LAM])  # Cov = sigma^2 P / (1 + lam), cf. eq. (19)
    std = math.sqrt(var)
    valid = core[COUNT] >= 2.0 and math.isfinite(w) and _hypot_positive(core[A_RE], core[A_IM]) and core[ABSENT] == 0.0
    confident = valid and core[COUNT] >= max(2.0 * theta.shape[0], 4.0) and std < consts[K_CONV_STD]
    inband = abs(w) <= consts[K_W_BB_MAX]
    core[INBAND] = 1.0 if (valid and inband) else 0.0
    conv = confident and inband
    # the ramp is handed to the reference only once it stands out of its own noise (3 sigma):
    # an early, noisy lam^ moved the reference needlessly during acquisition
    lam_sig = lam_bb if (deriv and lam_bb * lam_bb > 9.0 * s2 * max(P[1, 1], 0.0) / (1.0 + consts[K_LAM])) else 0.0
    return w, lam_bb, std, valid, confident, conv, lam_sig


@kernel
def transform_scratch(tab: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Index table idx[a, b] of w^a lam^b and scratch arrays (T, b0, work) for
    :func:`recenter_transform`."""
    p = tab.shape[0]
    nmax = 0
    for q in range(p):
        nmax = max(nmax, int(tab[q, 0]))
    idx = -np.ones((nmax + 1, nmax + 1), dtype=np.int64)
    for q in range(p):
        idx[int(tab[q, 0]) - int(tab[q, 1]), int(tab[q, 1])] = q
    return idx, np.zeros((p, p)), np.zeros(p), np.zeros((p, p + 1))


@kernel
def working_core(
    core_in: np.ndarray, theta_in: np.ndarray, P_in: np.ndarray, tab: np.ndarray
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
    np.ndarray, np.ndarray, np.ndarray, np.ndarray,
]:  # fmt: skip
    """Copies of the baseband estimator's state (core, theta, P: a kernel never writes its
    inputs), the scratch vectors of :func:`core_step` (rr, ri, xr, xi, px) and those of
    :func:`recenter_transform` (idx, T, b0, work)."""
    p = theta_in.shape[0]
    rr, ri, xr, xi, px = np.zeros(p), np.zeros(p), np.zeros(p), np.zeros(p), np.zeros(p)
    idx, T, b0, work = transform_scratch(tab)
    return core_in.copy(), theta_in.copy(), P_in.copy(), rr, ri, xr, xi, px, idx, T, b0, work


@kernel(inline="always")
def _ipow(x: float, k: int) -> float:
    r = 1.0
    for _ in range(k):
        r *= x
    return r


@kernel(refcount=False)
def recenter_transform(
    theta: np.ndarray,
    P: np.ndarray,
    tab: np.ndarray,
    idx: np.ndarray,
    delta: float,
    dw: float,
    dl: float,
    T: np.ndarray,
    b0: np.ndarray,
    work: np.ndarray,
) -> None:
    """Re-express theta (monomials w^a lam^b) after moving the time origin by ``delta``
    (T0 units) and the reference by ``dw`` (rad/T0) and ``dl`` (rad/T0^2):

        w' = w + lam delta - dw,  lam' = lam - dl
        theta'_q = (w')^a (lam')^b = b0_q + sum_r T_qr theta_r   (exact polynomial identity)
        P' = T P T'

    by the multinomial expansion (w + delta lam - dw)^a (lam - dl)^b = sum a!/(i! j! l!)
    C(b, s) delta^j (-dw)^l (-dl)^(b-s) w^i lam^(j+s), i + j + l = a. ``idx[a, b]`` is the
    index of w^a lam^b; T, b0, work are scratch.
    """
    p = theta.shape[0]
    for q in range(p):
        b0[q] = 0.0
        for r in range(p):
            T[q, r] = 0.0
    for q in range(p):
        m = int(tab[q, 0])
        bq = int(tab[q, 1])
        aq = m - bq
        for j in range(aq + 1):
            for ll in range(aq - j + 1):
                i = aq - j - ll
                ca = _MULTINOMIAL[aq, j, ll] * _ipow(delta, j) * _ipow(-dw, ll)
                if ca == 0.0:
                    continue
                for s_ in range(bq + 1):
                    cb = _MULTINOMIAL[bq, s_, 0] * _ipow(-dl, bq - s_)
                    v = ca * cb
                    if v == 0.0:
                        continue
                    d = j + s_
                    if i == 0 and d == 0:
                        b0[q] += v
                    else:
                        r = idx[i, d]
                        if r >= 0:
                            T[q, r] += v
    for q in range(p):  # theta <- b0 + T theta
        acc = b0[q]
        for r in range(p):
            acc += T[q, r] * theta[r]
        work[q, 0] = acc
    for q in range(p):
        theta[q] = work[q, 0]
    for q in range(p):  # work = T P
        for r in range(p):
            acc = 0.0
            for t in range(p):
                acc += T[q, t] * P[t, r]
            work[q, 1 + r] = acc
    for q in range(p):  # P <- (T P) T'
        for r in range(q, p):
            acc = 0.0
            for t in range(p):
                acc += work[q, 1 + t] * T[r, t]
            P[q, r] = acc
            P[r, q] = acc


@kernel
def _biquads_steady(x: float, sos: np.ndarray, zi: np.ndarray, off: int) -> None:
    """Delays of the biquad cascade in steady state for a constant input x."""
    y = x
    for s in range(2):
        b0 = sos[s, 0]
        b1 = sos[s, 1]
        b2 = sos[s, 2]
        a1 = sos[s, 4]
        a2 = sos[s, 5]
        out = y * (b0 + b1 + b2) / (1.0 + a1 + a2)
        zi[off + 2 * s + 1] = b2 * y - a2 * out
        zi[off + 2 * s] = out - b0 * y
        y = out


@kernel(inline="always")
def _bq(
    x: float, b0: float, b1: float, b2: float, a1: float, a2: float, z1: float, z2: float
) -> tuple[float, float, float]:
    """One DF2T biquad step: (y, z1', z2')."""
    y = b0 * x + z1
    return y, b1 * x - a1 * y + z2, b2 * x - a2 * y


@kernel
def _biquads(x: float, sos: np.ndarray, zi: np.ndarray, off: int) -> float:
    """Two cascaded DF2T biquads (:func:`_bq`) on one channel; zi[off:off+4] are the delays.
    The kernel runs the same steps on register copies of the delays."""
    y = x
    for s in range(2):
        j = off + 2 * s
        y, zi[j], zi[j + 1] = _bq(y, sos[s, 0], sos[s, 1], sos[s, 2], sos[s, 4], sos[s, 5], zi[j], zi[j + 1])
    return y


@kernel(refcount=False)
def rebase(
    core: np.ndarray,
    theta: np.ndarray,
    P: np.ndarray,
    tab: np.ndarray,
    consts: np.ndarray,
    dw: float,
    dl: float,
    idx: np.ndarray,
    T: np.ndarray,
    b0: np.ndarray,
    work: np.ndarray,
) -> None:
    """Move the time origin to t_k and the reference by (dw, dl); see recenter_transform."""
    deriv = consts[K_DERIV] != 0.0
    delta = core[TAU] if deriv else 0.0
    if delta != 0.0 or dw != 0.0 or dl != 0.0:
        recenter_transform(theta, P, tab, idx, delta, dw, dl if deriv else 0.0, T, b0, work)
    core[TAU] = 0.0
    core[SINCE_REBASE] = 0.0


@kernel
def _wrap(ph: float) -> float:
    while ph > math.pi:
        ph -= TWO_PI
    while ph <= -math.pi:
        ph += TWO_PI
    return ph


@kernel
def iq_kernel(
    cre: np.ndarray,
    cim: np.ndarray,
    u: np.ndarray,
    core_in: np.ndarray,
    theta_in: np.ndarray,
    P_in: np.ndarray,
    ref_in: np.ndarray,
    tab: np.ndarray,
    consts: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The paper's own setting: in-phase/quadrature samples c(k) = z(k) + j y(k) taken at
    intervals dt_k = u_k T0. Re-centring rotates c by a digital reference (psi2, w2, l2).
    Returns per step (w^ rad/T0, lam^ rad/T0^2, A^, phi^, std, converged) and the state."""
    core, theta, P, rr, ri, xr, xi, px, idx, T, b0, work = working_core(core_in, theta_in, P_in, tab)
    ref = ref_in.copy()
    n = cre.shape[0]
    out = np.empty((n, 6))
    recenter = consts[K_RECENTER] != 0.0
    for k in range(n):
        if k > 0:  # advance the digital reference over dt_k
            uk = u[k]
            ref[0] += ref[1] * uk + 0.5 * ref[2] * uk * uk
            ref[1] += ref[2] * uk
            ref[0] = math.pi - ((math.pi - ref[0]) % TWO_PI)
        c0 = math.cos(ref[0])
        s0 = math.sin(ref[0])
        cr = cre[k] * c0 + cim[k] * s0  # c e^{-j psi2}
        ci = cim[k] * c0 - cre[k] * s0
        core_step(cr, ci, u[k], core, theta, P, tab, consts, rr, ri, xr, xi, px)
        w, lb, std, valid, confident, conv, lsig = core_status(core, theta, P, consts)
        if core[SINCE_REBASE] >= consts[K_REBASE_EVERY]:
            dw = w if (recenter and confident) else 0.0
            dl = lsig if (recenter and confident) else 0.0
            rebase(core, theta, P, tab, consts, dw, dl, idx, T, b0, work)
            ref[1] += dw
            ref[2] += dl
            w, lb, std, valid, confident, conv, lsig = core_status(core, theta, P, consts)
        out[k, 0] = w + ref[1] if valid else np.nan
        out[k, 1] = lb + ref[2] if valid else np.nan
        out[k, 2] = math.hypot(core[A_RE], core[A_IM]) if valid else np.nan
        out[k, 3] = _wrap(math.atan2(core[A_IM], core[A_RE]) + ref[0]) if valid else np.nan
        out[k, 4] = std
        out[k, 5] = 1.0 if conv else 0.0
    return out, core, theta, P, ref


@kernel(inline="always")
def _cis_small(a: float) -> complex:
    """e^{j a} for a tiny angle (a chirp's per-sample step change), to 1e-22 relative."""
    a2 = a * a
    return complex(1.0 - 0.5 * a2, a * (1.0 - a2 / 6.0))


@kernel(inline="always")
def _stage_response(sos: np.ndarray, s: int, zc: complex) -> complex:
    """H_s(z) of biquad s at z = zc (complex)."""
    return _stage_response_inv(sos, s, 1.0 / zc)


@kernel(inline="always")
def _stage_response_inv(sos: np.ndarray, s: int, zi1: complex) -> complex:
    """H_s(z) of biquad s given zi1 = 1 / z (shared by the stages: one complex division)."""
    zi2 = zi1 * zi1
    h: complex = (sos[s, 0] + sos[s, 1] * zi1 + sos[s, 2] * zi2) / (1.0 + sos[s, 4] * zi1 + sos[s, 5] * zi2)
    return h


@kernel(refcount=False)
def lowpass_response(sos: np.ndarray, om: float) -> complex:
    """H(e^{j om}) of the biquad cascade, om in rad per input sample."""
    zi1 = 1.0 / complex(math.cos(om), math.sin(om))
    return _stage_response_inv(sos, 0, zi1) * _stage_response_inv(sos, 1, zi1)


@kernel(refcount=False)
def _lowpass_retune(sos: np.ndarray, fe: np.ndarray, X: complex, om_old: float, om_new: float) -> None:
    """Move the tonal part of the demodulator's low-pass state from baseband frequency
    om_old to om_new (rad/sample), for a tone of phasor X at the current sample: the steady
    state of a DF2T biquad driven by X z^n is z1 = (H - b0) X z, z2 = (b2 - a2 H) X before
    the next sample. Used when the reference oscillator is re-centred, so that the low-pass
    output continues as if the reference had always been at the new frequency."""
    zo = complex(math.cos(om_old), math.sin(om_old))
    zn = complex(math.cos(om_new), math.sin(om_new))
    _retune_stages(sos, fe, X, zo, zn, _stage_response(sos, 0, zo), _stage_response(sos, 1, zo),
                   _stage_response(sos, 0, zn), _stage_response(sos, 1, zn))  # fmt: skip


@kernel(inline="always")
def _retune_stages(
    sos: np.ndarray, fe: np.ndarray, X: complex, zo: complex, zn: complex, ho0: complex, ho1: complex,
    hn0: complex, hn1: complex,
) -> None:  # fmt: skip
    """:func:`_lowpass_retune` given z = e^{j om} and the stages' responses there."""
    xo = X
    xn = X
    for s in range(2):
        ho = ho0 if s == 0 else ho1
        hn = hn0 if s == 0 else hn1
        d1 = (hn - sos[s, 0]) * xn * zn - (ho - sos[s, 0]) * xo * zo
        d2 = (sos[s, 2] - sos[s, 5] * hn) * xn - (sos[s, 2] - sos[s, 5] * ho) * xo
        fe[F_ZI + 4 + 2 * s] += d1.real
        fe[F_ZI + 8 + 2 * s] += d1.imag
        fe[F_ZI + 4 + 2 * s + 1] += d2.real
        fe[F_ZI + 8 + 2 * s + 1] += d2.imag
        xo = ho * xo
        xn = hn * xn


@kernel(refcount=False)
def _retune_responses(
    sos: np.ndarray, fe: np.ndarray, a_now: complex, om_old: float, om_new: float
) -> tuple[complex, complex]:
    """``h_old = H(om_old)``, ``h_new = H(om_new)`` (:func:`lowpass_response`) and
    :func:`_lowpass_retune` for the tone ``a_now / h_old``, each stage's response computed
    once for both (the same values, the same bits)."""
    zo = complex(math.cos(om_old), math.sin(om_old))
    zn = complex(math.cos(om_new), math.sin(om_new))
    zoi = 1.0 / zo
    zni = 1.0 / zn
    ho0 = _stage_response_inv(sos, 0, zoi)
    ho1 = _stage_response_inv(sos, 1, zoi)
    hn0 = _stage_response_inv(sos, 0, zni)
    hn1 = _stage_response_inv(sos, 1, zni)
    h_old = ho0 * ho1
    h_new = hn0 * hn1
    _retune_stages(sos, fe, a_now / h_old, zo, zn, ho0, ho1, hn0, hn1)
    return h_old, h_new


@kernel(inline="always")
def _demodulate(
    xi: float, b_prev: float, snap_valid: float, snap_a: float, lo_re: float, lo_im: float, bb_re: float, bb_im: float,
    s0b0: float, s0b1: float, s0b2: float, s0a1: float, s0a2: float,
    s1b0: float, s1b1: float, s1b2: float, s1a1: float, s1a2: float,
    o1: float, o2: float, o3: float, o4: float, r1: float, r2: float, r3: float, r4: float,
    q1: float, q2: float, q3: float, q4: float,
) -> tuple[
    float, float, float, float, float, float, float, float,
    float, float, float, float, float, float, float, float,
]:  # fmt: skip
    """One input sample of the real-input front end, branch-free: the one-step prediction
    error of x(i) (for residual_rms), the offset B^ (the low-pass on x itself), and c = cr + j ci
    (quadrature demodulation and low-pass); then the 12 new biquad delays. The one definition,
    called by :func:`differential_rls_kernel` and, one lane per channel, by its bank."""
    # one-step prediction of x(i) from the estimate so far (computed either way, then chosen:
    # a select, which a bank's lanes run as one vector, where a branch would keep them apart)
    held = b_prev + snap_a * (lo_re * bb_im + lo_im * bb_re)  # (lo bb).imag, as complex product computes it
    pred = held if snap_valid != 0.0 else b_prev
    e = xi - pred
    # offset: the same low-pass on x itself
    y1, o1, o2 = _bq(xi, s0b0, s0b1, s0b2, s0a1, s0a2, o1, o2)
    bh, o3, o4 = _bq(y1, s1b0, s1b1, s1b2, s1a1, s1a2, o3, o4)
    # quadrature demodulation: m = 2j (x - B^) e^{-j psi}, so that LPF(m) = A e^{j phi_d}
    # for x = B + A sin(psi + phi_d) (c = z + j y of eqs. 1-2)
    d2 = 2.0 * (xi - bh)
    y1, r1, r2 = _bq(d2 * lo_im, s0b0, s0b1, s0b2, s0a1, s0a2, r1, r2)
    cr, r3, r4 = _bq(y1, s1b0, s1b1, s1b2, s1a1, s1a2, r3, r4)
    y1, q1, q2 = _bq(d2 * lo_re, s0b0, s0b1, s0b2, s0a1, s0a2, q1, q2)
    ci, q3, q4 = _bq(y1, s1b0, s1b1, s1b2, s1a1, s1a2, q3, q4)
    return e, bh, cr, ci, o1, o2, o3, o4, r1, r2, r3, r4, q1, q2, q3, q4


@kernel(inline="always")
def _decimated_step(
    cr: float, ci: float, u: float, core: np.ndarray, theta: np.ndarray, P: np.ndarray, tab: np.ndarray,
    consts: np.ndarray, rr: np.ndarray, ri: np.ndarray, xr_: np.ndarray, xi_: np.ndarray, px: np.ndarray,
    idx: np.ndarray, T: np.ndarray, b0: np.ndarray, work: np.ndarray, sos: np.ndarray, fe: np.ndarray,
    wref: float, lref: float, r1: float, r2: float, r3: float, r4: float,
    q1: float, q2: float, q3: float, q4: float,
) -> tuple[
    float, float, float, float, float, float, float, float, float, float, float, float, complex, complex,
]:  # fmt: skip
    """One decimated sample c = cr + j ci (dt = u T0) of the real-input estimator:
    :func:`core_step`, the periodic re-centring of the reference (with the low-pass state
    moved to the new frequency) and the snapshot the outputs hold until the next one (written
    into ``fe``). Returns the new reference frequency and ramp, the 8 delays of the
    demodulator's low-pass, ``a^ / H * |H|^2`` (whose argument is the snapshot's phase) and
    the prediction rotator and its step. The one definition, called by
    :func:`differential_rls_kernel` and, lane by lane, by its bank."""
    fs = consts[K_FS]
    inv_fs = 1.0 / fs
    T0 = consts[K_T0]
    d0 = T0 * fs
    w_lo = consts[K_W_NOM] - consts[K_W_RANGE]
    w_hi = consts[K_W_NOM] + consts[K_W_RANGE]
    recenter = consts[K_RECENTER] != 0.0
    core_step(cr, ci, u, core, theta, P, tab, consts, rr, ri, xr_, xi_, px)
    w, lb, std, val, confident, conv, lsig = core_status(core, theta, P, consts)
    if core[SINCE_REBASE] >= consts[K_REBASE_EVERY]:
        dw = 0.0
        dl = 0.0
        if recenter and confident:
            # periodic re-centring of the reference oscillator on the estimate (frequency
            # and, with the derivative model, its ramp), clamped to the tracking range
            wnew = wref + w / T0
            lnew = lref + lsig / (T0 * T0)
            if wnew > w_hi:
                wnew = w_hi
                lnew = 0.0
            elif wnew < w_lo:
                wnew = w_lo
                lnew = 0.0
            dw = (wnew - wref) * T0
            dl = (lnew - lref) * T0 * T0
            if dw != 0.0:
                om_old = w / d0
                om_new = (w - dw) / d0
                a_now = complex(core[A_RE], core[A_IM])
                fe[F_ZI + 4], fe[F_ZI + 5], fe[F_ZI + 6], fe[F_ZI + 7] = r1, r2, r3, r4
                fe[F_ZI + 8], fe[F_ZI + 9], fe[F_ZI + 10], fe[F_ZI + 11] = q1, q2, q3, q4
                h_old, h_new = _retune_responses(sos, fe, a_now, om_old, om_new)
                r1, r2, r3, r4 = fe[F_ZI + 4], fe[F_ZI + 5], fe[F_ZI + 6], fe[F_ZI + 7]
                q1, q2, q3, q4 = fe[F_ZI + 8], fe[F_ZI + 9], fe[F_ZI + 10], fe[F_ZI + 11]
                g = h_new / h_old  # c(k-1), a^, n^ as if filtered at the new frequency
                cp = complex(core[C_PREV_RE], core[C_PREV_IM]) * g
                core[C_PREV_RE] = cp.real
                core[C_PREV_IM] = cp.imag
                a_now = a_now * g
                core[A_RE] = a_now.real
                core[A_IM] = a_now.imag
                nh = complex(core[NH_RE], core[NH_IM]) * g
                core[NH_RE] = nh.real
                core[NH_IM] = nh.imag
            wref = wnew
            lref = lnew
        rebase(core, theta, P, tab, consts, dw, dl, idx, T, b0, work)
        w, lb, std, val, confident, conv, lsig = core_status(core, theta, P, consts)
    # snapshot, compensated for the low-pass response at the estimated baseband frequency
    h = lowpass_response(sos, w / d0)
    ah = complex(core[A_RE], core[A_IM]) * h.conjugate()  # a^ / H * |H|^2
    habs2 = h.real * h.real + h.imag * h.imag
    aah = abs(ah)
    amp = aah / habs2  # |a^ / H|
    val = val and amp > consts[K_MIN_AMP] and math.isfinite(amp)
    wb_s = w / T0
    lb_s = lb / (T0 * T0)
    # arg(a^ / H) = atan2(ah): only outputs read it, so it is taken when one is written
    # (or the block ends), from the same ah: the same bits, one atan2 a block at last_only
    ah_re = ah.real
    ah_im = ah.imag
    fe[F_SNAP_W] = wb_s
    fe[F_SNAP_L] = lb_s
    fe[F_SNAP_A] = amp
    fe[F_SNAP_VALID] = 1.0 if val else 0.0
    fe[F_SNAP_CONV] = 1.0 if (conv and val) else 0.0
    fe[F_SNAP_STD] = std / (TWO_PI * T0) if math.isfinite(std) else -1.0  # state stays finite
    fe[F_SINCE] = 0.0
    bb = ah / aah if amp > 0.0 else complex(1.0, 0.0)  # e^{j ph0}
    a_ = (wb_s + 0.5 * lb_s * inv_fs) * inv_fs
    bs = complex(math.cos(a_), math.sin(a_))
    return wref, lref, r1, r2, r3, r4, q1, q2, q3, q4, ah_re, ah_im, bb, bs


@kernel(inline="always")
def _write_outputs(
    out: np.ndarray, ext: np.ndarray, j: int, fe: np.ndarray, at: int, stride: int, b: float, psi: float,
    wref: float, lref: float, ts: float,
) -> None:
    """Row ``j`` of the real-input outputs: the snapshot of the last decimated sample held,
    its phase advanced by ``ts`` seconds at the estimated frequency; ``b`` the offset B^. The
    snapshot's slot ``F_x`` is ``fe[at + F_x * stride]`` (0 and 1 for a channel's own state
    vector, lane and LANES in a bank's lane-major work array)."""
    if fe[at + F_SNAP_VALID * stride] != 0.0:
        wbb = fe[at + F_SNAP_W * stride]
        lbb = fe[at + F_SNAP_L * stride]
        out[j, 0] = (wref + wbb + lbb * ts) / TWO_PI
        out[j, 1] = fe[at + F_SNAP_A * stride]
        out[j, 2] = _wrap(psi + fe[at + F_SNAP_PH * stride] + (wbb + 0.5 * lbb * ts) * ts)
        out[j, 3] = b
        out[j, 4] = fe[at + F_SNAP_CONV * stride]
        ext[j, 0] = (lref + lbb) / TWO_PI
        ext[j, 1] = fe[at + F_SNAP_STD * stride] if fe[at + F_SNAP_STD * stride] >= 0.0 else np.nan
    else:
        out[j, 0] = np.nan
        out[j, 1] = np.nan
        out[j, 2] = np.nan
        out[j, 3] = b
        out[j, 4] = 0.0
        ext[j, 0] = np.nan
        ext[j, 1] = np.nan
    ext[j, 2] = wref / TWO_PI


@kernel
def differential_rls_kernel(
    x: np.ndarray,
    fe_in: np.ndarray,
    core_in: np.ndarray,
    theta_in: np.ndarray,
    P_in: np.ndarray,
    ist_in: np.ndarray,
    sos: np.ndarray,
    tab: np.ndarray,
    cyc: np.ndarray,
    consts: np.ndarray,
    last_only: bool,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Real input -> quadrature demodulation against the reference oscillator -> low-pass
    (two biquads, ``sos``) -> decimation by the cyclic intervals ``cyc`` (input samples)
    -> :func:`core_step` at every decimated sample; outputs at every input sample.

    Returns (out (N or 1, 5), extras (N or 1, 3), sse, fe, core, theta, P, ist). Pure.
    """
    fe = fe_in.copy()
    core, theta, P, rr, ri, xr_, xi_, px, idx, T, b0, work = working_core(core_in, theta_in, P_in, tab)
    ist = ist_in.copy()
    n = x.shape[0]
    nout = 1 if last_only else n
    out = np.empty((nout, 5))
    ext = np.empty((nout, 3))
    fs = consts[K_FS]
    inv_fs = 1.0 / fs
    T0 = consts[K_T0]
    w_lo = consts[K_W_NOM] - consts[K_W_RANGE]
    w_hi = consts[K_W_NOM] + consts[K_W_RANGE]
    warm = consts[K_WARM]
    ncyc = cyc.shape[0]
    d0 = T0 * fs
    sse = 0.0
    psi = fe[F_PSI]
    wref = fe[F_WREF]
    lref = fe[F_LREF]
    lo = complex(fe[F_LO_RE], fe[F_LO_IM])  # e^{j psi}
    ls = complex(fe[F_LS_RE], fe[F_LS_IM])  # its per-sample step
    bb = complex(fe[F_BB_RE], fe[F_BB_IM])  # e^{j phi_bb} predicted for this sample
    bs = complex(fe[F_BS_RE], fe[F_BS_IM])  # its per-sample step
    # the chirp corrections of the two steps, _cis_small of (ramp / fs^2): computed once per
    # value of the ramp, not per sample (the same function of the same value: the same bits)
    cb_for = 0.0
    cb = complex(1.0, 0.0)
    cl_for = 0.0
    cl = complex(1.0, 0.0)
    ph_pending = False  # fe[F_SNAP_PH] still to take from (ah_re, ah_im)
    ah_re = 0.0
    ah_im = 0.0
    # e^{j a} of the reference's per-sample step a: recomputed only when a changes (on a
    # re-centring or with a ramp), the same function of the same value: the same bits
    ls_for = math.nan
    ls_exact = complex(1.0, 0.0)
    if ist[2] == 0:  # first sample ever: start the offset low-pass in steady state at x(0)
        _biquads_steady(x[0], sos, fe, F_ZI)
    # the low-pass coefficients and the 12 delays of its three channels live in registers
    s0b0, s0b1, s0b2, s0a1, s0a2 = sos[0, 0], sos[0, 1], sos[0, 2], sos[0, 4], sos[0, 5]
    s1b0, s1b1, s1b2, s1a1, s1a2 = sos[1, 0], sos[1, 1], sos[1, 2], sos[1, 4], sos[1, 5]
    o1, o2, o3, o4 = fe[F_ZI], fe[F_ZI + 1], fe[F_ZI + 2], fe[F_ZI + 3]
    r1, r2, r3, r4 = fe[F_ZI + 4], fe[F_ZI + 5], fe[F_ZI + 6], fe[F_ZI + 7]
    q1, q2, q3, q4 = fe[F_ZI + 8], fe[F_ZI + 9], fe[F_ZI + 10], fe[F_ZI + 11]
    for i in range(n):
        xi = x[i]
        if ist[2] < warm:
            ist[2] += 1
        e, bh, cr, ci, o1, o2, o3, o4, r1, r2, r3, r4, q1, q2, q3, q4 = _demodulate(
            xi, fe[F_B], fe[F_SNAP_VALID], fe[F_SNAP_A], lo.real, lo.imag, bb.real, bb.imag, s0b0, s0b1, s0b2, s0a1, s0a2,
            s1b0, s1b1, s1b2, s1a1, s1a2, o1, o2, o3, o4, r1, r2, r3, r4, q1, q2, q3, q4,
        )  # fmt: skip
        sse += e * e
        fe[F_B] = bh
        # ---- decimation with the cyclic intervals (nonuniform cyclic sampling, Section 5)
        ist[0] += 1
        stepped = False
        if ist[0] >= cyc[ist[1]] and ist[2] >= warm:  # the core starts once the low-pass settled
            stepped = True
            u = cyc[ist[1]] / d0
            ist[0] = 0
            ist[1] = (ist[1] + 1) % ncyc
            wref, lref, r1, r2, r3, r4, q1, q2, q3, q4, ah_re, ah_im, bb, bs = _decimated_step(
                cr, ci, u, core, theta, P, tab, consts, rr, ri, xr_, xi_, px, idx, T, b0, work, sos, fe,
                wref, lref, r1, r2, r3, r4, q1, q2, q3, q4,
            )  # fmt: skip
            ph_pending = True
        else:
            fe[F_SINCE] += 1.0
        # ---- outputs at this input sample (hold the decimated estimate, phase propagated)
        if not last_only or i == n - 1:
            j = 0 if last_only else i
            ts = fe[F_SINCE] * inv_fs
            if ph_pending:
                fe[F_SNAP_PH] = math.atan2(ah_im, ah_re)
                ph_pending = False
            _write_outputs(out, ext, j, fe, 0, 1, fe[F_B], psi, wref, lref, ts)
        # ---- advance the baseband prediction rotator by one sample
        bb = bb * bs
        snap_l = fe[F_SNAP_L]
        if snap_l != 0.0:
            if snap_l != cb_for:
                cb = _cis_small(snap_l * inv_fs * inv_fs)
                cb_for = snap_l
            bs = bs * cb
        # ---- advance the reference oscillator (linear frequency ramp, exact phase integral)
        psi = _wrap(psi + (wref + 0.5 * lref * inv_fs) * inv_fs)
        wref += lref * inv_fs
        clamped = False
        if wref > w_hi:
            wref = w_hi
            lref = 0.0
            clamped = True
        elif wref < w_lo:
            wref = w_lo
            lref = 0.0
            clamped = True
        if stepped or clamped:  # re-synchronise the rotator on psi (exact, once per decimated step)
            lo = complex(math.cos(psi), math.sin(psi))
            a_ = (wref + 0.5 * lref * inv_fs) * inv_fs
            if a_ != ls_for:
                ls_exact = complex(math.cos(a_), math.sin(a_))
                ls_for = a_
            ls = ls_exact
        else:
            lo = lo * ls
        if lref != 0.0:
            if lref != cl_for:
                cl = _cis_small(lref * inv_fs * inv_fs)
                cl_for = lref
            ls = ls * cl
    if ph_pending:
        fe[F_SNAP_PH] = math.atan2(ah_im, ah_re)
    fe[F_ZI], fe[F_ZI + 1], fe[F_ZI + 2], fe[F_ZI + 3] = o1, o2, o3, o4
    fe[F_ZI + 4], fe[F_ZI + 5], fe[F_ZI + 6], fe[F_ZI + 7] = r1, r2, r3, r4
    fe[F_ZI + 8], fe[F_ZI + 9], fe[F_ZI + 10], fe[F_ZI + 11] = q1, q2, q3, q4
    fe[F_PSI] = psi
    fe[F_WREF] = wref
    fe[F_LREF] = lref
    fe[F_LO_RE] = lo.real
    fe[F_LO_IM] = lo.imag
    fe[F_LS_RE] = ls.real
    fe[F_LS_IM] = ls.imag
    fe[F_BB_RE] = bb.real
    fe[F_BB_IM] = bb.imag
    fe[F_BS_RE] = bs.real
    fe[F_BS_IM] = bs.imag
    return out, ext, sse, fe, core, theta, P, ist


@kernel
def differential_rls_iq_kernel(
    x: np.ndarray,
    fe_in: np.ndarray,
    core_in: np.ndarray,
    theta_in: np.ndarray,
    P_in: np.ndarray,
    ist_in: np.ndarray,
    tab: np.ndarray,
    cyc: np.ndarray,
    consts: np.ndarray,
    last_only: bool,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """In-phase/quadrature input (the paper's own setting, eqs. 1-2): ``x`` is (N, 2), column
    0 the in-phase y = A sin(w t + phi), column 1 the quadrature z = A cos(w t + phi), taken
    against an external oscillator at consts[K_W_NOM]. c(k) = z + j y is taken every
    cyc[0], cyc[1], ... input samples (nonuniform cyclic sampling, Section 5; the first
    sample ever is the first c), rotated by the digital reference oscillator (phase psi2,
    offset w2 rad/T0 and ramp l2 rad/T0^2 from the external one, re-centred on the
    estimate as in :func:`iq_kernel`, kept within +- consts[K_W_RANGE]) and handed to
    :func:`core_step`; outputs at every input sample, held between decimated samples with
    the phase advanced at the estimated frequency. The one-step prediction error is that
    of the in-phase column (y = A sin(phase_rad), the output convention).

    Returns (out (N or 1, 5), extras (N or 1, 3), sse, fe, core, theta, P, ist). Pure.
    """
    fe = fe_in.copy()
    core, theta, P, rr, ri, xr_, xi_, px, idx, T, b0, work = working_core(core_in, theta_in, P_in, tab)
    ist = ist_in.copy()
    n = x.shape[0]
    nout = 1 if last_only else n
    out = np.empty((nout, 5))
    ext = np.empty((nout, 3))
    fs = consts[K_FS]
    inv_fs = 1.0 / fs
    T0 = consts[K_T0]
    d0 = T0 * fs
    w_nom = consts[K_W_NOM]
    w_max = consts[K_W_RANGE] * T0  # the digital reference stays within +- the tracking range
    recenter = consts[K_RECENTER] != 0.0
    ncyc = cyc.shape[0]
    psi2 = fe[F_PSI]
    w2 = fe[F_WREF]
    l2 = fe[F_LREF]
    pp = complex(fe[F_BB_RE], fe[F_BB_IM])  # predicted c for this sample (A e^{j phase})
    ps = complex(fe[F_BS_RE], fe[F_BS_IM])  # its per-sample step
    sse = 0.0
    for i in range(n):
        yi = x[i, 0]
        zi = x[i, 1]
        # ---- one-step prediction of the in-phase sample from the estimate so far (residual_rms)
        e = yi - pp.imag if fe[F_SNAP_VALID] != 0.0 else yi
        sse += e * e
        # ---- nonuniform cyclic sampling (Section 5): c(k) every cyc[j] input samples
        ist[0] += 1
        first = ist[2] == 0
        if first or ist[0] >= cyc[ist[1]]:
            if first:
                u = 0.0  # no interval before the first sample (core_step only stores it)
                ist[2] = 1
            else:
                u = cyc[ist[1]] / d0
                ist[1] = (ist[1] + 1) % ncyc
                # advance the digital reference over dt_k = u T0 (as iq_kernel does)
                psi2 += w2 * u + 0.5 * l2 * u * u
                w2 += l2 * u
                psi2 = math.pi - ((math.pi - psi2) % TWO_PI)
                if w2 > w_max or w2 < -w_max:
                    w2 = w_max if w2 > 0.0 else -w_max
                    l2 = 0.0
            ist[0] = 0
            c0 = math.cos(psi2)
            s0 = math.sin(psi2)
            cr = zi * c0 + yi * s0  # c e^{-j psi2}, c = z + j y (eqs. 1-2)
            ci = yi * c0 - zi * s0
            core_step(cr, ci, u, core, theta, P, tab, consts, rr, ri, xr_, xi_, px)
            w, lb, std, val, confident, conv, lsig = core_status(core, theta, P, consts)
            if core[SINCE_REBASE] >= consts[K_REBASE_EVERY]:
                dw = 0.0
                dl = 0.0
                if recenter and confident:
                    # periodic re-centring of the reference on the estimate (Section 10)
                    dw = w
                    dl = lsig
                    wnew = w2 + dw
                    if wnew > w_max or wnew < -w_max:  # clamped to the tracking range
                        wnew = w_max if wnew > 0.0 else -w_max
                        dw = wnew - w2
                        dl = -l2
                    w2 = wnew
                    l2 += dl
                rebase(core, theta, P, tab, consts, dw, dl, idx, T, b0, work)
                w, lb, std, val, confident, conv, lsig = core_status(core, theta, P, consts)
            amp = math.hypot(core[A_RE], core[A_IM])  # A^ = |a^|, eq. (23)
            val = val and amp > consts[K_MIN_AMP] and math.isfinite(amp)
            wt = (w + w2) / T0  # offset from the external oscillator, rad/s
            lt = (lb + l2) / (T0 * T0)
            ph = _wrap(math.atan2(core[A_IM], core[A_RE]) + psi2)  # phi^(t_k), eq. (23)
            fe[F_SNAP_W] = wt
            fe[F_SNAP_L] = lt
            fe[F_SNAP_PH] = ph
            fe[F_SNAP_A] = amp
            fe[F_SNAP_VALID] = 1.0 if val else 0.0
            fe[F_SNAP_CONV] = 1.0 if (conv and val) else 0.0
            fe[F_SNAP_STD] = std / (TWO_PI * T0) if math.isfinite(std) else -1.0  # state stays finite
            fe[F_SINCE] = 0.0
            pp = complex(amp * math.cos(ph), amp * math.sin(ph)) if val else complex(0.0, 0.0)
            a_ = (wt + 0.5 * lt * inv_fs) * inv_fs
            ps = complex(math.cos(a_), math.sin(a_))
        else:
            fe[F_SINCE] += 1.0
        # ---- outputs at this input sample (hold the decimated estimate, phase propagated)
        if not last_only or i == n - 1:
            j = 0 if last_only else i
            ts = fe[F_SINCE] * inv_fs
            if fe[F_SNAP_VALID] != 0.0:
                wt = fe[F_SNAP_W]
                lt = fe[F_SNAP_L]
                out[j, 0] = (w_nom + wt + lt * ts) / TWO_PI
                out[j, 1] = fe[F_SNAP_A]
                out[j, 2] = _wrap(fe[F_SNAP_PH] + (wt + 0.5 * lt * ts) * ts)
                out[j, 3] = 0.0  # the model (eqs. 1-2) has no offset
                out[j, 4] = fe[F_SNAP_CONV]
                ext[j, 0] = lt / TWO_PI
                ext[j, 1] = fe[F_SNAP_STD] if fe[F_SNAP_STD] >= 0.0 else np.nan
            else:
                out[j, 0] = np.nan
                out[j, 1] = np.nan
                out[j, 2] = np.nan
                out[j, 3] = np.nan
                out[j, 4] = 0.0
                ext[j, 0] = np.nan
                ext[j, 1] = np.nan
            ext[j, 2] = (w_nom + w2 / T0) / TWO_PI
        # ---- advance the prediction by one sample (a chirp's step turns at lt / fs^2)
        pp = pp * ps
        if fe[F_SNAP_L] != 0.0:
            ps = ps * _cis_small(fe[F_SNAP_L] * inv_fs * inv_fs)
    fe[F_PSI] = psi2
    fe[F_WREF] = w2
    fe[F_LREF] = l2
    fe[F_BB_RE] = pp.real
    fe[F_BB_IM] = pp.imag
    fe[F_BS_RE] = ps.real
    fe[F_BS_IM] = ps.imag
    return out, ext, sse, fe, core, theta, P, ist


def core_constants(
    *,
    fs: float,
    T0: float,
    lam: float,
    lam_a: float,
    rho: float,
    ls_start: int,
    p0: float,
    n_par: int,
    conv_std: float,
    w_bb_max: float,
    recenter_every: int,
    els: bool,
    derivative: bool,
    r1: float,
) -> np.ndarray:
    """The ``consts`` array (slots K_*) with the baseband estimator's entries filled in;
    the real-input front end adds its own (K_W_NOM, K_W_RANGE, K_MIN_AMP, K_WARM, K_HOLD).
    ``conv_std`` and ``w_bb_max`` in rad per T0."""
    k = np.zeros(N_CONSTS)
    k[K_FS] = fs
    k[K_T0] = T0
    k[K_LAM] = lam
    k[K_LAM_A] = lam_a
    k[K_RHO] = rho
    k[K_LS_START] = ls_start
    k[K_P0] = p0
    k[K_TRACE_MAX] = 1e8 * p0 * n_par
    k[K_CONV_STD] = conv_std
    k[K_W_BB_MAX] = w_bb_max
    k[K_REBASE_EVERY] = recenter_every if recenter_every > 0 else 16
    k[K_ELS] = 1.0 if els else 0.0
    k[K_DERIV] = 1.0 if derivative else 0.0
    k[K_RECENTER] = 1.0 if recenter_every > 0 else 0.0
    k[K_R1] = r1
    return k


def baseband_estimate(
    c: np.ndarray,
    dt: np.ndarray,
    *,
    n_terms: int = 2,
    rocof_model: bool = False,
    forgetting_factor: float = 0.98,
    phase_forgetting_factor: float | None = None,
    els: bool = True,
    els_damping: float = 0.9,
    noise_correlation: float = 0.0,
    ls_start: int = 20,
    p0: float = 1e4,
    recenter_every: int = 0,
    convergence_std_rad_s: float = 0.01,
) -> dict[str, np.ndarray]:
    """The paper's own setting (Section 10): complex in-phase/quadrature samples
    ``c(k) = z(k) + j y(k)`` taken at intervals ``dt[k]`` (s; dt[0] is ignored), run through
    the same core as the estimator. Re-centring (``recenter_every > 0``) rotates c by a
    digital reference. Returns per-sample arrays: ``frequency_rad_s``, ``rocof_rad_s2``,
    ``amplitude``, ``phase_rad``, ``frequency_std_rad_s``, ``converged``."""
    c = np.ascontiguousarray(c, dtype=np.complex128)
    dt = np.asarray(dt, dtype=np.float64)
    T0 = float(dt[1:].max()) if dt.size > 1 else 1.0
    u = np.ascontiguousarray(dt / T0)
    tab = monomial_table(n_terms, rocof_model)
    p = tab.shape[0]
    k = core_constants(
        fs=1.0 / T0,
        T0=T0,
        lam=forgetting_factor,
        lam_a=forgetting_factor if phase_forgetting_factor is None else phase_forgetting_factor,
        rho=els_damping,
        ls_start=ls_start,
        p0=p0,
        n_par=p,
        conv_std=convergence_std_rad_s * T0,
        w_bb_max=math.pi,
        recenter_every=recenter_every,
        els=els,
        derivative=rocof_model,
        r1=noise_correlation,
    )
    out, *_ = iq_kernel(
        np.ascontiguousarray(c.real), np.ascontiguousarray(c.imag), u,
        np.zeros(CORE_SIZE), np.zeros(p), np.eye(p) * p0, np.zeros(3), tab, k,
    )  # fmt: skip
    return {
        "frequency_rad_s": out[:, 0] / T0,
        "rocof_rad_s2": out[:, 1] / (T0 * T0),
        "amplitude": out[:, 2],
        "phase_rad": out[:, 3],
        "frequency_std_rad_s": out[:, 4] / T0,
        "converged": out[:, 5] != 0.0,
    }


def cyclic_intervals(k: int, values: list[float]) -> np.ndarray:
    """``k`` sampling intervals cycling through ``values`` (nonuniform cyclic sampling,
    Section 5), for :func:`baseband_estimate`; the first is 0 (no interval before it)."""
    dt = np.array([values[i % len(values)] for i in range(k)])
    dt[0] = 0.0
    return dt


def band_limited_iq_noise(k: int, m: float, var: float, seed: int) -> np.ndarray:
    """``k`` samples of complex noise, variance ``var`` per component, band-limited to 1/m
    of the Nyquist band (ideal low-pass, eq. 14): the paper's oversampled I/Q noise."""
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(k)
    out = []
    for _ in range(2):
        x = np.fft.ifft(np.where(np.abs(f) < 0.5 / m, np.fft.fft(rng.standard_normal(k)), 0.0)).real
        out.append(x * np.sqrt(var) / x.std())
    noise: np.ndarray = out[0] + 1j * out[1]
    return noise


class DifferentialRlsParams(EstimatorParams):
    input: Literal["real", "iq"] = Field(
        "real",
        description="'real': one column, demodulated against the reference oscillator; 'iq': two columns, "
        "in-phase y = A sin(phase) and quadrature z = A cos(phase) (the paper's eqs. 1-2)",
    )
    nominal_frequency_hz: float = Field(
        50.0,
        description="Initial frequency of the reference oscillator (the demodulation carrier), Hz; with "
        "input = 'iq', the frequency of the oscillator the I/Q were taken against (0: baseband)",
    )
    bandwidth_hz: float = Field(
        5.0,
        description="Low-pass bandwidth B_N after demodulation = the largest frequency offset "
        "from the reference handled at once (Omega_d / 2 pi), Hz",
    )
    oversampling: float = Field(
        10.0,
        description="M = T_sN / dt: decimated samples per Nyquist interval T_sN = 1 / (2 B_N) "
        "(Section 5); the decimation factor is round(fs / (2 B_N M))",
    )
    n_terms: int = Field(2, description="n: terms of the Taylor expansion of e^{j w dt} (eqs. 3-7)")
    rocof_model: bool = Field(
        True, description="Estimate the frequency derivative (eqs. 24-25) and ramp the reference with it"
    )
    forgetting_factor: float = Field(0.98, description="Exponential data weighting lambda, 0 < lambda <= 1")
    phase_forgetting_factor: float = Field(
        0.9, description="Exponential weighting of the phase/amplitude stage (eqs. 21-23), 0 < lambda_a <= 1"
    )
    els: bool = Field(True, description="Extended least squares whitening of the coloured noise (eqs. 11-13)")
    els_damping: float = Field(
        0.9, description="rho in [0, 1): whitening filter 1 - rho E z^-1 (the paper's passivity artifice)"
    )
    ls_start: int = Field(20, description="Decimated samples of plain least squares before ELS starts")
    cycle_spacing: float = Field(
        0.1, description="Nonuniform cyclic sampling: dt_j = dt (1 - j spacing), j < ceil(n/2), when n > 2"
    )
    recenter_every: int = Field(
        10, description="Re-centre the reference on the estimate every this many decimated samples (0: never)"
    )
    tracking_range_hz: float | None = Field(
        None, description="How far the reference may move from nominal, Hz; default: bandwidth_hz"
    )
    noise_correlation: float | None = Field(
        None,
        description="r1, lag-1 correlation of the noise at the decimated rate (ELS, eqs. 11-13); default: "
        "'real': from the demodulator's low-pass; 'iq': sinc(1/M), ideal low-pass noise of bandwidth B_N (eq. 14)",
    )
    p0: float = Field(1e4, description="Initial covariance P(0) = p0 I (amplitude-normalised units)")
    convergence_rel_std: float = Field(
        0.01, description="converged once the frequency standard deviation < this * bandwidth_hz"
    )
    min_amplitude: float = Field(1e-6, description="Below this amplitude the estimate is undefined (NaN)")

    @field_validator("bandwidth_hz", "p0", "convergence_rel_std")
    @classmethod
    def _positive(cls, v: float) -> float:
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"expected a finite value > 0, got {v}")
        return v

    @field_validator("nominal_frequency_hz")
    @classmethod
    def _nominal(cls, v: float) -> float:
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"expected a finite value >= 0, got {v}")
        return v

    @field_validator("noise_correlation")
    @classmethod
    def _r1(cls, v: float | None) -> float | None:
        if v is not None and not (math.isfinite(v) and -1.0 < v < 1.0):
            raise ValueError(f"expected -1 < noise_correlation < 1, got {v}")
        return v

    @model_validator(mode="after")
    def _carrier(self) -> DifferentialRlsParams:
        if self.input == "real" and self.nominal_frequency_hz <= 0.0:
            raise ValueError(
                f"nominal_frequency_hz: expected > 0 with input = 'real' (the demodulation carrier), "
                f"got {self.nominal_frequency_hz}"
            )
        return self

    @field_validator("oversampling")
    @classmethod
    def _m(cls, v: float) -> float:
        if not (math.isfinite(v) and v >= 1.0):
            raise ValueError(f"expected oversampling M >= 1, got {v}")
        return v

    @field_validator("n_terms")
    @classmethod
    def _n(cls, v: int) -> int:
        if not 1 <= v <= 6:
            raise ValueError(f"expected 1 <= n_terms <= 6, got {v}")
        return v

    @field_validator("forgetting_factor", "phase_forgetting_factor")
    @classmethod
    def _lam(cls, v: float) -> float:
        if not (0.0 < v <= 1.0):
            raise ValueError(f"expected 0 < forgetting factor <= 1, got {v}")
        return v

    @field_validator("els_damping")
    @classmethod
    def _rho(cls, v: float) -> float:
        if not (0.0 <= v < 1.0):
            raise ValueError(f"expected 0 <= els_damping < 1, got {v}")
        return v

    @field_validator("cycle_spacing")
    @classmethod
    def _sp(cls, v: float) -> float:
        if not (0.0 < v < 1.0):
            raise ValueError(f"expected 0 < cycle_spacing < 1, got {v}")
        return v

    @field_validator("ls_start", "recenter_every")
    @classmethod
    def _nonneg(cls, v: int) -> int:
        if v < 0:
            raise ValueError(f"expected an integer >= 0, got {v}")
        return v

    @field_validator("tracking_range_hz", "min_amplitude")
    @classmethod
    def _nonneg_f(cls, v: float | None) -> float | None:
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise ValueError(f"expected a finite value >= 0, got {v}")
        return v


def settling_samples(sos: np.ndarray, fs: float, bandwidth_hz: float, tol: float = 1e-2) -> int:
    """Input samples after which the low-pass impulse response has shed all but ``tol`` of
    its absolute area (the start-up transient of the demodulator)."""
    n = math.ceil(40.0 * fs / bandwidth_hz) + 8
    imp = np.zeros(n)
    imp[0] = 1.0
    h = np.abs(_sig.sosfilt(sos, imp))
    tail = np.cumsum(h[::-1])[::-1]
    return int(np.argmax(tail < tol * tail[0]))


def lowpass_noise_correlation(sos: np.ndarray, fs: float, bandwidth_hz: float, lag: int) -> float:
    """Correlation coefficient of white noise after the low-pass at ``lag`` input samples,
    sum h(i) h(i + lag) / sum h(i)^2: the r1 of the decimated noise (cf. eq. 14)."""
    n = math.ceil(40.0 * fs / bandwidth_hz) + lag + 8
    imp = np.zeros(n)
    imp[0] = 1.0
    h = _sig.sosfilt(sos, imp)
    return float(np.dot(h[:-lag], h[lag:]) / np.dot(h, h)) if lag < n else 0.0


def decimation_pattern(fs: float, bandwidth_hz: float, oversampling: float, n: int, spacing: float) -> list[int]:
    """Input samples between decimated samples, cycled: D0, D0 - s, ... (ceil(n/2) values when n > 2)."""
    d0 = round(fs / (2.0 * bandwidth_hz * oversampling))
    if d0 < 1:
        raise ParameterError(
            f"oversampling: expected 2 * bandwidth_hz * oversampling <= sample_rate_hz "
            f"(decimation factor >= 1), got 2 * {bandwidth_hz} * {oversampling} > {fs}"
        )
    if n <= 2:
        return [d0]
    step = max(1, round(spacing * d0))
    pattern = [d0 - j * step for j in range((n + 1) // 2)]
    if pattern[-1] < 1:
        raise ParameterError(
            f"n_terms: expected ceil(n/2) = {len(pattern)} distinct sampling intervals "
            f"(nonuniform cyclic sampling), got a decimation factor of only {d0} input samples: "
            "raise the sample rate or lower oversampling"
        )
    return pattern


@register
class DifferentialRls(Estimator[DifferentialRlsParams], kernel=differential_rls_kernel, name="differential-rls"):
    """Differential signal model + recursive extended least squares, with ROCOF. input = "real": one
    column, quadrature-mixed against a re-centred reference oscillator; input = "iq": two columns,
    in-phase y = A sin(phase) and quadrature z = A cos(phase) taken against an external oscillator at
    nominal_frequency_hz (0: baseband, the paper's setting); a block with the other column count is
    rejected (shape_mismatch)"""

    paper = (
        '"Differential signal model and sampling techniques for recursive (extended) least-squares '
        'estimation of frequency, frequency derivatives, phase and amplitude"'
    )
    example_frequency_hz = 50.3
    example_params: ClassVar[dict[str, Any]] = {"nominal_frequency_hz": 50.0, "bandwidth_hz": 5.0}
    # Printed by ``sinewatch bench kernels`` under its table.
    bench_note: ClassVar[str] = (
        "differential-rls is below the streaming FFT (about 0.55x: ~60 ns/sample against ~34 at 1024-sample "
        "blocks, `sinewatch bench kernels --estimators differential-rls`): it is one recursion, sample after "
        "sample, with nothing a block transform could share. Every input sample steps the reference "
        "oscillator, the quadrature demodulator's three channels of two cascaded biquads and the one-step "
        "prediction (~26 ns); every decimated sample (every 10th in the example) runs the pair of RLS "
        "updates (12) on 5 parameters, the ELS noise recursion (13), the phase stage (21)-(23) and the "
        "low-pass compensation, with 9 sin/cos/hypot/sqrt calls and 4 complex divisions in one dependency "
        "chain (~330 ns). The arithmetic order is fixed (recordings replay bit for bit), so the chain is "
        "neither reassociated nor vectorised."
    )
    # Printed by ``sinewatch bench kernels --bank N`` when the bank is below its target.
    bank_note: ClassVar[str] = (
        "the bank vectorises the per-input-sample work across 8 channels (the demodulator's six biquads, the "
        "prediction and the two rotators, packed vmulpd/vaddpd on ymm registers): timed alone (the bank kernel "
        "with the decimated stage switched off, 1024-sample blocks, 8 channels), it costs 11 ns a sample and "
        "channel against 25 for one channel at a time. The decimated stage is not vectorised: once every 10 "
        "input samples each channel runs the RLS pair (12) on 5 parameters, the ELS recursion (13), the phase "
        "stage (21)-(23), the re-centring and the low-pass compensation, one dependent chain with sin, cos, "
        "atan2, hypot and sqrt from the C library (a vectorised version would round differently) and branches "
        "that differ between channels; it is the same ~35 ns a sample and channel in the bank as alone, more "
        "than the whole budget of 2x the streaming FFT (~17 ns a sample), so the bank stays near one channel's "
        "rate (0.9-1.4x)"
    )

    @classmethod
    def params_for(cls, sample_rate_hz: float, hints: dict[str, Any]) -> dict[str, Any]:
        """Parameters for a bench scenario (``sinewatch bench accuracy``): reference at the
        nominal frequency, low-pass bandwidth 10 % of it, tracking range covering the
        scenario's frequency range as far as the demodulator allows, M <= 10."""
        nom = tuple(hints["nominal_frequency_hz"])
        n_inputs = hints.get("n_inputs", 1)
        if n_inputs == 2 and len(nom) == 1:
            # I/Q blocks (the paper's own setting): the baseband frequency and the design come with
            # the scenario (its suggested parameters, applied after these); no demodulator to fit
            return {"input": "iq"}
        if len(nom) != 1 or n_inputs != 1:
            raise ParameterError(
                f"expected one component on one (real) or two (I/Q) inputs, got {len(nom)} components "
                f"on {n_inputs} inputs"
            )
        f0 = float(nom[0])
        lo, hi = hints["frequency_range_hz"]
        bw = 0.1 * f0
        rng = min(max(f0 - float(lo), float(hi) - f0, bw), f0 - 2.0 * bw, 0.45 * sample_rate_hz - f0 - bw)
        m = min(10.0, sample_rate_hz / (2.0 * bw))
        if rng < 0.0 or m < 1.0:
            raise ParameterError(f"expected room for the demodulator below Nyquist, got f0 = {f0} Hz "
                                 f"at {sample_rate_hz} Hz")  # fmt: skip
        return {"nominal_frequency_hz": f0, "bandwidth_hz": bw, "tracking_range_hz": rng, "oversampling": m}

    @property
    def n_inputs(self) -> int:
        """1 with input = 'real', 2 (in-phase, quadrature) with input = 'iq'."""
        return 2 if self.params.input == "iq" else 1

    def _as_block(self, samples: Any) -> np.ndarray:
        """The block checked against ``input``: a typed error that names the parameter when
        the columns disagree with it (before the generic checks of the base class)."""
        if isinstance(samples, np.ndarray) and samples.ndim >= 1:
            cols = samples.shape[1] if samples.ndim == 2 else (1 if samples.ndim == 1 else -1)
            if cols != self.n_inputs:
                want = "2 columns (in-phase, quadrature)" if self.params.input == "iq" else "1 column"
                raise InputError(
                    f"samples: expected {want} with input = {self.params.input!r}, got shape {samples.shape}",
                    kind="shape_mismatch",
                )
        return super()._as_block(samples)

    def _run(
        self, samples: np.ndarray, state: dict[str, np.ndarray], last_only: bool
    ) -> tuple[Track, dict[str, np.ndarray]]:
        """Real input: the class kernel (:func:`differential_rls_kernel`), as the base class
        calls it; I/Q input: :func:`differential_rls_iq_kernel`, called the same way (block,
        state arrays, constants without the demodulator's low-pass, last_only). Two kernels
        rather than one that branches, so that a channel compiles only its own."""
        if self.params.input == "real":
            return super()._run(samples, state, last_only)
        kern: Callable[..., tuple[Any, ...]] = differential_rls_iq_kernel
        result = kern(samples, *state.values(), *self._constants[1:], last_only)
        n_outputs = len(result) - len(state)
        return self._track(result[:n_outputs], samples), dict(zip(state, result[n_outputs:]))  # noqa: B905

    def presence_samples(self, samples: np.ndarray) -> np.ndarray:
        """I/Q input: the magnitude |z + j y| with alternating sign, so that the presence
        detector's AC RMS over its (even, :attr:`presence_cycle_hz`) window reads the
        amplitude whatever the baseband frequency; real input: column 0."""
        if self.params.input == "real" or samples.ndim == 1:
            return super().presence_samples(samples)
        sign = np.where(np.arange(samples.shape[0]) % 2 == 0, 1.0, -1.0)
        return np.asarray(np.hypot(samples[:, 0], samples[:, 1]) * sign, dtype=np.float64)

    @property
    def presence_cycle_hz(self) -> float | None:
        """I/Q input: a window of 4 samples (see :meth:`presence_samples`)."""
        return self.sample_rate_hz / 4.0 if self.params.input == "iq" else None

    def _check_params(self) -> None:
        p = self.params
        fs = self.sample_rate_hz
        rng = p.bandwidth_hz if p.tracking_range_hz is None else p.tracking_range_hz
        if p.input == "iq":
            # complex samples at fs hold offsets within (-fs/2, fs/2) of the external oscillator
            if rng + p.bandwidth_hz >= fs / 2:
                raise ParameterError(
                    f"tracking_range_hz: expected tracking range + bandwidth below half the I/Q sample rate "
                    f"({fs / 2} Hz), got {rng} + {p.bandwidth_hz} = {rng + p.bandwidth_hz}"
                )
        else:
            top = p.nominal_frequency_hz + rng + p.bandwidth_hz
            if top >= fs / 2:
                raise ParameterError(
                    f"nominal_frequency_hz: expected nominal + tracking range + bandwidth below Nyquist "
                    f"({fs / 2} Hz), got {p.nominal_frequency_hz} + {rng} + {p.bandwidth_hz} = {top}"
                )
            if p.nominal_frequency_hz - rng - p.bandwidth_hz <= 0:
                raise ParameterError(
                    f"bandwidth_hz: expected nominal - tracking range - bandwidth > 0, got "
                    f"{p.nominal_frequency_hz} - {rng} - {p.bandwidth_hz}"
                )
        if p.rocof_model and p.n_terms > 4:
            raise ParameterError(f"n_terms: expected <= 4 with rocof_model (n(n+3)/2 parameters), got {p.n_terms}")
        decimation_pattern(fs, p.bandwidth_hz, p.oversampling, p.n_terms, p.cycle_spacing)

    def _setup(self) -> None:
        p = self.params
        fs = self.sample_rate_hz
        iq = p.input == "iq"
        self._cyc = np.array(
            decimation_pattern(fs, p.bandwidth_hz, p.oversampling, p.n_terms, p.cycle_spacing), dtype=np.int64
        )
        d0 = float(self._cyc[0])
        T0 = d0 / fs
        self._tab = monomial_table(p.n_terms, p.rocof_model)
        n_par = self._tab.shape[0]
        # the demodulator's low-pass (real input; passed but unused with I/Q input)
        self._sos = np.ascontiguousarray(_sig.butter(4, p.bandwidth_hz, fs=fs, output="sos"))
        rng = p.bandwidth_hz if p.tracking_range_hz is None else p.tracking_range_hz
        if p.noise_correlation is not None:
            r1 = p.noise_correlation
        elif iq:  # ideal low-pass noise of bandwidth B_N sampled at T_sN / M, eq. (14)
            r1 = float(np.sinc(1.0 / p.oversampling))
        else:
            r1 = lowpass_noise_correlation(self._sos, fs, p.bandwidth_hz, int(self._cyc[0]))
        c = core_constants(
            fs=fs,
            T0=T0,
            lam=p.forgetting_factor,
            lam_a=p.phase_forgetting_factor,
            rho=p.els_damping,
            ls_start=p.ls_start,
            p0=p.p0,
            n_par=n_par,
            conv_std=p.convergence_rel_std * p.bandwidth_hz * TWO_PI * T0,
            w_bb_max=TWO_PI * p.bandwidth_hz * T0,
            recenter_every=p.recenter_every,
            els=p.els,
            derivative=p.rocof_model,
            r1=r1,
        )
        c[K_W_NOM] = TWO_PI * p.nominal_frequency_hz
        c[K_W_RANGE] = TWO_PI * rng
        c[K_MIN_AMP] = p.min_amplitude
        if not iq:  # I/Q input: no low-pass to settle
            c[K_WARM] = settling_samples(self._sos, fs, p.bandwidth_hz)
            c[K_HOLD] = math.ceil(c[K_WARM] / d0)
        self._consts = c
        self._constants = (self._sos, self._tab, self._cyc, self._consts)

    def _initial_state(self) -> dict[str, np.ndarray]:
        """``fe`` (FE_SIZE,): the front end, slots named F_*. Real input: reference phase
        (rad), frequency (rad/s) and ramp (rad/s^2), offset, the low-pass delays, the
        snapshot at the last decimated step, the rotators. I/Q input: F_PSI, F_WREF, F_LREF
        hold the digital reference's phase (rad), offset from the external oscillator (rad
        per T0) and ramp (rad per T0^2), F_BB_* the predicted c and F_BS_* its per-sample
        step, the snapshot slots as for real input (F_SNAP_W, F_SNAP_L: offset from the
        external oscillator), the others unused. ``core`` (CORE_SIZE,): the baseband
        estimator, slots named by the constants above (c(k-1), n^, a^, the weighted
        powers, counters, flags); ``theta`` (p,): the parameter estimate (monomials w^a
        lam^b, :func:`monomial_table`); ``P`` (p, p): its covariance; ``ist`` (3,) int64:
        input samples since the last decimated one, position in the decimation cycle, and
        (real) samples seen while the low-pass warms up / (I/Q) 1 once the first sample
        was taken."""
        n_par = self._tab.shape[0]
        fe = np.zeros(FE_SIZE)
        if self.params.input == "real":
            w = TWO_PI * self.params.nominal_frequency_hz
            fe[F_WREF] = w
            fe[F_LO_RE] = 1.0
            fe[F_LS_RE] = math.cos(w / self.sample_rate_hz)
            fe[F_LS_IM] = math.sin(w / self.sample_rate_hz)
            fe[F_BB_RE] = 1.0
        fe[F_BS_RE] = 1.0
        return {
            "fe": fe,
            "core": np.zeros(CORE_SIZE),
            "theta": np.zeros(n_par),
            "P": np.eye(n_par) * self.params.p0,
            "ist": np.zeros(3, dtype=np.int64),
        }

    def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
        out, ext, sse = outputs
        rocof = ext[:, 0] if self.params.rocof_model else np.full(ext.shape[0], np.nan)
        extras = {
            "rocof_hz_per_s": rocof,
            "frequency_std_hz": ext[:, 1],
            "reference_frequency_hz": ext[:, 2],
        }
        track = track_from_columns(out, sse, block.shape[0], extras)
        if self.params.rocof_model:  # first class too (Estimate v2), the extra kept
            track.rocof_hz_per_s = rocof[:, None]
        return track


# ---- bank: the channels of a frame together (sinewatch.estimators.bank) -------------------
LANES = 8  # channels advanced together: 8 doubles, one AVX-512 register
# rows of the bank's lane-major work array, LANES doubles each: the FE_SIZE slots of ``fe``
# (rows 0..31, the same slot numbers), then the sample in, c = cr + j ci out of the front end,
# the sse, the lanes' fix-up flags of the advance, psi before its wrap
_RX, _RCR, _RCI, _RSSE, _RFIX, _RPRE = FE_SIZE, FE_SIZE + 1, FE_SIZE + 2, FE_SIZE + 3, FE_SIZE + 4, FE_SIZE + 5
_ROWS = FE_SIZE + 6
_FIX_CLAMPED, _FIX_WRAP = 1.0, 2.0  # _RFIX: the reference was clamped; psi needs more than one wrap


@kernel(inline="always")
def _bank_front(
    S: np.ndarray, lane: int,
    s0b0: float, s0b1: float, s0b2: float, s0a1: float, s0a2: float,
    s1b0: float, s1b1: float, s1b2: float, s1a1: float, s1a2: float,
) -> None:  # fmt: skip
    """:func:`_demodulate` on lane ``lane`` of ``S``: reads and writes that one array at
    constant offsets, so that the compiler runs the lanes as one vector."""
    L = LANES
    z = F_ZI * L + lane
    e, bh, cr, ci, o1, o2, o3, o4, r1, r2, r3, r4, q1, q2, q3, q4 = _demodulate(
        S[_RX * L + lane], S[F_B * L + lane], S[F_SNAP_VALID * L + lane], S[F_SNAP_A * L + lane],
        S[F_LO_RE * L + lane], S[F_LO_IM * L + lane], S[F_BB_RE * L + lane], S[F_BB_IM * L + lane],
        s0b0, s0b1, s0b2, s0a1, s0a2, s1b0, s1b1, s1b2, s1a1, s1a2,
        S[z], S[z + L], S[z + 2 * L], S[z + 3 * L], S[z + 4 * L], S[z + 5 * L], S[z + 6 * L], S[z + 7 * L],
        S[z + 8 * L], S[z + 9 * L], S[z + 10 * L], S[z + 11 * L],
    )  # fmt: skip
    S[_RSSE * L + lane] += e * e
    S[F_B * L + lane] = bh
    S[z], S[z + L], S[z + 2 * L], S[z + 3 * L] = o1, o2, o3, o4
    S[z + 4 * L], S[z + 5 * L], S[z + 6 * L], S[z + 7 * L] = r1, r2, r3, r4
    S[z + 8 * L], S[z + 9 * L], S[z + 10 * L], S[z + 11 * L] = q1, q2, q3, q4
    S[_RCR * L + lane] = cr
    S[_RCI * L + lane] = ci


@kernel(inline="always")
def _cmul(a: float, b: float, c: float, d: float) -> tuple[float, float]:
    """(a + j b)(c + j d) on floats, in the operations and order of numba's complex product
    (ac - bd, ad + bc): the same bits, and no complex value, which keeps a bank's loop over its
    lanes from being vectorised."""
    return a * c - b * d, a * d + b * c


@kernel(inline="always")
def _cis_small_parts(a: float) -> tuple[float, float]:
    """:func:`_cis_small` as two floats (the same operations)."""
    a2 = a * a
    return 1.0 - 0.5 * a2, a * (1.0 - a2 / 6.0)


@kernel(inline="always")
def _bank_advance(S: np.ndarray, lane: int, inv_fs: float, w_lo: float, w_hi: float) -> None:
    """The end of an input sample in :func:`differential_rls_kernel` on lane ``lane`` of ``S``,
    branch-free and on floats: the prediction rotator and its chirp step, the reference
    oscillator's phase (one wrap: more is flagged), frequency and ramp (clamped: flagged), its
    rotator advanced by its step. A flagged lane and a lane that took a decimated step are
    finished by :func:`_bank_fixup`, as the single kernel's branches do. A cached
    ``_cis_small`` there is recomputed here: the same function of the same value, the same
    bits. Every value is computed, then chosen (selects keep the lanes one vector)."""
    L = LANES
    bbr, bbi = S[F_BB_RE * L + lane], S[F_BB_IM * L + lane]
    bsr, bsi = S[F_BS_RE * L + lane], S[F_BS_IM * L + lane]
    snap_l = S[F_SNAP_L * L + lane]
    bbr, bbi = _cmul(bbr, bbi, bsr, bsi)
    cr_, ci_ = _cis_small_parts(snap_l * inv_fs * inv_fs)
    chr_, chi_ = _cmul(bsr, bsi, cr_, ci_)
    chirp = snap_l != 0.0
    bsr = chr_ if chirp else bsr
    bsi = chi_ if chirp else bsi
    wref = S[F_WREF * L + lane]
    lref = S[F_LREF * L + lane]
    pre = S[F_PSI * L + lane] + (wref + 0.5 * lref * inv_fs) * inv_fs
    down = pre - TWO_PI
    up = pre + TWO_PI
    psi = down if pre > math.pi else (up if pre <= -math.pi else pre)
    wref += lref * inv_fs
    hi = wref > w_hi
    low = wref < w_lo
    clamped = hi | low
    wref = w_hi if hi else (w_lo if low else wref)
    lref = 0.0 if clamped else lref
    lsr, lsi = S[F_LS_RE * L + lane], S[F_LS_IM * L + lane]
    lor, loi = _cmul(S[F_LO_RE * L + lane], S[F_LO_IM * L + lane], lsr, lsi)
    cr_, ci_ = _cis_small_parts(lref * inv_fs * inv_fs)
    chr_, chi_ = _cmul(lsr, lsi, cr_, ci_)
    chirp = lref != 0.0
    lsr = chr_ if chirp else lsr
    lsi = chi_ if chirp else lsi
    wrap = (psi <= -math.pi) | (psi > math.pi) | (psi != psi)  # out of (-pi, pi], or NaN
    S[_RFIX * L + lane] = (_FIX_CLAMPED if clamped else 0.0) + (_FIX_WRAP if wrap else 0.0)
    S[_RPRE * L + lane] = pre
    S[F_BB_RE * L + lane], S[F_BB_IM * L + lane] = bbr, bbi
    S[F_BS_RE * L + lane], S[F_BS_IM * L + lane] = bsr, bsi
    S[F_PSI * L + lane] = psi
    S[F_WREF * L + lane] = wref
    S[F_LREF * L + lane] = lref
    S[F_LO_RE * L + lane], S[F_LO_IM * L + lane] = lor, loi
    S[F_LS_RE * L + lane], S[F_LS_IM * L + lane] = lsr, lsi


@kernel(inline="always")
def _bank_fixup(S: np.ndarray, lane: int, stepped: bool, inv_fs: float) -> None:
    """The branches :func:`_bank_advance` left to lane ``lane``: psi wrapped in full, and after
    a decimated step or a clamp the reference's rotator re-synchronised on psi."""
    L = LANES
    fix = S[_RFIX * L + lane]
    if fix >= _FIX_WRAP:
        S[F_PSI * L + lane] = _wrap(S[_RPRE * L + lane])
    if stepped or fix == _FIX_CLAMPED or fix == _FIX_CLAMPED + _FIX_WRAP:
        psi = S[F_PSI * L + lane]
        wref = S[F_WREF * L + lane]
        lref = S[F_LREF * L + lane]
        lo = complex(math.cos(psi), math.sin(psi))
        a_ = (wref + 0.5 * lref * inv_fs) * inv_fs
        ls = complex(math.cos(a_), math.sin(a_))
        if lref != 0.0:
            ls = ls * _cis_small(lref * inv_fs * inv_fs)
        S[F_LO_RE * L + lane], S[F_LO_IM * L + lane] = lo.real, lo.imag
        S[F_LS_RE * L + lane], S[F_LS_IM * L + lane] = ls.real, ls.imag


@kernel
def differential_rls_bank_kernel(
    x: np.ndarray,
    fe_in: np.ndarray,
    core_in: np.ndarray,
    theta_in: np.ndarray,
    P_in: np.ndarray,
    ist_in: np.ndarray,
    sos: np.ndarray,
    tab: np.ndarray,
    cyc: np.ndarray,
    consts: np.ndarray,
    last_only: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`differential_rls_kernel` for C channels at once: ``x`` (N, C), the state arrays
    stacked with the channel last (``fe`` (FE_SIZE, C), ``core`` (CORE_SIZE, C), ``theta``
    (p, C), ``P`` (p, p, C), ``ist`` (3, C)); returns ``out`` (C, rows, 5), ``ext`` (C, rows, 3),
    ``sse`` (C,) and the new stacked state. Channels go ``LANES`` at a time through a
    lane-major work array: every input sample's front end (:func:`_demodulate`) and advance
    (:func:`_bank_advance`) run the lanes as one vector; the decimated steps
    (:func:`_decimated_step`: the RLS pair, the sin/cos/atan2/hypot/sqrt of the core, scalar
    library calls) and the output rows run lane by lane, as the single kernel runs them."""
    n, nc = x.shape
    p = theta_in.shape[0]
    nout = 1 if last_only else n
    out = np.empty((nc, nout, 5))
    ext = np.empty((nc, nout, 3))
    sse = np.empty(nc)
    new_fe = np.empty((FE_SIZE, nc))
    new_core = np.empty((CORE_SIZE, nc))
    new_theta = np.empty((p, nc))
    new_P = np.empty((p, p, nc))
    new_ist = np.empty((3, nc), dtype=np.int64)
    fs = consts[K_FS]
    inv_fs = 1.0 / fs
    d0 = consts[K_T0] * fs
    w_lo = consts[K_W_NOM] - consts[K_W_RANGE]
    w_hi = consts[K_W_NOM] + consts[K_W_RANGE]
    warm = consts[K_WARM]
    ncyc = cyc.shape[0]
    s0b0, s0b1, s0b2, s0a1, s0a2 = sos[0, 0], sos[0, 1], sos[0, 2], sos[0, 4], sos[0, 5]
    s1b0, s1b1, s1b2, s1a1, s1a2 = sos[1, 0], sos[1, 1], sos[1, 2], sos[1, 4], sos[1, 5]
    L = LANES
    S = np.empty(_ROWS * L)
    fel = np.empty(FE_SIZE)  # one lane's fe, for the decimated step
    core = np.empty((L, CORE_SIZE))
    theta = np.empty((L, p))
    P = np.empty((L, p, p))
    ist = np.zeros((3, L), dtype=np.int64)
    rr, ri, xr_, xi_, px, idx, T, b0, work = _bank_scratch(tab)
    stepped = np.zeros(L, dtype=np.bool_)
    pending = np.zeros(L, dtype=np.bool_)  # fe[F_SNAP_PH] still to take from ah
    ah = np.zeros((2, L))
    for g in range(0, nc, L):
        width = min(L, nc - g)
        S[:] = 0.0  # lanes past the last channel run on zeros, their results dropped
        for c in range(width):
            for k in range(FE_SIZE):
                fel[k] = fe_in[k, g + c]
            if ist_in[2, g + c] == 0:  # first sample ever: the offset low-pass in steady state at x(0)
                _biquads_steady(x[0, g + c], sos, fel, F_ZI)
            for k in range(FE_SIZE):
                S[k * L + c] = fel[k]
            for k in range(CORE_SIZE):
                core[c, k] = core_in[k, g + c]
            for a in range(p):
                theta[c, a] = theta_in[a, g + c]
                for b in range(p):
                    P[c, a, b] = P_in[a, b, g + c]
            for k in range(3):
                ist[k, c] = ist_in[k, g + c]
            pending[c] = False
        for i in range(n):
            for c in range(width):
                S[_RX * L + c] = x[i, g + c]
            for lane in range(L):  # literal trip count: one vector
                _bank_front(S, lane, s0b0, s0b1, s0b2, s0a1, s0a2, s1b0, s1b1, s1b2, s1a1, s1a2)
            for c in range(width):  # decimation, lane by lane (nonuniform cyclic sampling, Section 5)
                if ist[2, c] < warm:
                    ist[2, c] += 1
                ist[0, c] += 1
                stepped[c] = ist[0, c] >= cyc[ist[1, c]] and ist[2, c] >= warm
                if stepped[c]:
                    u = cyc[ist[1, c]] / d0
                    ist[0, c] = 0
                    ist[1, c] = (ist[1, c] + 1) % ncyc
                    _bank_step(S, c, u, core[c], theta[c], P[c], tab, consts, rr, ri, xr_, xi_, px,
                               idx, T, b0, work, sos, fel, ah)  # fmt: skip
                    pending[c] = True
                else:
                    S[F_SINCE * L + c] += 1.0
            if not last_only or i == n - 1:
                j = 0 if last_only else i
                for c in range(width):
                    if pending[c]:
                        S[F_SNAP_PH * L + c] = math.atan2(ah[1, c], ah[0, c])
                        pending[c] = False
                    _write_outputs(out[g + c], ext[g + c], j, S, c, L, S[F_B * L + c], S[F_PSI * L + c],
                                   S[F_WREF * L + c], S[F_LREF * L + c], S[F_SINCE * L + c] * inv_fs)  # fmt: skip
            for lane in range(L):
                _bank_advance(S, lane, inv_fs, w_lo, w_hi)
            for c in range(width):
                if stepped[c] or S[_RFIX * L + c] != 0.0:
                    _bank_fixup(S, c, stepped[c], inv_fs)
        for c in range(width):
            ch = g + c
            if pending[c]:
                S[F_SNAP_PH * L + c] = math.atan2(ah[1, c], ah[0, c])
            sse[ch] = S[_RSSE * L + c]
            for k in range(FE_SIZE):
                new_fe[k, ch] = S[k * L + c]
            for k in range(CORE_SIZE):
                new_core[k, ch] = core[c, k]
            for a in range(p):
                new_theta[a, ch] = theta[c, a]
                for b in range(p):
                    new_P[a, b, ch] = P[c, a, b]
            for k in range(3):
                new_ist[k, ch] = ist[k, c]
    return out, ext, sse, new_fe, new_core, new_theta, new_P, new_ist


@kernel
def _bank_scratch(
    tab: np.ndarray,
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
]:  # fmt: skip
    """The scratch of :func:`core_step` and :func:`recenter_transform` (see
    :func:`working_core`), shared by the lanes: each call writes its scratch before reading it."""
    p = tab.shape[0]
    idx, T, b0, work = transform_scratch(tab)
    return np.zeros(p), np.zeros(p), np.zeros(p), np.zeros(p), np.zeros(p), idx, T, b0, work


@kernel(inline="always")
def _bank_step(
    S: np.ndarray, c: int, u: float, core: np.ndarray, theta: np.ndarray, P: np.ndarray, tab: np.ndarray,
    consts: np.ndarray, rr: np.ndarray, ri: np.ndarray, xr_: np.ndarray, xi_: np.ndarray, px: np.ndarray,
    idx: np.ndarray, T: np.ndarray, b0: np.ndarray, work: np.ndarray, sos: np.ndarray, fel: np.ndarray,
    ah: np.ndarray,
) -> None:  # fmt: skip
    """:func:`_decimated_step` on lane ``c`` of ``S``: its fe gathered into ``fel`` and
    scattered back, ``a^ / H * |H|^2`` into ``ah[:, c]``."""
    L = LANES
    for k in range(FE_SIZE):
        fel[k] = S[k * L + c]
    z = F_ZI + 4
    wref, lref, r1, r2, r3, r4, q1, q2, q3, q4, ah_re, ah_im, bb, bs = _decimated_step(
        S[_RCR * L + c], S[_RCI * L + c], u, core, theta, P, tab, consts, rr, ri, xr_, xi_, px, idx, T, b0, work,
        sos, fel, fel[F_WREF], fel[F_LREF], fel[z], fel[z + 1], fel[z + 2], fel[z + 3],
        fel[z + 4], fel[z + 5], fel[z + 6], fel[z + 7],
    )  # fmt: skip
    fel[F_WREF], fel[F_LREF] = wref, lref
    fel[z], fel[z + 1], fel[z + 2], fel[z + 3] = r1, r2, r3, r4
    fel[z + 4], fel[z + 5], fel[z + 6], fel[z + 7] = q1, q2, q3, q4
    fel[F_BB_RE], fel[F_BB_IM], fel[F_BS_RE], fel[F_BS_IM] = bb.real, bb.imag, bs.real, bs.imag
    for k in range(FE_SIZE):
        S[k * L + c] = fel[k]
    ah[0, c], ah[1, c] = ah_re, ah_im


register_bank(DifferentialRls, differential_rls_bank_kernel, n_outputs=3)
