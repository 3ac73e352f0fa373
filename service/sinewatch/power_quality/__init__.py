"""Power quality: IEC 61000-4-7 harmonics, three-phase symmetrical components and
unbalance, IEC 61000-4-30 aggregation. Maths only (the estimators' layer): no Zenoh, no
MCAP, no asyncio.

* :class:`HarmonicAnalyser` (``harmonics``): 10/12-cycle windows synchronised to the
  measured fundamental, one :class:`HarmonicWindow` per window.
* :func:`symmetrical_components` (``sequence``): Fortescue, u2 and u0.
* :class:`Aggregator` (``aggregation``): 10-s frequency, 150/180-cycle, 10-min and 2-h
  aggregates.
* ``reports``: windows to wire messages (:mod:`sinewatch.schemas.power_quality`).
"""

import sinewatch.host_arithmetic  # noqa: F401  # first, before numpy loads (its docstring says why)

# isort: split

from sinewatch.power_quality.aggregation import Aggregator, WindowValues
from sinewatch.power_quality.harmonics import HarmonicAnalyser, HarmonicParams, HarmonicWindow
from sinewatch.power_quality.reports import (
    channel_window_values,
    group_window_values,
    harmonics_report,
    three_phase_report,
    window_sequence,
)
from sinewatch.power_quality.sequence import SequenceComponents, phases_from_sequence, symmetrical_components

__all__ = [
    "Aggregator",
    "HarmonicAnalyser",
    "HarmonicParams",
    "HarmonicWindow",
    "SequenceComponents",
    "WindowValues",
    "channel_window_values",
    "group_window_values",
    "harmonics_report",
    "phases_from_sequence",
    "symmetrical_components",
    "three_phase_report",
    "window_sequence",
]
