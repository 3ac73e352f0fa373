"""Compiled kernel of ``grip-mixing`` (the maths and the design: :mod:`sinewatch.estimators.grip_mixing`).

:func:`grip_mixing_kernel` runs the sampled observer (7) over a block, with the delay lines
of y, u, z and dhat and the modal read-out of each row.
"""

from __future__ import annotations

import math

import numpy as np

from sinewatch.estimators.base import cyclic_next, kernel


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
    freq = fconst[o + 2 * K * n : o + 2 * K * n + K]  # model frequencies, Hz (NaN: no modes)
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
        for j in range(nt):
            q = pos - tap_o[j]
            rd[j] = q + Lb if q < 0 else q
        qw = pos - window
        if qw < 0:
            qw += Lb
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
