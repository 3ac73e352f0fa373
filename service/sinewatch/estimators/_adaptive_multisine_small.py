"""``adaptive-multisine``: the automatic-rate kernel written out for n = 1 and n = 2 components
(the class's example and most uses), the observer, filters and gains in registers, the same
operations in the same order as the general :func:`auto_kernel` (hence the same bits, which
``tests/test_adaptive_multisine_small_n.py`` checks). They are long because they are unrolled,
each line a written-out step of the general loop, not logic of their own.
"""

from __future__ import annotations

import math

import numpy as np

from sinewatch.estimators._adaptive_multisine_auto import (
    _K_RC,
    _N_K,
    _S_CLOCK,
    _S_MEAN,
    _S_POW,
    _S_POWL,
    _S_STARTED,
    _S_XI,
    _component_outputs,
    _frequency_and_phase,
    _input_level,
    auto_bounds,
    auto_gains,
    auto_offsets,
    level_state,
    sample_and_row,
)
from sinewatch.estimators.base import fma, kernel


@kernel(inline="always")
def _place_one(om: float, dk: float, poles: np.ndarray, bias: float) -> tuple[float, float]:
    """:func:`_place` for one component, ``(l_2i-1, l_2i)`` from ``Omega_i = -a_i`` and ``dk``, the
    product of ``Omega_k - Omega_i`` over the other components (1 for n = 1): ``l_2i + j w_i
    l_2i-1 = P(j w_i) / D_i(j w_i)``. Inlined into :func:`auto_kernel_n1` and
    :func:`auto_kernel_n2`, so that a re-placement (AD8) calls nothing."""
    w = math.sqrt(om)
    sj = complex(0.0, w)
    pv = complex(1.0, 0.0)
    for m in range(poles.shape[0]):
        pv *= sj - poles[m]
    dv = sj if bias else complex(1.0, 0.0)
    dv *= dk
    r = pv / dv
    return r.imag / w, r.real


@kernel
def auto_kernel_n1(
    y: np.ndarray, state: np.ndarray, cf: np.ndarray, ci: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """:func:`auto_kernel` written out for n = 1, as :func:`auto_kernel_n2` for two: the state in
    locals, no output filter (n_f = 0), ``M`` and ``Phi_Xi`` scalars, so ``lambda_1 = Phi_Xi / M``
    (23) and (25) compares ``Phi_Xi`` with ``delta M``. Agrees with :func:`auto_kernel` to
    rounding (tests/test_adaptive_multisine_small_n.py)."""
    nx, bias = ci[1], ci[5]
    h, mu, rho2rel, mu_a, d_hi, d_lo, tbar, om_u, min_a, fade, c_alpha, c_tol, delay, zmax, l_alpha = auto_gains(cf)
    om_lo, om_hi, rc, _, xi_floor, p_alpha, lcap = auto_bounds(cf)
    poles = cf[_N_K : _N_K + nx]
    oz, oxi, oth, oA, ops, owb, odv, osc, oa_c, oL = auto_offsets(1, 0, nx)  # nf = 0, nz = nx
    s = state.copy()
    # ---- the state as locals: zh = [x_1, x_2, A0], xi_1 likewise (17)
    z1, z2 = s[oz], s[oz + 1]
    z0 = s[oz + 2] if bias else 0.0
    p1, p2 = s[oxi], s[oxi + 1]
    p0 = s[oxi + 2] if bias else 0.0
    th1, A1, ps1, wb1, dv1 = s[oth], s[oA], s[ops], s[owb], s[odv]
    clock, mean, pw, started, sxi, pwl = level_state(s, osc)
    a1 = s[oa_c]
    L1, L2 = s[oL], s[oL + 1]
    L0 = s[oL + 2] if bias else 0.0
    nrow = 1 if last_only else y.shape[0]
    out = np.empty((nrow, 5))
    ext = np.empty((nrow, 5))
    cph = np.empty(nrow)  # A_1 cos(phi_1) sin(omega_d h) per row, for (10)
    tb2 = tbar * tbar
    sse = 0.0
    nsamp = y.shape[0]
    for k in range(nsamp):
        yk, write, j = sample_and_row(y, k, nsamp, last_only)
        # AD4: smoothed mean and AC power of the input; AD7: is the signal present
        started, mean, pw, pwl, present = _input_level(yk, started, mean, pw, pwl, p_alpha, min_a)
        # output error C_z zh - eta (16), (22)
        c = z0 + z1
        e0 = c - yk
        sse += e0 * e0
        # C_z Xi, M = Xi^T Xi + rho^2 (AD4), Phi_Xi = (C_z Xi)^2 (23)
        c01 = p0 + p1
        tr = p1 * p1 + p2 * p2 + p0 * p0
        rho2 = rho2rel * max(sxi, xi_floor)  # (as auto_kernel: the smoothed size before this sample)
        sxi += l_alpha * (tr - sxi)
        M11 = tr + rho2
        P11 = c01 * c01
        # (25) on lambda_1 = Phi_Xi / M >= delta iff Phi_Xi >= delta M
        if P11 >= d_hi * M11:
            ps1 = 1.0
        elif P11 < d_lo * M11:
            ps1 = 0.0
        # AD7: settling dwell, as in auto_kernel
        if not present:
            dv1 = abs(wb1)
            clock = 0.0
        else:
            clock = min(clock + h, delay)
        adapting = clock >= delay and ps1 != 0.0
        # (22) thetah'_unc = -mu M^-1 Xi^T C_z^T e; AD5: above lambda_cap the rate mu lambda_1 is
        # capped at mu lambda_cap, i.e. M^-1 becomes lambda_cap / Phi_Xi
        td1 = 0.0
        if adapting:
            if P11 > lcap * M11:
                td1 = -mu * lcap * c01 * e0 / P11
            else:
                td1 = -mu * c01 * e0 / M11
            tu = th1 * td1
            if th1 * th1 >= tb2 and tu > 0.0:  # projection (19)-(21)
                td1 -= th1 * tu / tb2
            om1 = th1 - a1  # AD6: the band's clips (Remark 3.1)
            if (om1 <= om_lo and td1 < 0.0) or (om1 >= om_hi and td1 > 0.0):
                td1 = 0.0
        # outputs at t_k, (8)-(10) with the sampled-oscillator relations; (11); convergence
        thr = max(fade * max(0.0, A1), min_a)
        all_ok = adapting and present
        om1 = th1 - a1
        ok1, num1, A1, wb1, dv1, settled = _component_outputs(om1, z1, z2, A1, wb1, dv1, h, mu_a, c_alpha, c_tol)
        all_ok = all_ok and settled
        faded1 = not A1 >= thr
        if faded1:
            all_ok = False
        if write:  # Omegah_1, x_1 and A cos(phi) sin(omega_d h): (8), (10) after the loop
            out[j, 0] = om1 if ok1 and not faded1 else math.nan
            out[j, 2] = z1
            cph[j] = num1
            out[j, 1] = A1 if ok1 else math.nan
            out[j, 3] = z0 if bias else 0.0
            out[j, 4] = 1.0 if all_ok else 0.0
            ext[j, 0] = P11 / M11
            ext[j, 1] = ps1
            ext[j, 2] = 1.0 if faded1 else 0.0
            ext[j, 3] = 1.0 if present else 0.0
        # ---- step to t_{k+1}: (16) zh, with Xi thetah' from the current Xi
        inj = yk - c  # L (eta - C_z zh)
        x1 = z1 + h * (z2 + L1 * inj + p1 * td1)
        z2 += h * ((a1 - th1) * x1 + L2 * inj + p2 * td1)
        z1 = x1
        if bias:
            z0 += h * (L0 * inj + p0 * td1)
        # (17) xi_1' = A_L xi_1 + G_z_1(zh), G_z_1 = -x_1 e_2
        xx = p1 + h * (p2 - L1 * c01)
        p2 += h * (a1 * xx - L2 * c01)
        p2 -= h * x1
        p1 = xx
        if bias:
            p0 -= h * L0 * c01
        # (19): thetah, kept in the band's clips (AD6), and by them in the ball (as in auto_kernel_n2)
        th1 = a1 + min(max(th1 + h * td1 - a1, om_lo), om_hi)
        # AD8: re-centre a on the estimate and re-place L_x there (thetah -> 0)
        if abs(th1) > rc * abs(a1):
            a1 -= th1
            th1 = 0.0
            L1, L2 = _place_one(-a1, 1.0, poles, bias)  # as _place, written out for n = 1
            if bias:
                pz = 1.0  # P(0)
                for m in range(nx):
                    pz *= -poles[m]
                L0 = pz / -a1
        # guard (D7 of the explicit mode): restart a diverged observer from zero, thetah kept
        lim = zmax * (1.0 + abs(mean))  # the bound without sqrt(AC power): the common case
        bad = not (abs(z1) <= lim and abs(z2) <= lim and abs(z0) <= lim)
        if bad:  # also NaN; then the full bound
            lim = zmax * (1.0 + abs(mean) + math.sqrt(pw))
            bad = not (abs(z1) <= lim and abs(z2) <= lim and abs(z0) <= lim)
        if not abs(tr) < math.inf:  # tr(Xi^T Xi) of this sample: Xi finite
            bad = True
        if bad:
            z1 = z2 = z0 = 0.0
            p1 = p2 = p0 = 0.0
            if not abs(th1) <= tbar:
                th1 = 0.0
            ps1 = 0.0
            clock = 0.0
        if write:
            ext[j, 4] = 1.0 if bad else 0.0
    # (8) omega_d from 2 sin(omega_d h / 2) = h sqrt(Omegah), (10) the phase: after the loop, so that
    # the loop calls no library function
    for j in range(nrow):
        om = out[j, 0]
        if om == om:  # not NaN: present, not faded
            out[j, 0], out[j, 2] = _frequency_and_phase(om, out[j, 2], cph[j], h, om_u)
        else:
            out[j, 2] = math.nan
    # ---- the locals back into the new state
    s[oz], s[oz + 1], s[oxi], s[oxi + 1] = z1, z2, p1, p2
    if bias:
        s[oz + 2], s[oxi + 2], s[oL + 2] = z0, p0, L0
    s[oth], s[oA], s[ops], s[owb], s[odv] = th1, A1, ps1, wb1, dv1
    s[osc + _S_CLOCK], s[osc + _S_MEAN], s[osc + _S_POW] = clock, mean, pw
    s[osc + _S_STARTED], s[osc + _S_XI], s[osc + _S_POWL] = started, sxi, pwl
    s[oa_c], s[oL], s[oL + 1] = a1, L1, L2
    return out, ext, sse, s


@kernel(inline="always")
def _within(lim: float, z1: float, z2: float, z3: float, z4: float, z0: float, zf: float) -> bool:
    """Every entry of :func:`auto_kernel_n2`'s zh within ``lim`` (False for a NaN), tested in
    order and stopping at the first outside, as its guard's two bounds do."""
    return abs(z1) <= lim and abs(z2) <= lim and abs(z3) <= lim and abs(z4) <= lim and abs(z0) <= lim and abs(zf) <= lim


# :func:`auto_kernel_n2`'s state as one tuple of floats, in this order (a bank keeps entry r in row r
# of its lane-major work array): yf (12); zh = [x_1 .. x_4, A0, yfh] and xi_1, xi_2 likewise (17);
# thetah, Ah, psi, smoothed Omegah and its deviation; the level's scalars; a and L_x (AD8); and the
# block's sum of squared prediction errors
N2_STATE = (
    "yf", "z1", "z2", "z3", "z4", "z0", "zf", "p1", "p2", "p3", "p4", "p0", "pf", "q1", "q2", "q3", "q4",
    "q0", "qf", "th1", "th2", "A1", "A2", "ps1", "ps2", "wb1", "wb2", "dv1", "dv2", "clock", "mean", "pw",
    "started", "sxi", "pwl", "a1", "a2", "L1", "L2", "L3", "L4", "L0", "sse",
)  # fmt: skip
N2_ROW = 17  # the outputs of one sample (:func:`n2_observe`), before (8) and (10)
_N2_ROWS = 3 * 2 + 2  # out's and ext's columns for n = 2


@kernel(inline="always")
def n2_gains(cf: np.ndarray, ci: np.ndarray) -> tuple[float, ...]:
    """The constants of :func:`n2_observe` as one tuple: (h, mu, rho^2 relative, mu_a, delta_high,
    delta_low, Tbar^2, 1 / Tbar^2, omega_lo^2, omega_hi^2, separation, 1 / separation, Xi's floor,
    p_alpha, lambda_cap, F_f and B_f of (12), min amplitude, fade, c_alpha, c_tol, delay, bias as
    1.0 or 0.0, l_alpha)."""
    nx = ci[1]
    h, mu, rho2rel, mu_a, d_hi, d_lo, tbar, _, min_a, fade, c_alpha, c_tol, delay, _, l_alpha = auto_gains(cf)
    om_lo, om_hi, _, sep, xi_floor, p_alpha, lcap = auto_bounds(cf)
    tb2 = tbar * tbar
    return (
        h, mu, rho2rel, mu_a, d_hi, d_lo, tb2, 1.0 / tb2, om_lo, om_hi, sep, 1.0 / sep, xi_floor, p_alpha, lcap,
        cf[_N_K + nx], cf[_N_K + nx + 1], min_a, fade, c_alpha, c_tol, delay, 1.0 if ci[5] else 0.0, l_alpha,
    )  # fmt: skip


@kernel(inline="always")
def n2_load(s: np.ndarray, ci: np.ndarray) -> tuple[float, ...]:
    """The state tuple (:data:`N2_STATE`) from the state array ``s``; the sse 0."""
    nx, bias = ci[1], ci[5]
    oz, oxi, oth, oA, ops, owb, odv, osc, oa_c, oL = auto_offsets(2, 1, nx + 1)  # nf = 1
    b = oxi + nx + 1
    clock, mean, pw, started, sxi, pwl = level_state(s, osc)
    # two tuple literals joined: one of more than 30 entries compiles to a list turned into a
    # tuple (CPython), which numba does not take; so in every 43-entry tuple below
    return (  # noqa: RUF005
        s[0], s[oz], s[oz + 1], s[oz + 2], s[oz + 3], s[oz + 4] if bias else 0.0, s[oz + nx],
        s[oxi], s[oxi + 1], s[oxi + 2], s[oxi + 3], s[oxi + 4] if bias else 0.0, s[oxi + nx],
        s[b], s[b + 1], s[b + 2], s[b + 3], s[b + 4] if bias else 0.0, s[b + nx],
    ) + (
        s[oth], s[oth + 1], s[oA], s[oA + 1], s[ops], s[ops + 1], s[owb], s[owb + 1], s[odv], s[odv + 1],
        clock, mean, pw, started, sxi, pwl, s[oa_c], s[oa_c + 1],
        s[oL], s[oL + 1], s[oL + 2], s[oL + 3], s[oL + 4] if bias else 0.0, 0.0,
    )  # fmt: skip


@kernel(inline="always")
def n2_store(s: np.ndarray, ci: np.ndarray, st: tuple[float, ...]) -> float:
    """The state tuple into the state array ``s`` (which :func:`n2_load` read); returns the sse."""
    nx, bias = ci[1], ci[5]
    oz, oxi, oth, oA, ops, owb, odv, osc, oa_c, oL = auto_offsets(2, 1, nx + 1)
    b = oxi + nx + 1
    (
        yf, z1, z2, z3, z4, z0, zf, p1, p2, p3, p4, p0, pf, q1, q2, q3, q4, q0, qf, th1, th2, A1, A2, ps1,
        ps2, wb1, wb2, dv1, dv2, clock, mean, pw, started, sxi, pwl, a1, a2, L1, L2, L3, L4, L0, sse
    ) = st  # fmt: skip
    s[0] = yf
    s[oz], s[oz + 1], s[oz + 2], s[oz + 3] = z1, z2, z3, z4
    s[oxi], s[oxi + 1], s[oxi + 2], s[oxi + 3] = p1, p2, p3, p4
    s[b], s[b + 1], s[b + 2], s[b + 3] = q1, q2, q3, q4
    if bias:
        s[oz + 4], s[oxi + 4], s[b + 4] = z0, p0, q0
    s[oz + nx], s[oxi + nx], s[b + nx] = zf, pf, qf
    s[oth], s[oth + 1], s[oA], s[oA + 1], s[ops], s[ops + 1] = th1, th2, A1, A2, ps1, ps2
    s[owb], s[owb + 1], s[odv], s[odv + 1] = wb1, wb2, dv1, dv2
    s[osc + _S_CLOCK], s[osc + _S_MEAN], s[osc + _S_POW] = clock, mean, pw
    s[osc + _S_STARTED], s[osc + _S_XI], s[osc + _S_POWL] = started, sxi, pwl
    s[oa_c], s[oa_c + 1] = a1, a2
    s[oL], s[oL + 1], s[oL + 2], s[oL + 3] = L1, L2, L3, L4
    if bias:
        s[oL + 4] = L0
    return sse


@kernel(inline="always")
def n2_observe(
    yk: float, write: bool, st: tuple[float, ...], g: tuple[float, ...]
) -> tuple[tuple[float, ...], tuple[float, ...], float]:
    """One sample ``yk`` of :func:`auto_kernel_n2` up to thetah's step (19): the new state tuple
    (:data:`N2_STATE`), the sample's outputs (:data:`N2_ROW`: out's columns 0-7 before (8) and
    (10), then A_i cos(phi_i) sin(omega_d h), then ext's columns 0-6; the eigenvalues only when
    ``write``) and tr(M) for the guard. Floats and selects only, no array and no library call but
    sqrt: a bank's lanes run it as one vector. The re-centring AD8 (:func:`n2_recentred`) and the
    guard (:func:`n2_guard`) follow it."""
    (
        yf, z1, z2, z3, z4, z0, zf, p1, p2, p3, p4, p0, pf, q1, q2, q3, q4, q0, qf, th1, th2, A1, A2, ps1,
        ps2, wb1, wb2, dv1, dv2, clock, mean, pw, started, sxi, pwl, a1, a2, L1, L2, L3, L4, L0, sse
    ) = st  # fmt: skip
    (
        h, mu, rho2rel, mu_a, d_hi, d_lo, tb2, itb2, om_lo, om_hi, sep, isep, xi_floor, p_alpha, lcap, Ff,
        Bf, min_a, fade, c_alpha, c_tol, delay, bias, l_alpha
    ) = g  # fmt: skip
    # AD4: smoothed mean and AC power of the input; AD7: is the signal present
    started, mean, pw, pwl, present = _input_level(yk, started, mean, pw, pwl, p_alpha, min_a)
    # output error C_z zh - eta (16), (22)
    c = z0 + z1 + z3
    e0 = c - yk
    sse += e0 * e0
    e1 = zf - yf
    # C_z Xi (rows: y, yf), M = Xi^T Xi + rho^2 I, Phi_Xi = (C_z Xi)^T C_z Xi (23)
    c01 = p0 + p1 + p3
    c02 = q0 + q1 + q3
    # The loop's speed is the latency of its critical path: from thetah' through zh (16) to the
    # x_2 of xi_1 and the x_4 of xi_2 (17), the only entries of Xi that wait on this step's
    # law, then through M to the law (22) of the next. So those two enter M last, each
    # product is added by a fused multiply-add, and rho^2 is known before M is.
    # AD4: rho^2 relative to the smoothed size of Xi up to the previous sample, floored
    rho2 = rho2rel * max(sxi, xi_floor)
    m11 = fma(p1, p1, p3 * p3) + fma(p4, p4, fma(p0, p0, pf * pf))
    m22 = fma(q1, q1, q2 * q2) + fma(q3, q3, fma(q0, q0, qf * qf))
    M11 = fma(p2, p2, m11 + rho2)
    M21 = fma(q4, p4, fma(q2, p2, fma(q1, p1, fma(q3, p3, fma(q0, p0, qf * pf)))))
    M22 = fma(q4, q4, m22 + rho2)
    P11 = fma(c01, c01, pf * pf)
    P21 = fma(c02, c01, qf * pf)
    P22 = fma(c02, c02, qf * qf)
    tr = M11 + M22  # with rho^2: finite iff Xi is (the guard)
    sxi += l_alpha * (0.5 * fma(p2, p2, fma(q4, q4, m11 + m22)) - sxi)  # this sample's tr(Xi^T Xi) / 2
    # (25) without the eigenvalues: lambda_2 >= delta iff T = Phi_Xi - delta M >= 0 (T_11, T_22,
    # det T >= 0), lambda_1 < delta iff T < 0 (T_11 < 0 < det T): no division, no root
    t11 = P11 - d_hi * M11
    t22 = P22 - d_hi * M22
    t21 = P21 - d_hi * M21
    det_t = t11 * t22 - t21 * t21
    if not (t11 < 0.0 and det_t > 0.0):  # lambda_1 >= delta_high
        ps1 = 1.0
    if t11 >= 0.0 and t22 >= 0.0 and det_t >= 0.0:  # lambda_2 >= delta_high
        ps2 = 1.0
    t11 = P11 - d_lo * M11
    t22 = P22 - d_lo * M22
    t21 = P21 - d_lo * M21
    det_t = t11 * t22 - t21 * t21
    if t11 < 0.0 and det_t > 0.0:  # lambda_1 < delta_low
        ps1 = 0.0
    if not (t11 >= 0.0 and t22 >= 0.0 and det_t >= 0.0):  # lambda_2 < delta_low
        ps2 = 0.0
    n_on = int(ps1 != 0.0) + int(ps2 != 0.0)
    # AD7: settling dwell, as in auto_kernel
    if not present:
        dv1 = abs(wb1)
        dv2 = abs(wb2)
        clock = 0.0
    else:
        clock = min(clock + h, delay)
    adapting = clock >= delay and n_on > 0
    # the eigenvalues themselves (an output, and the law with one direction on or a rate
    # capped), (23)-(24) in closed form: det(Phi_Xi - lambda M) = det M lambda^2 - b lambda + det Phi_Xi
    # = 0 (det Phi_Xi = det(C_z Xi)^2), the smaller root as det Phi_Xi / (det M lambda_1)
    det_m = max(fma(M11, M22, -(M21 * M21)), M11 * rho2)  # M >= rho^2 I: det M >= M_11 rho^2
    bq = fma(P11, M22, fma(P22, M11, -2.0 * P21 * M21))  # det M tr(M^-1 Phi_Xi) = det M (lambda_1 + lambda_2)
    # the eigen-decomposition is needed while one direction of two is on, or AD5 caps a rate
    # (lambda_1 + lambda_2 above lambda_cap: auto_kernel's test), or for the output
    eig = adapting and (n_on == 1 or bq > lcap * det_m)
    lam1 = 0.0
    lam2 = 0.0
    sq = 0.0
    dc = 0.0
    root = 0.0
    if write or eig:  # lambda_1 = sq / (2 det M), lambda_2 = 2 det Phi_Xi / sq
        dc = fma(c01, qf, -(c02 * pf))
        root = math.sqrt(max(fma(bq, bq, -4.0 * det_m * (dc * dc)), 0.0))  # det M (lambda_1 - lambda_2)
        sq = bq + root
        if write and sq > 0.0:
            lam1 = 0.5 * sq / det_m
            lam2 = 2.0 * dc * dc / sq
    # (22) thetah'_unc = -mu V Psi V^T Xi^T C_z^T e, V V^T = M^-1
    td1 = 0.0
    td2 = 0.0
    if adapting:
        g1 = fma(c01, e0, pf * e1)  # g = (C_z Xi)^T e
        g2 = fma(c02, e0, qf * e1)
        if not eig:  # td = -mu M^-1 g, by the adjugate
            idet = -mu / det_m
            td1 = fma(M22, g1, -(M21 * g2)) * idet
            td2 = fma(M11, g2, -(M21 * g1)) * idet
        else:  # td = -mu V S V^T g, S = diag(s_i), s_i = psi_i min(1, lambda_cap / lambda_i) (AD5)
            # (lambda_1 > lambda_cap iff sq > 2 lambda_cap det M; lambda_2 likewise: no division
            # unless capped)
            s1 = ps1 * (2.0 * lcap * det_m / sq if sq > 2.0 * lcap * det_m else 1.0)
            s2 = ps2 * (lcap * sq / (2.0 * dc * dc) if 2.0 * dc * dc > lcap * sq else 1.0)
            # V S V^T = s_2 M^-1 + (s_1 - s_2) v_1 v_1^T (V V^T = M^-1, V^T M V = I), and
            # v_1 v_1^T = P_1 M^-1 with P_1 = (M^-1 Phi_Xi - lambda_2 I) / (lambda_1 - lambda_2), so
            # with u = adj(M) g = det M M^-1 g and w = adj(M) Phi_Xi u:
            # td = -mu (s_2 root u + (s_1 - s_2) (w - det M lambda_2 u)) / (det M root). No
            # eigenvector: the root and one division are all that wait on the eigenvalues.
            u1 = fma(M22, g1, -(M21 * g2))
            u2 = fma(M11, g2, -(M21 * g1))
            if root > 1e-6 * bq:
                r1 = fma(P11, u1, P21 * u2)  # Phi_Xi u
                r2 = fma(P21, u1, P22 * u2)
                hl = 2.0 * det_m * (dc * dc) / sq  # det M lambda_2 (not (bq - root) / 2: no cancellation)
                w1 = fma(-hl, u1, fma(M22, r1, -(M21 * r2)))
                w2 = fma(-hl, u2, fma(M11, r2, -(M21 * r1)))
                ds = s1 - s2
                sr = s2 * root
                qd = -mu / (det_m * root)
                td1 = fma(sr, u1, ds * w1) * qd
                td2 = fma(sr, u2, ds * w2) * qd
            else:  # lambda_1 = lambda_2 to rounding: every direction is an eigenvector, and
                # V S V^T averaged over them is the mean of s_1 and s_2 times M^-1
                idet = -mu * 0.5 * (s1 + s2) / det_m
                td1 = u1 * idet
                td2 = u2 * idet
        tt = fma(th1, th1, th2 * th2)
        tu = fma(th1, td1, th2 * td2)
        if tt >= tb2 and tu > 0.0:  # projection (19)-(21)
            td1 -= th1 * (tu * itb2)
            td2 -= th2 * (tu * itb2)
        om1 = th1 - a1  # AD6: the band's clips (Remark 3.1)
        om2 = th2 - a2
        if (om1 <= om_lo and td1 < 0.0) or (om1 >= om_hi and td1 > 0.0):
            td1 = 0.0
        if (om2 <= om_lo and td2 < 0.0) or (om2 >= om_hi and td2 > 0.0):
            td2 = 0.0
        if om2 <= om1 * sep and td2 < td1:  # AD6: the components stay ordered and apart
            mid = 0.5 * (td1 + td2)
            td1 = mid
            td2 = mid
    # outputs at t_k, (8)-(10) with the sampled-oscillator relations; (11); convergence
    thr = max(fade * max(0.0, A1, A2), min_a)
    all_ok = adapting and present
    om1 = th1 - a1
    ok1, num1, A1, wb1, dv1, settled = _component_outputs(om1, z1, z2, A1, wb1, dv1, h, mu_a, c_alpha, c_tol)
    all_ok = all_ok and settled
    faded1 = not A1 >= thr
    om2 = th2 - a2
    ok2, num2, A2, wb2, dv2, settled = _component_outputs(om2, z3, z4, A2, wb2, dv2, h, mu_a, c_alpha, c_tol)
    all_ok = all_ok and settled
    faded2 = not A2 >= thr
    if faded1 or faded2:
        all_ok = False
    if not abs(wb1 - wb2) > 2.0 * c_tol * max(wb1, wb2):  # two on one line: not converged
        all_ok = False
    row = (
        om1 if ok1 and not faded1 else math.nan, om2 if ok2 and not faded2 else math.nan,
        A1 if ok1 else math.nan, A2 if ok2 else math.nan, z1, z3, z0 if bias else 0.0, 1.0 if all_ok else 0.0,
        num1, num2, lam1, lam2, ps1, ps2, 1.0 if faded1 else 0.0, 1.0 if faded2 else 0.0, 1.0 if present else 0.0,
    )  # fmt: skip
    # ---- step to t_{k+1}: (16) zh, with Xi thetah' from the current Xi
    inj = yk - c  # L (eta - C_z zh): L acts on the first output only
    x1 = fma(h, fma(L1, inj, z2) + fma(p1, td1, q1 * td2), z1)
    z2 = fma(h, fma(a1 - th1, x1, L2 * inj) + fma(p2, td1, q2 * td2), z2)
    z1 = x1
    x3 = fma(h, fma(L3, inj, z4) + fma(p3, td1, q3 * td2), z3)
    z4 = fma(h, fma(a2 - th2, x3, L4 * inj) + fma(p4, td1, q4 * td2), z4)
    z3 = x3
    if bias:
        z0 = fma(h, fma(L0, inj, fma(p0, td1, q0 * td2)), z0)
    zf = fma(h, fma(Bf, c, Ff * zf) + fma(pf, td1, qf * td2), zf)
    # (17) xi_i' = A_L xi_i + G_z_i(zh), G_z_i = -x_{2i-1} e_{2i}
    xx = fma(h, fma(-L1, c01, p2), p1)
    p2 = fma(-h, x1, fma(h, fma(a1, xx, -L2 * c01), p2))
    p1 = xx
    xx = fma(h, fma(-L3, c01, p4), p3)
    p4 = fma(h, fma(a2, xx, -L4 * c01), p4)
    p3 = xx
    if bias:
        p0 = fma(-h * L0, c01, p0)
    pf = fma(h, fma(Bf, c01, Ff * pf), pf)
    xx = fma(h, fma(-L1, c02, q2), q1)
    q2 = fma(h, fma(a1, xx, -L2 * c02), q2)
    q1 = xx
    xx = fma(h, fma(-L3, c02, q4), q3)
    q4 = fma(-h, x3, fma(h, fma(a2, xx, -L4 * c02), q4))
    q3 = xx
    if bias:
        q0 = fma(-h * L0, c02, q0)
    qf = fma(h, fma(Bf, c02, Ff * qf), qf)
    # (12) the measured output's filter
    yf = fma(h, fma(Ff, yf, Bf * yk), yf)
    # (19): thetah, kept in the band's clips; as Omegah_i, ordered, apart (AD6). The clips keep
    # thetah in the ball |thetah| <= theta_bar of (19)-(21) by themselves: Omegah_i in
    # [w_lo^2, w_hi^2] and a_i too (its initial value, and -Omegah_i at each re-centring), so
    # |thetah_i| = |a_i + Omegah_i| <= w_hi^2 - w_lo^2 = theta_bar / sqrt(n). auto_kernel's
    # rescaling onto the ball is left out: never active, it cost a root and a division on the
    # loop's critical path each sample (the compiler computed them before the test).
    w1 = max(fma(h, td1, th1) - a1, om_lo)
    w2 = min(max(fma(h, td2, th2) - a2, w1 * sep), om_hi)
    w1 = min(w1, w2 * isep)
    th1 = a1 + w1
    th2 = a2 + w2
    return (  # noqa: RUF005
        yf, z1, z2, z3, z4, z0, zf, p1, p2, p3, p4, p0, pf, q1, q2, q3, q4, q0, qf,
    ) + (
        th1, th2, A1, A2, ps1, ps2, wb1, wb2, dv1, dv2,
        clock, mean, pw, started, sxi, pwl, a1, a2, L1, L2, L3, L4, L0, sse,
    ), row, tr  # fmt: skip


@kernel(inline="always")
def n2_recentre_due(st: tuple[float, ...], rc: float) -> bool:
    """AD8's test on the state tuple after :func:`n2_observe`: some ``|thetah_i| > rc |a_i|``."""
    return abs(st[19]) > rc * abs(st[35]) or abs(st[20]) > rc * abs(st[36])


@kernel(inline="always")
def n2_recentred(st: tuple[float, ...], rc: float, poles: np.ndarray, bias: float) -> tuple[float, ...]:
    """AD8 on the state tuple: when due (:func:`n2_recentre_due`), re-centre a on the estimates and
    re-place L_x there (thetah -> 0); else the tuple as it is."""
    (
        yf, z1, z2, z3, z4, z0, zf, p1, p2, p3, p4, p0, pf, q1, q2, q3, q4, q0, qf, th1, th2, A1, A2, ps1,
        ps2, wb1, wb2, dv1, dv2, clock, mean, pw, started, sxi, pwl, a1, a2, L1, L2, L3, L4, L0, sse
    ) = st  # fmt: skip
    if abs(th1) > rc * abs(a1) or abs(th2) > rc * abs(a2):
        a1 -= th1
        a2 -= th2
        th1 = 0.0
        th2 = 0.0
        L1, L2 = _place_one(-a1, -a2 + a1, poles, bias)  # as _place, written out for n = 2
        L3, L4 = _place_one(-a2, -a1 + a2, poles, bias)
        if bias:
            pz = 1.0  # P(0)
            for m in range(poles.shape[0]):
                pz *= -poles[m]
            L0 = pz / (-a1 * -a2)
    return (  # noqa: RUF005
        yf, z1, z2, z3, z4, z0, zf, p1, p2, p3, p4, p0, pf, q1, q2, q3, q4, q0, qf,
    ) + (
        th1, th2, A1, A2, ps1, ps2, wb1, wb2, dv1, dv2,
        clock, mean, pw, started, sxi, pwl, a1, a2, L1, L2, L3, L4, L0, sse,
    )  # fmt: skip


@kernel(inline="always")
def n2_guard(st: tuple[float, ...], tr: float, zmax: float, tbar: float) -> tuple[tuple[float, ...], bool]:
    """The guard (D7 of the explicit mode) on the state tuple: restart a diverged observer from
    zero, thetah kept; ``tr``: this sample's tr(M) (:func:`n2_observe`). Also whether it did."""
    (
        yf, z1, z2, z3, z4, z0, zf, p1, p2, p3, p4, p0, pf, q1, q2, q3, q4, q0, qf, th1, th2, A1, A2, ps1,
        ps2, wb1, wb2, dv1, dv2, clock, mean, pw, started, sxi, pwl, a1, a2, L1, L2, L3, L4, L0, sse
    ) = st  # fmt: skip
    lim = zmax * (1.0 + abs(mean))  # the bound without sqrt(AC power): the common case
    bad = not _within(lim, z1, z2, z3, z4, z0, zf)
    if bad:  # also NaN; then the full bound
        lim = zmax * (1.0 + abs(mean) + math.sqrt(pw))
        bad = not _within(lim, z1, z2, z3, z4, z0, zf)
    if not abs(tr) < math.inf:  # tr(Xi^T Xi) of this sample: Xi finite
        bad = True
    if bad:
        yf = z1 = z2 = z3 = z4 = z0 = zf = 0.0
        p1 = p2 = p3 = p4 = p0 = pf = 0.0
        q1 = q2 = q3 = q4 = q0 = qf = 0.0
        if not abs(th1) <= tbar:
            th1 = 0.0
        if not abs(th2) <= tbar:
            th2 = 0.0
        ps1 = ps2 = 0.0
        clock = 0.0
    return (  # noqa: RUF005
        yf, z1, z2, z3, z4, z0, zf, p1, p2, p3, p4, p0, pf, q1, q2, q3, q4, q0, qf,
    ) + (
        th1, th2, A1, A2, ps1, ps2, wb1, wb2, dv1, dv2,
        clock, mean, pw, started, sxi, pwl, a1, a2, L1, L2, L3, L4, L0, sse,
    ), bad  # fmt: skip


@kernel(inline="always")
def n2_write_row(out: np.ndarray, ext: np.ndarray, cph: np.ndarray, j: int, row: tuple[float, ...], bad: bool) -> None:
    """Row ``j`` of the outputs from a sample's :data:`N2_ROW` values and the guard's verdict:
    Omegah_i, A_i, x_1 and x_3 (turned into (8) and (10) by :func:`n2_phases`), A0, converged;
    A cos(phi) sin(omega_d h); lambda_i, psi_i, faded_i, present, reset."""
    for m in range(8):
        out[j, m] = row[m]
    cph[j, 0] = row[8]
    cph[j, 1] = row[9]
    for m in range(7):
        ext[j, m] = row[10 + m]
    ext[j, 7] = 1.0 if bad else 0.0


@kernel(inline="always")
def n2_phases(out: np.ndarray, cph: np.ndarray, h: float, om_u: float) -> None:
    """(8) omega_d from 2 sin(omega_d h / 2) = h sqrt(Omegah), (10) the phase, on every row: after
    the loop, so that the loop calls no library function (a call would cost the loop its
    registers)."""
    for j in range(out.shape[0]):
        for i in range(2):
            om = out[j, i]
            if om == om:  # not NaN: present, not faded
                out[j, i], out[j, 4 + i] = _frequency_and_phase(om, out[j, 4 + i], cph[j, i], h, om_u)
            else:
                out[j, 4 + i] = math.nan


@kernel
def auto_kernel_n2(
    y: np.ndarray, state: np.ndarray, cf: np.ndarray, ci: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """:func:`auto_kernel` written out for n = 2 (the paper's examples and the bench's): the same
    steps on the same state layout, every state variable a local for the whole block (written
    back at its end) and every 2 x 2 product spelt out, so that the compiler keeps them in
    registers instead of a chain of loads and stores through ``s``. The generalised eigenvalues
    of (23) come in closed form each sample (one square root), so (25) needs no pivot test, and
    the law (22) with one direction on or capped takes the projector onto the first eigenvector
    in closed form instead of the eigenvector; products are fused (:func:`fma`), and the ball
    rescaling of thetah, which the band's clips make inactive, is left out. Agrees with
    :func:`auto_kernel` to rounding (tests/test_adaptive_multisine_small_n.py). With
    ``bias=False`` the A0 state, its sensitivities and its gain are held at zero, which adds exact
    zeros."""
    nx = ci[1]
    h, _, _, _, _, _, tbar, om_u, _, _, _, _, _, zmax, _ = auto_gains(cf)
    rc = cf[_K_RC]
    g = n2_gains(cf, ci)
    poles = cf[_N_K : _N_K + nx]
    st = n2_load(state, ci)
    nrow = 1 if last_only else y.shape[0]
    out = np.empty((nrow, _N2_ROWS))
    ext = np.empty((nrow, _N2_ROWS))
    cph = np.empty((nrow, 2))  # A_i cos(phi_i) sin(omega_d h) per row, for (10)
    nsamp = y.shape[0]
    for k in range(nsamp):
        yk, write, j = sample_and_row(y, k, nsamp, last_only)
        st, row, tr = n2_observe(yk, write, st, g)
        st = n2_recentred(st, rc, poles, g[22])
        st, bad = n2_guard(st, tr, zmax, tbar)
        if write:
            n2_write_row(out, ext, cph, j, row, bad)
    n2_phases(out, cph, h, om_u)
    s = state.copy()
    sse = n2_store(s, ci, st)
    return out, ext, sse, s
