"""``differential-rls``: the baseband estimator of "Differential signal model and sampling
techniques for recursive (extended) least-squares estimation of frequency, frequency
derivatives, phase and amplitude": the differential model (4)-(7) and (25), extended least
squares (11)-(13), the phase and amplitude stage (21)-(23) and the re-centring (Sections 7 and
10), on complex samples c(k) (the equations and their reconstruction are in
:mod:`sinewatch.estimators.differential_rls`). Shared by the real-input kernel (its front end
in :mod:`sinewatch.estimators._differential_rls_front`) and the I/Q kernel, and the offline
Section 10 runs (:func:`baseband_estimate`).
"""

from __future__ import annotations

import math

import numpy as np

from sinewatch.estimators._differential_rls_rls import (
    _all_finite_sum,
    _rls_pair5,
    _rls_scalar,
)
from sinewatch.estimators.base import kernel

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


# (its keyword-only parameters with defaults read like other measuring functions' lists: a shape,
# not shared logic)
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
