"""A bank's channel against the same channel alone, with the channel at every position of the bank.

The probe (one channel's signal and estimator) runs alone through ``update``, block by block; then
for each bank size and each position p, the same signal runs as column p of a frame whose other
columns are fillers (other signals, estimators with other histories), through ``update_bank``.
Every block's Track and the state after it must be the probe's alone, bit for bit, and so must
each filler's (run alone beside it), whatever the size and the position.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from test_estimator_banks import assert_states_bitwise, assert_tracks_bitwise

from sinewatch.estimators.bank import update_bank
from sinewatch.estimators.base import Estimator, Track


def _no_poke(est: Estimator, i: int) -> None:
    """Leave the state as it is."""


def run_alone(
    est: Estimator, x: np.ndarray, block: int, poke: Callable[[Estimator, int], None] = _no_poke
) -> list[tuple[Track, dict[str, bytes]]]:
    """``est`` over ``x`` in blocks of ``block`` samples (``poke(est, i)`` before the block at
    ``i``): each block's Track and the bytes of the state after it."""
    runs = []
    for i in range(0, x.size, block):
        poke(est, i)
        track = est.update(np.ascontiguousarray(x[i : i + block]))
        runs.append((track, {k: np.ascontiguousarray(v).tobytes() for k, v in est._state.items()}))
    return runs


def assert_every_position(
    make: Callable[[], Estimator],
    probe: np.ndarray,
    fillers: Sequence[np.ndarray],
    sizes: Sequence[int],
    block: int,
    poke: Callable[[Estimator, int], None] = _no_poke,
) -> list[tuple[Track, dict[str, bytes]]]:
    """The probe signal at every position of banks of ``sizes`` channels, the fillers around it
    (filler channel c fed c % 3 blocks of its signal first, so that the lanes' states differ),
    each channel's bits checked against it alone; ``poke`` (a change of the probe's state before
    a block, in both runs) lets a test reach a rare branch. Returns the probe's run alone."""
    want = run_alone(make(), probe, block, poke)
    for size in sizes:
        for p in range(size):
            cols = [fillers[(p + f) % len(fillers)] for f in range(size - 1)]
            cols.insert(p, probe)
            x = np.ascontiguousarray(np.stack(cols, axis=1))
            banked, singles = [make() for _ in range(size)], [make() for _ in range(size)]
            for c in range(size):
                for est in (banked[c], singles[c]):
                    for b in range(c % 3 if c != p else 0):
                        est.update(np.ascontiguousarray(x[b * block : (b + 1) * block, c]))
            for i in range(0, x.shape[0], block):
                poke(banked[p], i)
                got = update_bank(banked, np.ascontiguousarray(x[i : i + block]))
                for c in range(size):
                    where = f"size {size}, probe at {p}, channel {c}, block at {i}"
                    if c == p:
                        track, state = want[i // block]
                        assert_tracks_bitwise(track, got[c], where)
                        assert {k: np.ascontiguousarray(v).tobytes() for k, v in banked[c]._state.items()} == state, (
                            where
                        )
                    else:
                        assert_tracks_bitwise(
                            singles[c].update(np.ascontiguousarray(x[i : i + block, c])), got[c], where
                        )
                        assert_states_bitwise(singles[c], banked[c], where)
    return want
