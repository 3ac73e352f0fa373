"""Compiled kernels of ``ipdft`` (the method and its error model: :mod:`sinewatch.estimators.interpolated_dft`).

:func:`ipdft_kernel` buffers a block's samples into windows and estimates them,
:func:`_window_estimates` many windows of a block at once (vectorised across windows),
:func:`_one_window_estimate` one at a time.
"""

from __future__ import annotations

import math

import numpy as np

from sinewatch.estimators.base import kernel, undefined_row, wrap_pi

CHUNK = 64  # windows estimated together (see _window_estimates): bounds the scratch to CHUNK x N
BATCH_MIN = 8  # fewer windows in a chunk are estimated one by one (_one_window_estimate)
# the one-step predictions behind residual_rms: sin of the held phase from the C library every
# PRED_ANCHOR samples after a window, rotated in between (error <= ~PRED_ANCHOR ulp of A)
PRED_ANCHOR = 32


@kernel(inline="always")
def _magnitude(re: float, im: float) -> float:
    """|X_k| of (D): a correctly rounded square root of the sum of squares, which vectorises
    across windows (``math.hypot`` is a C library call per bin and window, ~8 a window: more
    than the rest of the bins' arithmetic). It differs from hypot in the last bit at most; a
    bin beyond ~1e154 overflows to inf, which (P) treats as no peak."""
    return math.sqrt(re * re + im * im)


@kernel(inline="always")
def _peak(mags: np.ndarray, q: int, k_lo: int, k_hi: int, three_point: bool) -> float:
    """(P), (I3)/(I2) and (F): ``lambda`` (bins) from the magnitudes ``mags[:, q]`` of
    the bins k_lo-1 .. k_hi+1; NaN when there is no peak (an all-zero window)."""
    bp = 1
    for bb in range(2, k_hi - k_lo + 2):  # (P) peak in the band
        if mags[bb, q] > mags[bp, q]:
            bp = bb
    xm, x0, xp = mags[bp - 1, q], mags[bp, q], mags[bp + 1, q]
    if not (x0 > 0.0) or not math.isfinite(x0):
        return np.nan
    if three_point:  # (I3)
        delta = 2.0 * (xp - xm) / (xm + 2.0 * x0 + xp)
    else:  # (I2)
        if xp >= xm:
            alpha = xp / x0
            delta = (2.0 * alpha - 1.0) / (alpha + 1.0)
        else:
            alpha = xm / x0
            delta = -(2.0 * alpha - 1.0) / (alpha + 1.0)
    lam: float = (k_lo - 1 + bp) + delta  # (F)
    return lam


@kernel(inline="always")
def _prediction_at(th: float, fcy: float, p: int, cw: float, sw: float) -> tuple[float, float]:
    """``sin`` and ``cos`` of the held estimate's phase ``th + 2 pi fcy p``, p samples after its
    window: exact (the C library's) at the anchor ``a = p - p % PRED_ANCHOR``, then rotated
    p - a times by ``(cw, sw) = (cos, sin)(2 pi fcy)``. The kernel rotates on from one sample to
    the next and anchors again every PRED_ANCHOR samples, so each value depends on p only, not
    on where a block begins, and a hop of 20 samples takes 4 library calls instead of 20."""
    ph = th + 2.0 * math.pi * fcy * (p - p % PRED_ANCHOR)
    s, c = math.sin(ph), math.cos(ph)
    for _ in range(p % PRED_ANCHOR):
        s, c = s * cw + c * sw, c * cw - s * sw
    return s, c


@kernel(inline="always")
def segment_length(n: int, hop: int) -> int:
    """The length L (a multiple of the hop, <= N) of the segments that (D) sums once and shares
    between windows: the fewest operations per window and bin, 2 L for the segment's sum
    (amortised: one segment starts at each window) and 4 per segment combined, ceil(N / L)."""
    best, best_cost = hop, -1
    for g in range(1, n // hop + 1):
        seg = g * hop
        cost = 2 * seg + 4 * (n // seg + (1 if n % seg else 0))
        if best_cost < 0 or cost < best_cost:
            best, best_cost = seg, cost
    return best


@kernel
def _band_magnitudes(
    seg: np.ndarray, start0: int, hop: int, xt: np.ndarray, n_win: int, hann: np.ndarray, hann_sum: float,
    cos_tab: np.ndarray, sin_tab: np.ndarray, k_lo: int, k_hi: int, mu: np.ndarray, mags: np.ndarray,
) -> None:  # fmt: skip
    """(M) and (D) of the ``n_win`` windows of a chunk, window q = ``seg[start0 + q hop :][:N]``
    (the windows of a stream are a hop apart; ``xt[n, q]`` is its sample n): ``mu[q]``, and
    ``mags[b, q]`` = |X_k|, k = k_lo - 1 + b.

    The Hann window is three complex exponentials, ``w_n = 1/2 - e^{j 2 pi n/N}/4 -
    e^{-j 2 pi n/N}/4``, so the windowed bin is ``X_k = S_k/2 - S_{k-1}/4 - S_{k+1}/4`` of the
    plain DFT ``S_k = sum_n x_n e^{-j 2 pi k n/N}``, and removing the mean (M) changes bin 1
    alone (``X_1(w) = -N/4``): ``X_1 += mu N/4``. ``S_k`` of a window is the sum of its
    segments of L samples (:func:`segment_length`, the last one r = N mod L samples long),
    each turned by ``e^{-j 2 pi k s L/N}``: a segment starts every hop, so each is summed once
    and shared by the windows that hold it (at the example's 80-sample window and hop 20, the
    bins take 9 x 20 terms a window instead of 7 x 80). Every sum is over a window's own
    samples, in a fixed order: a window's bits depend on its samples only, not on the chunk."""
    N = xt.shape[0]
    Q = n_win
    seg_len = segment_length(N, hop)
    g = seg_len // hop
    m = N // seg_len  # whole segments in a window
    r = N - m * seg_len  # the last segment's length (0: none)
    n_full = Q + (m - 1) * g  # segment starts whose whole sum some window needs
    n_all = Q + m * g if r > 0 else n_full  # and those whose first r terms (the last segment)
    nbins = k_hi - k_lo + 5  # S_k for k = k_lo - 2 .. k_hi + 2
    k0 = k_lo - 2
    mu[:Q] = 0.0
    for n in range(N):  # (M) the Hann-weighted mean
        w = hann[n]
        xn = xt[n]
        for q in range(Q):
            mu[q] += w * xn[q]
    for q in range(Q):
        mu[q] = mu[q] / hann_sum
    xs = np.empty((seg_len, n_all))  # xs[n, i]: sample n of the segment starting at start0 + i hop
    for n in range(seg_len):
        base = start0 + n
        for i in range(n_all if n < r else n_full):
            xs[n, i] = seg[base + i * hop]
    pre = np.zeros((nbins, n_all))  # the segments' sums, real and imaginary parts
    pim = np.zeros((nbins, n_all))
    lre = np.empty((nbins, Q))  # the last segment's (its first r terms) of window q
    lim = np.empty((nbins, Q))
    for b in range(nbins):
        k = k0 + b
        are, aim = pre[b], pim[b]
        idx = 0
        for n in range(seg_len):
            if n == r:
                for q in range(Q):
                    lre[b, q] = are[q + m * g] if r > 0 else 0.0
                    lim[b, q] = aim[q + m * g] if r > 0 else 0.0
            cv = cos_tab[idx]
            sv = sin_tab[idx]
            xn = xs[n]
            for i in range(n_all if n < r else n_full):
                are[i] += xn[i] * cv
                aim[i] -= xn[i] * sv
            idx += k
            if idx >= N:
                idx -= N
    sre = np.zeros((nbins, Q))  # S_k of each window
    sim = np.zeros((nbins, Q))
    for b in range(nbins):
        k = k0 + b
        sr, si = sre[b], sim[b]
        for s in range(m + (1 if r > 0 else 0)):
            t = (k * s * seg_len) % N
            c, sn = cos_tab[t], sin_tab[t]
            src_re = pre[b, s * g : s * g + Q] if s < m else lre[b]
            src_im = pim[b, s * g : s * g + Q] if s < m else lim[b]
            for q in range(Q):
                sr[q] += c * src_re[q] + sn * src_im[q]
                si[q] += c * src_im[q] - sn * src_re[q]
    for bi in range(k_hi - k_lo + 3):  # X_k of the windowed, offset-cancelled samples
        k = k_lo - 1 + bi
        fix = 0.25 * N if k == 1 else 0.0
        lo_r, mid_r, hi_r = sre[bi], sre[bi + 1], sre[bi + 2]
        lo_i, mid_i, hi_i = sim[bi], sim[bi + 1], sim[bi + 2]
        mb = mags[bi]
        for q in range(Q):
            xr = 0.5 * mid_r[q] - 0.25 * lo_r[q] - 0.25 * hi_r[q] + mu[q] * fix
            xi = 0.5 * mid_i[q] - 0.25 * lo_i[q] - 0.25 * hi_i[q]
            mb[q] = _magnitude(xr, xi)


@kernel
def _one_window_estimate(
    xt: np.ndarray, q: int, mu_all: np.ndarray, mags: np.ndarray, k_lo: int, k_hi: int, three_point: bool,
    est: np.ndarray, st: np.ndarray, ct: np.ndarray,
) -> None:  # fmt: skip
    # The arguments of _window_estimates, whose every window this must reproduce bit for bit
    # (a chunk of too few windows takes this path): the same inputs by design, not a copy.
    """``est[q]`` as :func:`_window_estimates` computes it, for window q alone (a chunk of
    fewer than BATCH_MIN windows, where a loop over the windows has too few iterations to pay
    for itself): the same sums in the same order. ``st``, ``ct`` (N,) are scratch."""
    N = xt.shape[0]
    mu = mu_all[q]
    lam = _peak(mags, q, k_lo, k_hi, three_point)  # (P), (I3)/(I2), (F)
    if math.isnan(lam):
        est[q, 0] = 0.0
        return
    omega = 2.0 * math.pi * lam / N
    # (LS) u_n ~ a sin(omega t_n) + b cos(omega t_n) + d, t_n = n - c: sin/cos by rotation
    c = 0.5 * (N - 1)
    cw, sw = math.cos(omega), math.sin(omega)
    s, co = math.sin(-omega * c), math.cos(-omega * c)
    sss = scc = ssc = ss = sc = 0.0
    sus = suc = su = 0.0
    for n in range(N):
        u = xt[n, q] - mu
        st[n] = s
        ct[n] = co
        sss += s * s
        scc += co * co
        ssc += s * co
        ss += s
        sc += co
        sus += u * s
        suc += u * co
        su += u
        s, co = s * cw + co * sw, co * cw - s * sw
    # Cramer's rule on the symmetric 3x3 normal matrix [[sss,ssc,ss],[ssc,scc,sc],[ss,sc,N]]
    m00, m01, m02, m11, m12, m22 = sss, ssc, ss, scc, sc, float(N)
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    det = m00 * c00 + m01 * c01 + m02 * c02
    if not (abs(det) > 0.0) or not math.isfinite(det):
        est[q, 0] = 0.0
        return
    c11 = m00 * m22 - m02 * m02
    c12 = m01 * m02 - m00 * m12
    c22 = m00 * m11 - m01 * m01
    a = (c00 * sus + c01 * suc + c02 * su) / det
    b = (c01 * sus + c11 * suc + c12 * su) / det
    d = (c02 * sus + c12 * suc + c22 * su) / det
    sse = 0.0  # residual, second pass (one pass would cancel badly on large offsets)
    for n in range(N):
        e = xt[n, q] - mu - (a * st[n] + b * ct[n] + d)
        sse += e * e
    est[q, 0] = 1.0
    est[q, 1] = lam / N
    est[q, 2] = math.hypot(a, b)
    est[q, 3] = wrap_pi(omega * c + math.atan2(b, a))
    est[q, 4] = mu + d
    est[q, 5] = math.sqrt(sse / N)


@kernel
def _window_estimates(
    xt: np.ndarray, n_win: int, mu: np.ndarray, mags: np.ndarray, k_lo: int, k_hi: int, three_point: bool,
    est: np.ndarray,
) -> None:  # fmt: skip
    """``est[q]`` = (defined, f_cycles_per_sample, A, theta_end, B, r) of window q, for
    q < ``n_win``, from its mean ``mu[q]`` and band magnitudes ``mags[:, q]``
    (:func:`_band_magnitudes`); ``xt[n, q]`` is sample n (oldest first) of window q.

    The windows are independent, so every step runs over all of them at once, window index
    innermost: each sum of each window is accumulated in its own slot, term by term in the
    same order as for one window alone (the same roundings, bit for bit), but the loop over
    the windows has no dependency from one iteration to the next, so the compiler vectorises
    it and the CPU overlaps it, where one window alone is one long chain of dependent adds.
    Loops touch few arrays each, so that the compiler's aliasing checks stay cheap."""
    N = xt.shape[0]
    Q = n_win
    st = np.empty((N, Q))  # sin(omega t_n), cos(omega t_n) of (LS)
    ct = np.empty((N, Q))
    acc1 = np.zeros(Q)
    # (P), (I3)/(I2), (F), then the start of the rotation recurrence of (LS)
    c = 0.5 * (N - 1)
    rot = np.empty((4, Q))  # per window: lambda, omega and the rotation's cos and sin
    lam, omega, cw, sw = rot[0], rot[1], rot[2], rot[3]
    for q in range(Q):
        lam[q] = _peak(mags, q, k_lo, k_hi, three_point)
        om = 2.0 * math.pi * lam[q] / N
        omega[q] = om
        cw[q], sw[q] = math.cos(om), math.sin(om)
        st[0, q], ct[0, q] = math.sin(-om * c), math.cos(-om * c)
    # (LS) u_n ~ a sin(omega t_n) + b cos(omega t_n) + d, t_n = n - c: sin/cos by rotation
    for n in range(1, N):
        sp, cp, sn, cn = st[n - 1], ct[n - 1], st[n], ct[n]
        for q in range(Q):
            s, co = sp[q], cp[q]
            sn[q] = s * cw[q] + co * sw[q]
            cn[q] = co * cw[q] - s * sw[q]
    sums = np.zeros((8, Q))  # per window, the sums of (LS) below
    sss, scc, ssc, ss, sc, sus, suc, su = sums[0], sums[1], sums[2], sums[3], sums[4], sums[5], sums[6], sums[7]
    for n in range(N):
        sn = st[n]
        for q in range(Q):
            sss[q] += sn[q] * sn[q]
            ss[q] += sn[q]
    for n in range(N):
        cn = ct[n]
        for q in range(Q):
            scc[q] += cn[q] * cn[q]
            sc[q] += cn[q]
    for n in range(N):
        sn, cn = st[n], ct[n]
        for q in range(Q):
            ssc[q] += sn[q] * cn[q]
    for n in range(N):
        xn = xt[n]
        for q in range(Q):
            u = xn[q] - mu[q]
            su[q] += u
    for n in range(N):
        xn, sn = xt[n], st[n]
        for q in range(Q):
            u = xn[q] - mu[q]
            sus[q] += u * sn[q]
    for n in range(N):
        xn, cn = xt[n], ct[n]
        for q in range(Q):
            u = xn[q] - mu[q]
            suc[q] += u * cn[q]
    # Cramer's rule on the symmetric 3x3 normal matrix [[sss,ssc,ss],[ssc,scc,sc],[ss,sc,N]]
    ok = np.empty(Q, dtype=np.bool_)
    fa = np.zeros(Q)
    fb = np.zeros(Q)
    fd = np.zeros(Q)
    for q in range(Q):
        m00, m01, m02, m11, m12, m22 = sss[q], ssc[q], ss[q], scc[q], sc[q], float(N)
        c00 = m11 * m22 - m12 * m12
        c01 = m02 * m12 - m01 * m22
        c02 = m01 * m12 - m02 * m11
        det = m00 * c00 + m01 * c01 + m02 * c02
        ok[q] = (abs(det) > 0.0) and math.isfinite(det) and not math.isnan(lam[q])
        if not ok[q]:
            continue
        c11 = m00 * m22 - m02 * m02
        c12 = m01 * m02 - m00 * m12
        c22 = m00 * m11 - m01 * m01
        fa[q] = (c00 * sus[q] + c01 * suc[q] + c02 * su[q]) / det
        fb[q] = (c01 * sus[q] + c11 * suc[q] + c12 * su[q]) / det
        fd[q] = (c02 * sus[q] + c12 * suc[q] + c22 * su[q]) / det
    # residual, second pass (one pass would cancel badly on large offsets)
    acc1[:] = 0.0
    for n in range(N):
        xn, sn, cn = xt[n], st[n], ct[n]
        for q in range(Q):
            e = xn[q] - mu[q] - (fa[q] * sn[q] + fb[q] * cn[q] + fd[q])
            acc1[q] += e * e
    for q in range(Q):
        if not ok[q]:
            est[q, 0] = 0.0
            continue
        a, b = fa[q], fb[q]
        est[q, 0] = 1.0
        est[q, 1] = lam[q] / N
        est[q, 2] = math.hypot(a, b)
        est[q, 3] = wrap_pi(omega[q] * c + math.atan2(b, a))
        est[q, 4] = mu[q] + fd[q]
        est[q, 5] = math.sqrt(acc1[q] / N)


@kernel
def ipdft_kernel(
    x: np.ndarray,
    buf: np.ndarray,
    istate: np.ndarray,
    fstate: np.ndarray,
    rstate: np.ndarray,
    hann: np.ndarray,
    cos_tab: np.ndarray,
    sin_tab: np.ndarray,
    iconsts: np.ndarray,
    fconsts: np.ndarray,
    last_only: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run the sliding interpolated DFT over block ``x``; return
    ``(out, resid, rocof, age, sse, n_pred, new_buf, new_istate, new_fstate, new_rstate)``
    (``age``: samples since the last sample of the window each row's estimate is from).

    ROCOF is the difference of two consecutive windows' frequencies over the hop (Hz/s),
    held like the other outputs (``rstate`` = previous window's frequency in cycles/sample,
    the held ROCOF, and how many consecutive windows were defined, up to 2: ROCOF is defined
    from the second); it is as noisy as the frequency difference, so it is for slow
    ramps, not for a single report.

    ``buf``, ``istate`` and ``fstate`` are the ``buffer``, ``counters`` and ``estimate``
    arrays (layout: :meth:`InterpolatedDft._initial_state`); ``iconsts`` = (hop, k_lo, k_hi, three_point); ``fconsts`` = (fs, min_amplitude,
    max_relative_residual, sum of the Hann window). ``out`` columns are frequency_hz,
    amplitude, phase_rad, offset, converged (0/1); ``resid`` is the fit residual r per
    row. Pure: the inputs are not modified.

    The block is run in chunks of up to CHUNK windows: first the ring buffer's counters
    find the samples where a window is due and the windows are gathered from the stream
    (the buffer, oldest first, then the block), then the chunk's windows are estimated
    (a window's estimate depends on its samples only: together, :func:`_window_estimates`,
    or one by one below BATCH_MIN, :func:`_one_window_estimate`), then the samples are run
    again for the held estimates, the one-step predictions and the outputs; the buffer
    ends as the stream's last N samples.
    """
    N = buf.shape[0]
    hop, k_lo, k_hi, three_point = iconsts[0], iconsts[1], iconsts[2], iconsts[3] != 0
    fs, min_amp, max_rel, hann_sum = fconsts[0], fconsts[1], fconsts[2], fconsts[3]
    pos, fill, since, held, defined, m = istate[0], istate[1], istate[2], istate[3], istate[4], istate[5]
    fcy, A, th, B, r, conv = fstate[0], fstate[1], fstate[2], fstate[3], fstate[4], fstate[5]
    f_prev, rocof, run = rstate[0], rstate[1], rstate[2]
    n_in = x.shape[0]
    out = np.empty((1 if last_only else n_in, 5))
    rocof_out = np.empty(1 if last_only else n_in)
    resid = np.empty(1 if last_only else n_in)
    age = np.empty(1 if last_only else n_in)  # (U) samples since the held window's last sample
    chunk = min(CHUNK, (n_in - 1) // hop + 1)  # at most one window per hop samples
    # the stream: the buffer's N samples, oldest first, then the block (window ending at
    # block sample j = seg[j + 1 : j + 1 + N])
    seg = np.empty(N + n_in)
    for i in range(N):
        seg[i] = buf[pos + i if pos + i < N else pos + i - N]
    seg[N:] = x
    xt = np.empty((N, chunk))  # the chunk's windows, xt[n, q]: sample n of window q
    due_at = np.empty(chunk, dtype=np.int64)
    st1, ct1 = np.empty(N), np.empty(N)  # scratch of _one_window_estimate
    mu = np.empty(chunk)  # the chunk's windows' means and band magnitudes (_band_magnitudes)
    mags = np.empty((k_hi - k_lo + 3, chunk))
    est = np.zeros((chunk, 6))
    sse = 0.0
    n_pred = 0
    p_at = -1  # the offset p whose sine and cosine ps, pc hold (-1: none for this estimate)
    ps = pc = cw = sw = 0.0
    j0 = 0
    while j0 < n_in:
        n_win = 0  # the ring buffer's counters over the samples, the windows due
        j1 = j0
        while j1 < n_in and n_win < chunk:
            if fill < N:  # filling: sample by sample
                fill += 1
                if since < hop:
                    since += 1
                if fill == N and since >= hop:
                    since = 0
                    due_at[n_win] = j1
                    n_win += 1
                j1 += 1
                continue
            steps = hop - since if since < hop else 1  # full: the next window is due in steps samples
            if j1 + steps > n_in:
                since += n_in - j1
                j1 = n_in
            else:
                j1 += steps
                since = 0
                due_at[n_win] = j1 - 1
                n_win += 1
        for n in range(N):
            for q in range(n_win):
                xt[n, q] = seg[due_at[q] + 1 + n]
        if n_win > 0:  # (M), (D) of the chunk's windows, then the rest of each estimate
            _band_magnitudes(seg, due_at[0] + 1, hop, xt, n_win, hann, hann_sum, cos_tab, sin_tab, k_lo, k_hi, mu, mags)
        if n_win >= BATCH_MIN:
            _window_estimates(xt, n_win, mu, mags, k_lo, k_hi, three_point, est)
        else:
            for q in range(n_win):
                _one_window_estimate(xt, q, mu, mags, k_lo, k_hi, three_point, est, st1, ct1)
        q = 0
        for j in range(j0, j1):
            if held and defined:  # one-step prediction from the estimate held before x_j
                p = m + 1  # sin(th + omega p) by rotation from the anchor p - p % PRED_ANCHOR
                if p_at >= 0 and p == p_at + 1 and p % PRED_ANCHOR != 0:
                    ps, pc = ps * cw + pc * sw, pc * cw - ps * sw
                else:
                    if p_at < 0:  # a new estimate: its rotation by omega
                        cw, sw = math.cos(2.0 * math.pi * fcy), math.sin(2.0 * math.pi * fcy)
                    ps, pc = _prediction_at(th, fcy, p, cw, sw)
                p_at = p
                e = x[j] - (B + A * ps)
                sse += e * e
                n_pred += 1
            m += 1
            if q < n_win and due_at[q] == j:  # a hop: the estimate of the window ending here
                held = 1
                m = 0
                p_at = -1
                if est[q, 0] != 0.0:
                    defined = 1
                    fcy, A, th, B, r = est[q, 1], est[q, 2], est[q, 3], est[q, 4], est[q, 5]
                    conv = 1.0 if (A > min_amp and r <= max_rel * A) else 0.0
                    run = min(run + 1.0, 2.0)
                    rocof = (fcy - f_prev) * fs * fs / hop if run >= 2.0 else 0.0
                    f_prev = fcy
                else:
                    defined = 0
                    fcy = A = th = B = r = conv = 0.0
                    f_prev = rocof = run = 0.0
                q += 1
            if last_only and j != n_in - 1:
                continue
            row = 0 if last_only else j
            if held and defined:
                out[row, 0] = fcy * fs
                out[row, 1] = A
                out[row, 2] = wrap_pi(th + 2.0 * math.pi * fcy * m)
                out[row, 3] = B
                out[row, 4] = conv
                resid[row] = r
                rocof_out[row] = rocof if run >= 2.0 else np.nan
                age[row] = m
            else:
                undefined_row(out, row)
                resid[row] = np.nan
                rocof_out[row] = np.nan
                age[row] = np.nan
        j0 = j1
    pos = (pos + n_in) % N  # the last N samples of the stream back into the ring, oldest at pos
    b = np.empty(N)
    for i in range(N):
        b[pos + i if pos + i < N else pos + i - N] = seg[n_in + i]
    new_istate = np.array([pos, fill, since, held, defined, m], dtype=np.int64)
    new_fstate = np.array([fcy, A, th, B, r, conv])
    new_rstate = np.array([f_prev, rocof, run])
    return out, resid, rocof_out, age, sse, n_pred, b, new_istate, new_fstate, new_rstate


@kernel
def ipdft_bank_kernel(
    y: np.ndarray, buf: np.ndarray, istate: np.ndarray, fstate: np.ndarray, rstate: np.ndarray, hann: np.ndarray,
    cos_tab: np.ndarray, sin_tab: np.ndarray, iconsts: np.ndarray, fconsts: np.ndarray, last_only: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """:func:`ipdft_kernel` for the C channels of a frame in one compiled call (the bank of
    :mod:`sinewatch.estimators.bank`): ``y`` (N, C) and the state arrays stacked channel last,
    ``(*shape, C)``, as a lane-major bank's, so that :func:`~sinewatch.estimators.bank.update_bank`
    keeps them stacked between frames instead of gathering and scattering a dict a channel
    around every call; returns the outputs channel first (``out`` (C, rows, 5), ``resid``,
    ``rocof``, ``age`` (C, rows), ``sse``, ``n_pred`` (C,)) and the new states channel last.
    Each channel runs through :func:`ipdft_kernel` itself, on contiguous copies of its column
    of the samples and of each state array (the single kernel's own argument types, so it is
    compiled once for both), so its bits are the single channel's: the kernel's work is per
    window and already vectorised across the windows of a block."""
    nc = y.shape[1]
    out = np.empty((0, 0, 5))  # (each of these four sized by the first channel's rows)
    resid, rocof, age = np.empty((0, 0)), np.empty((0, 0)), np.empty((0, 0))
    sse, n_pred = np.empty(nc), np.empty(nc, dtype=np.int64)
    new_buf, new_i = np.empty_like(buf), np.empty_like(istate)
    new_f, new_r = np.empty_like(fstate), np.empty_like(rstate)
    for c in range(nc):
        r = ipdft_kernel(
            np.ascontiguousarray(y[:, c]), np.ascontiguousarray(buf[:, c]), np.ascontiguousarray(istate[:, c]),
            np.ascontiguousarray(fstate[:, c]), np.ascontiguousarray(rstate[:, c]), hann, cos_tab, sin_tab, iconsts,
            fconsts, last_only,
        )  # fmt: skip
        if c == 0:
            rows = r[1].shape[0]  # 1 or N: every channel's the same
            out = np.empty((nc, rows, 5))
            resid, rocof, age = np.empty((nc, rows)), np.empty((nc, rows)), np.empty((nc, rows))
        out[c], resid[c], rocof[c], age[c], sse[c], n_pred[c] = r[0], r[1], r[2], r[3], r[4], r[5]
        new_buf[:, c], new_i[:, c], new_f[:, c], new_r[:, c] = r[6], r[7], r[8], r[9]
    return out, resid, rocof, age, sse, n_pred, new_buf, new_i, new_f, new_r
