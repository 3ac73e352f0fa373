"""``nls``: the streaming kernel, for the channels of a frame at once (the compiled bank of
:mod:`sinewatch.estimators.bank`) and for one channel (the class runs it as a bank of one): one
kernel, so that numba compiles the window's fit once, and a channel's outputs and state are the
same bits whatever the bank's size and the channel's position in it.

Where a channel's time goes (1024-sample window and hop, one tone, read in a profile of the
single-channel kernel's machine code): about half in the one-step prediction of every input
sample (the held tones' rotation and the squared error, one chain through memory from sample to
sample) and half in the window's fit (:func:`~sinewatch.estimators._nls_fit.window_estimate`,
once a hop). The kernel runs the prediction for 8 channels as one lane loop over a lane-major
work array (the recipe of :mod:`sinewatch.estimators.lanes`: every quantity a row of 8 doubles,
the loop's loads and stores in that one array at constant offsets, each lane's operations in
the order of the single-channel kernel it replaces, so that LLVM vectorises the lanes and no
bit changes). The ring buffer is written only when a window is due and at the block's end, a
row of 8 channels as one vector while the channels stay in step. The window's fit and the
output rows stay lane by lane: the fit iterates until it converges, a number of steps that
differs between channels.
"""

from __future__ import annotations

import math

import numpy as np

from sinewatch.estimators._nls_fit import window_estimate
from sinewatch.estimators.base import kernel, wrap_pi
from sinewatch.estimators.lanes import LANES, aligned_lanes, copy_lanes

# rows of the work array, LANES doubles each: the sample in, whether an estimate is held (0/1),
# m (samples since the held estimate), the sum of squared prediction errors and their count,
# the prediction being summed, the held offset and its slope (glob[0], glob[1])
_RX, _RHELD, _RM, _RSSE, _RNPRED, _RPRED, _RG0, _RG1 = 0, 1, 2, 3, 4, 5, 6, 7
# the tone being rotated (copied in from its rows and out again): whether it counts (held and
# among the fit's tones), its amplitude, sin and cos of its phase m samples on, cos w and sin w
# (tones[i, 1], tones[i, 7], tones[i, 8], tones[i, 9], tones[i, 10])
_RACT, _RAMP, _RSIN, _RCOS, _RCW, _RSW = 8, 9, 10, 11, 12, 13
_FIXED_ROWS = 14
_TONE_ROWS = 6  # tone i's rows (see _tone_base), in the order above


@kernel(inline="always")
def write_row(
    out_k: np.ndarray, out_g: np.ndarray, r: int, tones: np.ndarray, glob: np.ndarray, held: int, m: int, fs: float
) -> None:
    """Row ``r`` of ``out_k`` (6, rows, k_cols) and ``out_g`` (5, rows): the held estimate ``m``
    samples after its window's last sample (phase advanced at the held frequency, its variance
    grown as the module :mod:`sinewatch.estimators.nls` gives), NaN where no tone is held."""
    kc = tones.shape[0]
    nt = int(glob[7])
    shown = nt if held else 0  # tones written; the rest of the kc columns are NaN
    for i in range(kc):
        if i < shown:
            w = tones[i, 0]
            out_k[0, r, i] = w * fs / (2.0 * math.pi)
            out_k[1, r, i] = tones[i, 1]
            out_k[2, r, i] = wrap_pi(tones[i, 2] + w * m)
            out_k[3, r, i] = math.sqrt(tones[i, 3]) * fs / (2.0 * math.pi)
            out_k[4, r, i] = math.sqrt(tones[i, 4])
            vphi = tones[i, 5] + m * m * tones[i, 3] + 2.0 * m * tones[i, 6]
            out_k[5, r, i] = math.sqrt(max(vphi, 0.0))
        else:
            for f in range(6):
                out_k[f, r, i] = np.nan
    if held:
        out_g[0, r] = glob[0] + glob[1] * m
        out_g[1, r] = math.sqrt(max(glob[2] + m * m * glob[3] + 2.0 * m * glob[4], 0.0))
        out_g[2, r] = glob[6]
        out_g[3, r] = nt
        out_g[4, r] = glob[5]
    else:
        out_g[0, r] = np.nan
        out_g[1, r] = np.nan
        out_g[2, r] = 0.0
        out_g[3, r] = np.nan
        out_g[4, r] = np.nan


@kernel(inline="always")
def _start_lane(W: np.ndarray, lane: int) -> None:
    """The held offset's prediction of this sample, ``glob[0] + glob[1] (m + 1)`` (m + 1 is an
    integer below 2^53: the same double as the single kernel's integer converted)."""
    L = LANES
    W[_RPRED * L + lane] = W[_RG0 * L + lane] + W[_RG1 * L + lane] * (W[_RM * L + lane] + 1.0)


@kernel(inline="always")
def _tone_lane(W: np.ndarray, lane: int) -> None:
    """One held tone's phase rotated by one sample (sin(a + w) = sin a cos w + cos a sin w) and its
    sine added to the prediction, in a lane where the tone counts; the others keep their values
    (computed, then chosen: a select keeps the lanes one vector)."""
    L = LANES
    s = W[_RSIN * L + lane]
    co = W[_RCOS * L + lane]
    cw = W[_RCW * L + lane]
    sw = W[_RSW * L + lane]
    sn = s * cw + co * sw
    cn = co * cw - s * sw
    on = W[_RACT * L + lane] != 0.0
    pred = W[_RPRED * L + lane]
    W[_RSIN * L + lane] = sn if on else s
    W[_RCOS * L + lane] = cn if on else co
    W[_RPRED * L + lane] = pred + W[_RAMP * L + lane] * sn if on else pred


@kernel(inline="always")
def _finish_lane(W: np.ndarray, lane: int) -> None:
    """The one-step prediction error's square summed (and counted) where an estimate is held;
    m advanced by one sample."""
    L = LANES
    held = W[_RHELD * L + lane] != 0.0
    e = W[_RX * L + lane] - W[_RPRED * L + lane]
    sse = W[_RSSE * L + lane]
    n = W[_RNPRED * L + lane]
    W[_RSSE * L + lane] = sse + e * e if held else sse
    W[_RNPRED * L + lane] = n + 1.0 if held else n
    W[_RM * L + lane] += 1.0


@kernel(inline="always")
def _predict_lanes(W: np.ndarray, kc: int) -> None:
    """Every lane's one-step prediction of its sample and its error (:func:`_start_lane`,
    :func:`_tone_lane` a tone, :func:`_finish_lane`), each a loop of literal trip count over the
    lanes: one vector (two with AVX2)."""
    for lane in range(LANES):
        _start_lane(W, lane)
    for i in range(kc):
        t = _tone_base(kc, i)
        if t != _RACT:
            _move_rows(W, _RACT, t, _TONE_ROWS)
        for lane in range(LANES):
            _tone_lane(W, lane)
        if t != _RACT:
            _move_rows(W, t + (_RSIN - _RACT), _RSIN, 2)
    for lane in range(LANES):
        _finish_lane(W, lane)


@kernel(inline="always")
def _predict_lane(W: np.ndarray, lane: int, kc: int) -> None:
    """:func:`_predict_lanes` for one lane, as scalars: a channel alone pays for one lane, not
    eight (the same functions, the same operations: the same bits)."""
    _start_lane(W, lane)
    for i in range(kc):
        t = _tone_base(kc, i)
        if t != _RACT:
            _move_rows(W, _RACT, t, _TONE_ROWS)
        _tone_lane(W, lane)
        if t != _RACT:
            _move_rows(W, t + (_RSIN - _RACT), _RSIN, 2)
    _finish_lane(W, lane)


@kernel(inline="always")
def _move_rows(W: np.ndarray, to: int, frm: int, rows: int) -> None:
    """Rows ``frm .. frm + rows - 1`` of ``W`` copied to rows ``to ..``, a row as one vector
    (:func:`copy_lanes`: the lane loop then loads what one vector stored; a tone in and out of the
    rows the lane loop reads)."""
    for k in range(rows):
        copy_lanes(W, (to + k) * LANES, W, (frm + k) * LANES)


@kernel(inline="always")
def _tone_base(kc: int, i: int) -> int:
    """The first row of tone ``i`` of ``kc``: with one tone, the rows the lane loop reads
    (nothing to move); with more, a block of its own, moved in and out around its step."""
    return _RACT if kc == 1 else _FIXED_ROWS + _TONE_ROWS * i


@kernel(inline="always")
def _load_lane(W: np.ndarray, lane: int, tones: np.ndarray, glob: np.ndarray, held: int, m: int) -> None:
    """A lane's held estimate into the work array's rows: at the start of a block and after
    each of its window fits."""
    L = LANES
    nt = int(glob[7])
    W[_RHELD * L + lane] = 1.0 if held else 0.0
    W[_RM * L + lane] = m
    W[_RG0 * L + lane] = glob[0]
    W[_RG1 * L + lane] = glob[1]
    for i in range(tones.shape[0]):
        t = _tone_base(tones.shape[0], i) * L + lane
        W[t + (_RACT - _RACT) * L] = 1.0 if (held and i < nt) else 0.0
        W[t + (_RAMP - _RACT) * L] = tones[i, 1]
        W[t + (_RSIN - _RACT) * L] = tones[i, 7]
        W[t + (_RCOS - _RACT) * L] = tones[i, 8]
        W[t + (_RCW - _RACT) * L] = tones[i, 9]
        W[t + (_RSW - _RACT) * L] = tones[i, 10]


@kernel(inline="always")
def _store_rotation(W: np.ndarray, lane: int, tones: np.ndarray) -> None:
    """A lane's rotated phases (tones[i, 7], tones[i, 8]) back from the work array, before its
    window fit (which starts from them) and at the end of the block."""
    L = LANES
    for i in range(tones.shape[0]):
        t = _tone_base(tones.shape[0], i) * L + lane
        tones[i, 7] = W[t + (_RSIN - _RACT) * L]
        tones[i, 8] = W[t + (_RCOS - _RACT) * L]


@kernel(inline="always")
def _first_due(fill: int, since: int, N: int, hop: int) -> int:
    """The first sample of the block at which a lane's window is due, as ``ring_push`` counts:
    once the ring is full (``fill`` reaches N) and ``since`` reaches the hop, each a sample at a
    time from its value at the block's start; then every ``hop`` samples."""
    return max(N - fill - 1, hop - since - 1, 0)


@kernel(inline="always")
def _earliest(due: np.ndarray, width: int) -> int:
    """The first sample at which some lane's window is due."""
    first: int = due[0]
    for c in range(1, width):
        first = min(first, due[c])
    return first


@kernel(inline="always")
def _ring_catch_up(
    b: np.ndarray, x: np.ndarray, ch: int, written: np.ndarray, pos: np.ndarray, fill: np.ndarray, c: int, upto: int
) -> None:
    """Channel ``ch``'s samples ``written[c] .. upto - 1`` into its ring (column ``ch`` of ``b``),
    as ``ring_push`` writes them one by one: the ring is read only when a window is due and at
    the block's end, so the bank writes it then, in one loop, not once a sample between the
    lanes' vector steps."""
    N = b.shape[0]
    p = pos[c]
    for s in range(written[c], upto):
        b[p, ch] = x[s, ch]
        p = 0 if p + 1 == N else p + 1
    fill[c] = min(fill[c] + upto - written[c], N)
    pos[c] = p
    written[c] = upto


@kernel(inline="always")
def _catch_up_lanes(
    b: np.ndarray, x: np.ndarray, g: int, width: int, written: np.ndarray, pos: np.ndarray, fill: np.ndarray, upto: int
) -> None:
    """Every lane's ring caught up to sample ``upto`` (:func:`_ring_catch_up`). Lanes that have
    written as much and write at the same position (channels that started together, the usual
    frame) take each sample's row as one vector (:func:`copy_lanes`): the ring is (W, C), a
    sample's channels side by side, as the frame's samples are."""
    N, nc = b.shape
    together = width == LANES
    for c in range(1, width):
        together = together and pos[c] == pos[0] and written[c] == written[0]
    if not together:
        for c in range(width):
            _ring_catch_up(b, x, g + c, written, pos, fill, c, upto)
        return
    bf = b.reshape(N * nc)
    xf = x.reshape(x.shape[0] * nc)
    p = pos[0]
    for s in range(written[0], upto):
        copy_lanes(bf, p * nc + g, xf, s * nc + g)
        p = 0 if p + 1 == N else p + 1
    for c in range(width):
        fill[c] = min(fill[c] + upto - written[c], N)
        pos[c] = p
        written[c] = upto


@kernel(inline="always")
def _chronological(b: np.ndarray, ch: int, p: int, xw: np.ndarray) -> None:
    """The window of channel ``ch`` in chronological order (the oldest sample, at the write
    position ``p``, first) into ``xw``: the ring's rows p .. W - 1, then 0 .. p - 1."""
    N = b.shape[0]
    for k in range(N - p):
        xw[k] = b[p + k, ch]
    for k in range(p):
        xw[N - p + k] = b[k, ch]


# the bank's calling convention (sinewatch.estimators.bank): the samples, each state array with a
# channel axis added last, the constants
@kernel
def nls_bank_kernel(
    x: np.ndarray, buf_in: np.ndarray, istate_in: np.ndarray, tones_in: np.ndarray, glob_in: np.ndarray,
    iconsts: np.ndarray, fconsts: np.ndarray, cos_tab: np.ndarray, sin_tab: np.ndarray, last_only: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The sliding fit over block ``x`` (N, C), a channel a column, from the channels' state
    arrays stacked with the channel last: ``buf_in`` (W, C) the rings of the last W samples;
    ``istate_in`` (5, C) = write position, fill, samples since the last hop, estimate held,
    samples since the held estimate; ``tones_in`` (k_cols, 11, C) and ``glob_in`` (8, C) the held
    estimate (TONE_FIELDS, GLOBAL_FIELDS of :mod:`sinewatch.estimators._nls_fit`). ``iconsts`` =
    (K fixed or 0, k_max, AIC?, 1 + trend, padded band low bin, padded band high bin, max
    iterations, hop, warm start?); ``fconsts`` = (fs, max_relative_residual).

    Returns ``out_k`` (C, 6, rows, k_cols) = frequency_hz, amplitude, phase_rad and their
    standard deviations; ``out_g`` (C, 5, rows) = offset, its standard deviation, converged
    (0/1), number of tones, fit residual RMS; ``sse`` and ``n_pred`` (C,), the one-step
    prediction errors' sum of squares and count; then the new stacked state. Pure: the inputs
    are not modified. Channels go ``LANES`` at a time: every input sample's prediction runs the
    lanes as one vector (:func:`_start_lane`, :func:`_tone_lane` a tone, :func:`_finish_lane`),
    the window fits and the output rows lane by lane."""
    n, nc = x.shape
    N = buf_in.shape[0]
    kc = tones_in.shape[0]
    hop = iconsts[7]
    fs = fconsts[0]
    rows = 1 if last_only else n
    out_k = np.empty((nc, 6, rows, kc))
    out_g = np.empty((nc, 5, rows))
    sse = np.zeros(nc)
    n_pred = np.zeros(nc, dtype=np.int64)
    b = buf_in.copy()
    new_istate = np.empty((5, nc), dtype=np.int64)
    new_tones = np.empty((kc, 11, nc))
    new_glob = np.empty((8, nc))
    L = LANES
    W = aligned_lanes((_FIXED_ROWS + _TONE_ROWS * kc) * L)
    xw = np.empty(N)
    xf = x.reshape(n * nc)  # the samples, flat (C order), for copy_lanes
    tones = np.empty((L, kc, 11))  # each lane's held estimate (tones[i, 7:9] kept in W between fits)
    glob = np.empty((L, 8))
    pos = np.zeros(L, dtype=np.int64)  # the ring's write position once samples 0 .. written - 1 are in
    fill = np.zeros(L, dtype=np.int64)
    since = np.zeros(L, dtype=np.int64)  # samples since the last fit (at most hop), at sample `counted`
    held = np.zeros(L, dtype=np.int64)
    written = np.zeros(L, dtype=np.int64)
    counted = np.zeros(L, dtype=np.int64)  # the samples `since` has counted
    due = np.zeros(L, dtype=np.int64)  # the sample at which the lane's next window is due
    for g in range(0, nc, L):
        width = min(L, nc - g)
        W[:] = 0.0  # lanes past the last channel run on zeros (nothing held), their results dropped
        for c in range(width):
            ch = g + c
            for i in range(kc):
                for f in range(11):
                    tones[c, i, f] = tones_in[i, f, ch]
            for f in range(8):
                glob[c, f] = glob_in[f, ch]
            pos[c], fill[c], since[c], held[c] = istate_in[0, ch], istate_in[1, ch], istate_in[2, ch], istate_in[3, ch]
            written[c] = 0
            counted[c] = 0
            due[c] = _first_due(fill[c], since[c], N, hop)
            _load_lane(W, c, tones[c], glob[c], held[c], istate_in[4, ch])
        next_due = _earliest(due, width)
        for j in range(n):
            if width == 1:  # one channel (the class's own path): lane 0 alone, scalar
                W[_RX * L] = x[j, g]
                _predict_lane(W, 0, kc)
            else:
                if width == L:  # the sample row as one vector (the lane loop loads it as one)
                    copy_lanes(W, _RX * L, xf, j * nc + g)
                else:
                    for c in range(width):
                        W[_RX * L + c] = x[j, g + c]
                _predict_lanes(W, kc)
            if j == next_due:  # a window is due in some lane: its fit, lane by lane
                _catch_up_lanes(b, x, g, width, written, pos, fill, j + 1)
                for c in range(width):
                    if due[c] == j:
                        since[c] = 0
                        counted[c] = j + 1
                        _chronological(b, g + c, pos[c], xw)
                        _store_rotation(W, c, tones[c])
                        window_estimate(xw, iconsts, fconsts, cos_tab, sin_tab, tones[c], glob[c])
                        held[c] = 1 if glob[c, 7] > 0.0 else 0
                        _load_lane(W, c, tones[c], glob[c], held[c], 0)
                        due[c] = j + hop
                next_due = _earliest(due, width)
            if not last_only or j == n - 1:
                r = 0 if last_only else j
                for c in range(width):
                    write_row(out_k[g + c], out_g[g + c], r, tones[c], glob[c], held[c], int(W[_RM * L + c]), fs)
        for c in range(width):
            since[c] = min(since[c] + n - counted[c], hop) if since[c] < hop else since[c]
        _catch_up_lanes(b, x, g, width, written, pos, fill, n)
        for c in range(width):
            ch = g + c
            _store_rotation(W, c, tones[c])
            sse[ch] = W[_RSSE * L + c]
            n_pred[ch] = int(W[_RNPRED * L + c])
            new_istate[0, ch], new_istate[1, ch], new_istate[2, ch] = pos[c], fill[c], since[c]
            new_istate[3, ch], new_istate[4, ch] = held[c], int(W[_RM * L + c])
            for i in range(kc):
                for f in range(11):
                    new_tones[i, f, ch] = tones[c, i, f]
            for f in range(8):
                new_glob[f, ch] = glob[c, f]
    return out_k, out_g, sse, n_pred, b, new_istate, new_tones, new_glob
