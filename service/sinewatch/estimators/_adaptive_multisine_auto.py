"""``adaptive-multisine``: the automatic-rate mode (``band_hz``) of B. Chen, G. Pin, W. M. Ng,
S. Y. Hui, T. Parisini, "An adaptive observer-based robust estimator of multi-sinusoidal
signals", IEEE Trans. Automatic Control 63(6), 1618-1631, 2018: its design AD1-AD8 (described in
:mod:`sinewatch.estimators.adaptive_multisine`), the pole placement and generalised eigenvalues it
takes at every sample, the general compiled kernel for any n, and the kernel that dispatches
between it and the explicit-gain mode (:mod:`sinewatch.estimators._adaptive_multisine_explicit`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sinewatch.estimators import _adaptive_multisine_explicit as explicit
from sinewatch.estimators.base import kernel

_DESIGN_KEYS = ("a", "poles", "filter_poles", "filter_gains", "mu", "rho", "mu_a", "omega0")


# ---- automatic design ---------------------------------------------------------------------------
#: The fields only the explicit mode reads (rejected with ``band_hz``).
EXPLICIT_ONLY = (
    "omega_unit_rad_s",
    "amplitude_unit",
    *_DESIGN_KEYS,
    "omega_max",
    "omega_ranges",
    "adaptation_delay",
    "level_time",
    "level_ratio",
    "min_separation",
    "convergence_time",
)

#: Samples per period of the band's top (with its margin) the automatic mode needs.
MIN_SAMPLES_PER_PERIOD = 10.0

#: The constants of the automatic design AD1-AD8 (module docstring), dimensionless.
DESIGN = {
    "p_min": 0.65,  # AD2: slowest observer pole / sqrt(omegah_1(0))
    "p_max": 1.3,  # AD2: fastest observer pole / sqrt(omegah_1(0))
    "rho_rel": 0.2,  # AD4: rho^2 = rho_rel * smoothed tr(Xi^T Xi) / n
    "kappa": 0.2,  # AD5: mu = kappa |slowest pole| / lambda_typ; no direction adapts faster
    "lambda_typ": 0.008,  # AD5: the excitation above which a direction's rate is capped
    "band_margin": 0.1,  # AD6: the clips are [f_lo (1 - m), f_hi (1 + m)]
    "separation": 0.15,  # AD6: adjacent components at least this fraction apart
    "dwell_poles": 2.0,  # AD7: dwell = this / |slowest pole|
    "recentre": 0.02,  # AD8: re-centre when some |thetah_i| exceeds this fraction of |a_i|
    "convergence_poles": 10.0,  # smoothing time of the convergence test = this / |slowest pole|
    "level_poles": 1.0,  # smoothing time of tr(Xi^T Xi) (AD4) = this / |slowest pole|
}


def auto_design(n: int, bias: bool, band_hz: tuple[float, float]) -> dict[str, Any]:
    """AD1-AD7: a, poles, F_f, B_f, omega0 (lists), mu, rho_rel, mu_a, dwell, times (floats),
    in units of ``w_ref = 2 pi f_hi``; ``w_ref`` itself in rad/s."""
    lo, hi = band_hz
    beta = lo / hi
    w0 = [beta ** (1.0 - (i + 0.5) / n) for i in range(n)]  # AD1
    nx = 2 * n + int(bias)
    anchor = math.sqrt(w0[0])  # geometric mean of the lowest initial frequency and f_hi
    p_lo, p_hi = DESIGN["p_min"] * anchor, DESIGN["p_max"] * anchor
    poles = [-p_lo * (p_hi / p_lo) ** (j / (nx - 1)) for j in range(nx)] if nx > 1 else [-p_lo]  # AD2
    slow = p_lo
    return {
        "w_ref": 2.0 * math.pi * hi,
        "a": [-w * w for w in w0],
        "poles": poles,
        "filter_poles": [-w0[j + 1] for j in range(n - 1)],  # AD3
        "filter_gains": [w0[j + 1] for j in range(n - 1)],
        "omega0": w0,
        "mu": DESIGN["kappa"] * slow / DESIGN["lambda_typ"],  # AD5
        "lambda_cap": DESIGN["lambda_typ"],
        "rho_rel": DESIGN["rho_rel"],
        "mu_a": slow / (w0[0] * w0[0]),
        "dwell": DESIGN["dwell_poles"] / slow,  # AD7
        "convergence_time": DESIGN["convergence_poles"] / slow,
        "level_time": DESIGN["level_poles"] / slow,
        "w_lo": beta * (1.0 - DESIGN["band_margin"]),  # AD6
        "w_hi": 1.0 + DESIGN["band_margin"],
    }


# packed constants of the automatic mode: ``ci`` = n, nx, nf, nz, 0, bias, 1 (the mode flag);
# ``cf`` = the scalars below, then the observer poles (nx), F_f (nf), B_f (nf).
_K_H, _K_MU, _K_RHO2, _K_MUA, _K_DHI, _K_DLO, _K_TBAR, _K_OMU = 0, 1, 2, 3, 4, 5, 6, 7
_K_MINA, _K_FADE, _K_CALPHA, _K_CTOL, _K_DELAY, _K_ZMAX, _K_LALPHA = 8, 9, 10, 11, 12, 13, 14
_K_OMLO, _K_OMHI, _K_RC, _K_SEP, _K_XIFLOOR, _K_PALPHA, _K_LCAP = 15, 16, 17, 18, 19, 20, 21
_N_K = 22
_I_MODE = 6
# the scalars of the automatic mode's state, after the per-component part
_S_CLOCK, _S_MEAN, _S_POW, _S_STARTED, _S_XI, _S_POWL = 0, 1, 2, 3, 4, 5
_N_S = 6


@kernel
def _gen_eig(G: np.ndarray, n: int) -> None:
    """``Phi v = lambda M v`` with ``M = R R^T``, on the packed ``G`` (5, n, n): ``G[0]`` Phi,
    ``G[1]`` R (lower), ``G[2]`` scratch, out: ``G[3]`` W (columns), ``G[4, 0]`` lambda
    (decreasing). ``S = R^-1 Phi R^-T`` by closed form (n = 2) or cyclic Jacobi; ``v = R^-T w``.
    One array argument: numba counts a reference per array passed (an atomic operation each)."""
    for i in range(n):  # S = R^-1 Phi (forward substitution, row by row: one division a row)
        inv = 1.0 / G[1, i, i]
        for j in range(n):
            acc = G[0, i, j]
            for k in range(i):
                acc -= G[1, i, k] * G[2, k, j]
            G[2, i, j] = acc * inv
    # the same substitution on the other side (columns, R transposed): two loops alike by nature
    for j in range(n):  # S <- S R^-T (forward substitution, column by column)
        inv = 1.0 / G[1, j, j]
        for i in range(n):
            acc = G[2, i, j]
            for k in range(j):
                acc -= G[2, i, k] * G[1, j, k]
            G[2, i, j] = acc * inv
    if n == 2:  # closed form: the eigenvalues of [[a, b], [b, c]] and the rotation that diagonalises it
        a = G[2, 0, 0]
        b = 0.5 * (G[2, 0, 1] + G[2, 1, 0])
        c = G[2, 1, 1]
        half = 0.5 * (a - c)
        r = math.sqrt(half * half + b * b)
        G[4, 0, 0] = 0.5 * (a + c) + r
        G[4, 0, 1] = 0.5 * (a + c) - r
        if r == 0.0:
            cs, sn = 1.0, 0.0
        elif half >= 0.0:  # first eigenvector (cos, sin) of the larger eigenvalue
            t = b / (half + r)
            cs = 1.0 / math.sqrt(1.0 + t * t)
            sn = t * cs
        else:
            t = b / (r - half)
            sn = 1.0 / math.sqrt(1.0 + t * t)
            cs = t * sn
        G[3, 0, 0] = cs
        G[3, 1, 0] = sn
        G[3, 0, 1] = -sn
        G[3, 1, 1] = cs
        return
    for i in range(n):  # symmetric up to rounding: symmetrise, or Jacobi never meets its tolerance
        for j in range(i):
            v = 0.5 * (G[2, i, j] + G[2, j, i])
            G[2, i, j] = v
            G[2, j, i] = v
    for i in range(n):
        for j in range(n):
            G[3, i, j] = 1.0 if i == j else 0.0
    for _sweep in range(30):
        off = 0.0
        tot = 0.0
        for i in range(n):
            tot += G[2, i, i] * G[2, i, i]
            for j in range(i + 1, n):
                off += G[2, i, j] * G[2, i, j]
        if off <= 1e-30 * tot or off == 0.0:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = G[2, p, q]
                if apq == 0.0:
                    continue
                theta = (G[2, q, q] - G[2, p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):
                    skp = G[2, k, p]
                    skq = G[2, k, q]
                    G[2, k, p] = c * skp - s * skq
                    G[2, k, q] = s * skp + c * skq
                for k in range(n):
                    spk = G[2, p, k]
                    sqk = G[2, q, k]
                    G[2, p, k] = c * spk - s * sqk
                    G[2, q, k] = s * spk + c * sqk
                for k in range(n):
                    wkp = G[3, k, p]
                    wkq = G[3, k, q]
                    G[3, k, p] = c * wkp - s * wkq
                    G[3, k, q] = s * wkp + c * wkq
    for i in range(n):
        G[4, 0, i] = G[2, i, i]
    for i in range(n):  # selection sort, decreasing
        best = i
        for j in range(i + 1, n):
            if G[4, 0, j] > G[4, 0, best]:
                best = j
        if best != i:
            tmp = G[4, 0, i]
            G[4, 0, i] = G[4, 0, best]
            G[4, 0, best] = tmp
            for k in range(n):
                tmp = G[3, k, i]
                G[3, k, i] = G[3, k, best]
                G[3, k, best] = tmp


@kernel
def _place(s: np.ndarray, oa: int, oL: int, poles: np.ndarray, n: int, bias: int) -> None:
    """L_x with eig(F_x - L_x C_x) = poles for F_x = blockdiag(J_i, 0), a = s[oa : oa + n] < 0,
    into s[oL : oL + nx]. Closed form (matrix determinant lemma): with D(s) = s^b prod(s^2 -
    a_k) and P(s) = prod(s - p_m), ``l_2i + j w_i l_2i-1 = P(j w_i) / D_i(j w_i)`` at
    ``w_i = sqrt(-a_i)``, ``D_i = D / (s^2 - a_i)``, and ``l_bias = P(0) / prod(-a_k)``."""
    nx = 2 * n + bias
    for i in range(n):
        om = -s[oa + i]
        w = math.sqrt(om)
        sj = complex(0.0, w)
        pv = complex(1.0, 0.0)
        for m in range(nx):
            pv *= sj - poles[m]
        dv = sj if bias else complex(1.0, 0.0)
        for k in range(n):
            if k != i:
                dv *= -s[oa + k] - om
        r = pv / dv
        s[oL + 2 * i + 1] = r.real
        s[oL + 2 * i] = r.imag / w
    if bias:
        p0 = 1.0
        for m in range(nx):
            p0 *= -poles[m]
        d0 = 1.0
        for k in range(n):
            d0 *= -s[oa + k]
        s[oL + nx - 1] = p0 / d0


@kernel(inline="always")
def _input_level(
    yk: float, started: float, mean: float, pw: float, pwl: float, p_alpha: float, min_a: float
) -> tuple[float, float, float, float, bool]:
    """AD4 and AD7's input level, one sample: (started, mean, AC power, its slow mean, present).
    The signal is present above ``min_a`` and above a quarter of its power over ten times as
    long (a signal that stops is absent within ~1.4 periods of omegah_1(0)). Scalars only, so
    every kernel inlines it without reference counting."""
    if started == 0.0:
        started = 1.0
        mean = yk
    mean += p_alpha * (yk - mean)
    dy = yk - mean
    pw += p_alpha * (dy * dy - pw)
    pwl += 0.1 * p_alpha * (dy * dy - pwl)
    return started, mean, pw, pwl, 2.0 * pw >= min_a * min_a and pw >= 0.25 * pwl


@kernel(inline="always")
def _frequency_and_phase(om: float, x1: float, cph: float, h: float, om_u: float) -> tuple[float, float]:
    """(8) and (10) for one component from ``Omegah = om > 0``: the frequency in Hz of the sampled
    oscillator, omega_d from ``2 sin(omega_d h / 2) = h sqrt(Omegah)``, and the phase from
    ``x_{2i-1} = A sin(phi)`` and ``cph = A cos(phi) sin(omega_d h)``."""
    cd = 1.0 - 0.5 * h * h * om  # cos(omega_d h)
    wd = 2.0 / h * math.asin(min(0.5 * h * math.sqrt(om), 1.0))
    return wd * om_u / (2.0 * math.pi), math.atan2(x1, cph / math.sqrt(max(1.0 - cd * cd, 1e-300)))


@kernel(inline="always")
def _component_outputs(
    om: float, x1: float, x2: float, A: float, wb: float, dv: float, h: float, mu_a: float, c_alpha: float,
    c_tol: float,
) -> tuple[bool, float, float, float, float, bool]:  # fmt: skip
    """One component's outputs at t_k from ``Omegah = om``, ``x_{2i-1} = x1``, ``x_{2i} = x2``:
    (ok: om > 0, A cos(phi) sin(omega_d h) for (10), A (9)/(11), smoothed Omegah, its smoothed
    deviation, settled: deviation within 2 convergence_tol). Scalars: inlined, no reference counts."""
    if not om > 0.0:
        return False, 0.0, A, wb, dv, False
    cd = 1.0 - 0.5 * h * h * om  # cos(omega_d h)
    sd2 = max(1.0 - cd * cd, 1e-300)  # sin^2(omega_d h)
    num = h * x2 + x1 * (1.0 - cd)  # A cos(phi) sin(omega_d h)
    A += min(h * mu_a * om, 1.0) * (math.sqrt(x1 * x1 + num * num / sd2) - A)  # (9), (11)
    wb += c_alpha * (om - wb)
    dv += c_alpha * (abs(om - wb) - dv)
    return True, num, A, wb, dv, dv <= 2.0 * c_tol * wb


@kernel(inline="always")
def sample_and_row(y: np.ndarray, k: int, nsamp: int, last_only: bool) -> tuple[float, bool, int]:
    """Sample ``k`` of ``y``, whether its outputs are written (every row, or the block's last
    with ``last_only``) and the row they go to; the head of every automatic-rate kernel's loop."""
    return y[k], (not last_only) or k == nsamp - 1, 0 if last_only else k


@kernel(inline="always")
def auto_gains(
    cf: np.ndarray,
) -> tuple[
    float, float, float, float, float, float, float, float, float, float, float, float, float, float, float,
]:  # fmt: skip
    """The automatic mode's gains and thresholds from ``cf``, read in one place for
    :func:`auto_kernel` and its written-out n = 1, 2 forms: (h, mu, rho^2 relative, mu_a,
    delta_high, delta_low, Tbar, omega_u, min amplitude, fade, c_alpha, c_tol, delay, z_max,
    l_alpha)."""
    return (
        cf[_K_H], cf[_K_MU], cf[_K_RHO2], cf[_K_MUA], cf[_K_DHI], cf[_K_DLO], cf[_K_TBAR], cf[_K_OMU], cf[_K_MINA],
        cf[_K_FADE], cf[_K_CALPHA], cf[_K_CTOL], cf[_K_DELAY], cf[_K_ZMAX], cf[_K_LALPHA],
    )  # fmt: skip


@kernel(inline="always")
def auto_bounds(cf: np.ndarray) -> tuple[float, float, float, float, float, float, float]:
    """The band and the level constants from ``cf``: (omega_lo, omega_hi, rc, separation, the
    floor of Xi's smoothed size, p_alpha, the cap of L)."""
    return cf[_K_OMLO], cf[_K_OMHI], cf[_K_RC], cf[_K_SEP], cf[_K_XIFLOOR], cf[_K_PALPHA], cf[_K_LCAP]


@kernel(inline="always")
def auto_offsets(n: int, nf: int, nz: int) -> tuple[int, int, int, int, int, int, int, int, int, int]:
    """The automatic mode's state layout, after the output filter's ``nf`` states: the offsets of
    zh (nz), Xi (nz x n), thetah, A, psi, omega_bar, the dwell, the scalars (``_N_S``), a (n,
    re-centred, AD8) and L_x (re-placed with a). The one definition for :func:`auto_kernel` and
    its written-out forms (the explicit mode's state has its own)."""
    oth = nf + nz + nz * n  # zh and Xi first
    osc = oth + 5 * n  # five blocks of n: thetah, A, psi, omega_bar, dwell
    oa_c = osc + _N_S
    return nf, nf + nz, oth, oth + n, oth + 2 * n, oth + 3 * n, oth + 4 * n, osc, oa_c, oa_c + n


@kernel(inline="always")
def level_state(s: np.ndarray, osc: int) -> tuple[float, float, float, float, float, float]:
    """The scalars of the input level and the observer's clock at ``osc`` in the state: (clock,
    mean, AC power, started, Xi's smoothed size, the power's slow mean)."""
    return s[osc + _S_CLOCK], s[osc + _S_MEAN], s[osc + _S_POW], s[osc + _S_STARTED], s[osc + _S_XI], s[osc + _S_POWL]


@kernel
def auto_kernel(
    y: np.ndarray, state: np.ndarray, cf: np.ndarray, ci: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """The automatic mode over block ``y`` from ``state``: ``(out, extras, sse, new_state)``,
    columns as :func:`adaptive_multisine_kernel`. One symplectic-Euler step of (12), (16),
    (17), (19)-(22) and (11) per sample. ``M = L D L^T`` (no square root) serves the law (22)
    while every direction is on, and the excitation test (23)-(25) is then the sign of the
    pivots of ``Phi_Xi - delta_low M`` (positive definite: every lambda_i >= delta_low, all
    stay on); otherwise the generalised eigen-decomposition on ``R = L D^(1/2)``. No compiled
    helper taking arrays is called per sample: numba counts a reference (an atomic operation)
    per array passed, which cost about 20 % of the loop."""
    n, nx, nf, nz, bias = ci[0], ci[1], ci[2], ci[3], ci[5]
    h, mu, rho2rel, mu_a, d_hi, d_lo, tbar, om_u, min_a, fade, c_alpha, c_tol, delay, zmax, l_alpha = auto_gains(cf)
    om_lo, om_hi, rc, sep, xi_floor, p_alpha, lcap = auto_bounds(cf)
    oFf = _N_K + nx  # the output filter's F_f and B_f in cf
    oBf = oFf + nf
    oz, oxi, oth, oA, ops, owb, odv, osc, oa_c, oL = auto_offsets(n, nf, nz)
    poles = cf[_N_K : _N_K + nx]
    s = state.copy()
    nrow = 1 if last_only else y.shape[0]
    out = np.empty((nrow, 3 * n + 2))
    ext = np.empty((nrow, 3 * n + 2))
    cx = np.empty((n, n))  # C_z Xi
    M = np.empty((n, n))
    T = np.empty((n, n))
    L = np.zeros((n, n))  # M = L D L^T, L unit lower
    D = np.empty(n)
    Dinv = np.empty(n)
    # the generalised eigen-problem's packed arrays (one argument for _gen_eig): Phi_Xi, R, scratch,
    # W, lambda; views made once per block (in the loop each would count a reference)
    G = np.zeros((5, n, n))
    Phi = G[0]
    R = G[1]
    W = G[3]
    lam = G[4, 0]
    ev = np.empty(n)  # C_z zh - eta
    g = np.empty(n)
    q = np.empty(n)
    td = np.empty(n)  # thetah'
    xo = np.empty(n)  # new x_{2i-1} of zh
    dz = np.empty(nz)
    two_pi = 2.0 * math.pi
    tb2 = tbar * tbar
    sse = 0.0
    nsamp = y.shape[0]
    for k in range(nsamp):
        yk, write, j = sample_and_row(y, k, nsamp, last_only)
        # AD4: smoothed mean and AC power of the input; AD7: is the signal present
        s[osc + _S_STARTED], s[osc + _S_MEAN], s[osc + _S_POW], s[osc + _S_POWL], present = _input_level(
            yk, s[osc + _S_STARTED], s[osc + _S_MEAN], s[osc + _S_POW], s[osc + _S_POWL], p_alpha, min_a
        )
        # output error C_z zh - eta (16), (22)
        c = s[oz + nx - 1] if bias else 0.0
        for i in range(n):
            c += s[oz + 2 * i]
        ev[0] = c - yk
        sse += ev[0] * ev[0]
        for jj in range(1, n):
            ev[jj] = s[oz + nx + jj - 1] - s[jj - 1]
        # C_z Xi, M = Xi^T Xi + rho^2 I, Phi_Xi = (C_z Xi)^T C_z Xi (23)
        for i in range(n):
            b = oxi + i * nz
            acc = s[b + nx - 1] if bias else 0.0
            for r in range(n):
                acc += s[b + 2 * r]
            cx[0, i] = acc
            for jj in range(1, n):
                cx[jj, i] = s[b + nx + jj - 1]
        for i in range(n):
            bi = oxi + i * nz
            for i2 in range(i + 1):
                bj = oxi + i2 * nz
                acc = 0.0
                for r in range(nz):
                    acc += s[bi + r] * s[bj + r]
                M[i, i2] = acc
                acc = 0.0
                for r in range(n):
                    acc += cx[r, i] * cx[r, i2]
                Phi[i, i2] = acc
                Phi[i2, i] = acc
        # AD4: rho^2 relative to the smoothed size of Xi, floored
        tr = 0.0
        for i in range(n):
            tr += M[i, i]
        # (the smoothed size up to the previous sample: this sample's joins the smoother after,
        # so that the kernels written out for n = 1, 2 know rho^2 before they know M)
        rho2 = rho2rel * max(s[osc + _S_XI], xi_floor)
        s[osc + _S_XI] += l_alpha * (tr / n - s[osc + _S_XI])
        for i in range(n):
            M[i, i] += rho2
        # M = L D L^T (no square root, one division per pivot); M >= rho^2 I guards rounding.
        # Written out here: a compiled helper taking arrays costs atomic reference counts per call
        for jj in range(n):
            d = M[jj, jj]
            for kk in range(jj):
                d -= L[jj, kk] * L[jj, kk] * D[kk]
            d = max(d, rho2)
            D[jj] = d
            inv = 1.0 / d
            Dinv[jj] = inv
            for i in range(jj + 1, n):
                acc = M[i, jj]
                for kk in range(jj):
                    acc -= L[i, kk] * L[jj, kk] * D[kk]
                L[i, jj] = acc * inv
        # (25): while every psi_i is on, all stay on iff T = Phi_Xi - delta_low M > 0, i.e. every
        # pivot of its L D L^T is positive (T, overwritten by the elimination, holds them)
        n_on = 0
        for i in range(n):
            if s[ops + i] != 0.0:
                n_on += 1
        fast = False
        if n_on == n:
            for i in range(n):
                for i2 in range(i + 1):
                    T[i, i2] = Phi[i, i2] - d_lo * M[i, i2]
            fast = True
            for jj in range(n):
                d = T[jj, jj]
                if not d > 0.0:
                    fast = False
                    break
                if jj < n - 1:
                    inv = 1.0 / d
                    for i in range(jj + 1, n):
                        f = T[i, jj] * inv
                        for i2 in range(jj + 1, i + 1):
                            T[i, i2] -= f * T[i2, jj]
        # AD5: every lambda_i <= tr(M^-1 Phi_Xi) = sum_r |D^-1/2 L^-1 (C_z Xi)^T e_r|^2; above
        # lambda_cap the law (22) runs on the eigen-decomposition, each rate capped (below)
        lsum = 0.0
        for r in range(n):
            for i in range(n):
                acc = cx[r, i]
                for kk in range(i):
                    acc -= L[i, kk] * q[kk]
                q[i] = acc
                lsum += acc * acc * Dinv[i]
        capped = lsum > lcap
        if not fast or write or capped:
            for jj in range(n):  # the Cholesky factor R = L D^(1/2) of M
                rj = math.sqrt(D[jj])
                R[jj, jj] = rj
                for i in range(jj + 1, n):
                    R[i, jj] = L[i, jj] * rj
            _gen_eig(G, n)
        if not fast:
            n_on = 0
            for i in range(n):
                if lam[i] >= d_hi:
                    s[ops + i] = 1.0
                elif lam[i] < d_lo:
                    s[ops + i] = 0.0
                if s[ops + i] != 0.0:
                    n_on += 1
        # AD7: settling dwell from the start and from the signal's return; while the signal is
        # absent nothing adapts on the observer's free response, and the convergence test
        # starts over (its smoothed deviation is reset to 100 %). Not re-armed by a total
        # dis-excitation: with one component lambda_1 passes zero twice a period.
        if not present:
            for i in range(n):
                s[odv + i] = abs(s[owb + i])
            s[osc + _S_CLOCK] = 0.0
        else:
            s[osc + _S_CLOCK] = min(s[osc + _S_CLOCK] + h, delay)
        adapting = s[osc + _S_CLOCK] >= delay and n_on > 0
        # (22) thetah'_unc = -mu V Psi V^T Xi^T C_z^T e, V V^T = M^-1
        for i in range(n):
            td[i] = 0.0
        if adapting:
            for i in range(n):  # g = (C_z Xi)^T e
                acc = 0.0
                for r in range(n):
                    acc += cx[r, i] * ev[r]
                g[i] = acc
            if n_on == n and not capped:  # td = M^-1 g = L^-T D^-1 L^-1 g
                for i in range(n):
                    acc = g[i]
                    for kk in range(i):
                        acc -= L[i, kk] * q[kk]
                    q[i] = acc
                for i in range(n - 1, -1, -1):
                    acc = q[i] * Dinv[i]
                    for kk in range(i + 1, n):
                        acc -= L[kk, i] * td[kk]
                    td[i] = acc
            else:  # td = R^-T W Psi W^T R^-1 g
                for i in range(n):  # q = R^-1 g
                    acc = g[i]
                    for kk in range(i):
                        acc -= R[i, kk] * q[kk]
                    q[i] = acc / R[i, i]
                for i in range(n):  # q <- W Psi W^T q
                    acc = 0.0
                    for kk in range(n):
                        acc += W[kk, i] * q[kk]
                    g[i] = acc * s[ops + i]
                    if lam[i] > lcap:  # AD5: rate mu lambda_i capped at mu lambda_typ = kappa |p|
                        g[i] *= lcap / lam[i]
                for i in range(n):
                    acc = 0.0
                    for kk in range(n):
                        acc += W[i, kk] * g[kk]
                    q[i] = acc
                for i in range(n - 1, -1, -1):  # R^-T q
                    acc = q[i]
                    for kk in range(i + 1, n):
                        acc -= R[kk, i] * td[kk]
                    td[i] = acc / R[i, i]
            tt = 0.0
            tu = 0.0
            for i in range(n):
                td[i] *= -mu
                tt += s[oth + i] * s[oth + i]
                tu += s[oth + i] * td[i]
            if tt >= tb2 and tu > 0.0:  # projection (19)-(21)
                for i in range(n):
                    td[i] -= s[oth + i] * tu / tb2
            for i in range(n):  # AD6: the band's clips (Remark 3.1)
                om2 = s[oth + i] - s[oa_c + i]
                if (om2 <= om_lo and td[i] < 0.0) or (om2 >= om_hi and td[i] > 0.0):
                    td[i] = 0.0
            for i in range(n - 1):  # AD6: the components stay ordered and apart
                lo2 = s[oth + i] - s[oa_c + i]
                hi2 = s[oth + i + 1] - s[oa_c + i + 1]
                if hi2 <= lo2 * sep and td[i + 1] < td[i]:
                    mid = 0.5 * (td[i] + td[i + 1])
                    td[i] = mid
                    td[i + 1] = mid
        # outputs at t_k, (8)-(10) with the sampled-oscillator relations; (11); convergence
        amax = 0.0
        for i in range(n):
            amax = max(amax, s[oA + i])
        thr = max(fade * amax, min_a)
        all_ok = adapting and present
        for i in range(n):
            om2 = s[oth + i] - s[oa_c + i]
            x1 = s[oz + 2 * i]
            x2 = s[oz + 2 * i + 1]
            ok = om2 > 0.0
            if ok:
                cd = 1.0 - 0.5 * h * h * om2  # cos(omega_d h)
                sd2 = max(1.0 - cd * cd, 1e-300)  # sin^2(omega_d h)
                num = h * x2 + x1 * (1.0 - cd)  # A cos(phi) sin(omega_d h)
                ainst = math.sqrt(x1 * x1 + num * num / sd2)
                s[oA + i] += min(h * mu_a * om2, 1.0) * (ainst - s[oA + i])  # (11)
                s[owb + i] += c_alpha * (om2 - s[owb + i])
                s[odv + i] += c_alpha * (abs(om2 - s[owb + i]) - s[odv + i])
                if not s[odv + i] <= 2.0 * c_tol * s[owb + i]:
                    all_ok = False
            else:
                all_ok = False
            faded = not s[oA + i] >= thr
            if faded:
                all_ok = False
            if write:
                if ok and not faded:
                    wd = 2.0 / h * math.asin(min(0.5 * h * math.sqrt(om2), 1.0))
                    out[j, i] = wd * om_u / two_pi
                    out[j, 2 * n + i] = math.atan2(x1, num / math.sqrt(sd2))
                else:
                    out[j, i] = math.nan
                    out[j, 2 * n + i] = math.nan
                out[j, n + i] = s[oA + i] if ok else math.nan
                ext[j, i] = lam[i]
                ext[j, n + i] = s[ops + i]
                ext[j, 2 * n + i] = 1.0 if faded else 0.0
        for i in range(n):  # two components on one line are not a converged estimate
            for i2 in range(i + 1, n):
                if not abs(s[owb + i] - s[owb + i2]) > 2.0 * c_tol * max(s[owb + i], s[owb + i2]):
                    all_ok = False
        if write:
            out[j, 3 * n] = s[oz + nx - 1] if bias else 0.0
            out[j, 3 * n + 1] = 1.0 if all_ok else 0.0
            ext[j, 3 * n] = 1.0 if present else 0.0
        # ---- step to t_{k+1}: (16) zh, with Xi thetah' from the current Xi
        any_td = False
        for i in range(n):
            if td[i] != 0.0:
                any_td = True
        for r in range(nz):
            dz[r] = 0.0
        if any_td:
            for i in range(n):
                b = oxi + i * nz
                for r in range(nz):
                    dz[r] += s[b + r] * td[i]
        inj = yk - c  # L (eta - C_z zh): L acts on the first output only
        for i in range(n):
            r = oz + 2 * i
            x1 = s[r] + h * (s[r + 1] + s[oL + 2 * i] * inj + dz[2 * i])
            s[r + 1] += h * ((s[oa_c + i] - s[oth + i]) * x1 + s[oL + 2 * i + 1] * inj + dz[2 * i + 1])
            s[r] = x1
            xo[i] = x1
        if bias:
            s[oz + nx - 1] += h * (s[oL + nx - 1] * inj + dz[nx - 1])
        for jj in range(nf):
            r = oz + nx + jj
            s[r] += h * (cf[oBf + jj] * c + cf[oFf + jj] * s[r] + dz[nx + jj])
        # (17) xi_i' = A_L xi_i + G_z_i(zh), G_z_i = -x_{2i-1} e_{2i}
        for i in range(n):
            b = oxi + i * nz
            cv = cx[0, i]
            for m in range(n):
                r = b + 2 * m
                x1 = s[r] + h * (s[r + 1] - s[oL + 2 * m] * cv)
                s[r + 1] += h * (s[oa_c + m] * x1 - s[oL + 2 * m + 1] * cv)
                s[r] = x1
            s[b + 2 * i + 1] -= h * xo[i]
            if bias:
                s[b + nx - 1] -= h * s[oL + nx - 1] * cv
            for jj in range(nf):
                r = b + nx + jj
                s[r] += h * (cf[oBf + jj] * cv + cf[oFf + jj] * s[r])
        # (12) the measured output's filter
        for jj in range(nf):
            s[jj] += h * (cf[oFf + jj] * s[jj] + cf[oBf + jj] * yk)
        # (19): thetah, kept in the band's clips and the ball
        for i in range(n):  # as Omegah_i, ordered, apart, inside the band (AD6)
            q[i] = s[oth + i] + h * td[i] - s[oa_c + i]
        q[0] = max(q[0], om_lo)
        for i in range(1, n):
            q[i] = max(q[i], q[i - 1] * sep)
        q[n - 1] = min(q[n - 1], om_hi)
        for i in range(n - 2, -1, -1):
            q[i] = min(q[i], q[i + 1] / sep)
        tt = 0.0
        far = False
        for i in range(n):
            s[oth + i] = s[oa_c + i] + q[i]
            tt += s[oth + i] * s[oth + i]
            if abs(s[oth + i]) > rc * abs(s[oa_c + i]):
                far = True
        if tt > tb2:
            f = tbar / math.sqrt(tt)
            for i in range(n):
                s[oth + i] *= f
        # AD8: re-centre a on the estimates and re-place L_x there (thetah -> 0)
        if far:
            for i in range(n):
                s[oa_c + i] -= s[oth + i]
                s[oth + i] = 0.0
            _place(s, oa_c, oL, poles, n, bias)
        # guard (D7 of the explicit mode): a frozen observer far from the truth can be
        # unstable; restart it from zero, thetah kept
        lim = zmax * (1.0 + abs(s[osc + _S_MEAN]) + math.sqrt(s[osc + _S_POW]))
        bad = False
        for r in range(oz, oxi):
            if not abs(s[r]) <= lim:  # also catches NaN
                bad = True
        if not abs(tr) < math.inf:  # tr(Xi^T Xi) of this sample: Xi finite
            bad = True
        if bad:
            for r in range(oth):
                s[r] = 0.0
            for i in range(n):
                if not abs(s[oth + i]) <= tbar:
                    s[oth + i] = 0.0
                s[ops + i] = 0.0
            s[osc + _S_CLOCK] = 0.0
        if write:
            ext[j, 3 * n + 1] = 1.0 if bad else 0.0
    return out, ext, sse, s


def adaptive_multisine_kernel(
    y: np.ndarray, state: np.ndarray, cf: np.ndarray, ci: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Run the estimator over block ``y`` from ``state``; return ``(out, extras, sse, new_state)``.
    A Python function choosing one of two compiled kernels: compiled, it would be a third copy
    of both (numba generates a caller's machine code again with every kernel it calls linked
    in: 6.3 s of CPU more on a cold cache, ``tests/compile_kernels.py``'s longest task), for
    a saving of ~0.1 us a block.

    ``ci[6]`` selects the mode: 1 the automatic design (:func:`auto_kernel`; for n = 1 and 2 the
    class runs the same written out, :func:`auto_kernel_n1`, :func:`auto_kernel_n2`), 0 the explicit gains
    (:func:`sinewatch.estimators._adaptive_multisine_explicit.explicit_kernel`).
    ``out`` columns: frequency_hz (n), amplitude (n), phase (n), offset, converged;
    ``extras``: lambda (n), psi (n), faded (n), signal present, observer reset. One row per
    sample, or only the last with ``last_only``. Pure: the inputs are not modified."""
    if int(ci[_I_MODE]) == 1:
        return auto_kernel(y, state, cf, ci, last_only)
    return explicit.explicit_kernel(y, state, cf, ci, last_only)
