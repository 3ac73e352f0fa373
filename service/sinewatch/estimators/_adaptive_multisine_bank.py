"""``adaptive-multisine``: the compiled bank (:mod:`sinewatch.estimators.bank`) of the automatic mode
for n = 2 (the class's example and most uses), the channels of a frame through one kernel call,
each channel's outputs and state bit for bit those of :func:`auto_kernel_n2` run on it alone.

Both kernels run the same per-sample functions of :mod:`sinewatch.estimators._adaptive_multisine_small`
(:func:`n2_observe`, :func:`n2_recentred`, :func:`n2_guard`) on the same floats, so they agree by
construction. Here the channels go ``LANES`` at a time through one lane-major work array ``S``
(row r, lane c at ``S[r * LANES + c]``: the one-array, literal-trip-count form in which numba's
LLVM vectorises a loop over lanes, :mod:`sinewatch.estimators.bank`): the observer, the law (22)
and the guard of every lane as one vector; the re-centring AD8 (a product over the poles in
complex arithmetic, rare) and the output rows lane by lane. The other modes (n = 1, n >= 3, the
explicit gains) have no bank: their channels run one by one.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from sinewatch.estimators._adaptive_multisine_auto import _K_H, _K_OMU, _K_RC, _K_TBAR, _K_ZMAX, _N_K
from sinewatch.estimators._adaptive_multisine_small import (
    N2_ROW,
    N2_STATE,
    auto_kernel_n2,
    n2_gains,
    n2_guard,
    n2_load,
    n2_observe,
    n2_phases,
    n2_recentre_due,
    n2_recentred,
    n2_store,
    n2_write_row,
)
from sinewatch.estimators.base import Track, kernel

LANES = 8  # channels advanced together: two 256-bit vectors of doubles (one 512-bit)
# rows of the work array after the state's (N2_STATE): the sample in, tr(M) for the guard, AD8 due,
# the guard's verdict, then the sample's outputs (N2_ROW)
_RX = len(N2_STATE)
_RTR, _RDUE, _RBAD, _RROW = _RX + 1, _RX + 2, _RX + 3, _RX + 4
_ROWS = _RROW + N2_ROW


@kernel(inline="always")
def _lane_state(S: np.ndarray, lane: int) -> tuple[float, ...]:
    """Lane ``lane``'s state tuple (:data:`N2_STATE`), entry r from row r of ``S``."""
    L = LANES
    # a tuple literal of more than 30 entries compiles to a list turned into a tuple (CPython),
    # which numba does not take: two literals joined
    return (  # noqa: RUF005
        S[0 * L + lane], S[1 * L + lane], S[2 * L + lane], S[3 * L + lane], S[4 * L + lane], S[5 * L + lane],
        S[6 * L + lane], S[7 * L + lane], S[8 * L + lane], S[9 * L + lane], S[10 * L + lane], S[11 * L + lane],
        S[12 * L + lane], S[13 * L + lane], S[14 * L + lane], S[15 * L + lane], S[16 * L + lane], S[17 * L + lane],
        S[18 * L + lane], S[19 * L + lane], S[20 * L + lane], S[21 * L + lane],
    ) + (
        S[22 * L + lane], S[23 * L + lane], S[24 * L + lane], S[25 * L + lane], S[26 * L + lane], S[27 * L + lane],
        S[28 * L + lane], S[29 * L + lane], S[30 * L + lane], S[31 * L + lane], S[32 * L + lane], S[33 * L + lane],
        S[34 * L + lane], S[35 * L + lane], S[36 * L + lane], S[37 * L + lane], S[38 * L + lane], S[39 * L + lane],
        S[40 * L + lane], S[41 * L + lane], S[42 * L + lane],
    )  # fmt: skip


@kernel(inline="always")
def _set_lane_state(S: np.ndarray, lane: int, st: tuple[float, ...]) -> None:
    """Lane ``lane``'s state tuple into rows 0-42 of ``S``."""
    L = LANES
    (
        S[0 * L + lane], S[1 * L + lane], S[2 * L + lane], S[3 * L + lane], S[4 * L + lane], S[5 * L + lane],
        S[6 * L + lane], S[7 * L + lane], S[8 * L + lane], S[9 * L + lane], S[10 * L + lane], S[11 * L + lane],
        S[12 * L + lane], S[13 * L + lane], S[14 * L + lane], S[15 * L + lane], S[16 * L + lane], S[17 * L + lane],
        S[18 * L + lane], S[19 * L + lane], S[20 * L + lane], S[21 * L + lane],
        S[22 * L + lane], S[23 * L + lane], S[24 * L + lane], S[25 * L + lane], S[26 * L + lane], S[27 * L + lane],
        S[28 * L + lane], S[29 * L + lane], S[30 * L + lane], S[31 * L + lane], S[32 * L + lane], S[33 * L + lane],
        S[34 * L + lane], S[35 * L + lane], S[36 * L + lane], S[37 * L + lane], S[38 * L + lane], S[39 * L + lane],
        S[40 * L + lane], S[41 * L + lane], S[42 * L + lane],
    ) = st  # fmt: skip


@kernel(inline="always")
def _lane_observe(S: np.ndarray, lane: int, write: bool, g: tuple[float, ...], rc: float) -> None:
    """:func:`n2_observe` on lane ``lane`` of ``S``: its state, sample and outputs in rows of that
    one array at constant offsets, so that the compiler runs the lanes as one vector."""
    L = LANES
    st, row, tr = n2_observe(S[_RX * L + lane], write, _lane_state(S, lane), g)
    _set_lane_state(S, lane, st)
    r = _RROW * L + lane
    (
        S[r], S[r + L], S[r + 2 * L], S[r + 3 * L], S[r + 4 * L], S[r + 5 * L], S[r + 6 * L], S[r + 7 * L],
        S[r + 8 * L], S[r + 9 * L], S[r + 10 * L], S[r + 11 * L], S[r + 12 * L], S[r + 13 * L], S[r + 14 * L],
        S[r + 15 * L], S[r + 16 * L],
    ) = row  # fmt: skip
    S[_RTR * L + lane] = tr
    S[_RDUE * L + lane] = 1.0 if n2_recentre_due(st, rc) else 0.0


@kernel(inline="always")
def _lane_guard(S: np.ndarray, lane: int, zmax: float, tbar: float) -> None:
    """:func:`n2_guard` on lane ``lane`` of ``S``, as :func:`_lane_observe` runs the observer."""
    L = LANES
    st, bad = n2_guard(_lane_state(S, lane), S[_RTR * L + lane], zmax, tbar)
    _set_lane_state(S, lane, st)
    S[_RBAD * L + lane] = 1.0 if bad else 0.0


@kernel(inline="always")
def _lane_row(S: np.ndarray, lane: int) -> tuple[float, ...]:
    """Lane ``lane``'s outputs of the sample (:data:`N2_ROW`)."""
    L = LANES
    r = _RROW * L + lane
    return (
        S[r], S[r + L], S[r + 2 * L], S[r + 3 * L], S[r + 4 * L], S[r + 5 * L], S[r + 6 * L], S[r + 7 * L],
        S[r + 8 * L], S[r + 9 * L], S[r + 10 * L], S[r + 11 * L], S[r + 12 * L], S[r + 13 * L], S[r + 14 * L],
        S[r + 15 * L], S[r + 16 * L],
    )  # fmt: skip


@kernel(refcount=False)
def _bank_sample(
    S: np.ndarray, width: int, write: bool, g: tuple[float, ...], rc: float, poles: np.ndarray, bias: float,
    zmax: float, tbar: float,
) -> None:  # fmt: skip
    """One sample of every lane of ``S`` (its row ``_RX``): :func:`n2_observe`, AD8 where due,
    :func:`n2_guard`. Compiled on its own without reference counting: numba's reference counts of
    ``S`` in the inlined steps are calls, and a loop with a call is not vectorised."""
    L = LANES
    for lane in range(L):  # literal trip count: one vector
        _lane_observe(S, lane, write, g, rc)
    for c in range(width):  # AD8, rare: lane by lane
        if S[_RDUE * L + c] != 0.0:
            _set_lane_state(S, c, n2_recentred(_lane_state(S, c), rc, poles, bias))
    for lane in range(L):
        _lane_guard(S, lane, zmax, tbar)


@kernel
def adaptive_multisine_n2_bank_kernel(
    x: np.ndarray, s_in: np.ndarray, cf: np.ndarray, ci: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`auto_kernel_n2` for C channels at once: ``x`` (N, C), ``s_in`` (C, state size), the
    channels' states stacked channel first; returns ``out`` (C, rows, 8), ``ext`` (C, rows, 8),
    ``sse`` (C,) and the new states (C, state size). Lanes past the last channel of a group run
    on copies of its first channel, their results dropped."""
    n, nc = x.shape
    nx = ci[1]
    g = n2_gains(cf, ci)
    h, tbar, om_u, zmax, rc = cf[_K_H], cf[_K_TBAR], cf[_K_OMU], cf[_K_ZMAX], cf[_K_RC]
    poles = cf[_N_K : _N_K + nx]
    bias = g[22]
    rows = 1 if last_only else n
    out = np.empty((nc, rows, 8))
    ext = np.empty((nc, rows, 8))
    cph = np.empty((nc, rows, 2))
    sse = np.zeros(nc)
    s_out = s_in.copy()
    L = LANES
    S = np.zeros(_ROWS * L)
    for g0 in range(0, nc, L):
        width = min(L, nc - g0)
        for lane in range(L):
            _set_lane_state(S, lane, n2_load(s_in[g0 + (lane if lane < width else 0)], ci))
        for i in range(n):
            write = (not last_only) or i == n - 1
            j = 0 if last_only else i
            for lane in range(L):
                S[_RX * L + lane] = x[i, g0 + (lane if lane < width else 0)]
            _bank_sample(S, width, write, g, rc, poles, bias, zmax, tbar)
            if write:
                for c in range(width):
                    n2_write_row(out[g0 + c], ext[g0 + c], cph[g0 + c], j, _lane_row(S, c), S[_RBAD * L + c] != 0.0)
        for c in range(width):
            sse[g0 + c] = n2_store(s_out[g0 + c], ci, _lane_state(S, c))
    for c in range(nc):
        n2_phases(out[c], cph[c], h, om_u)
    return out, ext, sse, s_out


def run_adaptive_multisine_bank(
    estimators: Sequence[Any], x: np.ndarray, last_only: bool, t0_ns: int | None
) -> list[Track] | None:
    """The bank of ``estimators`` (AdaptiveMultisine instances of one rule) over ``x`` (N, C),
    validated by ``update_bank``; None (their channels run one by one) unless they run
    :func:`auto_kernel_n2`. The states are gathered channel first by one copy and each channel's
    new state is its row of the kernel's result, a view."""
    first = estimators[0]
    if first._small_n_kernel is not auto_kernel_n2:
        return None
    s_in = np.concatenate([e._state["s"] for e in estimators]).reshape(len(estimators), -1)
    cf, ci = first._constants
    out, ext, sse, s_out = adaptive_multisine_n2_bank_kernel(x, s_in, cf, ci, last_only)
    tracks = [e._track((out[c], ext[c], sse[c]), x[:, c]) for c, e in enumerate(estimators)]
    for e, s in zip(estimators, list(s_out), strict=True):
        e._state = {"s": s}
    return tracks
