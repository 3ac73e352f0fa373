"""Compiled kernels of ``kkl-biased`` (the maths: :mod:`sinewatch.estimators.kkl_biased`).

The single-channel kernel :func:`kkl_biased_kernel` and :func:`kkl_biased_bank_kernel`, its
bank for :mod:`sinewatch.estimators.bank`, built as ``kkl``'s
(:mod:`sinewatch.estimators.kkl_kernels`): every operation of a sample is a helper that both
call (the centred sums, the inverse map, the read-out, the fit residual), so that every
channel's bits are the single kernel's whatever the bank's size and the channel's position.
The single kernel keeps its branches (one channel: skipping work pays); the bank evaluates
each step for all 8 lanes and selects, which gives the same values where they are used.
"""

from __future__ import annotations

import math

import numpy as np

from sinewatch.estimators import detmath
from sinewatch.estimators.base import kernel
from sinewatch.estimators.kkl_kernels import (
    _RACOS,
    _RASIN,
    _RDEF,
    _RDET,
    _RE2,
    _REF,
    _RENV,
    _RES,
    _RFF,
    _RHALF,
    _RHP,
    _RINV,
    _RJUMP,
    _RLEV,
    _RMU,
    _RNG,
    _RPV,
    _RRR,
    _RS,
    _RSH,
    _RSQ,
    _RSSE,
    _RWTS,
    _RXI,
    _RY,
    _RYP,
    _RYPRED,
    _RZ0,
    _RZ1,
    _RZ2,
    ABS_FLOOR,
    LANES,
    bank_arrays,
    bank_filter,
    bank_good,
    bank_lane_row,
    bank_load,
    bank_next_sample,
    bank_sines,
    bank_store,
    bank_write,
    consistent,
    half_step,
    half_step_of,
    jump_detector,
    next_sample,
    observer_constants,
    observer_head,
    packed_state,
    prediction_error,
    record_sample,
    sqrt,
    undefined_sample,
    write_rows,
)
from sinewatch.estimators.lanes import frozen, select

DC_FLOOR = 1e-9  # |eta_c| below 1e-9 |eta_bar| is rounding of a constant input, not an oscillation

# ---- per-sample helpers, shared by the single kernel and the bank ------------------------


@kernel(inline="always")
def level_step(yk: float, y_avg: float, yv_avg: float, avg_gain: float) -> tuple[float, float]:
    """The running mean and variance of y, advanced by sample ``yk``."""
    y_avg += avg_gain * (yk - y_avg)
    dy = yk - y_avg
    return y_avg, yv_avg + avg_gain * (dy * dy - yv_avg)


@kernel(inline="always")
def run_step(n_run: float, have_prev: float, n_settle: float) -> float:
    """Samples the filters have run, counted up to n_settle (not the first sample)."""
    return select((have_prev != 0.0) & (n_run < n_settle), n_run + 1.0, frozen(n_run))  # (see lanes.frozen)


@kernel(inline="always")
def centred_sums(
    lam: float, c: float, s2: float, a1: float, a2: float, a3: float, a4: float, q2: float
) -> tuple[float, float, float, float, float, float]:
    """The sums over the filters, advanced by filter (lambda~ = lam, eta_c entry c):
    |eta_c|^2, sum lambda~^j eta_c (j = 1..4), sum lambda~^2 eta_c^2."""
    l2c = lam * lam * c
    return s2 + c * c, a1 + lam * c, a2 + l2c, a3 + lam * l2c, a4 + lam * lam * l2c, q2 + l2c * c


@kernel(inline="always")
def live_oscillation(s: float, eta_bar: float, env: float, silence_ratio: float) -> bool:
    """An oscillation to estimate: |eta_c| above zero, above rounding of a constant input
    and above ``silence_ratio`` of its recent peak."""
    return (s > ABS_FLOOR + DC_FLOOR * abs(eta_bar)) & (s >= silence_ratio * env)


@kernel(inline="always")
def biased_inverse_map(
    a1: float, a2: float, a3: float, a4: float, q2: float, s: float,
    kvt: tuple[float, float, float, float, float, float, float, float, float], kk: tuple[float, float, float],
    ik: tuple[float, float, float], det_k0: float, ell: float,
) -> tuple[float, float, float, bool, float, float, float, float]:  # fmt: skip
    """gamma_b on the unit vector eta_c/|eta_c| from the sums of :func:`centred_sums`
    (s = |eta_c|): the 4 x 4 system by its Schur complement in the eigenbasis ``kvt``
    (row-major) / ``kk`` of C^T C (``ik`` = 1/kk, ``det_k0`` = det(C^T C)). Returns
    ``(1/s, det(L_c^T L_c), mu_b, solved, z0, z1, z2, z3)``; ``solved``: the Schur
    complement invertible and x3~ = z3 > 0 (z is meaningless otherwise). Straight-line,
    so that a bank runs it as one vector."""
    inv = 1.0 / s
    # unit eta_c: L_c^T L_c = [[C^T C, c], [c^T, 1]], c = -(a2, a1, 0) / s,
    # r = L_c^T F^2 eta_c = ((a4, a3, a2) / s, -q2 / s^2)
    c0 = -a2 * inv
    c1 = -a1 * inv
    r0 = a4 * inv
    r1 = a3 * inv
    r2 = a2 * inv
    r3 = -q2 * inv * inv
    v00, v01, v02, v10, v11, v12, v20, v21, v22 = kvt
    # into the eigenbasis of C^T C (c has no third entry: sum eta_c = 0)
    ch0 = v00 * c0 + v10 * c1
    ch1 = v01 * c0 + v11 * c1
    ch2 = v02 * c0 + v12 * c1
    rh0 = v00 * r0 + v10 * r1 + v20 * r2
    rh1 = v01 * r0 + v11 * r1 + v21 * r2
    rh2 = v02 * r0 + v12 * r1 + v22 * r2
    # Gram determinant det(L_c^T L_c) = det(C^T C) (1 - c^T (C^T C)^-1 c)
    det = det_k0 * (1.0 - ch0 * ch0 * ik[0] - ch1 * ch1 * ik[1] - ch2 * ch2 * ik[2])
    mu = ell - 2.0 * det
    mu = select(0.0 > mu, 0.0, mu)  # max(mu, 0), as Python's max
    # (C^T C + mu I)^-1 in the eigenbasis; at mu = 0, 1/(k + 0) is 1/k bit for bit, so
    # the select only spares the single kernel three divisions
    i0 = select(mu == 0.0, ik[0], 1.0 / (kk[0] + mu))
    i1 = select(mu == 0.0, ik[1], 1.0 / (kk[1] + mu))
    i2 = select(mu == 0.0, ik[2], 1.0 / (kk[2] + mu))
    schur = 1.0 + mu - (ch0 * ch0 * i0 + ch1 * ch1 * i1 + ch2 * ch2 * i2)
    z3 = (r3 - (ch0 * rh0 * i0 + ch1 * rh1 * i1 + ch2 * rh2 * i2)) / schur
    w0 = (rh0 - ch0 * z3) * i0
    w1 = (rh1 - ch1 * z3) * i1
    w2 = (rh2 - ch2 * z3) * i2
    z0 = v00 * w0 + v01 * w1 + v02 * w2
    z1 = v10 * w0 + v11 * w1 + v12 * w2
    z2 = v20 * w0 + v21 * w1 + v22 * w2
    return inv, det, mu, (schur > 1e-300) & (z3 > 0.0), z0, z1, z2, z3


@kernel(inline="always")
def biased_read_out(
    s: float, eta_bar: float, z0: float, z1: float, z2: float, z3: float, sq: float, sh: float, ch: float, g: float
) -> tuple[float, float, float, float]:
    """From z = ((x1 + x4 - eta_bar) / s, (x2 / omega_ref) / s, x3~ (x4 - eta_bar) / s, x3~):
    the offset x4, A sin(theta) = x1, A cos(theta) = -x2 / omega (corrected by g = 1/sinc^2
    of the first-order hold) and the prediction of y(k+1)."""
    dx4 = z2 / z3
    offset = eta_bar + s * dx4
    a_sin = s * (z0 - dx4) * g
    a_cos = -s * z1 * g / sq
    return offset, a_sin, a_cos, offset + a_sin * (1.0 - 2.0 * sh * sh) + a_cos * (2.0 * sh * ch)


@kernel(inline="always")
def biased_fit_residual(
    lam: float, lam_phys: float, xi: float, eta_bar: float, inv: float, z0: float, z1: float, z2: float, z3: float
) -> tuple[float, float]:
    """Filter i's residual of L_c z = F^2 eta_c on the unit eta_c, and its term of F^2 eta_c."""
    cn = (lam_phys * xi - eta_bar) * inv
    t = lam * lam * cn
    return lam * lam * z0 + lam * z1 + z2 - cn * z3 - t, t


@kernel(inline="always")
def eigen_tuples(
    kv: np.ndarray, kk: np.ndarray
) -> tuple[
    tuple[float, float, float, float, float, float, float, float, float],
    tuple[float, float, float],
    tuple[float, float, float],
    float,
]:
    """C^T C's eigenvectors (row-major), eigenvalues, their inverses and their product, as
    both kernels pass them to :func:`biased_inverse_map`."""
    kvt = (kv[0, 0], kv[0, 1], kv[0, 2], kv[1, 0], kv[1, 1], kv[1, 2], kv[2, 0], kv[2, 1], kv[2, 2])
    return kvt, (kk[0], kk[1], kk[2]), (1.0 / kk[0], 1.0 / kk[1], 1.0 / kk[2]), kk[0] * kk[1] * kk[2]


# ---- single channel ------------------------------------------------------------------------


@kernel
def kkl_biased_kernel(
    y: np.ndarray,
    state: np.ndarray,
    lam: np.ndarray,
    lam_phys: np.ndarray,
    fa: np.ndarray,
    fb0: np.ndarray,
    fb1: np.ndarray,
    kv: np.ndarray,
    kk: np.ndarray,
    consts: np.ndarray,
    last_only: bool,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Run the biased observer over ``y`` from ``state``; return ``(out, extras, sse, new_state)``.

    ``lam`` = lambda~ (units of omega_ref), ``lam_phys`` = lambda (rad/s); ``fa, fb0, fb1``
    the exact first-order-hold coefficients; ``kv`` (3 x 3, columns) and ``kk`` (3,) the
    eigenvectors and eigenvalues of C^T C, C = (lambda~^2 lambda~ 1), used to solve the
    4 x 4 system by its Schur complement for any mu. ``state`` is the ``xi_state`` array
    (layout: :meth:`KklBiased._initial_state`). ``consts`` packs Ts, omega_ref, l_b, silence_ratio, env_decay,
    n_settle, max_fit_residual, max_prediction_error, avg_gain, the omega Ts bounds of the
    converged range, and the gains of the jump detector's fast and slow means. Pure: the
    inputs are not modified.
    """
    Ts, w_ref, ell, silence_ratio, env_decay, n_settle, max_fit2, max_pred2, avg_gain, wts_lo, wts_hi, fast_gain, slow_gain = (
        observer_constants(consts)
    )  # fmt: skip
    m, n = lam.shape[0], y.shape[0]
    xi, y_prev, have_prev, y_pred, pred_valid, n_good, env, out, ext, rec = observer_head(state, m, n, last_only)
    e2_avg, y_avg, yv_avg, n_run = state[m + 6], state[m + 7], state[m + 8], state[m + 9]
    e2_fast, e2_slow = state[m + 10], state[m + 11]
    kvt, kkt, ikt, det_k0 = eigen_tuples(kv, kk)
    inv_m = 1.0 / m
    sse = 0.0
    defined, good, det, a_sin, a_cos, wts, rr, ff = undefined_sample()  # (n >= 1: set by the loop)
    offset = np.nan
    for k in range(n):
        yk = next_sample(y, k, xi, fa, fb0, fb1, have_prev, y_prev)  # (12)
        n_run = run_step(n_run, have_prev, n_settle)
        have_prev = 1.0
        y_prev = yk
        # one-step prediction error; running mean and variance of y
        e2, sse, e2_avg = prediction_error(yk, y_pred, pred_valid, sse, e2_avg, avg_gain)
        y_avg, yv_avg = level_step(yk, y_avg, yv_avg, avg_gain)
        jump, e2_fast, e2_slow = jump_detector(e2, e2_fast, e2_slow, fast_gain, slow_gain, yv_avg)
        # eta = lambda xi, its mean and centred part
        eta_bar = 0.0
        for i in range(m):
            eta_bar += lam_phys[i] * xi[i]
        eta_bar *= inv_m
        s2 = a1 = a2 = a3 = a4 = q2 = 0.0
        for i in range(m):
            s2, a1, a2, a3, a4, q2 = centred_sums(lam[i], lam_phys[i] * xi[i] - eta_bar, s2, a1, a2, a3, a4, q2)
        s = sqrt(s2)
        env = max(s, env * env_decay)
        pred_valid = 0.0
        defined, good, det, a_sin, a_cos, wts, rr, ff = undefined_sample()
        offset = np.nan
        if n_run >= n_settle:
            offset = eta_bar  # exact for a constant input; replaced below when defined
            y_pred = eta_bar
            pred_valid = 1.0
        if live_oscillation(s, eta_bar, env, silence_ratio):
            inv, det, mu, solved, z0, z1, z2, z3 = biased_inverse_map(a1, a2, a3, a4, q2, s, kvt, kkt, ikt, det_k0, ell)
            if solved:
                sq = sqrt(z3)
                wts = w_ref * sq * Ts  # omega Ts
                if wts < math.pi:
                    defined = True
                    sh, chh, g = half_step(wts)
                    offset, a_sin, a_cos, y_pred = biased_read_out(s, eta_bar, z0, z1, z2, z3, sq, sh, chh, g)
                    pred_valid = 1.0
                    ff = 0.0
                    for i in range(m):
                        res, t = biased_fit_residual(lam[i], lam_phys[i], xi[i], eta_bar, inv, z0, z1, z2, z3)
                        rr += res * res
                        ff += t * t
                    good = n_run >= n_settle and consistent(
                        mu, rr, ff, max_fit2, e2_avg, max_pred2, yv_avg, jump, wts, wts_lo, wts_hi
                    )
        # the offset is reported even while the oscillation is undefined
        n_good = record_sample(rec, k, last_only, good, n_good, n_settle, defined, wts, a_sin, a_cos, offset, det,
                               rr, ff, e2_avg, yv_avg)  # fmt: skip
    write_rows(out, ext, rec, last_only, good, n_good, n_settle, defined, wts, Ts, a_sin, a_cos, offset, det, ell,
               rr, ff, e2_avg, yv_avg)  # fmt: skip
    tail = np.array(
        [y_prev, have_prev, y_pred, pred_valid, n_good, env, e2_avg, y_avg, yv_avg, n_run, e2_fast, e2_slow]
    )
    return out, ext, sse, packed_state(xi, tail)


# ---- bank: the channels of a frame together (sinewatch.estimators.bank) -------------------
# rows of the bank's lane-major work array S (one row of LANES doubles per quantity): kkl's
# (kkl_kernels: its rows' names, so that its helpers serve both), five more, then the m
# filters' xi (rows _XI + i) last
_YA, _NR, _EB, _Z3, _OFF = range(_RXI, _RXI + 5)  # beyond kkl's rows: y_avg, n_run, eta_bar, z3, offset
_XI = _RXI + 5
_TAIL = (_RYP, _RHP, _RYPRED, _RPV, _RNG, _RENV, _RE2, _YA, _RLEV, _NR, _REF, _RES)  # the state's tail, in order


@kernel(inline="always")
def _bank_front(
    S: np.ndarray, lane: int, lam: tuple[float, ...], lp: tuple[float, ...], fa: tuple[float, ...],
    fb0: tuple[float, ...], fb1: tuple[float, ...], consts: tuple[float, ...],
    kvt: tuple[float, float, float, float, float, float, float, float, float], kk: tuple[float, float, float],
    ik: tuple[float, float, float], det_k0: float, inv_m: float,
) -> None:  # fmt: skip
    """Lane ``lane`` of one sample of :func:`kkl_biased_kernel` up to omega Ts: the filters
    (12) (unrolled: the constants are tuples), eta_bar, the statistics of y, the centred sums
    and the inverse map, each value kept or replaced as the single kernel's branches would
    (selects, so that the lanes run as one vector)."""
    Ts, w_ref, ell, silence_ratio, env_decay, n_settle, avg_gain, fast_gain, slow_gain = consts
    L = LANES
    yp, yk, hp = S[_RYP * L + lane], S[_RY * L + lane], S[_RHP * L + lane]
    eta_bar = 0.0
    for i in range(len(lam)):
        eta_bar += lp[i] * bank_filter(S, (_XI + i) * L + lane, fa[i], fb0[i], fb1[i], yp, yk, hp)
    eta_bar *= inv_m
    S[_NR * L + lane] = run_step(S[_NR * L + lane], hp, n_settle)
    S[_RHP * L + lane] = 1.0
    S[_RYP * L + lane] = yk
    e2, sse, e2_avg = prediction_error(
        yk, S[_RYPRED * L + lane], S[_RPV * L + lane], S[_RSSE * L + lane], S[_RE2 * L + lane], avg_gain
    )
    y_avg, yv_avg = level_step(yk, S[_YA * L + lane], S[_RLEV * L + lane], avg_gain)
    jump, e2_fast, e2_slow = jump_detector(e2, S[_REF * L + lane], S[_RES * L + lane], fast_gain, slow_gain, yv_avg)
    S[_RSSE * L + lane], S[_RE2 * L + lane], S[_YA * L + lane], S[_RLEV * L + lane] = sse, e2_avg, y_avg, yv_avg
    S[_REF * L + lane], S[_RES * L + lane] = e2_fast, e2_slow
    S[_RJUMP * L + lane] = select(jump, 1.0, 0.0)
    s2 = a1 = a2 = a3 = a4 = q2 = 0.0
    for i in range(len(lam)):
        c = lp[i] * S[(_XI + i) * L + lane] - eta_bar
        s2, a1, a2, a3, a4, q2 = centred_sums(lam[i], c, s2, a1, a2, a3, a4, q2)
    s = sqrt(s2)
    decayed = S[_RENV * L + lane] * env_decay
    env = select(decayed > s, decayed, s)  # max(s, decayed), as Python's max
    S[_RENV * L + lane] = env
    inv, det, mu, solved, z0, z1, z2, z3 = biased_inverse_map(a1, a2, a3, a4, q2, s, kvt, kk, ik, det_k0, ell)
    live = live_oscillation(s, eta_bar, env, silence_ratio)
    solved = live & solved
    sq = sqrt(z3)  # (NaN where z3 < 0: not solved, not used)
    wts = select(solved, w_ref * sq * Ts, 0.0)
    S[_RDEF * L + lane] = select(solved & (wts < math.pi), 1.0, 0.0)
    S[_RS * L + lane], S[_EB * L + lane], S[_RINV * L + lane] = s, eta_bar, inv
    S[_RDET * L + lane], S[_RMU * L + lane] = select(live, det, 0.0), mu
    S[_RZ0 * L + lane], S[_RZ1 * L + lane], S[_RZ2 * L + lane], S[_Z3 * L + lane] = z0, z1, z2, z3
    S[_RSQ * L + lane], S[_RWTS * L + lane], S[_RHALF * L + lane] = sq, wts, 0.5 * wts


@kernel(inline="always")
def _bank_back(
    S: np.ndarray, lane: int, lam: tuple[float, ...], lp: tuple[float, ...], n_settle: float, max_fit2: float,
    max_pred2: float, wts_lo: float, wts_hi: float,
) -> None:  # fmt: skip
    """Lane ``lane``: the read-out from the sine in row ``_RSH``, the fit residual, the offset
    and prediction (the settled mean while undefined), ``good`` and the run of good samples."""
    L = LANES
    defined = S[_RDEF * L + lane] != 0.0
    settled = S[_NR * L + lane] >= n_settle
    s, eta_bar, inv = S[_RS * L + lane], S[_EB * L + lane], S[_RINV * L + lane]
    z0, z1, z2, z3 = S[_RZ0 * L + lane], S[_RZ1 * L + lane], S[_RZ2 * L + lane], S[_Z3 * L + lane]
    sh, ch, g = half_step_of(S[_RHALF * L + lane], S[_RSH * L + lane])
    offset, a_sin, a_cos, y_pred = biased_read_out(s, eta_bar, z0, z1, z2, z3, S[_RSQ * L + lane], sh, ch, g)
    rr = 0.0
    ff = 0.0
    for i in range(len(lam)):
        res, t = biased_fit_residual(lam[i], lp[i], S[(_XI + i) * L + lane], eta_bar, inv, z0, z1, z2, z3)
        rr += res * res
        ff += t * t
    S[_RRR * L + lane], S[_RFF * L + lane] = rr, ff  # (bank_good keeps them where defined)
    S[_RASIN * L + lane] = select(defined, a_sin, 0.0)
    S[_RACOS * L + lane] = select(defined, a_cos, 0.0)
    S[_OFF * L + lane] = select(defined, offset, select(settled, eta_bar, np.nan))
    kept = select(settled, eta_bar, S[_RYPRED * L + lane])
    S[_RYPRED * L + lane] = select(defined, y_pred, kept)
    S[_RPV * L + lane] = select(defined | settled, 1.0, 0.0)
    bank_good(S, lane, settled, n_settle, max_fit2, max_pred2, wts_lo, wts_hi)


@kernel(inline="always")
def _bank_sample(
    S: np.ndarray, lam: tuple[float, ...], lp: tuple[float, ...], fa: tuple[float, ...], fb0: tuple[float, ...],
    fb1: tuple[float, ...], front: tuple[float, ...],
    kvt: tuple[float, float, float, float, float, float, float, float, float], kk: tuple[float, float, float],
    ik: tuple[float, float, float], det_k0: float, inv_m: float, back: tuple[float, float, float, float, float],
) -> None:  # fmt: skip
    """One sample of every lane: two loops over the lanes that LLVM vectorises and between
    them the sines (:func:`sinewatch.estimators.detmath.sin`, vectorised too)."""
    n_settle, max_fit2, max_pred2, wts_lo, wts_hi = back
    for lane in range(LANES):  # (12), eta_bar, the sums over the filters, the inverse map
        _bank_front(S, lane, lam, lp, fa, fb0, fb1, front, kvt, kk, ik, det_k0, inv_m)
    bank_sines(S)
    for lane in range(LANES):  # read-out, fit residual, offset, converged
        _bank_back(S, lane, lam, lp, n_settle, max_fit2, max_pred2, wts_lo, wts_hi)


def kkl_biased_bank_kernel(
    y: np.ndarray, state: np.ndarray, lam: np.ndarray, lam_phys: np.ndarray, fa: np.ndarray, fb0: np.ndarray,
    fb1: np.ndarray, kv: np.ndarray, kk: np.ndarray, consts: np.ndarray, last_only: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """:func:`kkl_biased_kernel` for C channels at once (:func:`_kkl_biased_bank`), the
    filters' constants passed as tuples: the compiled bank is specialised on their number m."""
    return _kkl_biased_bank(y, state, tuple(lam.tolist()), tuple(lam_phys.tolist()), tuple(fa.tolist()),
                            tuple(fb0.tolist()), tuple(fb1.tolist()), kv, kk, consts, last_only)  # fmt: skip


@kernel
def _kkl_biased_bank(
    y: np.ndarray, state: np.ndarray, lam: tuple[float, ...], lp: tuple[float, ...], fa: tuple[float, ...],
    fb0: tuple[float, ...], fb1: tuple[float, ...], kv: np.ndarray, kk: np.ndarray, consts: np.ndarray,
    last_only: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """:func:`kkl_biased_kernel` for C channels at once: ``y`` (N, C), ``state`` (m + 12, C),
    one channel per column; returns ``out`` (C, rows, 5), ``extras`` (C, rows, 3), ``sse``
    (C,) and the new state (m + 12, C). Channels go ``LANES`` at a time through a lane-major
    work array, as in ``kkl``'s bank: two loops over the lanes a sample (the filters, the
    sums and the inverse map; the read-out, the fit residual and converged), and between
    them the sine of the first-order hold's correction (:func:`sinewatch.estimators.detmath.sin`,
    as in the single kernel), 8 doubles a vector where the CPU has AVX-512."""
    detmath.prefer_512_bit_vectors()  # 8 lanes: one 512-bit vector
    Ts, w_ref, ell, silence_ratio, env_decay, n_settle, max_fit2, max_pred2, avg_gain, wts_lo, wts_hi, fast_gain, slow_gain = (
        observer_constants(consts)
    )  # fmt: skip
    front = (Ts, w_ref, ell, silence_ratio, env_decay, n_settle, avg_gain, fast_gain, slow_gain)
    back = (n_settle, max_fit2, max_pred2, wts_lo, wts_hi)
    n, nc = y.shape
    m = len(lam)
    kvt, kkt, ikt, det_k0 = eigen_tuples(kv, kk)
    inv_m = 1.0 / m
    L = LANES
    out, ext, sse_out, new_state, S, ys, rec = bank_arrays(n, nc, m, len(_TAIL), _XI, last_only)
    for g in range(0, nc, L):
        width = bank_load(S, ys, y, state, g, _TAIL, _XI, _RY)
        for k in range(n):
            _bank_sample(S, lam, lp, fa, fb0, fb1, front, kvt, kkt, ikt, det_k0, inv_m, back)
            bank_next_sample(S, ys, rec, k, width, last_only, _OFF)
        for c in range(width):
            bank_write(out[g + c], ext[g + c], rec[c], last_only, bank_lane_row(S, c, _OFF), n_settle, Ts, ell)
        bank_store(S, new_state, sse_out, g, width, _TAIL, _XI, _RSSE)
    return out, ext, sse_out, new_state
