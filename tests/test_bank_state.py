"""A bank's states kept stacked between frames, and its Tracks made only when read
(``sinewatch.estimators.bank``: ``StackedStates``, ``ColumnTracks``).

Between frames a bank's channels' states stay in the arrays its kernel returned, channel
last; a channel read or given a state on its own leaves the stack, and the next frame gathers
the bank afresh. Whatever happens between frames, each channel must hold exactly the state,
and give exactly the bits, of the same channel run alone by the single-channel path: checked
here over frames where nothing happens (the stack kept), a snapshot read (``get_state``, which
leaves the stack as it is), a channel updated alone, a reset, a channel leaving and coming
back, a state restored, and a frame the bank refuses.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_estimator_banks import assert_states_bitwise, assert_tracks_bitwise

from sinewatch.estimators import get
from sinewatch.estimators.bank import ColumnTracks, update_bank
from sinewatch.estimators.base import StackedStates
from sinewatch.estimators.presence import DEFAULT_HYSTERESIS, EDGE_RATIO, SignalPresence, read_presence_bank
from sinewatch.scenarios.demo import KALMAN_10K
from sinewatch.schemas.errors import InputError

FS = 10_000.0
N = 256
C = 6


def _signals(frames: int, seed: int) -> np.ndarray:
    """(frames * N, C): each channel its own frequency, phase and noise (seeded)."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames * N) / FS
    f = 49.5 + rng.uniform(0.0, 1.0, C)
    phase = rng.uniform(0.0, 2 * np.pi, C)
    x = np.sin(2 * np.pi * f[None, :] * t[:, None] + phase[None, :])
    return np.ascontiguousarray(x + 0.01 * rng.standard_normal(x.shape))


def _pair(name: str) -> tuple[list, list]:
    cls = get(name)
    params = KALMAN_10K if name == "ges-kalman" else {}
    return [cls(FS, params) for _ in range(C)], [cls(FS, params) for _ in range(C)]


@pytest.mark.parametrize("name", ["ges-kalman", "sogi-fll", "kkl"])
def test_a_bank_kept_stacked_between_frames_gives_each_channel_its_own_bits(name):
    banked, alone = _pair(name)
    x = _signals(12, seed=7)
    everyone = list(range(C))
    # frame -> (what happens before it, the bank's channels in it)
    plan = {
        0: ("", everyone),
        1: ("", everyone),  # the stack kept: no gather, no scatter
        2: ("peek", everyone),  # a snapshot read between frames: the stack stays live
        3: ("", everyone),
        4: ("alone 2", everyone),  # channel 2 updated on its own in between: it leaves the stack
        5: ("", everyone),
        6: ("reset 4", everyone),
        7: ("", [0, 1, 3, 4, 5]),  # channel 2 leaves the bank for a frame
        8: ("", everyone),  # and comes back
        9: ("restore 1", everyone),  # a state restored from a snapshot (set_state)
        10: ("refused", everyone),  # a frame with a NaN refused whole: nothing changes
        11: ("", everyone),
    }
    extra = _signals(1, seed=99)[:, 0]
    # the frames whose bank is the last frame's, nobody having read or replaced a state on
    # its own since (a snapshot's read and a refused frame leave the stack as it is)
    kept = {1, 2, 3, 5, 10, 11}
    for k, (event, cols) in plan.items():
        block = x[k * N : (k + 1) * N]
        if event == "peek":
            stack = banked[0]._stack
            assert isinstance(stack, StackedStates) and stack.live
            snaps = [e.get_state() for e in banked]
            assert snaps == [e.get_state() for e in alone]
            assert banked[0]._stack is stack and stack.live  # reading a snapshot left it as it was
        elif event.startswith("alone"):
            c = int(event.split()[1])
            assert_tracks_bitwise(banked[c].update(extra), alone[c].update(extra), f"{name} alone")
        elif event.startswith("reset"):
            c = int(event.split()[1])
            banked[c].reset()
            alone[c].reset()
        elif event.startswith("restore"):
            c = int(event.split()[1])
            snap = alone[c].get_state()
            banked[c].set_state(snap)
            alone[c].set_state(snap)
        elif event == "refused":
            bad = block.copy()
            bad[10, 3] = np.nan
            before = [e.get_state() for e in banked]
            with pytest.raises(InputError):
                update_bank(banked, bad, last_only=True)
            assert [e.get_state() for e in banked] == before
        before = banked[cols[0]]._stack
        got = update_bank([banked[c] for c in cols], np.ascontiguousarray(block[:, cols]), last_only=True)
        stack = banked[cols[0]]._stack
        assert stack is not None and stack.live and stack.holds([banked[c] for c in cols])
        assert (stack is before) == (k in kept), f"frame {k}: the stack kept or gathered afresh"
        for i, c in enumerate(cols):
            want = alone[c].update(np.ascontiguousarray(block[:, c]), last_only=True)
            assert_tracks_bitwise(got[i], want, f"{name} frame {k} channel {c}")
    for c in range(C):
        assert_states_bitwise(banked[c], alone[c], f"{name} channel {c} at the end")
        assert banked[c]._stack is None  # read on its own: out of the stack


def test_a_bank_s_tracks_are_made_only_when_read_and_their_last_row_is_every_track_s():
    banked, alone = _pair("ges-kalman")
    x = _signals(2, seed=3)
    update_bank(banked, x[:N], last_only=True)
    tracks = update_bank(banked, x[N:], last_only=True)
    assert isinstance(tracks, ColumnTracks) and tracks.sealed and tracks._tracks is None
    assert tracks.last_row is not None
    converged = tracks.converged_last()
    values = tracks.last_row.values.copy()
    assert tracks._tracks is None  # neither read a Track
    for c in range(C):
        alone[c].update(np.ascontiguousarray(x[:N, c]), last_only=True)
        want = alone[c].update(np.ascontiguousarray(x[N:, c]), last_only=True)
        assert_tracks_bitwise(tracks[c], want, f"channel {c}")
        assert converged[c] == bool(want.converged[-1])
        assert want.std is not None
        row = [
            want.frequency_hz.item(-1),
            want.amplitude.item(-1),
            want.phase_rad.item(-1),
            want.offset.item(-1),
            want.std.frequency_hz.item(-1),
            want.std.amplitude.item(-1),
            want.std.phase_rad.item(-1),
            want.std.offset.item(-1),
            want.residual_rms,
        ]
        assert values[c].tobytes() == np.array(row).tobytes()
        assert tracks[c].bank_row == (tracks.last_row, c)
    assert len(tracks) == C and len(list(tracks)) == C and tracks[1:3] == [tracks[1], tracks[2]]


def test_a_bank_of_detectors_reads_each_one_s_run_and_onset_latency_as_its_properties():
    """``read_presence_bank``'s readings after each frame are each detector's ``run_samples``
    and ``onset_latency_samples``, through the quadrature test's arming (latency 4 H, then
    Q + m - 1), a DC offset on one channel (the test off there) and an interruption; the
    bank's state arrays are passed on from frame to frame, and gathered afresh after one
    detector ran on its own: the runs are each detector's alone, bit for bit."""
    x = _signals(14, seed=11)
    x[:, 2] += 0.6  # a DC part above FAST_DC of the reference: (F) does not apply there
    x[6 * N + 40 : 7 * N + 10, 4] = 0.0  # an interruption
    detectors, alone = [_detector() for _ in range(C)], [_detector() for _ in range(C)]
    seen = set()
    for k in range(14):
        block = x[k * N : (k + 1) * N]
        if k == 8:  # detector 3 run on its own between frames: the bank is gathered afresh
            extra = np.ascontiguousarray(x[:N, 3])
            assert detectors[0].bank_rows is not None and detectors[0].bank_rows.holds(detectors)
            assert detectors[3].update(extra)[0].tobytes() == alone[3].update(extra)[0].tobytes()
            assert not detectors[0].bank_rows.holds(detectors)
        readings = read_presence_bank(detectors, block, list(range(C)))
        assert readings is not None
        for c in range(C):
            run, _ = alone[c].update(np.ascontiguousarray(block[:, c]))
            assert readings.runs[c].tobytes() == run.tobytes()
            assert readings.run_samples[c] == alone[c].run_samples == detectors[c].run_samples
            assert readings.onset_latency_samples[c] == alone[c].onset_latency_samples
            seen.add(readings.onset_latency_samples[c])
    assert len(seen) == 2  # both tests' latencies were read


def _detector() -> SignalPresence:
    """A detector as the pipeline makes one under today's validity rules."""
    return SignalPresence(FS, 50.0, hold=True, hysteresis=DEFAULT_HYSTERESIS, fast=True, edge=EDGE_RATIO)
