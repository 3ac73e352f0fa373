"""From analyser windows to the wire messages of :mod:`sinewatch.schemas.power_quality`
and to the 10/12-cycle values the aggregator takes."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sinewatch.power_quality.aggregation import WindowValues
from sinewatch.power_quality.harmonics import HarmonicWindow
from sinewatch.power_quality.sequence import SequenceComponents, symmetrical_components
from sinewatch.schemas.power_quality import (
    HarmonicsReport,
    SequencePhasor,
    ThreePhaseReport,
    finite_or_none,
)


def _list(a: np.ndarray) -> list[float | None]:
    return [finite_or_none(v) for v in np.asarray(a, dtype=np.float64).tolist()]


def harmonics_report(window: HarmonicWindow, channel: str, column: int, nominal_frequency_hz: float) -> HarmonicsReport:
    """The HarmonicsReport of column ``column`` of an analyser window."""
    i = column
    return HarmonicsReport(
        channel=channel,
        timestamp_ns=window.end_ns,
        window_start_ns=window.start_ns,
        n_cycles=window.n_cycles,
        nominal_frequency_hz=nominal_frequency_hz,
        frequency_hz=finite_or_none(window.frequency_hz),
        converged=window.converged,
        resync=window.resync,
        gap=window.gap,
        rms=finite_or_none(window.rms[i]),
        harmonic_rms=_list(window.harmonic_rms[i]),
        harmonic_phase_rad=_list(window.harmonic_phase_rad[i]),
        harmonic_group_rms=_list(window.harmonic_group_rms[i]),
        harmonic_subgroup_rms=_list(window.harmonic_subgroup_rms[i]),
        interharmonic_group_rms=_list(window.interharmonic_group_rms[i]),
        interharmonic_centred_subgroup_rms=_list(window.interharmonic_centred_subgroup_rms[i]),
        thd=finite_or_none(window.thd[i]),
        thdg=finite_or_none(window.thdg[i]),
        thds=finite_or_none(window.thds[i]),
    )


def _phasor(z: complex) -> SequencePhasor:
    return SequencePhasor(magnitude_rms=finite_or_none(abs(z)), angle_rad=finite_or_none(float(np.angle(z))))


def three_phase_report(
    group: str,
    phases: Sequence[str],
    timestamp_ns: int,
    phasors_rms: Sequence[complex],
    frequency_hz: float,
    missing: Sequence[str] = (),
) -> ThreePhaseReport:
    """The ThreePhaseReport of three fundamental phasors (complex RMS, one instant); a
    missing phase is NaN (its entries and every sequence quantity are then null)."""
    va, vb, vc = (complex(z) for z in phasors_rms)
    sc = symmetrical_components(va, vb, vc)
    return ThreePhaseReport(
        group=group,
        timestamp_ns=int(timestamp_ns),
        phases=list(phases),
        frequency_hz=finite_or_none(frequency_hz),
        phase_rms=[finite_or_none(abs(z)) for z in (va, vb, vc)],
        phase_angle_rad=[finite_or_none(float(np.angle(z))) for z in (va, vb, vc)],
        positive=_phasor(complex(sc.positive)),
        negative=_phasor(complex(sc.negative)),
        zero=_phasor(complex(sc.zero)),
        u2=finite_or_none(float(sc.u2)),
        u0=finite_or_none(float(sc.u0)),
        missing=list(missing),
    )


def window_sequence(window: HarmonicWindow, columns: Sequence[int] = (0, 1, 2)) -> SequenceComponents:
    """Symmetrical components of three columns of one analyser window (a common grid)."""
    z = window.fundamental_phasor
    return symmetrical_components(z[columns[0]], z[columns[1]], z[columns[2]])


def channel_window_values(window: HarmonicWindow, column: int = 0) -> WindowValues:
    """The 10/12-cycle values of one channel for :class:`Aggregator`: magnitude (true RMS
    and fundamental), frequency, THD/THDG/THDS, and the harmonic and interharmonic
    subgroups per order."""
    i = column
    return WindowValues(
        start_ns=window.start_ns,
        end_ns=window.end_ns,
        n_cycles=window.n_cycles,
        values={
            "rms": float(window.rms[i]),
            "fundamental_rms": float(window.harmonic_rms[i, 1]),
            "frequency_hz": float(window.frequency_hz),
            "thd": float(window.thd[i]),
            "thdg": float(window.thdg[i]),
            "thds": float(window.thds[i]),
        },
        arrays={
            "harmonic_subgroup_rms": window.harmonic_subgroup_rms[i],
            "interharmonic_centred_subgroup_rms": window.interharmonic_centred_subgroup_rms[i],
        },
    )


def group_window_values(window: HarmonicWindow, columns: Sequence[int] = (0, 1, 2)) -> WindowValues:
    """The 10/12-cycle values of a three-phase group: u2, u0, the sequence magnitudes and
    the frequency."""
    sc = window_sequence(window, columns)
    return WindowValues(
        start_ns=window.start_ns,
        end_ns=window.end_ns,
        n_cycles=window.n_cycles,
        values={
            "u2": float(sc.u2),
            "u0": float(sc.u0),
            "positive_rms": float(abs(sc.positive)),
            "negative_rms": float(abs(sc.negative)),
            "zero_rms": float(abs(sc.zero)),
            "frequency_hz": float(window.frequency_hz),
        },
    )
