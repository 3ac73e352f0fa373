"""Estimator banks: the channels of a multi-channel frame that share one estimator rule,
advanced together.

:func:`update_bank` is the one entry point the pipeline uses for a frame. Its contract is
the single-channel path's, channel by channel: after ``update_bank(ests, x)`` every
``ests[c]`` holds exactly the state, and the returned ``tracks[c]`` exactly the bits, that
``ests[c].update(x[:, c])`` would have given, whatever the bank's size and the channel's
position in it. Recordings, replay, snapshots and failover therefore never depend on how
channels were grouped.

This generic implementation runs each channel's own kernel in turn; an estimator class may
provide a compiled bank (state laid out across channels) through ``_update_bank``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from sinewatch.estimators.base import Estimator, Track


def update_bank(
    estimators: Sequence[Estimator[Any]],
    samples: np.ndarray,
    *,
    last_only: bool = False,
    t0_ns: int | None = None,
) -> list[Track]:
    """Advance ``estimators[c]`` by column ``c`` of ``samples`` (shape (N, C), one column per
    estimator, all of one class, parameters and sample rate) and return one Track each."""
    if samples.ndim != 2 or samples.shape[1] != len(estimators):
        raise ValueError(f"samples: expected shape (N, {len(estimators)}), got {samples.shape}")
    return [est.update(samples[:, c], last_only=last_only, t0_ns=t0_ns) for c, est in enumerate(estimators)]
