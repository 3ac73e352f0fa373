"""Compiled kernel of ``grip-mixing`` (the maths and the design: :mod:`sinewatch.estimators.grip_mixing`).

:func:`grip_mixing_kernel` runs the sampled observer (7) over a block, with the delay lines
of y, u, z and dhat and the modal read-out of each row.
"""

from __future__ import annotations

import math

import numpy as np

from sinewatch.estimators import detmath
from sinewatch.estimators.base import cyclic_next, kernel
from sinewatch.estimators.lanes import LANES, aligned_lanes, copy_lanes


@kernel(inline="always")
def _write_row(
    out: np.ndarray, r: int, x: np.ndarray, cx: float, Du: float, dsum: float, dhat: float, k: int,
    Wre: np.ndarray, Wim: np.ndarray, freq: np.ndarray, modal_ok: bool, window: int, warm: int,
) -> None:  # fmt: skip
    """Row ``r`` of ``out`` after the sample that brought the count to ``k``: the modal
    read-out of xhat (module docstring), the offset, converged, dhat and xhat."""
    K, n = Wre.shape
    rest = cx + Du + dsum / window
    for c in range(K):
        qre = 0.0
        qim = 0.0
        for a in range(n):
            qre += Wre[c, a] * x[a]
            qim += Wim[c, a] * x[a]
        out[r, c] = freq[c]
        if modal_ok:
            out[r, K + c] = math.sqrt(qre * qre + qim * qim)
            ph = math.atan2(qre, -qim)  # q = a e^{j(phase - pi/2)}
            out[r, 2 * K + c] = ph + 2.0 * math.pi if ph <= -math.pi else ph
            rest -= qre
        else:
            out[r, K + c] = np.nan
            out[r, 2 * K + c] = np.nan
    out[r, 3 * K] = rest
    out[r, 3 * K + 1] = 1.0 if modal_ok and k - 1 >= warm else 0.0
    out[r, 3 * K + 2] = dhat
    for a in range(n):
        out[r, 3 * K + 3 + a] = x[a]


@kernel(inline="always")
def _ring_reads(pos: int, tap_o: np.ndarray, Lb: int, window: int, rd: np.ndarray) -> int:
    """The ring positions the sample at ring position ``pos`` reads: each tap's into ``rd``, and
    (returned) the one ``window`` samples back, which leaves the mean of dhat."""
    for j in range(tap_o.shape[0]):
        q = pos - tap_o[j]
        rd[j] = q + Lb if q < 0 else q
    qw = pos - window
    return qw + Lb if qw < 0 else qw


@kernel(inline="always")
def _model(
    fconst: np.ndarray, n: int, m: int, K: int, nt: int
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
]:  # fmt: skip
    """The views of ``fconst`` (its layout: :func:`grip_mixing_kernel`) for n states, m inputs,
    K modes and nt taps: Ad, Bd0, Bd1, C, Cbar = C (I - e^{-AT}), C e^{-AT}, Ld, D, the tap
    weights, Wre, Wim and the mode frequencies (Hz; NaN: no modes)."""
    o = 0
    Ad = fconst[o : o + n * n].reshape((n, n))
    o += n * n
    Bd0 = fconst[o : o + n * m].reshape((n, m))
    o += n * m
    Bd1 = fconst[o : o + n * m].reshape((n, m))
    o += n * m
    Cr = fconst[o : o + n]
    Cbar = fconst[o + n : o + 2 * n]
    CE = fconst[o + 2 * n : o + 3 * n]
    Ld = fconst[o + 3 * n : o + 4 * n]
    o += 4 * n
    Dr = fconst[o : o + m]
    o += m
    tap_h = fconst[o : o + nt]
    o += nt
    Wre = fconst[o : o + K * n].reshape((K, n))
    Wim = fconst[o + K * n : o + 2 * K * n].reshape((K, n))
    freq = fconst[o + 2 * K * n : o + 2 * K * n + K]
    return Ad, Bd0, Bd1, Cr, Cbar, CE, Ld, Dr, tap_h, Wre, Wim, freq


@kernel
def grip_mixing_kernel(
    block: np.ndarray,
    state: np.ndarray,
    count0: np.ndarray,
    fconst: np.ndarray,
    iconst: np.ndarray,
    last_only: bool,
) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """Run the sampled observer (7) over ``block`` (N, 1 + m): column 0 = y, then u.

    ``state`` and ``count0`` are the ``state`` and ``count`` arrays (layout:
    :meth:`GripMixing._initial_state`). ``fconst`` packs Ad, Bd0, Bd1 (FOH model), C, C (I - e^{-AT}), C e^{-AT},
    Ld, D, the tap weights, the modal rows Wre, Wim (K, n) and the mode frequencies (K);
    ``iconst`` packs n, m, K,
    the number of taps, Lb, Lz, window, reset_half, warm, modal_ok, the tap offsets and
    whether Ad is a bank of 2 x 2 blocks.
    Returns ``(out, sse, new_state, new_count)`` with ``out`` one row per sample (or the
    last) and columns frequency (K), amplitude (K), phase (K), offset, converged (0/1),
    dhat, xhat (n).
    Pure: the inputs are not modified.
    """
    n = iconst[0]
    m = iconst[1]
    K = iconst[2]
    nt = iconst[3]
    Lb = iconst[4]
    Lz = iconst[5]
    window = iconst[6]
    reset_half = iconst[7]
    warm = iconst[8]
    modal_ok = iconst[9] != 0
    tap_o = iconst[10 : 10 + nt]
    pairs = iconst[10 + nt] != 0  # Ad block-diagonal with 2 x 2 blocks (oscillator banks)
    Ad, Bd0, Bd1, Cr, Cbar, CE, Ld, Dr, tap_h, Wre, Wim, freq = _model(fconst, n, m, K, nt)
    new_state = state.copy()  # the views below write into the copy only
    o = 0
    x = new_state[o : o + n]
    o += n
    up = new_state[o : o + m]
    o += m
    z = new_state[o : o + 2 * n].reshape((2, n))
    o += 2 * n
    zb = new_state[o : o + 2 * Lz * n].reshape((2, Lz, n))
    o += 2 * Lz * n
    yb = new_state[o : o + Lb]
    o += Lb
    ub = new_state[o : o + Lb * m].reshape((Lb, m))
    o += Lb * m
    db = new_state[o : o + Lb]
    o += Lb
    dsum = new_state[o]
    k = count0[0]
    N = block.shape[0]
    P = 2 * reset_half  # reset interval of each z copy
    rows = 1 if last_only else N
    out = np.empty((rows, 3 * K + 3 + n))
    xp = np.empty(n)
    zn = np.empty(n)
    rd = np.empty(nt, dtype=np.int64)  # ring positions of the taps of the delay T
    sse = 0.0
    cx = Du = dhat = 0.0  # (N >= 1: set by the loop)
    pos = k % Lb  # ring position of sample k; kept by increments below (no modulo per sample)
    kw = k % window  # phase of k in the mean-of-dhat window
    kp = k % P  # phase of k in the reset interval of z
    for i in range(N):
        y = block[i, 0]
        qw = _ring_reads(pos, tap_o, Lb, window, rd)
        # (5a) sampled exactly (FOH): xhat^-_k = Ad xhat_{k-1} + Bd0 u_{k-1} + Bd1 u_k
        if k == 0:
            for a in range(n):
                xp[a] = x[a]
        elif pairs:  # the same product, skipping the zeros of a bank of 2 x 2 blocks
            for a in range(0, n, 2):
                x0 = x[a]
                x1 = x[a + 1]
                xp[a] = Ad[a, a] * x0 + Ad[a, a + 1] * x1
                xp[a + 1] = Ad[a + 1, a] * x0 + Ad[a + 1, a + 1] * x1
            if m > 0:
                for a in range(n):
                    for b in range(m):
                        xp[a] += Bd0[a, b] * up[b] + Bd1[a, b] * block[i, 1 + b]
        else:
            for a in range(n):
                s = 0.0
                for b in range(n):
                    s += Ad[a, b] * x[b]
                for b in range(m):
                    s += Bd0[a, b] * up[b] + Bd1[a, b] * block[i, 1 + b]
                xp[a] = s
        # y_d(t - T): delay line initialised with zeros (Sec. III-A)
        yb[pos] = y
        yd = 0.0
        for j in range(nt):
            yd += tap_h[j] * yb[rd[j]]
        Du = 0.0
        for b in range(m):
            Du += Dr[b] * block[i, 1 + b]
        # u_Delta_d = C (z_d(t - T) - e^{-AT} z(t)) + D u_d(t - T)   (Sec. III-B)
        udel = 0.0
        if m > 0:
            for b in range(m):
                ub[pos, b] = block[i, 1 + b]
            age0 = kp  # samples since the last reset of copy 0 (resets at k = 0, P, 2P, ...)
            if k < reset_half:
                age1 = k  # copy 1 resets at k = 0, H, H + P, ...
            else:
                age1 = kp - reset_half if kp >= reset_half else kp - reset_half + P
            for c in range(2):
                if (age0 if c == 0 else age1) == 0:
                    for a in range(n):
                        z[c, a] = 0.0  # reset: (8) holds again one period later
                else:
                    for a in range(n):
                        s = 0.0
                        for b in range(n):
                            s += Ad[a, b] * z[c, b]
                        for b in range(m):
                            s += Bd0[a, b] * up[b] + Bd1[a, b] * block[i, 1 + b]
                        zn[a] = s
                    for a in range(n):
                        z[c, a] = zn[a]
                for a in range(n):
                    zb[c, pos, a] = z[c, a]
            sel = 0 if age0 >= age1 else 1  # the copy reset longer ago
            for a in range(n):
                zda = 0.0
                for j in range(nt):
                    zda += tap_h[j] * zb[sel, rd[j], a]
                udel += Cr[a] * zda - CE[a] * z[sel, a]
            for b in range(m):
                uda = 0.0
                for j in range(nt):
                    uda += tap_h[j] * ub[rd[j], b]
                udel += Dr[b] * uda
        # innovation of (7): ybar - C (I - e^{-AT}) xhat^- - D u + u_Delta_d
        eps = y - yd - Du + udel
        cxp = 0.0  # C xhat^-, for the prediction error below
        for a in range(n):
            eps -= Cbar[a] * xp[a]
            cxp += Cr[a] * xp[a]
        # dhat = y - C xhat - D u (Sec. III-A); one-step prediction error with d predicted
        # by its value one period earlier
        cx = 0.0
        for a in range(n):
            x[a] = xp[a] + Ld[a] * eps
            cx += Cr[a] * x[a]
        dhat = y - cx - Du
        dpred = 0.0
        for j in range(nt):
            dpred += tap_h[j] * db[rd[j]]
        e = y - cxp - Du - dpred
        sse += e * e
        # mean of dhat over the last period (exact re-sum once per window: no drift)
        dsum += dhat - db[qw]
        db[pos] = dhat
        kw += 1
        if kw == window:
            kw = 0
            dsum = 0.0
            q = pos
            for _ in range(window):
                dsum += db[q]
                q = q - 1 if q > 0 else Lb - 1
        for b in range(m):
            up[b] = block[i, 1 + b]
        k += 1
        pos = cyclic_next(pos, Lb)
        kp = cyclic_next(kp, P)
        if not last_only:  # row i (last_only: the last row, after the loop)
            _write_row(out, i, x, cx, Du, dsum, dhat, k, Wre, Wim, freq, modal_ok, window, warm)
    if last_only:
        _write_row(out, 0, x, cx, Du, dsum, dhat, k, Wre, Wim, freq, modal_ok, window, warm)
    new_state[o] = dsum
    count = np.empty(1, dtype=np.int64)
    count[0] = k
    return out, sse, new_state, count


# the bank's results: out (C, rows, columns), sse (C,), the new state (S, C) and count (1, C)
_BankResult = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


NMAX = 8  # states of the lanes' work array (4 oscillators); more run run channel by channel
# rows of the lanes' work array W (each LANES wide, lane l of row r at W[r * LANES + l]): xhat, the
# sample, the taps of y's and dhat's delay lines and dhat's window tail, the mean's running sum,
# the sum of squared prediction errors, C xhat and dhat, xhat^-, then the constants broadcast to
# every lane (Ad's 2 x 2 blocks, C (I - e^{-AT}), C, Ld, the tap weights): every row is a literal,
# so the compiler sees the lanes independent and runs the lane loop as one vector
_RX, _RY, _RYT, _RDT, _RDQ, _RDS, _RSSE, _RCX, _RDH, _RXP = 0, 8, 9, 13, 17, 18, 19, 20, 21, 22
_RAD, _RCB, _RCR, _RLD, _RH = 30, 46, 54, 62, 70
_TAPS = 4  # the taps of a delay line: 4 for a fractional period, 1 (and 3 zero weights) for a whole one
_ROWS = 74


@kernel(inline="always")
def _lane_step(W: np.ndarray, ln: int, first: bool) -> None:
    """One sample of lane ``ln`` of ``W``: :func:`grip_mixing_kernel`'s m = 0 path for a bank of
    2 x 2 blocks, operation for operation (its sums from 0.0 in the same order; Du and u_Delta_d
    are 0.0). The states beyond n, and the taps beyond the plant's (one tap for a whole period,
    four for a fractional one: four here), are zeros whose products add +-0.0 to sums that start
    at +0.0 and so are never -0.0, which changes no bit. ``first`` (a literal at each call): the
    sample at count 0, xhat^- = xhat."""
    L = LANES
    y = W[_RY * L + ln]
    for a in range(0, NMAX, 2):
        x0 = W[(_RX + a) * L + ln]
        x1 = W[(_RX + a + 1) * L + ln]
        if first:
            xp0, xp1 = x0, x1
        else:
            b = (_RAD + 2 * a) * L + ln
            xp0 = W[b] * x0 + W[b + L] * x1
            xp1 = W[b + 2 * L] * x0 + W[b + 3 * L] * x1
        W[(_RXP + a) * L + ln] = xp0
        W[(_RXP + a + 1) * L + ln] = xp1
    yd = 0.0
    for j in range(_TAPS):
        yd += W[(_RH + j) * L + ln] * W[(_RYT + j) * L + ln]
    Du = 0.0
    udel = 0.0
    eps = y - yd - Du + udel
    cxp = 0.0
    for a in range(NMAX):
        xpa = W[(_RXP + a) * L + ln]
        eps -= W[(_RCB + a) * L + ln] * xpa
        cxp += W[(_RCR + a) * L + ln] * xpa
    cx = 0.0
    for a in range(NMAX):
        xa = W[(_RXP + a) * L + ln] + W[(_RLD + a) * L + ln] * eps
        W[(_RX + a) * L + ln] = xa
        cx += W[(_RCR + a) * L + ln] * xa
    dhat = y - cx - Du
    dpred = 0.0
    for j in range(_TAPS):
        dpred += W[(_RH + j) * L + ln] * W[(_RDT + j) * L + ln]
    e = y - cxp - Du - dpred
    W[_RSSE * L + ln] += e * e
    W[_RDS * L + ln] = W[_RDS * L + ln] + (dhat - W[_RDQ * L + ln])
    W[_RCX * L + ln] = cx
    W[_RDH * L + ln] = dhat


@kernel
def _bank_lanes(
    block: np.ndarray, state: np.ndarray, count0: np.ndarray, fconst: np.ndarray, iconst: np.ndarray, last_only: bool
) -> _BankResult:
    """:func:`grip_mixing_bank_kernel` for a bank of 2 x 2 blocks with at most :data:`NMAX`
    states: the channels grouped by sample count (a frame's agree) into groups of :data:`LANES`
    lanes (padded with copies of the group's first channel), each group advanced in lock step
    through the lanes' work array, its delay lines in rings of their own (the taps copied into
    the work array before each sample, the new values out after it)."""
    detmath.prefer_512_bit_vectors()
    n, K, nt, Lb, Lz, window, warm = iconst[0], iconst[2], iconst[3], iconst[4], iconst[5], iconst[6], iconst[8]
    modal_ok = iconst[9] != 0
    tap_o = iconst[10 : 10 + nt]
    Ad, _, _, Cr, Cbar, _, Ld, _, tap_h, Wre, Wim, freq = _model(fconst, n, 0, K, nt)  # m = 0
    o_yb = n + 2 * n + 2 * Lz * n  # m = 0: xhat, z, z's line, then y's line, dhat's, the sum
    o_db = o_yb + Lb
    o_ds = o_db + Lb
    N, nc = block.shape
    L = LANES
    S = state.copy()
    kout = count0.copy()
    rows = 1 if last_only else N
    out = np.empty((nc, rows, 3 * K + 3 + n))
    sse = np.zeros(nc)
    W = aligned_lanes(_ROWS * L)  # rows on 64-byte boundaries: a row is one cache line
    W[:] = 0.0
    for a in range(0, n, 2):  # the constants, broadcast to every lane
        for ln in range(L):
            b = (_RAD + 2 * a) * L + ln
            W[b], W[b + L] = Ad[a, a], Ad[a, a + 1]
            W[b + 2 * L], W[b + 3 * L] = Ad[a + 1, a], Ad[a + 1, a + 1]
    for a in range(n):
        for ln in range(L):
            W[(_RCB + a) * L + ln] = Cbar[a]
            W[(_RCR + a) * L + ln] = Cr[a]
            W[(_RLD + a) * L + ln] = Ld[a]
    for j in range(nt):
        for ln in range(L):
            W[(_RH + j) * L + ln] = tap_h[j]
    yb = aligned_lanes(Lb * L)
    db = aligned_lanes(Lb * L)
    yg = aligned_lanes(N * L)
    rd = np.empty(nt, dtype=np.int64)
    xl = np.empty(n)
    cols = np.empty(L, dtype=np.int64)
    order = np.argsort(count0[0], kind="mergesort")
    g0 = 0
    while g0 < nc:
        k = count0[0, order[g0]]
        g1 = g0 + 1
        while g1 < nc and g1 - g0 < L and count0[0, order[g1]] == k:
            g1 += 1
        act = g1 - g0
        for ln in range(L):  # the group's channels, padded with its first
            cols[ln] = order[g0 + ln] if ln < act else order[g0]
        for ln in range(L):
            c = cols[ln]
            for a in range(NMAX):
                W[(_RX + a) * L + ln] = S[a, c] if a < n else 0.0
            for q in range(Lb):
                yb[q * L + ln] = S[o_yb + q, c]
                db[q * L + ln] = S[o_db + q, c]
            W[_RDS * L + ln] = S[o_ds, c]
            W[_RSSE * L + ln] = 0.0
            for i in range(N):  # the group's samples lane-major, one vector a sample
                yg[i * L + ln] = block[i, c]
        pos = k % Lb
        kw = k % window
        for i in range(N):
            qw = _ring_reads(pos, tap_o, Lb, window, rd)
            copy_lanes(W, _RY * L, yg, i * L)  # the sample and the taps into the work array
            copy_lanes(W, _RDQ * L, db, qw * L)
            for j in range(nt):
                copy_lanes(W, (_RYT + j) * L, yb, rd[j] * L)
                copy_lanes(W, (_RDT + j) * L, db, rd[j] * L)
            if k == 0:
                for ln in range(L):  # literal trip count: one vector
                    _lane_step(W, ln, True)
            else:
                for ln in range(L):
                    _lane_step(W, ln, False)
            copy_lanes(yb, pos * L, W, _RY * L)  # the new values into the delay lines
            copy_lanes(db, pos * L, W, _RDH * L)
            kw += 1
            if kw == window:  # the exact re-sum of the single kernel, each lane's in its order
                kw = 0
                for ln in range(L):
                    W[_RDS * L + ln] = 0.0
                q = pos
                for _ in range(window):  # the lanes inner: eight independent chains, not one
                    for ln in range(L):
                        W[_RDS * L + ln] += db[q * L + ln]
                    q = q - 1 if q > 0 else Lb - 1
            k += 1
            pos = cyclic_next(pos, Lb)
            if not last_only:
                for ln in range(act):
                    _lanes_row(out[cols[ln]], i, W, ln, xl, k, Wre, Wim, freq, modal_ok, window, warm)
        for ln in range(act):
            c = cols[ln]
            if last_only:
                _lanes_row(out[c], 0, W, ln, xl, k, Wre, Wim, freq, modal_ok, window, warm)
            for a in range(n):
                S[a, c] = W[(_RX + a) * L + ln]
            for q in range(Lb):
                S[o_yb + q, c] = yb[q * L + ln]
                S[o_db + q, c] = db[q * L + ln]
            S[o_ds, c] = W[_RDS * L + ln]
            sse[c] = W[_RSSE * L + ln]
            kout[0, c] = k
        g0 = g1
    return out, sse, S, kout


@kernel(inline="always")
def _lanes_row(
    out: np.ndarray, r: int, W: np.ndarray, ln: int, xl: np.ndarray, k: int,
    Wre: np.ndarray, Wim: np.ndarray, freq: np.ndarray, modal_ok: bool, window: int, warm: int,
) -> None:  # fmt: skip
    """Row ``r`` of one lane's ``out``: :func:`_write_row` of its values in the work array."""
    for a in range(xl.shape[0]):
        xl[a] = W[(_RX + a) * LANES + ln]
    L = LANES
    _write_row(
        out, r, xl, W[_RCX * L + ln], 0.0, W[_RDS * L + ln], W[_RDH * L + ln], k, Wre, Wim, freq, modal_ok, window, warm
    )


def grip_mixing_bank_kernel(
    block: np.ndarray, state: np.ndarray, count0: np.ndarray, fconst: np.ndarray, iconst: np.ndarray, last_only: bool
) -> _BankResult:
    """:func:`grip_mixing_kernel` for C one-input channels at once (``block`` (N, C); the bank
    path takes no known input u, so m = 0: no z and no u delay lines): ``state`` (S, C) and
    ``count0`` (1, C), each column one channel's ``state`` and ``count``. Returns ``out`` (C, rows,
    columns as the single kernel's), ``sse`` (C,), the new state (S, C) and count (1, C).

    Each channel is its own observer chain (7), independent of the others: one channel waits on
    its chain's latency at every sample, a bank runs the channels' chains side by side. A bank of
    oscillators (Ad of 2 x 2 blocks, the ``harmonics`` preset) of at most :data:`NMAX` states runs
    as vector lanes (:func:`_bank_lanes`, each lane the single kernel's operations in order, so
    its bits are the single channel's); any other plant runs each channel through the single
    kernel itself, in turn. Plain Python, so that only the kernel it picks is compiled. Pure:
    the inputs are not modified."""
    n, nt = int(iconst[0]), int(iconst[3])
    if iconst[10 + nt] != 0 and n <= NMAX and nt in (1, 4):
        return _bank_lanes(block, state, count0, fconst, iconst, last_only)
    runs = [
        grip_mixing_kernel(
            np.ascontiguousarray(block[:, c]).reshape(-1, 1), np.ascontiguousarray(state[:, c]), count0[:, c].copy(),
            fconst, iconst, last_only,
        )
        for c in range(block.shape[1])
    ]  # fmt: skip
    out = np.stack([r[0] for r in runs])
    sse = np.array([r[1] for r in runs])
    return out, sse, np.stack([r[2] for r in runs], axis=1), np.stack([r[3] for r in runs], axis=1)
