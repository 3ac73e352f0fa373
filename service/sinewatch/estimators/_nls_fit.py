"""The maths of ``nls``: the windowed maximum-likelihood fit of K sinusoids, compiled.

The estimator class and its streaming kernel are in :mod:`sinewatch.estimators.nls`; this
module holds what one window's fit computes, numbered as below.


The maximum-likelihood estimator of tones in white Gaussian noise is the least-squares fit
of the exact model; it attains the Cramer-Rao bound at moderate SNR. This module fits it
over a sliding window, by variable projection, and reports with every estimate the
standard deviation the inverse Fisher information gives it. References:

* [GP] G. H. Golub and V. Pereyra, "The differentiation of pseudo-inverses and nonlinear
  least squares problems whose variables separate", SIAM J. Numer. Anal. 10(2), 413-432,
  1973: the separable problem, the variable-projection functional (eq. 1.3 there:
  ``r2(alpha) = || P_perp(alpha) y ||^2``).
* [Ka] L. Kaufman, "A variable projection method for solving separable nonlinear least
  squares problems", BIT 15, 49-57, 1975: the Gauss-Newton step on the projected
  functional with the simplified Jacobian ``J = -P_perp (dPhi/dalpha) c`` (the term of
  [GP]'s exact derivative that involves the pseudo-inverse's derivative dropped).
* [SM] P. Stoica and R. Moses, "Spectral Analysis of Signals", Prentice Hall, 2005,
  Section 4.3: the nonlinear least-squares estimator of sinusoidal frequencies, its
  concentrated cost (eq. 4.3.8, the variable-projection functional for sinusoids), its
  coarse start from the periodogram peak and its statistical efficiency (Section 4.3.1,
  the CRB for sinusoids, eq. 4.3.9-4.3.10).
* [Ka93] S. M. Kay, "Fundamentals of Statistical Signal Processing: Estimation Theory",
  1993: Fisher information for a general Gaussian model, eq. (3.31)
  ``I(theta) = (1/sigma^2) (ds/dtheta)^T (ds/dtheta)``; the transformation of the bound,
  eq. (3.30) ``C_g = (dg/dtheta) I^-1 (dg/dtheta)^T``; Example 3.14 (one real sinusoid).
* [Dj] P. M. Djuric, "A model selection rule for sinusoids in white Gaussian noise",
  IEEE Trans. Signal Processing 44(7), 1744-1751, 1996: the order-selection penalty
  ``(5/2) ln N`` per sinusoid (``3/2 ln N`` for its frequency, ``1/2 ln N`` for each of
  its two linear parameters), i.e. Rissanen's MDL with each parameter weighed by the rate
  its estimate sharpens with N.
* [Ak] H. Akaike, "A new look at the statistical model identification", IEEE Trans.
  Automatic Control 19(6), 716-723, 1974 (AIC: ``-2 ln L + 2 p``).

Model over a window of N samples ``x_0 .. x_{N-1}`` (oldest first), time centred,
``m_n = n - c``, ``c = (N - 1)/2``, and scaled, ``u_n = m_n / c`` in [-1, 1]::

    (1)  x_n = B + [D u_n] + sum_{k=1..K} (a_k sin(w_k m_n) + b_k cos(w_k m_n)) + v_n

v white Gaussian (sigma^2); ``D u_n`` only with ``trend = true``. Linear parameters
``c = (B, [D], a_1, b_1, .., a_K, b_K)``, nonlinear ``w`` (rad/sample), handled through
``nu_k = w_k c`` (the phase the tone gains from the centre to the last sample), so that
``w_k m_n = nu_k u_n`` and every column lies in [-1, 1].

(2)  Variable projection [GP, eq. 1.3; SM, eq. 4.3.8]: for given nu, ``c(nu)`` is the
     linear least-squares solution ``(Phi^T Phi)^-1 Phi^T x`` (Phi the columns of (1))
     and the cost is ``r2(nu) = || x - Phi c(nu) ||^2``. The ML frequencies minimise r2.
(3)  Kaufman's Gauss-Newton step [Ka]: with ``d_k = dPhi/dnu_k c = u (a_k cos(nu_k u) -
     b_k sin(nu_k u))``, the step ``delta = (D^T P_perp D)^-1 D^T r`` (D = [d_1 .. d_K],
     r = P_perp x) is obtained by solving the joint normal equations of
     ``x ~ Phi c' + D delta`` (the Schur complement of the Phi block is D^T P_perp D).
     All the inner products come from one pass per iteration that accumulates the Gram
     matrix of ``[Phi, u sin(nu_k u), u cos(nu_k u)]`` and its products with x. A step
     that raises r2 is halved (backtracking) up to 30 times. When every ``|delta_k|`` is
     below 0.05 of its own standard deviation (or 1e-11 rad) that step is the last: it
     is taken with the linear part of the joint solution as ``c`` (exact to second order
     in delta: a change of ~1e-3 of the variance) and the covariance of the pass, which
     saves a pass; not converged after ``max_iterations``. The Gram sums of one tone
     use the centred grid's symmetry (:func:`_gram_one`).
(4)  Coarse start (sequential, in the spirit of [SM, Section 4.3] and of the RELAX
     procedure of J. Li and P. Stoica, "Efficient mixed-spectrum estimation with
     applications to target feature extraction", IEEE Trans. Signal Processing 44(2),
     281-295, 1996): tone k+1 starts at the peak of the zero-padded periodogram
     ``|sum_n r_n exp(-j w n)|^2`` of the residual r of the k-tone fit, within the search
     band and at least ``0.7`` DFT bins from the tones already found, refined by a
     parabola through the three padded bins around the peak; then (3) refines all
     k + 1 frequencies jointly. The FFT is an in-kernel radix-2 transform.
(5)  Order (``n_components = null``): k = 0 .. k_max tones are fitted in turn and the one
     that minimises [Dj]'s criterion
     ``MDL(k) = (N/2) ln(r2_k / N) + (p_lin(k)/2 + (3/2) k) ln N``,
     ``p_lin(k) = 1 + [1] + 2k``, is kept (or AIC [Ak]: ``(N/2) ln(r2_k/N) + p(k)``,
     ``p(k) = p_lin(k) + k``). MDL is the default because it is consistent (the
     probability of choosing the true order tends to 1), whereas AIC overestimates the
     order with a non-vanishing probability, and [Dj]'s frequency weight 3/2 reflects
     that a frequency is resolved N times more finely than a linear parameter. r2 is
     floored at ``N (1e-7 rms(x))^2`` (about single-precision resolution), so that a
     noise-free window does not keep buying tones with round-off.
(8)  Warm start (``warm_start``, K fixed): a window whose predecessor's fit converged with
     K tones starts (3) from that fit's frequencies instead of (4); the result stands if
     (3) converges, no two tones merge and the residual RMS is at most 1.5 times the
     previous window's (plus 1e-7 of the window's RMS), else the window is fitted from
     (4). A tone that jumps or appears raises the residual and gets the periodogram start;
     on a steady signal the two starts end in the same minimum (tested) and the warm one
     saves the FFT.
(6)  Reported parameters, at the last sample of the window (``u = 1``):
     ``A_k = hypot(a_k, b_k)``, ``phi_k = atan2(b_k, a_k) + nu_k`` (so that
     ``a sin + b cos = A sin(w m + atan2(b, a))``), ``f_k = nu_k fs / (2 pi c)``,
     offset ``B + D``; tones sorted by frequency, absent ones NaN.
(7)  Uncertainty [Ka93, eq. 3.31 and 3.30]: the Fisher information of (c, nu) is
     ``J^T J / sigma^2`` with ``J = [Phi, D]``, evaluated at the estimate, with
     ``sigma^2`` estimated by ``r2 / (N - p)`` (p = p_lin + K unknowns); the covariance
     of a reported parameter g is ``grad g^T (J^T J)^-1 grad g sigma^2``, with
     ``grad f_k = (fs / (2 pi c)) e_nu_k``, ``grad A_k = (a_k e_a + b_k e_b) / A_k``,
     ``grad phi_k = (-b_k e_a + a_k e_b) / A_k^2 + e_nu_k``, ``grad offset = e_B [+ e_D]``.
     At the true parameters this is exactly the finite-window CRLB (``sinewatch.crlb``)
     with sigma^2 known; the tests check it, and that error / std has unit spread.

"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from sinewatch.estimators.base import wrap_pi

Arr = np.ndarray  # numba ignores annotations; these are for the type checker
MAX_TONES = 8
# per tone in the held estimate: w (rad/sample), A, phi (last sample), var_w, var_A,
# var_phi, cov(w, phi); then sin and cos of the phase m samples on, cos w and sin w (the
# one-step prediction advances the phase by rotation instead of a sine per sample)
TONE_FIELDS = 11
# global: B, D/c (offset slope per sample), var_B, var_slope, cov(B, slope), fit rms,
# converged, number of tones
GLOBAL_FIELDS = 8


# ---- small dense linear algebra ---------------------------------------------------------------


@njit(cache=True, nogil=True, error_model="numpy")
def _chol_inverse(a: Arr, n: int, inv: Arr) -> bool:
    """Inverse of the symmetric positive-definite leading n x n block of ``a`` into ``inv``,
    by Cholesky after a symmetric diagonal (Jacobi) scaling. Returns False when the
    scaled matrix is not numerically positive definite."""
    d = np.empty(n)
    for i in range(n):
        if not (a[i, i] > 0.0) or not math.isfinite(a[i, i]):
            return False
        d[i] = 1.0 / math.sqrt(a[i, i])
    L = np.zeros((n, n))
    for j in range(n):
        s = a[j, j] * d[j] * d[j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 1e-13):
            return False
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            s = a[i, j] * d[i] * d[j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    # inverse of L, then (L L^T)^-1 = L^-T L^-1
    Li = np.zeros((n, n))
    for j in range(n):
        Li[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, n):
            s = 0.0
            for k in range(j, i):
                s -= L[i, k] * Li[k, j]
            Li[i, j] = s / L[i, i]
    for i in range(n):
        for j in range(i, n):
            s = 0.0
            for k in range(j, n):
                s += Li[k, i] * Li[k, j]
            inv[i, j] = s * d[i] * d[j]
            inv[j, i] = inv[i, j]
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _fft_inplace(re: Arr, im: Arr, cos_tab: Arr, sin_tab: Arr, tstride: int) -> None:
    """Radix-2 decimation-in-time FFT (forward, exp(-j)) of length n = re.size, a power of
    2; ``cos_tab[j tstride]``/``sin_tab[j tstride]`` hold cos/sin(2 pi j / n), j < n/2."""
    n = re.shape[0]
    j = 0
    for i in range(1, n):  # bit reversal
        bit = n >> 1
        while j & bit:
            j ^= bit
            bit >>= 1
        j |= bit
        if i < j:
            re[i], re[j] = re[j], re[i]
            im[i], im[j] = im[j], im[i]
    size = 2
    while size <= n:
        half = size >> 1
        step = (n // size) * tstride
        for start in range(0, n, size):
            t = 0
            for k in range(start, start + half):
                wr = cos_tab[t]
                wi = -sin_tab[t]
                h = k + half
                xr = re[h] * wr - im[h] * wi
                xi = re[h] * wi + im[h] * wr
                re[h] = re[k] - xr
                im[h] = im[k] - xi
                re[k] += xr
                im[k] += xi
                t += step
        size <<= 1


# ---- one fit ---------------------------------------------------------------------------------


@njit(cache=True, nogil=True, error_model="numpy")
def _gram_one(xw: Arr, nu0: float, n_lin0: int, G: Arr, gy: Arr) -> float:
    """:func:`_gram` for one tone, its sums in registers (the common case). Samples are
    taken in pairs ``m, -m`` (the time index is centred): sin and u are odd, cos even, so
    the odd sums (of sin, u cos, sin cos, u sin^2, u^2 sin cos, u, ...) are exactly zero
    and the others need half the samples; ``cos^2 = 1 - sin^2`` saves three more."""
    N = xw.shape[0]
    c = 0.5 * (N - 1)
    w = nu0 / c
    cw = math.cos(w)
    sw = math.sin(w)
    s_c = s_us = s_uuc = 0.0
    s_ss = s_usc = s_uuss = 0.0
    s_uu = 0.0
    x1 = xu = xs = xc = xus = xuc = xx = 0.0
    s = 0.0
    co = 1.0
    half = N // 2
    for n in range(half):  # m = n - c < 0, its mirror -m at N - 1 - n
        m = n - c
        if (n & 255) == 0:
            s = math.sin(w * m)
            co = math.cos(w * m)
        u = m / c
        us = u * s
        xa = xw[n]
        xb = xw[N - 1 - n]
        xp = xa + xb  # multiplies the even columns
        xm = xa - xb  # the odd ones
        s_uu += u * u
        s_c += co
        s_us += us
        s_uuc += u * u * co
        s_ss += s * s
        s_usc += us * co
        s_uuss += us * us
        x1 += xp
        xu += xm * u
        xs += xm * s
        xc += xp * co
        xus += xp * us
        xuc += xm * u * co
        xx += xa * xa + xb * xb
        sn = s * cw + co * sw
        co = co * cw - s * sw
        s = sn
    # pairs counted once: double; the centre sample (N odd) has m = 0: sin 0, cos 1, u 0
    s_uu *= 2.0
    s_c *= 2.0
    s_us *= 2.0
    s_uuc *= 2.0
    s_ss *= 2.0
    s_usc *= 2.0
    s_uuss *= 2.0
    if N & 1:
        xm0 = xw[half]
        s_c += 1.0
        x1 += xm0
        xc += xm0
        xx += xm0 * xm0
    q = n_lin0 + 4
    for a in range(q):
        for b in range(q):
            G[a, b] = 0.0
    i = n_lin0
    G[0, 0] = N
    gy[0] = x1
    if n_lin0 == 2:
        G[1, 1] = s_uu
        G[1, i] = s_us
        G[1, i + 3] = s_uuc
        gy[1] = xu
    G[0, i + 1] = s_c
    G[0, i + 2] = s_us
    G[i, i] = s_ss
    G[i, i + 3] = s_usc
    G[i + 1, i + 1] = N - s_ss
    G[i + 1, i + 2] = s_usc
    G[i + 2, i + 2] = s_uuss
    G[i + 3, i + 3] = s_uu - s_uuss
    gy[i] = xs
    gy[i + 1] = xc
    gy[i + 2] = xus
    gy[i + 3] = xuc
    for a in range(q):
        for b in range(a):
            G[a, b] = G[b, a]
    return xx


@njit(cache=True, nogil=True, error_model="numpy")
def _gram(xw: Arr, nu: Arr, k: int, n_lin0: int, G: Arr, gy: Arr) -> float:
    """One pass over the window: the Gram matrix G of the columns
    ``[1, (u), sin(nu_j u), cos(nu_j u) (j < k), u sin(nu_j u), u cos(nu_j u) (j < k)]``
    and ``gy`` = columns^T x; returns x^T x. Sines by rotation, re-seeded every 256
    samples (error ~ 256 eps)."""
    if k == 1:
        return _gram_one(xw, nu[0], n_lin0, G, gy)
    N = xw.shape[0]
    c = 0.5 * (N - 1)
    q = n_lin0 + 4 * k
    for i in range(q):
        gy[i] = 0.0
        for j in range(q):
            G[i, j] = 0.0
    xx = 0.0
    col = np.empty(q)
    s = np.empty(k)
    co = np.empty(k)
    cw = np.empty(k)
    sw = np.empty(k)
    for j in range(k):
        w = nu[j] / c
        cw[j] = math.cos(w)
        sw[j] = math.sin(w)
    col[0] = 1.0
    for n in range(N):
        m = n - c
        if (n & 255) == 0:
            for j in range(k):
                arg = nu[j] / c * m
                s[j] = math.sin(arg)
                co[j] = math.cos(arg)
        u = m / c
        if n_lin0 == 2:
            col[1] = u
        for j in range(k):
            col[n_lin0 + 2 * j] = s[j]
            col[n_lin0 + 2 * j + 1] = co[j]
            col[n_lin0 + 2 * k + 2 * j] = u * s[j]
            col[n_lin0 + 2 * k + 2 * j + 1] = u * co[j]
        xn = xw[n]
        xx += xn * xn
        for a in range(q):
            ca = col[a]
            gy[a] += ca * xn
            for b in range(a, q):
                G[a, b] += ca * col[b]
        for j in range(k):
            sn = s[j] * cw[j] + co[j] * sw[j]
            co[j] = co[j] * cw[j] - s[j] * sw[j]
            s[j] = sn
    for a in range(q):
        for b in range(a):
            G[a, b] = G[b, a]
    return xx


@njit(cache=True, nogil=True, error_model="numpy")
def _gn_step(
    G: Arr, gy: Arr, xx: float, k: int, n_lin0: int, coef: Arr, JtJ: Arr, cov: Arr, zlin: Arr
) -> tuple[bool, float, Arr]:
    """From the pass at nu: the linear solution ``coef`` (2), r2, the joint matrix
    ``J^T J`` of (3), its inverse ``cov`` and the linear part ``zlin`` of the joint
    solution; returns (ok, r2, delta as an array)."""
    p = n_lin0 + 2 * k
    q = p + k
    delta = np.zeros(k)
    Pinv = np.empty((p, p))
    if not _chol_inverse(G, p, Pinv):
        return False, math.inf, delta
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += Pinv[i, j] * gy[j]
        coef[i] = acc
    r2 = xx
    for i in range(p):
        r2 -= coef[i] * gy[i]
    if r2 < 0.0:
        r2 = 0.0
    # J = [Phi, D], d_j = a_j (u cos_j) - b_j (u sin_j): columns of E = G's last 2k
    e0 = n_lin0 + 2 * k
    for i in range(p):
        for j in range(p):
            JtJ[i, j] = G[i, j]
    rhs = np.empty(q)
    for i in range(p):
        rhs[i] = gy[i]
    for j in range(k):
        aj = coef[n_lin0 + 2 * j]
        bj = coef[n_lin0 + 2 * j + 1]
        sj = e0 + 2 * j
        cj = sj + 1
        for i in range(p):
            v = aj * G[i, cj] - bj * G[i, sj]
            JtJ[i, p + j] = v
            JtJ[p + j, i] = v
        rhs[p + j] = aj * gy[cj] - bj * gy[sj]
        for i2 in range(j, k):
            al = coef[n_lin0 + 2 * i2]
            bl = coef[n_lin0 + 2 * i2 + 1]
            sl = e0 + 2 * i2
            cl = sl + 1
            v = aj * al * G[cj, cl] - aj * bl * G[cj, sl] - bj * al * G[sj, cl] + bj * bl * G[sj, sl]
            JtJ[p + j, p + i2] = v
            JtJ[p + i2, p + j] = v
    if not _chol_inverse(JtJ, q, cov):
        return False, r2, delta
    for j in range(k):
        acc = 0.0
        for i in range(q):
            acc += cov[p + j, i] * rhs[i]
        delta[j] = acc
    for j in range(p):  # the linear part of the joint solution: c at nu + delta, to first order
        acc = 0.0
        for i in range(q):
            acc += cov[j, i] * rhs[i]
        zlin[j] = acc
    return True, r2, delta


@njit(cache=True, nogil=True, error_model="numpy")
def _fit(
    xw: Arr, nu0: Arr, k: int, n_lin0: int, max_iter: int, nu_max: float, coef: Arr, cov: Arr
) -> tuple[bool, bool, float, Arr]:
    """Gauss-Newton (3) with backtracking from ``nu0``. Returns (ok, converged, r2, nu);
    ``coef`` and ``cov`` (the inverse of J^T J) are those at the returned nu."""
    N = xw.shape[0]
    p = n_lin0 + 2 * k
    q = p + k
    nmax = n_lin0 + 4 * k
    G = np.empty((nmax, nmax))
    gy = np.empty(nmax)
    JtJ = np.empty((q, q))
    zlin = np.empty(p)
    nu = nu0.copy()
    nu_prev = nu0.copy()
    r2_prev = math.inf
    halvings = 0
    ok_any = False
    coef_best = np.zeros(p)
    cov_best = np.zeros((q, q))
    r2_best = math.inf
    nu_best = nu0.copy()
    converged = False
    for _ in range(max_iter):
        xx = _gram(xw, nu, k, n_lin0, G, gy)
        ok, r2, delta = _gn_step(G, gy, xx, k, n_lin0, coef, JtJ, cov, zlin)
        if ok and r2 > r2_prev * (1.0 + 1e-12) + 1e-300 and halvings < 30:
            halvings += 1
            for j in range(k):  # backtrack towards the previous point
                nu[j] = nu_prev[j] + 0.5 * (nu[j] - nu_prev[j])
            continue
        if not ok:
            if ok_any and halvings < 30:
                halvings += 1
                for j in range(k):
                    nu[j] = nu_prev[j] + 0.5 * (nu[j] - nu_prev[j])
                continue
            break
        ok_any = True
        halvings = 0
        r2_best = r2
        for j in range(k):
            nu_best[j] = nu[j]
        for i in range(p):
            coef_best[i] = coef[i]
        for i in range(q):
            for j in range(q):
                cov_best[i, j] = cov[i, j]
        sigma2 = r2 / max(N - q, 1)
        small = True
        for j in range(k):
            tol = max(0.05 * math.sqrt(max(sigma2 * cov[p + j, p + j], 0.0)), 1e-11)
            if not (abs(delta[j]) < tol):
                small = False
        if small:  # the last step, taken without another pass
            converged = True
            for j in range(k):
                nu_best[j] = min(max(nu[j] + delta[j], 1e-9), nu_max)
            for i in range(p):
                coef_best[i] = zlin[i]
            break
        r2_prev = r2
        for j in range(k):
            nu_prev[j] = nu[j]
            v = nu[j] + delta[j]
            nu[j] = min(max(v, 1e-9), nu_max)
    for i in range(p):
        coef[i] = coef_best[i]
    for i in range(q):
        for j in range(q):
            cov[i, j] = cov_best[i, j]
    return ok_any, converged, r2_best, nu_best


@njit(cache=True, nogil=True, error_model="numpy")
def _rbin(re: Arr, im: Arr, k: int, cos_tab: Arr, sin_tab: Arr) -> tuple[float, float]:
    """Bin k (0..M) of the 2M-point DFT of a real sequence r from the M-point FFT Z of
    ``z_n = r_2n + j r_2n+1``: ``X_k = E_k + exp(-j pi k / M) O_k``, ``E_k = (Z_k +
    conj Z_{M-k}) / 2``, ``O_k = -j (Z_k - conj Z_{M-k}) / 2``."""
    M = re.shape[0]
    kk = k % M
    km = (M - k) % M
    er = 0.5 * (re[kk] + re[km])
    ei = 0.5 * (im[kk] - im[km])
    orr = 0.5 * (im[kk] + im[km])
    oi = -0.5 * (re[kk] - re[km])
    if k < M:
        tc = cos_tab[k]
        ts = -sin_tab[k]
    else:
        tc = -1.0
        ts = 0.0
    return er + tc * orr - ts * oi, ei + tc * oi + ts * orr


@njit(cache=True, nogil=True, error_model="numpy")
def _next_peak(
    resid: Arr, mean: float, nu: Arr, k: int, iconsts: Arr, cos_tab: Arr, sin_tab: Arr, re: Arr, im: Arr
) -> float:
    """Coarse start (4) of tone k+1 from the residual ``resid - mean``: nu of the periodogram peak in the
    band, at least 0.7 bins from the k tones found; -1 if none. The periodogram is a real
    FFT (a half-length complex one, :func:`_rbin`). Between bins: Candan's form of
    Jacobsen's estimator when the FFT length is the window's (E. Jacobsen and P. Kootsookos,
    "Fast, accurate frequency estimators", IEEE Signal Processing Magazine 24(3), 2007;
    C. Candan, "A method for fine resolution frequency estimation from three DFT samples",
    IEEE Signal Processing Letters 18(6), 2011, eq. 6), else a parabola through the
    three padded power bins."""
    N = resid.shape[0]
    M = re.shape[0]
    nfft = 2 * M
    pad_lo, pad_hi = iconsts[4], iconsts[5]
    c = 0.5 * (N - 1)
    for i in range(M):
        re[i] = resid[2 * i] - mean if 2 * i < N else 0.0
        im[i] = resid[2 * i + 1] - mean if 2 * i + 1 < N else 0.0
    _fft_inplace(re, im, cos_tab, sin_tab, 2)
    best = -1
    pbest = 0.0
    excl = 0.7 * nfft / N  # 0.7 DFT bins of the window, in padded bins
    for b in range(pad_lo, pad_hi + 1):
        xr, xi = _rbin(re, im, b, cos_tab, sin_tab)
        pw = xr * xr + xi * xi
        if pw <= pbest:
            continue
        far = True
        for j in range(k):
            if abs(b - nu[j] / c * nfft / (2.0 * math.pi)) < excl:
                far = False
        if far:
            best = b
            pbest = pw
    if best < 0 or not (pbest > 0.0):
        return -1.0
    mr, mi = _rbin(re, im, best - 1, cos_tab, sin_tab)
    zr, zi = _rbin(re, im, best, cos_tab, sin_tab)
    pr, pi_ = _rbin(re, im, best + 1, cos_tab, sin_tab)
    d = 0.0
    if nfft == N:
        # Re[(X_{k-1} - X_{k+1}) / (2 X_k - X_{k-1} - X_{k+1})] tan(pi/N) / (pi/N)
        nr, ni = mr - pr, mi - pi_
        dr, di = 2.0 * zr - mr - pr, 2.0 * zi - mi - pi_
        den = dr * dr + di * di
        if den > 0.0:
            d = (nr * dr + ni * di) / den * math.tan(math.pi / N) / (math.pi / N)
    else:
        pm = mr * mr + mi * mi
        pp = pr * pr + pi_ * pi_
        den = pm - 2.0 * pbest + pp
        d = 0.5 * (pm - pp) / den if den < 0.0 else 0.0
    if d > 0.5:
        d = 0.5
    if d < -0.5:
        d = -0.5
    return float(2.0 * math.pi * (best + d) / nfft * c)


@njit(cache=True, nogil=True, error_model="numpy")
def _residual(xw: Arr, nu: Arr, k: int, n_lin0: int, coef: Arr, out: Arr) -> float:
    """The fit's residual into ``out``; returns its sum of squares (exact, unlike the
    normal-equation value, whose round-off would decide the order of a noise-free fit)."""
    N = xw.shape[0]
    c = 0.5 * (N - 1)
    s = np.empty(k)
    co = np.empty(k)
    cw = np.empty(k)
    sw = np.empty(k)
    for j in range(k):
        cw[j] = math.cos(nu[j] / c)
        sw[j] = math.sin(nu[j] / c)
    r2 = 0.0
    for n in range(N):
        m = n - c
        if (n & 255) == 0:
            for j in range(k):
                s[j] = math.sin(nu[j] / c * m)
                co[j] = math.cos(nu[j] / c * m)
        v = coef[0]
        if n_lin0 == 2:
            v += coef[1] * (m / c)
        for j in range(k):
            v += coef[n_lin0 + 2 * j] * s[j] + coef[n_lin0 + 2 * j + 1] * co[j]
            sn = s[j] * cw[j] + co[j] * sw[j]
            co[j] = co[j] * cw[j] - s[j] * sw[j]
            s[j] = sn
        e = xw[n] - v
        out[n] = e
        r2 += e * e
    return r2


@njit(cache=True, nogil=True, error_model="numpy")
def _merged(nu: Arr, k: int) -> bool:
    """Two of the k frequencies within a quarter DFT bin of the window (a bin is nu = pi)."""
    for a in range(k):
        for b in range(a + 1, k):
            if abs(nu[a] - nu[b]) < 0.25 * math.pi:
                return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def window_estimate(xw: Arr, iconsts: Arr, fconsts: Arr, cos_tab: Arr, sin_tab: Arr, tones: Arr, glob: Arr) -> None:
    """Fit (2)-(7) on the chronological window ``xw``; write the held estimate into
    ``tones`` (k_cols, 7) and ``glob`` (8,)."""
    N = xw.shape[0]
    k_fixed, k_max, use_aic, n_lin0, max_iter = iconsts[0], iconsts[1], iconsts[2], iconsts[3], iconsts[6]
    # The order 0 and a single iteration as int64, not as literals: numba compiles a callee once
    # per argument type and a literal int is a type of its own (Literal[int](0)), so literal
    # arguments compiled _fit, _gram, _gn_step and _residual a second time (3 s of CPU cold).
    # (int() of a numpy int64 is int64 to numba, not a literal, and int to mypy.)
    no_tones, one_iteration = int(np.int64(0)), int(np.int64(1))
    max_rel = fconsts[1]
    c = 0.5 * (N - 1)
    nu_max = math.pi * c * (1.0 - 1e-9)
    k_top = k_fixed if k_fixed > 0 else k_max
    nfft = cos_tab.shape[0] * 2
    re = np.empty(nfft // 2)
    im = np.empty(nfft // 2)
    resid = np.empty(N)
    p_top = n_lin0 + 2 * k_top
    q_top = p_top + k_top
    # every order's fit, kept for the choice (5)
    nus = np.zeros((k_top + 1, max(k_top, 1)))
    coefs = np.zeros((k_top + 1, p_top))
    covs = np.zeros((k_top + 1, q_top, q_top))
    r2s = np.full(k_top + 1, math.inf)
    convs = np.zeros(k_top + 1, dtype=np.bool_)
    xx = 0.0
    for n in range(N):
        xx += xw[n] * xw[n]
    floor = max(N * (1e-7) ** 2 * (xx / N), 1e-300)
    # warm start (8): K fixed and the previous window's fit converged with K tones
    warm = False
    k_done = -1
    if iconsts[8] != 0 and k_fixed > 0 and glob[6] != 0.0 and int(glob[7]) == k_fixed:
        nu_w = np.empty(k_fixed)
        for j in range(k_fixed):
            nu_w[j] = tones[j, 0] * c
        coef = np.zeros(p_top)
        cov = np.zeros((q_top, q_top))
        ok, cv, r2, nu = _fit(xw, nu_w, k_fixed, n_lin0, max_iter, nu_max, coef, cov)
        if ok and cv and not _merged(nu, k_fixed) and math.sqrt(r2 / N) <= 1.5 * glob[5] + 1e-7 * math.sqrt(xx / N):
            warm = True
            nus[k_fixed, :k_fixed] = nu
            coefs[k_fixed, :p_top] = coef
            covs[k_fixed, :q_top, :q_top] = cov
            r2s[k_fixed] = r2
            convs[k_fixed] = cv
            k_done = k_fixed
    if not warm:
        # k = 0: offset (and trend) only
        coef = np.zeros(n_lin0)
        cov = np.zeros((n_lin0, n_lin0))
        nu = np.zeros(0)
        if n_lin0 == 1:  # the mean, directly
            ok = True
            coef[0] = np.sum(xw) / N
            cov[0, 0] = 1.0 / N
        else:
            ok, cv, r2, nu = _fit(xw, nu, no_tones, n_lin0, one_iteration, nu_max, coef, cov)
        if ok:
            mean = 0.0
            if n_lin0 == 1:  # the residual is x - mean: subtracted in (4) directly
                mean = coef[0]
                if k_fixed == 0:
                    r2s[0] = _residual(xw, nu, no_tones, n_lin0, coef, resid)
                src = xw
            else:
                r2s[0] = _residual(xw, nu, no_tones, n_lin0, coef, resid)
                src = resid
            convs[0] = True
            coefs[0, :n_lin0] = coef
            covs[0, :n_lin0, :n_lin0] = cov
            k_done = 0
            for k in range(k_top):
                nu_start = np.empty(k + 1)
                for j in range(k):
                    nu_start[j] = nus[k, j]
                if k == 0:
                    cand = _next_peak(src, mean, nu_start, k, iconsts, cos_tab, sin_tab, re, im)
                else:
                    cand = _next_peak(resid, 0.0, nu_start, k, iconsts, cos_tab, sin_tab, re, im)
                if cand < 0.0:
                    break
                nu_start[k] = cand
                p = n_lin0 + 2 * (k + 1)
                coef = np.zeros(p)
                cov = np.zeros((p + k + 1, p + k + 1))
                ok, cv, r2, nu = _fit(xw, nu_start, k + 1, n_lin0, max_iter, nu_max, coef, cov)
                if not ok:
                    break
                if _merged(nu, k + 1):  # two tones on one frequency: the order is not supported
                    break
                nus[k + 1, : k + 1] = nu
                coefs[k + 1, :p] = coef
                covs[k + 1, : p + k + 1, : p + k + 1] = cov
                if k_fixed == 0 or k + 1 < k_top:  # exact sums for (5), the residual for (4)
                    r2s[k + 1] = _residual(xw, nu, k + 1, n_lin0, coef, resid)
                else:
                    r2s[k + 1] = r2
                convs[k + 1] = cv
                k_done = k + 1
    for i in range(tones.shape[0]):
        for f in range(tones.shape[1]):
            tones[i, f] = 0.0
    for f in range(glob.shape[0]):
        glob[f] = 0.0
    if k_done < 0:
        return
    # order (5)
    if k_fixed > 0:
        kk = k_done
    else:
        kk = 0
        best = math.inf
        lnN = math.log(N)
        for k in range(k_done + 1):
            ll = 0.5 * N * math.log(max(r2s[k], floor) / N)
            p_lin = n_lin0 + 2 * k
            crit = ll + (p_lin + k) if use_aic else ll + (0.5 * p_lin + 1.5 * k) * lnN
            if crit < best:
                best = crit
                kk = k
    p = n_lin0 + 2 * kk
    q = p + kk
    if kk == 0 and not math.isfinite(r2s[0]):  # K fixed and no tone found: offset only
        r2s[0] = _residual(xw, nus[0, :0].copy(), no_tones, n_lin0, coefs[0, :n_lin0].copy(), resid)
    nu = nus[kk, :kk].copy()
    coef = coefs[kk, :p].copy()
    cov = covs[kk, :q, :q].copy()
    r2 = r2s[kk]
    cv = convs[kk]
    sigma2 = r2 / max(N - q, 1)
    order = np.argsort(nu)
    a_max = 0.0
    for slot in range(kk):
        j = order[slot]
        a = coef[n_lin0 + 2 * j]
        b = coef[n_lin0 + 2 * j + 1]
        ia = n_lin0 + 2 * j
        ib = ia + 1
        inu = p + j
        A = math.hypot(a, b)
        a_max = max(a_max, A)
        tones[slot, 0] = nu[j] / c
        tones[slot, 1] = A
        tones[slot, 2] = wrap_pi(math.atan2(b, a) + nu[j])
        tones[slot, 7] = math.sin(tones[slot, 2])
        tones[slot, 8] = math.cos(tones[slot, 2])
        tones[slot, 9] = math.cos(tones[slot, 0])
        tones[slot, 10] = math.sin(tones[slot, 0])
        # (7): var(w) = var(nu)/c^2; A: grad (a, b)/A; phi: (-b, a)/A^2 + e_nu
        tones[slot, 3] = sigma2 * cov[inu, inu] / (c * c)
        if A > 0.0:
            ga, gb = a / A, b / A
            tones[slot, 4] = sigma2 * (ga * ga * cov[ia, ia] + 2.0 * ga * gb * cov[ia, ib] + gb * gb * cov[ib, ib])
            pa, pb = -b / (A * A), a / (A * A)
            vphi = (
                pa * pa * cov[ia, ia]
                + pb * pb * cov[ib, ib]
                + cov[inu, inu]
                + 2.0 * (pa * pb * cov[ia, ib] + pa * cov[ia, inu] + pb * cov[ib, inu])
            )
            tones[slot, 5] = sigma2 * vphi
            tones[slot, 6] = sigma2 * (pa * cov[ia, inu] + pb * cov[ib, inu] + cov[inu, inu]) / c
    B = coef[0]
    vB = cov[0, 0]
    slope = 0.0
    vS = 0.0
    cBS = 0.0
    if n_lin0 == 2:
        B += coef[1]
        vB += cov[1, 1] + 2.0 * cov[0, 1]
        slope = coef[1] / c
        vS = cov[1, 1] / (c * c)
        cBS = (cov[0, 1] + cov[1, 1]) / c
    glob[0] = B
    glob[1] = slope
    glob[2] = sigma2 * vB
    glob[3] = sigma2 * vS
    glob[4] = sigma2 * cBS
    glob[5] = math.sqrt(r2 / N)
    conv = cv and (k_fixed == 0 or kk == k_fixed) and (kk == 0 or glob[5] <= max_rel * a_max)
    glob[6] = 1.0 if conv else 0.0
    glob[7] = kk + 0.5  # + 0.5: "defined" even with zero tones (0 = nothing held)
