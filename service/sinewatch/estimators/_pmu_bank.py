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

from sinewatch.estimators._pmu_kernels import N_REPORT_COLUMNS, N_TRANSITION, pmu_kernel, transition_kernel
from sinewatch.estimators.base import GridReports, Track, TrackStd, kernel, track_from_columns

if TYPE_CHECKING:
    from sinewatch.estimators.pmu import Pmu


@kernel
def pmu_bank_kernel(
    x: np.ndarray,
    ring: np.ndarray,
    dcring: np.ndarray,
    istate: np.ndarray,
    fstate: np.ndarray,
    anchor: np.ndarray,
    noise: np.ndarray,
    trans: np.ndarray,
    kernels: np.ndarray,
    osc: np.ndarray,
    weights: np.ndarray,
    iconsts: np.ndarray,
    fconsts: np.ndarray,
    g_pass: np.ndarray,
    a2_bias: np.ndarray,
    g_chirp: np.ndarray,
    g_image: np.ndarray,
    noise_gram: np.ndarray,
    probe_taper: np.ndarray,
    probe_gram: np.ndarray,
    fs_rep: float,
    n_hold: int,
    last_only: bool,
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
]:  # fmt: skip
    """Channel c (row c of ``x`` (C, N) and of every stacked state array) through
    :func:`pmu_kernel` and (T) over its reports. Returns (out (C, rows, 6), reports (C, cap,
    14), reports per channel (C,), sse (C,), n_pred (C,), the reports' converged (C, cap),
    then the new ring, dc_ring, counters, values, anchor, noise and transition state, each
    stacked channel first). Pure: no input is modified."""
    nc, n_in = x.shape
    rows = 1 if last_only else n_in
    cap = n_in // max(1, int(fconsts[5])) + 2  # pmu_kernel's own bound on a block's reports
    min_amp = fconsts[6]
    out = np.empty((nc, rows, 6))
    reps = np.empty((nc, cap, N_REPORT_COLUMNS))
    n_rep = np.zeros(nc, dtype=np.int64)
    sse = np.empty(nc)
    n_pred = np.zeros(nc, dtype=np.int64)
    conv = np.zeros((nc, cap), dtype=np.bool_)
    rg2, dr2, ist2, fst2 = np.empty_like(ring), np.empty_like(dcring), np.empty_like(istate), np.empty_like(fstate)
    anc2, nz2, tr2 = np.empty_like(anchor), np.empty_like(noise), np.empty_like(trans)
    for c in range(nc):
        o, r, s, npd, rg, dr, ist, fst, anc, nz = pmu_kernel(
            x[c], ring[c], dcring[c], istate[c], fstate[c], anchor[c], noise[c], kernels, osc, weights, iconsts,
            fconsts, g_pass, a2_bias, g_chirp, g_image, noise_gram, probe_taper, probe_gram, last_only,
        )  # fmt: skip
        k = r.shape[0]
        out[c] = o
        reps[c, :k] = r
        n_rep[c] = k
        sse[c] = s
        n_pred[c] = npd
        rg2[c], dr2[c], ist2[c], fst2[c], anc2[c], nz2[c] = rg, dr, ist, fst, anc, nz
        if k:  # (T) as Pmu._converged calls it: contiguous columns of the reports
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
        else:
            tr2[c] = trans[c]
    return out, reps, n_rep, sse, n_pred, conv, rg2, dr2, ist2, fst2, anc2, nz2, tr2


_STATE_KEYS = ("ring", "dc_ring", "counters", "values", "anchor_ns", "noise")


def run_pmu_bank(ests: Sequence[Any], x: np.ndarray, last_only: bool, t0_ns: int | None) -> list[Track] | None:
    """The bank of ``ests`` (Pmu instances of one rule) over ``x`` (N, C), validated by
    ``update_bank``; None when the channels cannot share one call (an 'auto' channel still
    undecided, or channels that decided different nominal frequencies): they then run one by
    one."""
    first: Pmu = ests[0]
    nominal = first._nominal
    if nominal == 0 or any(e._nominal != nominal for e in ests):
        return None
    nc = len(ests)
    states, fresh = [], []
    for e in ests:  # the time anchor, per channel as Pmu._run_timed does it
        st = e._state if t0_ns is None else e._state_for_block(e._state, t0_ns)
        states.append(st)
        fresh.append(st is not e._state)  # anchored afresh: (T) starts over
    # one C call a state array (as update_bank's channel-first banks)
    stacked = [np.concatenate([st[k] for st in states]).reshape((nc, *states[0][k].shape)) for k in _STATE_KEYS]
    trans = np.concatenate([np.zeros(N_TRANSITION) if f else e._transition for e, f in zip(ests, fresh, strict=True)])
    xt = np.ascontiguousarray(x.T)
    out, reps, n_rep, sse, n_pred, conv, *new = pmu_bank_kernel(
        xt, *stacked, trans.reshape(nc, N_TRANSITION), *first._constants,
        float(first.reporting_rate), first._n_hold, last_only,
    )  # fmt: skip
    new_trans = list(new.pop())
    rows = [list(s) for s in new]
    refer = first.design.f_osc != first.design.f0
    tracks = []
    for c, e in enumerate(ests):
        e._state = dict(zip(_STATE_KEYS, (r[c] for r in rows), strict=True))
        e._transition = new_trans[c]
        k = int(n_rep[c])
        track = grid_track(e.reporting_rate, out[c], reps[c, :k], float(sse[c]), int(n_pred[c]), conv[c, :k])
        if refer and k:
            e._refer_to_nominal(track.reports, int(e._state["anchor_ns"][0]))
        tracks.append(track)
    return tracks


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
