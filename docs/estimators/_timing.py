"""Timing shared by the figure scripts in this folder (imported as a sibling module)."""

from __future__ import annotations

import time

import numpy as np

from sinewatch.estimators import Estimator


def ns_per_sample(est: Estimator, block: np.ndarray, reps: int) -> tuple[float, float]:
    """Best of 5 runs of ``reps`` updates on ``block``: ns per sample with the full track
    and with ``last_only`` (one untimed update first, each way). The estimator's state
    advances: give it the signal that precedes ``block``."""
    res = []
    for last_only in (False, True):
        est.update(block, last_only=last_only)
        best = np.inf
        for _ in range(5):
            t0 = time.perf_counter()
            for _ in range(reps):
                est.update(block, last_only=last_only)
            best = min(best, (time.perf_counter() - t0) / reps / block.size * 1e9)
        res.append(best)
    return res[0], res[1]
