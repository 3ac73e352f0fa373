"""``ges-kalman``'s compiled bank (:mod:`sinewatch.estimators.bank`): the channels of a frame
through one kernel call, each channel's outputs and state bit for bit those of
:func:`~sinewatch.estimators._ges_kalman_kernels.ges_kalman_kernel` run on it alone (same
equations, same order of operations; eq. numbers as in that module).
"""

from __future__ import annotations

import numpy as np

from sinewatch.estimators import detmath, lanes
from sinewatch.estimators._ges_kalman_kernels import (
    BIAS_SIZE,
    T_NEGLIGIBLE,
    TINY,
    UNC_BASE,
    UNC_SIZE,
    _bias_column,
    _bias_head,
    _bias_pair,
    _estimate_row,
    _filter_step,
    _noise_means_cap,
    _noise_means_screened,
    _propagate_error,
)
from sinewatch.estimators.bank import bank_outputs
from sinewatch.estimators.base import kernel

LANES = 8  # channels advanced together: 8 doubles, one AVX-512 register
# rows of the bank's lane-major work array: one row of LANES doubles per per-sample quantity
# x1..x4; the 10 entries of P; T (16); U (16); sse; the sample in; u of (U5) out; M and b (B2-B3);
# the bias recursion's inputs from the filter's step (_RB: s, k0..k3, h1, 1/S, the prior p02, p12,
# p22, p23) and its Dv entries (_RV: v01, v11, v12, v13); the noise means (_RM: w, <u>, <log u>,
# _noise_means' x_ref and e_ref, the cap's exponent x, 1 where the cap's exp is taken, u, log u)
_RX, _RP, _RT, _RU, _RSSE, _RS, _RUO, _RG = 0, 4, 14, 30, 46, 47, 48, 49
_RB = _RG + BIAS_SIZE
_RV = _RB + 11
_RM = _RV + 4
_ROWS = _RM + 9
_P_IN_XP = (4, 5, 6, 7, 9, 10, 11, 14, 15, 19)  # p00 p01 p02 p03 p11 p12 p13 p22 p23 p33 in ``xP``
_P_OF_ENTRY = (0, 1, 2, 3, 1, 4, 5, 6, 2, 5, 7, 8, 3, 6, 8, 9)  # P[i, j] (row-major) -> its distinct entry


_select = lanes.select  # (a Python conditional's branches kept ges-kalman's bank the longest compile)


@kernel(inline="always")
def _bank_sample(
    S: np.ndarray, lane: int, rs: int, with_t: bool, q0: float, q1: float, q2: float, q3: float, R: float
) -> None:
    """One sample (row ``rs``) of lane ``lane`` of the work array ``S`` (rows ``_R*``, each
    ``LANES`` wide): the filter (:func:`_filter_step`), T (U3) and U (U4) advanced exactly as
    :func:`ges_kalman_kernel` does (T's branches as selects: the propagation is computed and
    kept or not), the sse summed, u of (U5) into row ``_RUO`` and the bias recursion's inputs into
    rows ``_RB`` (:func:`_bank_bias` runs it after the lanes' step). Straight-line arithmetic that
    reads and writes one array at constant offsets only, so the compiler can prove the lanes
    independent and run them as one vector (a second array would need a run-time overlap
    check, which LLVM does not add to a loop of 8 iterations)."""
    L = LANES
    s = S[rs * L + lane]
    x1, x2, x3, x4 = S[(_RX + 0) * L + lane], S[(_RX + 1) * L + lane], S[(_RX + 2) * L + lane], S[(_RX + 3) * L + lane]
    b = _RP * L + lane
    p00, p01, p02, p03, p11 = S[b], S[b + L], S[b + 2 * L], S[b + 3 * L], S[b + 4 * L]
    p12, p13, p22, p23, p33 = S[b + 5 * L], S[b + 6 * L], S[b + 7 * L], S[b + 8 * L], S[b + 9 * L]
    x3_prior = x3
    r02, r12, r22, r23 = p02, p12, p22, p23  # P(k|k) before the step, for (B1)-(B3)
    x1, x2, x3, x4, p00, p01, p02, p03, p11, p12, p13, p22, p23, p33, e, k0, k1, k2, k3, inv_S = _filter_step(
        s, x1, x2, x3, x4, p00, p01, p02, p03, p11, p12, p13, p22, p23, p33, q0, q1, q2, q3, R
    )
    S[(_RX + 0) * L + lane], S[(_RX + 1) * L + lane], S[(_RX + 2) * L + lane], S[(_RX + 3) * L + lane] = x1, x2, x3, x4
    S[b], S[b + L], S[b + 2 * L], S[b + 3 * L], S[b + 4 * L] = p00, p01, p02, p03, p11
    S[b + 5 * L], S[b + 6 * L], S[b + 7 * L], S[b + 8 * L], S[b + 9 * L] = p12, p13, p22, p23, p33
    S[_RSSE * L + lane] += e * e
    h1 = k1 + x3_prior  # h = K + g_k (U2)
    i = _RB * L + lane  # (B2)-(B3)'s inputs: P(k|k) before the step, the gain, h1 and 1/S
    S[i], S[i + L], S[i + 2 * L], S[i + 3 * L], S[i + 4 * L], S[i + 5 * L] = s, k0, k1, k2, k3, h1
    S[i + 6 * L], S[i + 7 * L], S[i + 8 * L], S[i + 9 * L], S[i + 10 * L] = inv_S, r02, r12, r22, r23
    if with_t:  # else no lane's T is propagated: the caller applies (U3)'s zeroing
        t = _RT * L + lane
        t00, t01, t02, t03 = S[t], S[t + L], S[t + 2 * L], S[t + 3 * L]
        t10, t11, t12, t13 = S[t + 4 * L], S[t + 5 * L], S[t + 6 * L], S[t + 7 * L]
        t20, t21, t22, t23 = S[t + 8 * L], S[t + 9 * L], S[t + 10 * L], S[t + 11 * L]
        t30, t31, t32, t33 = S[t + 12 * L], S[t + 13 * L], S[t + 14 * L], S[t + 15 * L]
        n00, n01, n02, n03, n10, n11, n12, n13, n20, n21, n22, n23, n30, n31, n32, n33 = _propagate_error(
            t00, t01, t02, t03, t10, t11, t12, t13, t20, t21, t22, t23, t30, t31, t32, t33,
            s, k0, k1, k2, k3, k0, h1, k2, k3, 0.0,
        )  # fmt: skip
        keep = t00 + t11 + t22 + t33 > T_NEGLIGIBLE  # (U3) as in ges_kalman_kernel
        zero = (not keep) & (t00 != 0.0)  # not `and`: no branch (see _select)
        # T <- propagated if keep, 0 if zero, else as it was (the single kernel's if / elif)
        t00 = _select(keep, n00, _select(zero, 0.0, t00))
        t01 = _select(keep, n01, _select(zero, 0.0, t01))
        t02 = _select(keep, n02, _select(zero, 0.0, t02))
        t03 = _select(keep, n03, _select(zero, 0.0, t03))
        t10 = _select(keep, n10, _select(zero, 0.0, t10))
        t11 = _select(keep, n11, _select(zero, 0.0, t11))
        t12 = _select(keep, n12, _select(zero, 0.0, t12))
        t13 = _select(keep, n13, _select(zero, 0.0, t13))
        t20 = _select(keep, n20, _select(zero, 0.0, t20))
        t21 = _select(keep, n21, _select(zero, 0.0, t21))
        t22 = _select(keep, n22, _select(zero, 0.0, t22))
        t23 = _select(keep, n23, _select(zero, 0.0, t23))
        t30 = _select(keep, n30, _select(zero, 0.0, t30))
        t31 = _select(keep, n31, _select(zero, 0.0, t31))
        t32 = _select(keep, n32, _select(zero, 0.0, t32))
        t33 = _select(keep, n33, _select(zero, 0.0, t33))
        S[t], S[t + L], S[t + 2 * L], S[t + 3 * L] = t00, t01, t02, t03
        S[t + 4 * L], S[t + 5 * L], S[t + 6 * L], S[t + 7 * L] = t10, t11, t12, t13
        S[t + 8 * L], S[t + 9 * L], S[t + 10 * L], S[t + 11 * L] = t20, t21, t22, t23
        S[t + 12 * L], S[t + 13 * L], S[t + 14 * L], S[t + 15 * L] = t30, t31, t32, t33
    v = _RU * L + lane
    u00, u01, u02, u03 = S[v], S[v + L], S[v + 2 * L], S[v + 3 * L]
    u10, u11, u12, u13 = S[v + 4 * L], S[v + 5 * L], S[v + 6 * L], S[v + 7 * L]
    u20, u21, u22, u23 = S[v + 8 * L], S[v + 9 * L], S[v + 10 * L], S[v + 11 * L]
    u30, u31, u32, u33 = S[v + 12 * L], S[v + 13 * L], S[v + 14 * L], S[v + 15 * L]
    u = e * e / (1.0 + u00 + 2.0 * u01 + u11)  # (U5), from the predicted U
    u00, u01, u02, u03, u10, u11, u12, u13, u20, u21, u22, u23, u30, u31, u32, u33 = _propagate_error(
        u00, u01, u02, u03, u10, u11, u12, u13, u20, u21, u22, u23, u30, u31, u32, u33,
        s, k0, k1, k2, k3, k0, h1, k2, k3, 1.0,
    )  # (U4)  # fmt: skip
    S[v], S[v + L], S[v + 2 * L], S[v + 3 * L] = u00, u01, u02, u03
    S[v + 4 * L], S[v + 5 * L], S[v + 6 * L], S[v + 7 * L] = u10, u11, u12, u13
    S[v + 8 * L], S[v + 9 * L], S[v + 10 * L], S[v + 11 * L] = u20, u21, u22, u23
    S[v + 12 * L], S[v + 13 * L], S[v + 14 * L], S[v + 15 * L] = u30, u31, u32, u33
    S[_RUO * L + lane] = u


@kernel(refcount=False)
def _bank_bias(S: np.ndarray) -> None:
    """One sample of the bias recursion (B1)-(B3) for every lane of ``S``: the three steps of
    :func:`~sinewatch.estimators._ges_kalman_kernels._propagate_bias` (the same helpers, each
    lane's operations in the single kernel's order), each a loop over the lanes at constant
    offsets in one array, which the compiler vectorises. Inside the lanes' step (one lane's
    whole recursion, 10 + 4 inner loops and a call) it kept the step scalar: the bank ran at
    half the speed of one channel."""
    detmath.prefer_512_bit_vectors()  # 8 lanes: one 512-bit vector
    L = LANES
    for lane in range(L):
        i = _RB * L + lane
        s, k0, k1, k2, k3 = S[i], S[i + L], S[i + 2 * L], S[i + 3 * L], S[i + 4 * L]
        inv_s, p02, p12, p22, p23 = S[i + 6 * L], S[i + 7 * L], S[i + 8 * L], S[i + 9 * L], S[i + 10 * L]
        v01, v11, v12, v13 = _bias_head(S, _RG * L + lane, L, s, k0, k1, k2, k3, inv_s, p02, p12, p22, p23)
        v = _RV * L + lane
        S[v], S[v + L], S[v + 2 * L], S[v + 3 * L] = v01, v11, v12, v13
        # the pairs in the same lane loop: in a loop of their own over the lanes, the body is
        # small enough that LLVM unrolls the 8 lanes as scalars instead of vectorising them
        for p in range(10):
            _bias_pair(S, (_RG + 4 * p) * L + lane, L, s, k0, k1, k2, k3)
    for c in range(4):
        hr = _RB + (1 if c == 0 else (5 if c == 1 else c + 1))  # h = (k0, h1, k2, k3)
        for lane in range(L):
            i = _RB * L + lane
            s, k0, k1, k2, k3 = S[i], S[i + L], S[i + 2 * L], S[i + 3 * L], S[i + 4 * L]
            v = _RV * L + lane
            _bias_column(
                S, _RG * L + lane, L, c, s, k0, k1, k2, k3, S[v], S[v + L], S[v + 2 * L], S[v + 3 * L], S[hr * L + lane]
            )


@kernel(inline="always")
def _bank_t_live(S: np.ndarray) -> bool:
    """Whether some lane of ``S`` propagates its T at the next sample (U3), as
    :func:`ges_kalman_kernel` decides it. Once no lane does, none will again (T then stays
    zero or as it was)."""
    L = LANES
    live = False
    for lane in range(L):
        t = _RT * L + lane
        live |= S[t] + S[t + 5 * L] + S[t + 10 * L] + S[t + 15 * L] > T_NEGLIGIBLE
    return live


@kernel(inline="always")
def _bank_t_zero(S: np.ndarray) -> None:
    """The zeroing of T (U3) in lanes where no lane propagates it: 0 where ``T[0, 0] != 0``."""
    L = LANES
    for lane in range(L):
        if S[_RT * L + lane] != 0.0:
            for i in range(16):
                S[(_RT + i) * L + lane] = 0.0


@kernel(inline="always")
def _bank_noise_variance(S: np.ndarray, lane: int, R: float) -> float:
    """sigma_hat^2 = <u> / w (U5) of lane ``lane``, R while no weight has built up."""
    m_u, w = S[(_RM + 1) * LANES + lane], S[_RM * LANES + lane]
    return m_u / w if w > 0.0 else R


@kernel(inline="always")
def _bank_row(
    S: np.ndarray, lane: int, s2: float, Ts: float, rel_std: float, corr: bool,
    out: np.ndarray, std: np.ndarray, row: int, T: np.ndarray, U: np.ndarray, J: np.ndarray,
) -> None:  # fmt: skip
    """Row ``row`` of ``out`` and ``std`` (one channel's) from lane ``lane`` of ``S``, as
    :func:`ges_kalman_kernel` writes it (its own :func:`_estimate_row`)."""
    L = LANES
    for i in range(16):
        T[i // 4, i % 4] = S[(_RT + i) * L + lane]
        U[i // 4, i % 4] = S[(_RU + i) * L + lane]
    x1, x2, x3, x4 = S[(_RX + 0) * L + lane], S[(_RX + 1) * L + lane], S[(_RX + 2) * L + lane], S[(_RX + 3) * L + lane]
    p22 = S[(_RP + 7) * L + lane]
    _estimate_row(out, std, row, x1, x2, x3, x4, S, _RG * L + lane, L, s2, corr, T, U, J, p22, Ts, rel_std)


@kernel(inline="always")
def _bank_means_lane(S: np.ndarray, lane: int, lam: float) -> None:
    """One sample of the noise means (U5) of lane ``lane`` from its u (row ``_RUO``), as
    :func:`_noise_means` takes it: u's log (:func:`sinewatch.estimators.detmath.log`, plain
    arithmetic) and :func:`_noise_means_screened`, the new means and the cap's exponent, and 1 in
    row ``_RM + 6`` where the cap (U5a) needs its exp (:func:`_bank_means_caps`)."""
    L = LANES
    m = _RM * L + lane
    u = S[_RUO * L + lane]
    w, m_u, m_l, x, screened = _noise_means_screened(
        u, detmath.log(max(u, TINY)), S[m], S[m + L], S[m + 2 * L], lam, S[m + 3 * L], S[m + 4 * L]
    )
    S[m], S[m + L], S[m + 2 * L], S[m + 5 * L] = w, m_u, m_l, x
    S[m + 6 * L] = _select(screened, 0.0, 1.0)


@kernel(inline="always")
def _bank_means_caps(S: np.ndarray) -> None:
    """The cap (U5a) with its exp (the C library's, as the single kernel's) in the lanes where
    :func:`_bank_means_lane` found that the bound does not show it idle (x_ref and e_ref move
    on there). The lanes are searched with an early exit: such a loop stays scalar, so that the
    exp under its branch is not taken for every lane (a vectorised loop speculates it)."""
    L = LANES
    first = L
    for lane in range(L):
        if S[(_RM + 6) * L + lane] != 0.0:
            first = lane
            break
    for lane in range(first, L):
        if S[(_RM + 6) * L + lane] != 0.0:
            m = _RM * L + lane
            x = S[m + 5 * L]
            S[m + L], S[m + 4 * L] = _noise_means_cap(S[m + L], S[m], x)
            S[m + 3 * L] = x


@kernel(refcount=False)
def _bank_samples(
    S: np.ndarray, ys: np.ndarray, start: int, stop: int, t_live: bool, corr: bool,
    q0: float, q1: float, q2: float, q3: float, R: float, lam: float,
) -> bool:  # fmt: skip
    """Samples ``start`` to ``stop`` of every lane of ``S`` (:func:`_bank_sample`, then the bias
    recursion :func:`_bank_bias` when ``corr``, and the noise means (U5)-(U5a)); ``ys`` holds
    the block's samples lane-major; returns whether some lane still propagates its T (U3).
    Compiled on its own and called once a block (once a sample when each sample's row is
    reported), not inlined by numba: its two copies of the lanes' step are most of the bank's
    code, and numba inlines a function by copying its IR block by block, each copy with the
    whole function's scope (this step inlined into the kernel cost it ~20 s of CPU to compile)."""
    detmath.prefer_512_bit_vectors()  # 8 lanes: one 512-bit vector
    L = LANES
    for k in range(start, stop):
        # the sample's row as one vector store, which the lanes' vector loads then read (8 scalar
        # stores would stall them: store forwarding fails); ys was written before the block
        lanes.copy_lanes(S, _RS * L, ys, k * L)
        if t_live:  # some lane's T is still propagated (U3): half the arithmetic
            t_live = _bank_t_live(S)
            if not t_live:  # none from now on: the single kernel's zeroing of T where it applies,
                _bank_t_zero(S)  # once: after it every lane's T[0, 0] is 0 and T no longer changes
        # T's switch a constant in each loop, so the compiler sees the lanes independent
        if t_live:
            for lane in range(L):  # literal trip count: one vector (two with AVX2)
                _bank_sample(S, lane, _RS, True, q0, q1, q2, q3, R)
        else:
            for lane in range(L):
                _bank_sample(S, lane, _RS, False, q0, q1, q2, q3, R)
        if corr:  # (B2)-(B3), as ges_kalman_kernel
            _bank_bias(S)
        for lane in range(L):  # the noise means (U5) of the 8 lanes as vectors
            _bank_means_lane(S, lane, lam)
        _bank_means_caps(S)  # (U5a) where its bound fails, lane by lane
    return t_live


@kernel
def ges_kalman_bank_kernel(
    y: np.ndarray, xP: np.ndarray, unc: np.ndarray, consts: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`ges_kalman_kernel` for C channels at once: ``y`` (N, C), ``xP`` (20, C), ``unc``
    (35, C), one channel per column; returns ``out`` (C, rows, 5), ``sse`` (C,), ``std``
    (C, rows, 4) and the new ``xP`` and ``unc``. Channels go ``LANES`` at a time through a
    lane-major work array (copied in and out once per block): each sample, the filter, T and U
    of the ``LANES`` channels advance as one vector (:func:`_bank_sample`, a loop of literal trip
    count over one array), then the bias recursion (:func:`_bank_bias`) and the noise means
    (U5) with u's log (:func:`_bank_means_lane`, :func:`sinewatch.estimators.detmath.log` as the
    single kernel), the cap's exp (U5a, the C library's) only in the lanes whose bound fails."""
    detmath.prefer_512_bit_vectors()  # 8 lanes: one 512-bit vector
    n, nc = y.shape
    out, std, sse = bank_outputs(n, nc, 4, last_only)
    new_xP = np.empty((20, nc))
    new_unc = np.empty((UNC_SIZE, nc))
    q0, q1, q2, q3 = consts[0], consts[1], consts[2], consts[3]
    R, Ts, rel_std = consts[4], consts[5], consts[6]
    lam = 1.0 - 1.0 / consts[7]  # (U5)
    corr = consts[8] != 0.0  # the bias recursion (B1)-(B4)
    L = LANES
    S = lanes.aligned_lanes(_ROWS * L)  # rows on 64-byte boundaries: a row is one cache line
    ys = lanes.aligned_lanes(n * L)
    T = np.empty((4, 4))
    U = np.empty((4, 4))
    J = np.empty((4, 4))
    for g in range(0, nc, L):
        width = min(L, nc - g)
        S[:] = 0.0  # lanes past the last channel run on zeros, their results dropped
        if width < L:
            ys[:] = 0.0
        for c in range(width):
            for i in range(4):
                S[(_RX + i) * L + c] = xP[i, g + c]
            for i in range(10):
                S[(_RP + i) * L + c] = xP[_P_IN_XP[i], g + c]
            for i in range(32):
                S[(_RT + i) * L + c] = unc[i, g + c]
            for i in range(BIAS_SIZE):
                S[(_RG + i) * L + c] = unc[UNC_BASE + i, g + c]
        for k in range(n):  # row by row: y (N, C) is read in its own order
            for c in range(width):
                ys[k * L + c] = y[k, g + c]
        for c in range(width):  # <u>, w, <log u>; x_ref and e_ref start each block at 0 (S's zeros)
            S[(_RM + 1) * L + c], S[_RM * L + c], S[(_RM + 2) * L + c] = unc[32, g + c], unc[33, g + c], unc[34, g + c]
        t_live = width > 0  # True, typed bool: the literal True would compile _bank_samples twice
        step = max(n, 1) if last_only else 1  # the whole block in one call, or a sample and its row
        for k in range(0, n, step):  # one call site: one signature compiled
            t_live = _bank_samples(S, ys, k, k + step, t_live, corr, q0, q1, q2, q3, R, lam)
            if not last_only:
                for c in range(width):  # row k
                    _bank_row(
                        S, c, _bank_noise_variance(S, c, R), Ts, rel_std, corr, out[g + c], std[g + c], k, T, U, J
                    )
        if last_only:  # the last row (an empty block: the state's, as ges_kalman_kernel writes it)
            for c in range(width):
                _bank_row(S, c, _bank_noise_variance(S, c, R), Ts, rel_std, corr, out[g + c], std[g + c], 0, T, U, J)
        for c in range(width):
            ch = g + c
            sse[ch] = S[_RSSE * L + c]
            for i in range(4):
                new_xP[i, ch] = S[(_RX + i) * L + c]
            for i in range(16):  # P's 16 entries (row-major) from its 10 distinct ones
                new_xP[4 + i, ch] = S[(_RP + _P_OF_ENTRY[i]) * L + c]
            for i in range(32):
                new_unc[i, ch] = S[(_RT + i) * L + c]
            new_unc[32, ch], new_unc[33, ch] = S[(_RM + 1) * L + c], S[_RM * L + c]
            new_unc[34, ch] = S[(_RM + 2) * L + c]
            for i in range(BIAS_SIZE):
                new_unc[UNC_BASE + i, ch] = S[(_RG + i) * L + c]
    return out, sse, std, new_xP, new_unc
