"""Power-quality messages (format version 2): IEC 61000-4-7 harmonics per channel, the
three-phase group (symmetrical components, unbalance) and the IEC 61000-4-30 aggregates.

Like :mod:`sinewatch.schemas.messages`: pydantic v2 models, unknown keys rejected, JSON
without NaN (an undefined value is ``null``), no wall-clock data (a replay reproduces the
bytes). All magnitudes are RMS values in the unit of the channel; ratios (THD, u2, u0)
are plain ratios (x 100 for percent); phases are radians in (-pi, pi], sine convention
(``x(t) = sqrt(2) rms sin(phase + 2 pi h f (t - timestamp))``), at ``timestamp_ns``.

Array fields of a harmonics report are indexed by harmonic order: index h is order h,
0..max_harmonic, index 0 the DC value; the interharmonic arrays' index n is the
interharmonic group (or centred subgroup) between orders n and n+1.
"""

from __future__ import annotations

from typing import Any, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from sinewatch.schemas.codec import dumps, finite_or_none
from sinewatch.schemas.messages import Time, fill_time

__all__ = [
    "PQ_FORMAT_VERSION",
    "PQ_MESSAGE_MODELS",
    "PQ_ROLES",
    "HarmonicsReport",
    "PqAggregate",
    "SequencePhasor",
    "ThreePhaseReport",
    "encode_pq",
    "finite_or_none",
    "json_encoding",
]

PQ_FORMAT_VERSION = 2  # 2 added ``timestamp`` ({sec, nsec}, exact in JavaScript) beside timestamp_ns

OptFloat = float | None


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid")

    @model_validator(mode="after")
    def _timestamp(self) -> Self:
        if "timestamp" in type(self).model_fields:
            fill_time(self, getattr(self, "timestamp_ns"))  # noqa: B009 (the subclasses that have a timestamp)
        return self


class HarmonicsReport(_Message):
    """One IEC 61000-4-7 window of one channel: N = 10 (50 Hz) or 12 (60 Hz) cycles of the
    measured fundamental, reported at the window end."""

    format_version: Literal[1, 2] = 2
    channel: str
    timestamp_ns: int = Field(description="End of the window, ns since the epoch")
    timestamp: Time | None = Field(None, description="timestamp_ns as {sec, nsec} (format version 2)")
    window_start_ns: int = Field(description="Start of the window, ns since the epoch")
    n_cycles: int = Field(description="Cycles of the fundamental the window spans: 10 or 12")
    nominal_frequency_hz: float
    frequency_hz: OptFloat = Field(description="The measured fundamental the window is synchronised to")
    converged: bool = Field(description="The window synchronisation met its tolerance")
    resync: bool = Field(False, description="The window starts on a 10-min tick (IEC 61000-4-30 resynchronisation)")
    gap: bool = Field(False, description="Input was discontinuous before this window; the analysis restarted")
    rms: OptFloat = Field(description="True RMS over the window")
    harmonic_rms: list[OptFloat] = Field(description="Harmonic components C_h, h = 0..H (0 = DC)")
    harmonic_phase_rad: list[OptFloat] = Field(description="Phase of each harmonic component at the window end")
    harmonic_group_rms: list[OptFloat] = Field(description="Harmonic groups G_g,h (IEC 61000-4-7 3.2)")
    harmonic_subgroup_rms: list[OptFloat] = Field(description="Harmonic subgroups G_sg,h (IEC 61000-4-7 3.2)")
    interharmonic_group_rms: list[OptFloat] = Field(description="Interharmonic groups C_ig,n, n = 0..H")
    interharmonic_centred_subgroup_rms: list[OptFloat] = Field(
        description="Interharmonic centred subgroups C_isg,n, n = 0..H (IEC 61000-4-7 3.3)"
    )
    thd: OptFloat = Field(description="Total harmonic distortion, components 2..40 over C_1 (IEC 61000-4-7)")
    thdg: OptFloat = Field(description="Group total harmonic distortion, groups 2..40 over G_g,1")
    thds: OptFloat = Field(description="Subgroup total harmonic distortion, subgroups 2..40 over G_sg,1")


class SequencePhasor(_Message):
    magnitude_rms: OptFloat
    angle_rad: OptFloat


class ThreePhaseReport(_Message):
    """A three-phase group at one instant: the phases' fundamental phasors and their
    symmetrical components (Fortescue), u2 = |V2|/|V1| and u0 = |V0|/|V1|."""

    format_version: Literal[1, 2] = 2
    group: str
    timestamp_ns: int = Field(description="The instant the phasors refer to, ns since the epoch")
    timestamp: Time | None = Field(None, description="timestamp_ns as {sec, nsec} (format version 2)")
    phases: list[str] = Field(description="Channel of phase a, b, c", min_length=3, max_length=3)
    frequency_hz: OptFloat
    phase_rms: list[OptFloat] = Field(description="Fundamental RMS of phase a, b, c", min_length=3, max_length=3)
    phase_angle_rad: list[OptFloat] = Field(description="Fundamental phase of a, b, c", min_length=3, max_length=3)
    positive: SequencePhasor
    negative: SequencePhasor
    zero: SequencePhasor
    u2: OptFloat = Field(description="Negative-sequence unbalance |V2|/|V1|")
    u0: OptFloat = Field(description="Zero-sequence unbalance |V0|/|V1|")
    missing: list[str] = Field(default_factory=list, description="Phases that did not arrive in time")


class PqAggregate(_Message):
    """An IEC 61000-4-30 class A aggregate of the 10/12-cycle values of one source (a channel
    or a group): RMS of the values for magnitudes, THD and unbalance; total cycles over total
    duration for frequency."""

    format_version: Literal[1, 2] = 2
    source: str = Field(description="Channel or group the values come from")
    interval: Literal["10-s", "150/180-cycle", "10-min", "2-h"] = Field(
        description="10-s: the IEC 61000-4-30 frequency value (values: frequency_hz only); 150/180-cycle, 10-min, "
        "2-h: aggregates of the 10/12-cycle values (2-h: of the twelve 10-min values)"
    )
    timestamp_ns: int = Field(description="End of the interval (the clock tick for 10-s, 10-min and 2-h values)")
    timestamp: Time | None = Field(None, description="timestamp_ns as {sec, nsec} (format version 2)")
    start_ns: int = Field(description="Start of the interval")
    n_windows: int = Field(ge=0, description="10/12-cycle values aggregated")
    complete: bool = Field(
        description="150/180-cycle: 15 contiguous values; 10-min: no value missing; 2-h: twelve complete 10-min "
        "values; 10-s: whole cycles from tick to tick, none missing"
    )
    values: dict[str, OptFloat] = Field(default_factory=dict, description="Aggregated scalar quantities")
    arrays: dict[str, list[OptFloat]] = Field(default_factory=dict, description="Aggregated per-order quantities")


PQ_MESSAGE_MODELS: dict[str, type[BaseModel]] = {
    "HarmonicsReport": HarmonicsReport,
    "ThreePhaseReport": ThreePhaseReport,
    "PqAggregate": PqAggregate,
}

PQ_MESSAGE_VERSIONS: dict[str, int] = dict.fromkeys(PQ_MESSAGE_MODELS, PQ_FORMAT_VERSION)

# The role of each message kind in a recording (MCAP channel metadata ``role``): replay
# compares every output role bit for bit.
PQ_ROLES: dict[str, str] = {
    "HarmonicsReport": "harmonics",
    "ThreePhaseReport": "three_phase",
    "PqAggregate": "pq_aggregate",
}


def json_encoding(name: str) -> str:
    """The Zenoh encoding of a power-quality message, as for the other JSON messages."""
    return f"application/json;sinewatch/{name}@{PQ_MESSAGE_VERSIONS[name]}"


def encode_pq(msg: BaseModel, version: int = PQ_FORMAT_VERSION) -> bytes:
    """Compact, deterministic JSON bytes of a power-quality message (as the codec writes
    the other JSON messages), in format ``version`` (1 for replaying recordings of earlier
    builds: without ``timestamp``)."""
    data: dict[str, Any] = msg.model_dump(mode="json", exclude={"timestamp"} if version < 2 else None)
    data["format_version"] = version
    return dumps(data)
