"""The ``pmu`` estimator's bank: the channels of a frame that share one pmu rule, advanced
by one compiled call (``sinewatch.estimators.bank``).

Each channel runs through :func:`pmu_kernel` and then (T) :func:`transition_kernel` over its
reports, the very kernels the single-channel path calls, in one compiled loop over the
channels: the outputs are the single path's bit for bit by construction. What the bank saves
is the Python around each channel's block (the kernels' dispatch, the anchoring, (T)'s call,
the Track's assembly), about as much time as the kernel itself on a 1024-sample block. The
time anchor stays per channel (a channel whose block starts a gap in time restarts on the
grid alone); the channels' states are stacked channel first, so each channel's state after
the call is a view of one row.

Not done here: the lane-major form (the channels as SIMD lanes). A pmu's channels advance in
lock step only while their sample counts agree (the demodulation weights, the decimation
phase and the report instants all follow the count since the channel's own anchor), which a
frame's channels do but a bank's need not.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from sinewatch.estimators._pmu_kernels import (
    N_REPORT_COLUMNS,
    N_TRANSITION,
    _held_model,
    _next_report,
    _out_row,
    _report,
    transition_kernel,
)
from sinewatch.estimators.base import GridReports, Track, TrackStd, cyclic_next, kernel, track_from_columns
from sinewatch.estimators.lanes import LANES, aligned_lanes, copy_lanes, frozen, select

if TYPE_CHECKING:
    from sinewatch.estimators.pmu import Pmu


# fmt: off
@kernel
def pmu_bank_kernel(
    x: np.ndarray, ring: np.ndarray, dcring: np.ndarray, istate: np.ndarray, fstate: np.ndarray, anchor: np.ndarray,
    noise: np.ndarray, trans: np.ndarray, active: np.ndarray, design: tuple[np.ndarray, ...], fs_rep: float,
    n_hold: int, last_only: bool,
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
]:
    # fmt: on
    """The channels of ``x`` (N, C), C = LANES x groups (``design``: the class's constants, as
    :func:`pmu_kernel` takes them one by one), in groups of LANES lanes (group g's
    first ``active[g]`` lanes are channels, the rest pad it) through :func:`_lanes`, then
    (T) over each channel's reports. Returns (out (C, rows, 6), reports (C, cap, 14),
    reports per channel (C,), sse (C,), n_pred (C,), the reports' converged (C, cap), then
    the new ring, dc_ring, counters, values, anchor, noise and transition state, each stacked
    channel first). Pure: no input is modified."""
    fconsts = design[4]
    n_in, nc = x.shape
    rows = 1 if last_only else n_in
    cap = n_in // max(1, int(fconsts[5])) + 2  # pmu_kernel's own bound on a block's reports
    min_amp = fconsts[6]
    out = np.empty((nc, rows, 6))
    reps = np.empty((nc, cap, N_REPORT_COLUMNS))
    n_rep = np.zeros(nc, dtype=np.int64)
    sse = np.zeros(nc)
    n_pred = np.zeros(nc, dtype=np.int64)
    conv = np.zeros((nc, cap), dtype=np.bool_)
    rg2, dr2, ist2, fst2 = ring.copy(), dcring.copy(), istate.copy(), fstate.copy()
    anc2, nz2, tr2 = anchor.copy(), noise.copy(), trans.copy()
    for g in range(nc // LANES):
        _lanes(
            x, g * LANES, active[g], rg2, dr2, ist2, fst2, nz2, design, last_only, out, reps, n_rep, sse, n_pred,
        )  # fmt: skip
    for c in range(nc):
        k = n_rep[c]
        if k:  # (T) as Pmu._converged calls it: contiguous columns of the reports
            r = reps[c, :k]
            cv, st = transition_kernel(
                np.ascontiguousarray(r[:, 3]),
                np.ascontiguousarray(r[:, 1]),
                np.ascontiguousarray(r[:, 2]),
                trans[c],
                fs_rep,
                n_hold,
                min_amp,
            )
            conv[c, :k] = cv
            tr2[c] = st
    return out, reps, n_rep, sse, n_pred, conv, rg2, dr2, ist2, fst2, anc2, nz2, tr2


# the rows of _lanes's work array
_ACR = 0 * LANES
_ACI = 1 * LANES
_ANR = 2 * LANES
_ANI = 3 * LANES
_DCC = 4 * LANES
_DCN = 5 * LANES
_F = 6 * LANES
_A = 7 * LANES
_B = 8 * LANES
_ROCOF = 9 * LANES
_CONV = 10 * LANES
_CTH = 11 * LANES
_STH = 12 * LANES
_CSTEP = 13 * LANES
_SSTEP = 14 * LANES
_SSE = 15 * LANES
_BETA = 16 * LANES
_DEFINED = 17 * LANES
_N_PRED = 18 * LANES
_LIVE = 19 * LANES  # held and defined (0/1)
_X0 = 20 * LANES  # the samples, rows alternating: the next written while this one is read
_X1 = 21 * LANES
_W_ROWS = 22


@kernel(inline="always")
def _lane_sample(
    w: np.ndarray, ln: int, xrow: int, w0: float, w1: float, w2: float, w3: float, w4: float, w5: float
) -> None:
    """Lane ``ln``'s sample (row ``xrow`` of ``w``): the held model's prediction and (D), the
    operations of :func:`pmu_kernel` in its order, the branch on the held model a select."""
    xi = w[xrow + ln]
    live = w[_LIVE + ln] != 0.0
    e = xi - (w[_B + ln] + w[_A + ln] * w[_STH + ln])
    # selects, the kept rows frozen: blends and plain stores, not masked ones (see lanes.frozen)
    w[_SSE + ln] = select(live, w[_SSE + ln] + e * e, frozen(w[_SSE + ln]))
    w[_N_PRED + ln] = select(live, w[_N_PRED + ln] + 1.0, frozen(w[_N_PRED + ln]))
    w[_ACR + ln] += xi * w0
    w[_ACI + ln] += xi * w1
    w[_ANR + ln] += xi * w2
    w[_ANI + ln] += xi * w3
    w[_DCC + ln] += xi * w4
    w[_DCN + ln] += xi * w5


@kernel(inline="always")
def _lane_rotor(w: np.ndarray, ln: int) -> None:
    """Lane ``ln``'s rotor advanced to the next sample where a defined report is held."""
    live = w[_LIVE + ln] != 0.0
    c2 = w[_CTH + ln] * w[_CSTEP + ln] - w[_STH + ln] * w[_SSTEP + ln]
    s2 = w[_STH + ln] * w[_CSTEP + ln] + w[_CTH + ln] * w[_SSTEP + ln]
    w[_CTH + ln] = select(live, c2, frozen(w[_CTH + ln]))  # (see lanes.frozen)
    w[_STH + ln] = select(live, s2, frozen(w[_STH + ln]))


@kernel
def _lanes(
    x: np.ndarray,
    b: int,
    active: int,
    ring: np.ndarray,
    dcring: np.ndarray,
    istate: np.ndarray,
    fstate: np.ndarray,
    noise: np.ndarray,
    design: tuple[np.ndarray, ...],
    last_only: bool,
    out: np.ndarray,
    reps: np.ndarray,
    n_rep: np.ndarray,
    sse_out: np.ndarray,
    n_pred_out: np.ndarray,
) -> None:
    """:func:`pmu_kernel` for channels ``b .. b + LANES - 1`` (columns of ``x``, rows of the
    state arrays, which are updated in place), whose sample counts, decimation and report
    schedule agree (counters 0-4 and the grid offset ``values[0]``): the per-sample work
    (the held model's prediction, (D)'s demodulation, the rotor) runs across the lanes, each
    lane's operations those of :func:`pmu_kernel` in the same order; reports are made per
    lane by the single kernel's own functions, for the first ``active`` lanes only (the
    others pad the group)."""
    kernels, osc, weights, iconsts, fconsts, g_pass, a2_bias, g_chirp, g_image, noise_gram, probe_taper, probe_gram = (
        design
    )
    D, m_lo, L = iconsts[0], iconsts[2], iconsts[3]
    M = kernels.shape[2]
    f0, fs, spr, min_amp = fconsts[0], fconsts[1], fconsts[5], fconsts[6]
    n, j, k_next, k0, held = istate[b, 0], istate[b, 1], istate[b, 2], istate[b, 3], istate[b, 4]
    delta0 = fstate[b, 0]
    n_in, nc = x.shape
    # every lane variable a row of ONE work array, at constant offsets (what LLVM needs to
    # vectorise the lane loops without run-time overlap checks)
    w = aligned_lanes(_W_ROWS * LANES)  # rows on 64-byte boundaries: a row is one cache line
    w[:] = 0.0
    est = np.zeros((LANES, 12))
    for ln in range(LANES):
        c = b + ln
        w[_BETA + ln] = fstate[c, 1]
        w[_ACR + ln], w[_ACI + ln], w[_ANR + ln], w[_ANI + ln], w[_DCC + ln], w[_DCN + ln] = (
            fstate[c, 2], fstate[c, 3], fstate[c, 4], fstate[c, 5], fstate[c, 6], fstate[c, 7],
        )  # fmt: skip
        w[_F + ln], w[_A + ln], w[_B + ln], w[_ROCOF + ln], w[_CONV + ln] = (
            fstate[c, 8],
            fstate[c, 9],
            fstate[c, 11],
            fstate[c, 12],
            fstate[c, 13],
        )
        w[_CTH + ln], w[_STH + ln] = fstate[c, 14], fstate[c, 15]
        w[_DEFINED + ln] = istate[c, 5]
        w[_SSE + ln] = 0.0
        w[_CSTEP + ln] = 1.0
        w[_SSTEP + ln] = 0.0
        w[_LIVE + ln] = 1.0 if (held and w[_DEFINED + ln] != 0.0) else 0.0
        if held and w[_DEFINED + ln] != 0.0:
            w[_CSTEP + ln] = math.cos(2.0 * math.pi * w[_F + ln] / fs)
            w[_SSTEP + ln] = math.sin(2.0 * math.pi * w[_F + ln] / fs)
    copy_lanes(w, _X0, x, b)  # sample 0's row
    Q = weights.shape[0]
    ph = n % Q
    rho = n % D
    for i in range(n_in):
        w0, w1, w2, w3, w4, w5 = (
            weights[ph, 0],
            weights[ph, 1],
            weights[ph, 2],
            weights[ph, 3],
            weights[ph, 4],
            weights[ph, 5],
        )
        # sample i + 1 into the row sample i does not read, a step before it is read as a vector
        copy_lanes(w, _X1 if i % 2 == 0 else _X0, x, min(i + 1, n_in - 1) * nc + b)
        if i % 2 == 0:  # the rows as constants, so the compiler sees the lanes independent
            for ln in range(LANES):
                _lane_sample(w, ln, _X0, w0, w1, w2, w3, w4, w5)
        else:
            for ln in range(LANES):
                _lane_sample(w, ln, _X1, w0, w1, w2, w3, w4, w5)
        if rho == D - 1:  # c_j complete, in every lane
            slot = j % L
            for ln in range(LANES):
                c = b + ln
                ring[c, slot, 0] = w[_ACR + ln]
                ring[c, slot, 1] = w[_ACI + ln]
                ring[c, slot + L, 0] = w[_ACR + ln]
                ring[c, slot + L, 1] = w[_ACI + ln]
                dcring[c, slot] = w[_DCC + ln]
                dcring[c, slot + L] = w[_DCC + ln]
            # the next c_j's sums become the current ones as whole rows (the next sample's lane
            # loop loads them as vectors: 8 scalar stores each would stall those loads)
            copy_lanes(w, _ACR, w, _ANR)
            copy_lanes(w, _ACI, w, _ANI)
            copy_lanes(w, _DCC, w, _DCN)
            for ln in range(LANES):
                w[_ANR + ln] = w[_ANI + ln] = w[_DCN + ln] = 0.0
            while True:  # the report schedule, common to the lanes (pmu_kernel's loop)
                due, u, n_r, ph_r, oldest = _next_report(delta0, k_next, k0, spr, D, m_lo, M, j)
                if due == 0:
                    break
                if due == 1:
                    k_next += 1
                    continue
                held = 1
                for ln in range(active):
                    c = b + ln
                    _report(
                        ring[c], dcring[c], oldest % L, kernels[ph_r], osc, n_r, fconsts, g_pass[ph_r],
                        a2_bias[ph_r], g_chirp[ph_r], g_image[ph_r], noise_gram[ph_r], probe_taper[ph_r],
                        probe_gram[ph_r], noise[c], est[ln],
                    )  # fmt: skip
                    (
                        w[_DEFINED + ln],
                        w[_F + ln],
                        w[_A + ln],
                        w[_B + ln],
                        w[_ROCOF + ln],
                        w[_CONV + ln],
                        w[_CTH + ln],
                        w[_STH + ln],
                        w[_CSTEP + ln],
                        w[_SSTEP + ln],
                        k,
                    ) = _held_model(
                        est[ln],
                        u,
                        n_r,
                        n,
                        k_next,
                        w[_BETA + ln],
                        f0,
                        fs,
                        min_amp,
                        reps[c],
                        n_rep[c],
                        w[_CSTEP + ln],
                        w[_SSTEP + ln],
                    )
                    n_rep[c] = k
                    w[_LIVE + ln] = 1.0 if w[_DEFINED + ln] != 0.0 else 0.0  # held now
                k_next += 1
            j += 1
        if not (last_only and i != n_in - 1):
            for ln in range(active):
                _out_row(
                    out[b + ln], 0 if last_only else i, held != 0 and w[_DEFINED + ln] != 0.0, w[_F + ln], w[_A + ln], w[_B + ln], w[_CONV + ln], w[_ROCOF + ln],
                    w[_CTH + ln], w[_STH + ln],
                )  # fmt: skip
        for ln in range(LANES):  # advance the rotor to sample n + 1
            _lane_rotor(w, ln)
        n += 1
        ph = cyclic_next(ph, Q)
        rho = cyclic_next(rho, D)
    for ln in range(active):
        c = b + ln
        istate[c, 0], istate[c, 1], istate[c, 2], istate[c, 3], istate[c, 4], istate[c, 5] = (
            n, j, k_next, k0, held, int(w[_DEFINED + ln]),
        )  # fmt: skip
        fstate[c, 0], fstate[c, 1] = delta0, w[_BETA + ln]
        fstate[c, 2], fstate[c, 3], fstate[c, 4], fstate[c, 5], fstate[c, 6], fstate[c, 7] = (
            w[_ACR + ln], w[_ACI + ln], w[_ANR + ln], w[_ANI + ln], w[_DCC + ln], w[_DCN + ln],
        )  # fmt: skip
        fstate[c, 8], fstate[c, 9], fstate[c, 10], fstate[c, 11] = w[_F + ln], w[_A + ln], 0.0, w[_B + ln]
        fstate[c, 12], fstate[c, 13], fstate[c, 14], fstate[c, 15] = (
            w[_ROCOF + ln],
            w[_CONV + ln],
            w[_CTH + ln],
            w[_STH + ln],
        )
        sse_out[c] = w[_SSE + ln]
        n_pred_out[c] = int(w[_N_PRED + ln])


_STATE_KEYS = ("ring", "dc_ring", "counters", "values", "anchor_ns", "noise")


def run_pmu_bank(ests: Sequence[Any], x: np.ndarray, last_only: bool, t0_ns: int | None) -> list[Track] | None:
    """The bank of ``ests`` (Pmu instances of one rule) over ``x`` (N, C), validated by
    ``update_bank``; None when the channels cannot share one call (an 'auto' channel still
    undecided, or channels that decided different nominal frequencies): they then run one by
    one. Channels whose schedules agree (a frame's, anchored together) share groups of lanes;
    each group is padded to LANES lanes with copies of its first channel."""
    first: Pmu = ests[0]
    nominal = first._nominal
    if nominal == 0 or any(e._nominal != nominal for e in ests):
        return None
    states: list[dict[str, np.ndarray]] = []
    trans: list[np.ndarray] = []
    groups: dict[bytes, list[int]] = {}
    for c, e in enumerate(ests):  # the time anchor, per channel as Pmu._run_timed does it
        st = e._state if t0_ns is None else e._state_for_block(e._state, t0_ns)
        states.append(st)
        trans.append(e._transition if st is e._state else np.zeros(N_TRANSITION))  # anchored afresh: (T) over
        # lanes advance in lock step: the same sample count, decimation, grid index and report
        key = st["counters"][:5].tobytes() + st["values"][:1].tobytes()
        groups.setdefault(key, []).append(c)
    order, active = [], []
    for members in groups.values():
        for s in range(0, len(members), LANES):
            part = members[s : s + LANES]
            order += part + [part[0]] * (LANES - len(part))
            active.append(len(part))
    slot = {c: i for i, c in enumerate(order) if i % LANES < active[i // LANES]}  # channel -> its lane
    last = getattr(first, "_bank_last", None)
    if last is not None and last.fits(ests, order, slot, states, trans):
        # the steady state of a frame: every channel's state is still its row of the last
        # call's stacked arrays, in the same lanes; the kernel copies them (it is pure)
        stacked, trans_in = last.stacked, last.trans
    else:  # one C call a state array
        stacked = [
            np.concatenate([states[c][k] for c in order]).reshape((len(order), *states[0][k].shape))
            for k in _STATE_KEYS
        ]
        trans_in = np.concatenate([trans[c] for c in order]).reshape(len(order), N_TRANSITION)
    # the samples as the kernel is compiled for them (writable, C order): a frame's read-only
    # payload view would compile it a second time
    in_order = order == list(range(x.shape[1]))
    xg = (x if x.flags.writeable else x.copy()) if in_order else np.ascontiguousarray(x[:, order])
    args: tuple[Any, ...] = (
        xg, *stacked, trans_in, np.array(active, dtype=np.int64), first._constants,
        float(first.reporting_rate), first._n_hold, last_only,
    )  # fmt: skip
    out, reps, n_rep, sse, n_pred, conv, *new = pmu_bank_kernel(*args)
    new_trans = new.pop()
    refer = first.design.f_osc != first.design.f0
    after = _LastCall(order, new, new_trans)
    nc = len(ests)
    k0 = int(n_rep[0])
    # a frame's channels in lanes 0..C-1 with as many reports each (lock step): their Tracks
    # with one numpy call a field (grid_track, a channel at a time, makes ~30 views each)
    same = all(slot[c] == c for c in range(nc)) and bool(np.all(n_rep[:nc] == k0))
    rate = first.reporting_rate
    batch = grid_tracks(rate, out[:nc], reps[:nc, :k0], sse[:nc], n_pred[:nc], conv[:nc, :k0]) if same else None
    tracks = []
    for c, e in enumerate(ests):
        i = slot[c]
        e._state = after.states[i] = {k: a[i] for k, a in zip(_STATE_KEYS, new, strict=True)}
        e._transition = after.transitions[i] = new_trans[i]
        e._bank_last = after
        k = int(n_rep[i])
        if batch is not None:
            track = batch[c]
        else:
            track = grid_track(rate, out[i], reps[i, :k], float(sse[i]), int(n_pred[i]), conv[i, :k])
        if refer and k:
            e._refer_to_nominal(track.reports, int(e._state["anchor_ns"][0]))
        tracks.append(track)
    return tracks


class _LastCall:
    """A bank call's stacked new state, kept so that the next call of the same channels in the
    same lanes can pass it on without gathering each channel's arrays again (~8 us a channel)."""

    __slots__ = ("order", "stacked", "states", "trans", "transitions")

    def __init__(self, order: list[int], stacked: list[np.ndarray], trans: np.ndarray) -> None:
        self.order, self.stacked, self.trans = order, stacked, trans
        self.states: dict[int, dict[str, np.ndarray]] = {}
        self.transitions: dict[int, np.ndarray] = {}

    def fits(
        self,
        ests: Sequence[Any],
        order: list[int],
        slot: dict[int, int],
        states: list[dict[str, np.ndarray]],
        trans: list[np.ndarray],
    ) -> bool:
        """Whether channel c's state and (T) state are still the very arrays this call left in
        its lane (nothing re-anchored, restored or reset them since), for every channel."""
        if order != self.order:
            return False
        return all(
            getattr(e, "_bank_last", None) is self
            and states[c] is self.states.get(slot[c])
            and trans[c] is self.transitions.get(slot[c])
            for c, e in enumerate(ests)
        )


def grid_track(
    reporting_rate: int, out: np.ndarray, reps: np.ndarray, sse: float, n_pred: int, conv: np.ndarray
) -> Track:
    """A pmu block's Track from its kernel's outputs (``pmu_kernel``'s out, reports, sse and
    n_pred) and its reports' converged; shared by the single path (``Pmu._track``) and the
    bank, so that both assemble the same arrays."""
    return track_from_columns(
        out,
        sse,
        n_pred,
        rocof_hz_per_s=out[:, 5:6],
        reports=GridReports(
            index=reps[:, 0].astype(np.int64),
            reporting_rate_hz=reporting_rate,
            track=Track(
                frequency_hz=reps[:, 1:2],
                amplitude=reps[:, 5:6],
                phase_rad=reps[:, 6:7],
                offset=reps[:, 7],
                converged=conv,
                residual_rms=math.sqrt(sse / n_pred) if n_pred else math.nan,
                extras={
                    "synchrophasor_magnitude": reps[:, 3],
                    "synchrophasor_angle_rad": reps[:, 4],
                    "std_rocof_hz_per_s": reps[:, 9],
                    "std_tve": reps[:, 13],
                },
                rocof_hz_per_s=reps[:, 2:3],
                std=TrackStd(
                    frequency_hz=reps[:, 8:9],
                    amplitude=reps[:, 10:11],
                    phase_rad=reps[:, 11:12],
                    offset=reps[:, 12],
                ),
            ),
        ),
    )


def grid_tracks(
    reporting_rate: int, out: np.ndarray, reps: np.ndarray, sse: np.ndarray, n_pred: np.ndarray, conv: np.ndarray
) -> list[Track]:
    """:func:`grid_track` of C channels with as many reports each: channel c's Track is exactly
    the one ``grid_track`` makes of row c of ``out`` (C, rows, 6), ``reps`` (C, k, 14), ``sse``,
    ``n_pred`` (C,) and ``conv`` (C, k), built with one numpy call a field for all channels
    (element-wise: the residual's division and square root round as ``math``'s do)."""
    nc = out.shape[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        rms = np.where(n_pred > 0, np.sqrt(sse / n_pred), math.nan).tolist()
    col = {j: list(out[:, :, j : j + 1]) for j in (0, 1, 2, 5)}
    offset, o_conv = list(out[:, :, 3]), list(out[:, :, 4].astype(np.bool_))
    index, r_conv = list(reps[:, :, 0].astype(np.int64)), list(conv)
    rc = {j: list(reps[:, :, j : j + 1]) for j in (1, 2, 5, 6, 8, 10, 11)}
    rv = {j: list(reps[:, :, j]) for j in (3, 4, 7, 9, 12, 13)}
    tracks = []
    for c in range(nc):
        extras = {
            "synchrophasor_magnitude": rv[3][c],
            "synchrophasor_angle_rad": rv[4][c],
            "std_rocof_hz_per_s": rv[9][c],
            "std_tve": rv[13][c],
        }
        std = TrackStd(rc[8][c], rc[10][c], rc[11][c], rv[12][c])
        rtrack = Track(rc[1][c], rc[5][c], rc[6][c], rv[7][c], r_conv[c], rms[c], extras, rc[2][c], std)
        reports = GridReports(index[c], reporting_rate, rtrack)
        tracks.append(Track(col[0][c], col[1][c], col[2][c], offset[c], o_conv[c], rms[c], {}, col[5][c], None, reports))
    return tracks
