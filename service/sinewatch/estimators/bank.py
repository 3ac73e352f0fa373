"""Estimator banks: the channels of a multi-channel frame that share one estimator rule,
advanced together.

:func:`update_bank` is the one entry point the pipeline uses for a frame. Its contract is
the single-channel path's, channel by channel: after ``update_bank(ests, x)`` every
``ests[c]`` holds exactly the state, and the returned ``tracks[c]`` exactly the bits, that
``ests[c].update(x[:, c])`` would have given, whatever the bank's size and the channel's
position in it. Recordings, replay, snapshots and failover therefore never depend on how
channels were grouped.

Why a bank is faster: every estimator is a recursion, each sample waiting on the previous
one, so one channel leaves most of the CPU's execution ports idle. A bank kernel runs the
samples in the outer loop and the channels in the inner one, with each state array laid out
across channels (shape ``(*single_shape, C)``): the C chains are independent, so the CPU
overlaps them (out-of-order execution, and SIMD where the compiler vectorises the inner
loop). Each channel's arithmetic is the single-channel kernel's, operation for operation:
both kernels call the same compiled per-sample step function, so they agree by
construction, not by test alone (the tests check it too). No fast-math, and no vectorised
library function where it would round differently: without Intel's SVML (numba uses it only
when it is installed; ``numba -s`` says), ``tan``, ``atan2`` and the like stay scalar C library
calls per lane, the same calls the single-channel kernel makes, and a bank keeps any such call
in a loop of its own so that the rest of the step may vectorise; ``sqrt`` and the project's
:func:`fma` are correctly rounded either way.

What it takes for numba's LLVM to vectorise a channel loop (ges-kalman's bank, read in its
assembly): a literal trip count (8 lanes, channels padded), and every load and store of the
loop in ONE array at constant offsets (``S[row * 8 + lane]``): across two arrays LLVM needs a
run-time overlap check, which it does not add to a loop of fewer than 16 iterations, so the
loop stays scalar. A vector load of a row just written by scalar stores stalls (store
forwarding fails): rows that the next step reads are written a step ahead. And a pure library
call under a branch (an exp taken only sometimes) is speculated for every lane once the loop
is vectorised, so such loops are kept out of the vectoriser's reach.

A class plugs a compiled bank in with :func:`register_bank`: a kernel that takes
``(X (N, C), *stacked state arrays (*shape, C), *constants, last_only)`` and returns its
outputs with the channel as the leading axis, then the new stacked state arrays. The
estimators' states are gathered into the stacked arrays (``np.array`` of the channels'
arrays, then channel last) the first time a bank runs, and stay stacked between frames
(:class:`~sinewatch.estimators.base.StackedStates`): the kernel's new arrays are the next
frame's arguments while the bank holds the same channels and none of them was read or given a
state on its own (then it leaves the stack with a copy of its column, and the next frame
gathers the bank afresh). A class whose ``_track`` is
:func:`~sinewatch.estimators.base.track_from_columns` passes ``tracks`` built by
:func:`column_tracks`: one numpy call a field for the whole frame, made only when a Track is
read (:class:`ColumnTracks`; a frame's usual Estimates read the bank's last row instead).
A class without one runs each channel's own kernel in turn; :data:`NO_BANK` says why.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, overload

import numpy as np

from sinewatch.estimators.base import (
    BankLastRow,
    Estimator,
    StackedStates,
    Track,
    TrackStd,
    _all_finite,
    kernel,
    kernel_samples,
)
from sinewatch.schemas.errors import InputError, InputTypeError, ParameterError


@dataclass(frozen=True, slots=True)
class BankKernel:
    """A compiled bank for one estimator class (see the module docstring for the calling
    convention). ``n_outputs``: how many of the kernel's results are outputs (the rest are
    the new state arrays, in the state dict's key order)."""

    kernel: Callable[..., tuple[Any, ...]]
    n_outputs: int
    #: the channels' Tracks from the stacked outputs in one pass (``tracks(first estimator,
    #: outputs, samples)``), for a class whose ``_track`` does numpy work that a whole frame
    #: can share; None: each channel's ``_track`` on its slice of the outputs
    tracks: Callable[[Any, tuple[Any, ...], np.ndarray], Sequence[Track]] | None = None
    #: a bank that runs the frame itself (``run(estimators, samples (N, C), last_only, t0_ns)``,
    #: the samples validated): an estimator whose per-block Python (pmu's time anchor, its (T)
    #: test over the reports) is part of the call; it returns the Tracks, or None for channels
    #: that cannot share one call (they then run one by one)
    run: Callable[[Sequence[Any], np.ndarray, bool, int | None], list[Track] | None] | None = None


_BANKS: dict[type[Estimator[Any]], BankKernel] = {}

#: Registered estimators without a compiled bank, and why (``sinewatch bench kernels`` prints it).
NO_BANK: dict[str, str] = {}


def register_bank(
    cls: type[Estimator[Any]],
    kernel: Callable[..., tuple[Any, ...]],
    n_outputs: int,
    tracks: Callable[[Any, tuple[Any, ...], np.ndarray], Sequence[Track]] | None = None,
    run: Callable[[Sequence[Any], np.ndarray, bool, int | None], list[Track] | None] | None = None,
) -> None:
    """Make ``kernel`` the compiled bank of ``cls`` (exactly that class, not subclasses);
    ``tracks`` and ``run``: see :class:`BankKernel`."""
    _BANKS[cls] = BankKernel(kernel, n_outputs, tracks, run)
    NO_BANK.pop(cls.name, None)


def bank_of(cls: type[Estimator[Any]]) -> BankKernel | None:
    """The compiled bank of ``cls``, or None when its channels run one by one."""
    return _BANKS.get(cls)


def update_bank(
    estimators: Sequence[Estimator[Any]],
    samples: np.ndarray,
    *,
    last_only: bool = False,
    t0_ns: int | None = None,
    finite: bool = False,
) -> Sequence[Track]:
    """Advance ``estimators[c]`` by column ``c`` of ``samples`` (shape (N, C), one column per
    estimator, all of one class, parameters and sample rate) and return one Track each.

    A block that ``update`` would reject (wrong type or shape, no samples, a NaN or Inf in any
    column) raises the same typed error before any estimator changes: the caller takes the
    bad channels out (one NaN column is that channel's error) and calls again with the rest.
    ``finite``: the caller has found every value finite already (the pipeline's frame check),
    so the bank does not read the samples a second time for it."""
    if not isinstance(samples, np.ndarray):
        raise InputTypeError(f"samples: expected a numpy array, got {type(samples).__name__}")
    if samples.ndim != 2 or samples.shape[1] != len(estimators):
        raise InputError(f"samples: expected shape (N, {len(estimators)}), got {samples.shape}", kind="shape_mismatch")
    if not estimators:
        return []
    first = estimators[0]
    cls = type(first)
    bank = _BANKS.get(cls)
    if (
        bank is None
        or samples.shape[0] == 0
        or samples.dtype != np.float64
        or first.n_inputs != 1
        # an instance's own ``update`` (a caller routing it, e.g. replay's full track) must run
        or any("update" in vars(est) for est in estimators)
    ):
        return _one_by_one(estimators, samples, last_only, t0_ns)
    stack = first._stack
    if stack is None or not stack.holds(estimators):  # (a live stack's members were checked alike when stacked)
        stack = None
        _check_alike(estimators, cls)
    x = kernel_samples(samples)  # one numba type per bank kernel
    if not finite and not _all_finite(x.reshape(-1)):
        raise _non_finite_columns(x)
    if bank.run is not None:
        ran = bank.run(estimators, x, last_only, t0_ns)
        return _one_by_one(estimators, x, last_only, t0_ns) if ran is None else ran
    if stack is not None:  # the same bank as last frame: its states are stacked already
        stacked = stack.arrays
    else:  # (C, *shape) in one C call, then channel last (np.stack: ~3x the Python)
        keys = tuple(first._state)
        stacked = [_channel_last(np.array([e._state[k] for e in estimators])) for k in keys]
    result = bank.kernel(x, *stacked, *first._constants, last_only)
    outputs, new_state = result[: bank.n_outputs], list(result[bank.n_outputs :])
    tracks = _bank_tracks(bank, estimators, outputs, x, x.T)
    # the new states kept stacked (as the kernel returns them: (*shape, C), C-contiguous), only
    # now that nothing can fail: a bank that raised leaves every channel's state as it was
    if stack is not None:
        stack.arrays = new_state
    else:
        stack = StackedStates(tuple(estimators), keys, new_state)
        for c, est in enumerate(estimators):
            est._state = {}  # (the old dict let go; the stack holds the state from here)
            est._stack, est._stack_index = stack, c
    return tracks


def update_reporting_at(estimator: Estimator[Any], samples: np.ndarray, row: int, *, t0_ns: int | None = None) -> Track:
    """``estimator.update(samples)`` whose Track is the one row ``row`` (0-based; the block's
    last is ``len(samples) - 1``), as ``update(samples, last_only=False)`` gives it, without
    writing the others: two ``last_only`` calls split after ``row``. Every estimator's output
    does not depend on where its blocks are split (tests/test_estimator_conformance.py's block
    boundaries; tests/test_report_at_confirmed.py for this split), so the row and the state left
    are the one call's, bit for bit. The Track's ``residual_rms`` is that of the samples up to
    ``row``. A rejected block raises before the state changes; a fault in the second call
    leaves the first call's state (the pipeline rolls both back)."""
    n = samples.shape[0]
    if not 0 <= row < n:
        raise InputError(f"row: expected 0 <= row < {n}, got {row}", kind="shape_mismatch")
    if row == n - 1:
        return estimator.update(samples, last_only=True, t0_ns=t0_ns)
    x = estimator._as_block(samples)  # checked whole first: a bad sample after the row changes nothing
    saved = estimator._state_checkpoint()  # (kernels return new arrays: what it names stays intact)
    track = estimator.update(x[: row + 1], last_only=True, t0_ns=t0_ns)
    try:
        estimator.update(x[row + 1 :], last_only=True, t0_ns=_piece_t0(t0_ns, row + 1, estimator.sample_rate_hz))
    except Exception:
        estimator._state_rollback(saved)  # a fault in the second call: the state as before the first
        raise
    return track


def _bank_split_after(
    estimators: Sequence[Estimator[Any]], samples: np.ndarray, row: int, t0_ns: int | None, finite: bool
) -> Sequence[Track]:
    """One bank's block in two :func:`update_bank` calls split after ``row``: the first call's Tracks."""
    first = update_bank(estimators, samples[: row + 1], last_only=True, t0_ns=t0_ns, finite=finite)
    if row + 1 < samples.shape[0]:
        t0_rest = _piece_t0(t0_ns, row + 1, estimators[0].sample_rate_hz)
        update_bank(estimators, samples[row + 1 :], last_only=True, t0_ns=t0_rest, finite=finite)
    return first


def _non_finite_columns(x: np.ndarray) -> InputError:
    """The error for a frame with NaN/Inf samples, naming every column that holds one."""
    bad = [c for c in range(x.shape[1]) if not np.isfinite(x[:, c]).all()]
    return InputError(f"samples: expected finite values, got NaN/Inf in columns {bad}", kind="non_finite")


def _piece_t0(t0_ns: int | None, start: int, sample_rate_hz: float) -> int | None:
    """The time of a block's sample ``start``, as the next block's ``t0_ns`` is reckoned."""
    return None if t0_ns is None else t0_ns + round(start * 1e9 / sample_rate_hz)


def update_bank_reporting_at(
    estimators: Sequence[Estimator[Any]],
    samples: np.ndarray,
    rows: Sequence[int],
    *,
    t0_ns: int | None = None,
    finite: bool = False,
) -> Sequence[Track]:
    """:func:`update_bank` whose ``tracks[c]`` is row ``rows[c]`` of channel ``c``'s track
    (:func:`update_reporting_at` for a bank): the channels that report at one row advance as one
    bank split after it, two bank calls a distinct row (usually one row for all: two calls). Each
    channel's row, residual RMS (of its samples up to its row) and state are its single path's,
    bit for bit, as :func:`update_bank`'s are."""
    n = samples.shape[0]
    if len(rows) != len(estimators) or any(not 0 <= r < n for r in rows):
        raise InputError(f"rows: expected {len(estimators)} rows in [0, {n}), got {list(rows)}", kind="shape_mismatch")
    if not estimators:
        return []
    if not finite and isinstance(samples, np.ndarray) and samples.dtype.kind == "f" and not np.isfinite(samples).all():
        # the whole block checked before the first call: a bad sample after a row changes nothing
        raise _non_finite_columns(samples)
    # where every state is now: a call that raises after another has advanced a stack puts it
    # back, so that this function, as update_bank, leaves every state as it was when it raises
    saved = [est._state_checkpoint() for est in estimators]
    stacks = {id(e._stack): (e._stack, e._stack.arrays, e._stack.live) for e in estimators if e._stack is not None}
    try:
        if rows.count(rows[0]) == len(rows):  # the usual case: the first call's Tracks as they are
            return _bank_split_after(estimators, samples, rows[0], t0_ns, finite)
        tracks: list[Track | None] = [None] * len(estimators)
        for row in sorted(set(rows)):
            lanes = [c for c, r in enumerate(rows) if r == row]
            got = _bank_split_after([estimators[c] for c in lanes], samples[:, lanes], row, t0_ns, finite)
            for c, track in zip(lanes, got, strict=True):
                tracks[c] = track
        return tracks  # type: ignore[return-value]  # (every channel is in its row's group)
    except Exception:
        for stack, arrays, live in stacks.values():
            stack.arrays, stack.live = arrays, live
        for est, checkpoint in zip(estimators, saved, strict=True):
            est._state_rollback(checkpoint)
        raise


def _bank_tracks(
    bank: BankKernel,
    estimators: Sequence[Estimator[Any]],
    outputs: tuple[Any, ...],
    x: np.ndarray,
    channel_rows: np.ndarray,
) -> Sequence[Track]:
    """The channels' Tracks from a bank kernel's outputs: the bank's own ``tracks`` (sealed
    when they are a :class:`ColumnTracks`), else each channel's ``_track`` on its slice of the
    outputs and its samples (``channel_rows[c]``)."""
    if bank.tracks is not None:
        tracks = bank.tracks(estimators[0], outputs, x)
        if isinstance(tracks, ColumnTracks):
            tracks.seal()
        return tracks
    return [est._track(tuple(o[c] for o in outputs), channel_rows[c]) for c, est in enumerate(estimators)]


@kernel(inline="always")
def bank_outputs(n: int, nc: int, m: int, last_only: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A compiled bank's outputs for ``nc`` channels of ``n`` samples: ``out`` (nc, rows, 5),
    a second per-row array (nc, rows, m) (extras, or standard deviations) and the sums of
    squared prediction errors (nc,), zeroed; ``rows`` is 1 when only the last is wanted."""
    rows = 1 if last_only else n
    return np.empty((nc, rows, 5)), np.empty((nc, rows, m)), np.zeros(nc)


def _channel_last(a: np.ndarray) -> np.ndarray:
    """``a`` (C, *shape) as a C-contiguous (*shape, C): the lane-major kernels' stacked state."""
    return np.ascontiguousarray(a.transpose(*range(1, a.ndim), 0))


def column_tracks(
    out: np.ndarray,
    sse: np.ndarray,
    n_samples: int,
    extras: dict[str, np.ndarray] | None = None,
    rocof: np.ndarray | None = None,
    std: np.ndarray | None = None,
) -> ColumnTracks:
    """The Tracks of a bank's channels, each exactly what
    :func:`~sinewatch.estimators.base.track_from_columns` makes of that channel's outputs, built
    with one numpy call a field for the whole bank instead of one a field and channel, and only
    when first asked for (:class:`ColumnTracks`). ``out`` (C, rows, 5) and ``sse`` (C,) as a bank
    kernel returns them; ``extras``: name -> (C, rows) or (C, rows, m); ``rocof``: (C, rows, 1);
    ``std``: (C, rows, 4), the standard deviations of frequency, amplitude, phase and offset.
    Element-wise throughout (the residual's ``sse / n`` and square root are correctly rounded
    in numpy as in ``math``), so each channel's bits do not depend on the channels beside it."""
    return ColumnTracks(out, sse, n_samples, extras, rocof, std)


class ColumnTracks(Sequence[Track]):
    """A bank's Tracks (:func:`column_tracks`), made all at once when one is first asked for.

    A frame's usual Estimates need none of them: they are written from :attr:`last_row`
    (every channel's last row of every output in one array) and :meth:`converged_last`, so the
    daemon's frame path does not build eight Track and TrackStd objects and their ~70 views a
    frame (~30 us a frame of 8, ``sinewatch bench pipeline --frame-channels 8``). ``sealed``:
    the bank's own ``tracks`` function returned them untouched (:func:`update_bank` seals
    them), so :attr:`last_row` says what every Track would (a bank that changes a Track after
    making it, e.g. ipdft's residual RMS, has made them all by then and is not sealed)."""

    __slots__ = ("_args", "_tracks", "last_row", "layout", "sealed")

    def __init__(
        self,
        out: np.ndarray,
        sse: np.ndarray,
        n_samples: int,
        extras: dict[str, np.ndarray] | None,
        rocof: np.ndarray | None,
        std: np.ndarray | None,
    ) -> None:
        self._args = (out, sse, n_samples, extras, rocof, std)
        self._tracks: list[Track] | None = None
        #: (components, rocof present, std present): what an Estimate's template depends on
        self.layout = (1, rocof is not None, std is not None)
        rms = np.sqrt(sse / n_samples) if n_samples else None
        self.last_row = None if extras or rms is None or not out.shape[1] else _bank_last_row(out, rms, rocof, std)
        self.sealed = False

    def seal(self) -> None:
        self.sealed = self._tracks is None

    def converged_last(self) -> list[bool]:
        """Each channel's ``converged`` at its last row (what ``bool(track.converged[-1])`` reads)."""
        return self.converged_last_array().tolist()  # type: ignore[no-any-return]

    def converged_last_array(self) -> np.ndarray:
        """:meth:`converged_last` as a boolean array, a channel each."""
        return self._args[0][:, -1, 4].astype(np.bool_)

    def __len__(self) -> int:
        return int(self._args[0].shape[0])

    @overload
    def __getitem__(self, index: int) -> Track: ...

    @overload
    def __getitem__(self, index: slice) -> list[Track]: ...

    def __getitem__(self, index: int | slice) -> Track | list[Track]:
        tracks = self._tracks
        if tracks is None:
            tracks = self._tracks = self._make()
        return tracks[index]

    def __iter__(self) -> Iterator[Track]:
        return iter(self[:])

    def _make(self) -> list[Track]:
        out, sse, n_samples, extras, rocof, std = self._args
        nc = out.shape[0]
        freq, amp, phase = list(out[:, :, 0:1]), list(out[:, :, 1:2]), list(out[:, :, 2:3])
        offset, conv = list(out[:, :, 3]), list(out[:, :, 4].astype(np.bool_))
        rms = np.sqrt(sse / n_samples).tolist() if n_samples else [math.nan] * nc
        names = list(extras) if extras else []
        cols = [list(v) for v in extras.values()] if extras else []
        roc: list[np.ndarray | None] = list(rocof) if rocof is not None else [None] * nc
        pairs = list(zip(names, cols, strict=True))
        tracks = [
            Track(freq[c], amp[c], phase[c], offset[c], conv[c], rms[c], {k: col[c] for k, col in pairs}, roc[c])
            for c in range(nc)
        ]
        if std is not None:
            sf, sa, sp, so = list(std[:, :, 0:1]), list(std[:, :, 1:2]), list(std[:, :, 2:3]), list(std[:, :, 3])
            for c, track in enumerate(tracks):
                track.std = TrackStd(sf[c], sa[c], sp[c], so[c])
        if self.last_row is not None:
            for c, track in enumerate(tracks):
                track.bank_row = (self.last_row, c)
        return tracks


def _bank_last_row(
    out: np.ndarray, rms: np.ndarray, rocof: np.ndarray | None, std: np.ndarray | None
) -> BankLastRow | None:
    """The bank's last row of every output in one array (:class:`BankLastRow`: a frame's
    Estimates are written from it in one pass); only when every part is float64, what an
    Estimate's usual case writes."""
    parts = [out[:, -1, :4]]
    if rocof is not None:
        parts.append(rocof[:, -1, :])
    if std is not None:
        parts.append(std[:, -1, :])
    parts.append(rms[:, None])
    if any(p.dtype != np.float64 for p in parts):
        return None
    return BankLastRow(np.concatenate(parts, axis=1))


def _check_alike(estimators: Sequence[Estimator[Any]], cls: type[Estimator[Any]]) -> None:
    first = estimators[0]
    for c, est in enumerate(estimators):
        if type(est) is not cls:
            raise InputTypeError(
                f"estimators[{c}]: expected {cls.__name__} like estimators[0], got {type(est).__name__}"
            )
        if est.sample_rate_hz != first.sample_rate_hz or (
            # the fields' dict first: one C-level comparison (~0.3 us) against the model's own
            # __eq__ (~5 us a channel, measured); a difference is then confirmed by __eq__
            est.params is not first.params
            and est.params.__dict__ != first.params.__dict__
            and est.params != first.params
        ):
            raise ParameterError(
                f"estimators[{c}]: expected the sample rate and parameters of estimators[0] "
                f"({first.sample_rate_hz} Hz, {first.params!r}), got {est.sample_rate_hz} Hz, {est.params!r}"
            )


def _one_by_one(
    estimators: Sequence[Estimator[Any]], samples: np.ndarray, last_only: bool, t0_ns: int | None
) -> list[Track]:
    """Each channel's own kernel in turn, every column checked first so that a rejected
    column leaves every estimator as it was."""
    if samples.dtype == np.float64 and samples.shape[0] and estimators[0].n_inputs == 1:
        # the common case in one pass: one transposing copy makes every column contiguous (what
        # ``update`` takes as is), one finiteness check covers them all
        cols = np.ascontiguousarray(samples.T)
        if _all_finite(cols.reshape(-1)):
            return [est.update(cols[c], last_only=last_only, t0_ns=t0_ns) for c, est in enumerate(estimators)]
    blocks = [est._as_block(samples[:, c]) for c, est in enumerate(estimators)]
    return [est.update(b, last_only=last_only, t0_ns=t0_ns) for est, b in zip(estimators, blocks, strict=True)]
