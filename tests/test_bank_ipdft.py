"""ipdft's bank (``ipdft_bank_kernel``, states stacked channel last between frames) against the
single-channel path, bit for bit, on what tests/test_estimator_banks.py does not reach: channels
still filling their first window beside settled ones (no one-step prediction yet: a NaN residual
RMS, which the bank hands over as a quotient of its own), frame after frame with the stack kept,
a channel read on its own between frames (the stack leaves it and the next frame gathers the
bank afresh), and the Tracks made only when one is read.
"""

from __future__ import annotations

import json

import numpy as np
from test_estimator_banks import assert_states_bitwise, assert_tracks_bitwise

from sinewatch.estimators import get
from sinewatch.estimators.bank import ColumnTracks, update_bank
from sinewatch.estimators.base import StackedStates

CLS = get("ipdft")
WINDOW = 80  # the example's window (4 cycles of 50 Hz at 1 kHz); a hop is 20 samples
# samples each channel has seen before the bank: none, less than a window, a window less one,
# a window and one hop and some
HISTORIES = (0, 30, WINDOW - 1, 0, 137, 2_000, 55, 1_003, 0)


def _pairs(size: int) -> tuple[np.ndarray, list, list]:
    x = np.stack([CLS.example_signal(6_000, seed=70 + c) for c in range(size)], axis=1)
    singles, banked = [CLS.example() for _ in range(size)], [CLS.example() for _ in range(size)]
    for c in range(size):
        for est in (singles[c], banked[c]):
            if HISTORIES[c]:
                est.update(np.ascontiguousarray(x[3_000 : 3_000 + HISTORIES[c], c]))
    return x[:3_000], singles, banked


def _step(singles: list, banked: list, x: np.ndarray, last_only: bool, where: str) -> None:
    expected = [e.update(np.ascontiguousarray(x[:, c]), last_only=last_only) for c, e in enumerate(singles)]
    got = update_bank(banked, x, last_only=last_only)
    for c in range(len(singles)):
        assert_tracks_bitwise(expected[c], got[c], f"{where}, channel {c}")
        assert_states_bitwise(singles[c], banked[c], f"{where}, channel {c}")


def test_channels_filling_their_first_window_beside_settled_ones_match_the_single_path() -> None:
    x, singles, banked = _pairs(len(HISTORIES))
    # 10 samples: channels 0 and 3 are still filling (no estimate, no prediction: NaN RMS)
    expected = [e.update(np.ascontiguousarray(x[:10, c]), last_only=True) for c, e in enumerate(singles)]
    got = update_bank(banked, x[:10], last_only=True)
    assert np.isnan(expected[0].residual_rms) and np.isfinite(expected[5].residual_rms)
    for c in range(len(HISTORIES)):
        assert_tracks_bitwise(expected[c], got[c], f"10 samples, channel {c}")
    pos = 10
    for n, last_only in ((1, False), (69, True), (333, False), (1024, True), (7, True)):
        _step(singles, banked, x[pos : pos + n], last_only, f"{n} samples from {pos}")
        pos += n


def test_states_stay_stacked_between_frames_until_a_channel_is_read_alone() -> None:
    x, singles, banked = _pairs(4)
    for a, b in ((0, 200), (200, 500)):  # (the banked states are not read: reading takes a channel out)
        expected = [e.update(np.ascontiguousarray(x[a:b, c]), last_only=True) for c, e in enumerate(singles)]
        got = update_bank(banked, x[a:b], last_only=True)
        for c in range(4):
            assert_tracks_bitwise(expected[c], got[c], f"frame {a}:{b}, channel {c}")
    stack = banked[0]._stack
    assert isinstance(stack, StackedStates) and stack.holds(banked), "expected the bank's states kept stacked"
    # a snapshot between frames reads the stack without taking the channel out
    snapshot = json.loads(json.dumps(banked[2].get_state()))
    assert stack.live
    # channel 2 run alone on a block (as the pipeline's checked path does) leaves the stack;
    # the next frame gathers the bank afresh
    for est in (singles[2], banked[2]):
        est.update(np.ascontiguousarray(x[500:560, 2]))
    assert not stack.live
    _step(singles, banked, x[560:900], False, "frame after a channel ran alone")
    # the snapshot, restored and fed what channel 2 was fed since, is where the bank's channel is
    restored = CLS.from_state(snapshot)
    restored.update(np.ascontiguousarray(x[500:560, 2]))
    restored.update(np.ascontiguousarray(x[560:900, 2]))
    assert_states_bitwise(restored, banked[2], "restored from the snapshot")


def test_a_frames_tracks_are_made_when_first_read_and_then_as_the_single_path_gives() -> None:
    x, singles, banked = _pairs(3)
    tracks = update_bank(banked, x[:400], last_only=True)
    assert isinstance(tracks, ColumnTracks) and tracks.sealed  # nothing changed a Track after the bank made them
    expected = [e.update(np.ascontiguousarray(x[:400, c]), last_only=True) for c, e in enumerate(singles)]
    update_bank(banked, x[400:900], last_only=True)  # the next frame before this one's Tracks are read
    for c in range(3):
        assert_tracks_bitwise(expected[c], tracks[c], f"channel {c}, read a frame late")
