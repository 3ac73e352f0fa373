"""Wire-format messages (format version 1), as pydantic v2 models.

These models are the contract: the JSON Schemas in ``schemas/sinewatch/schemas/json/`` are exported from
them (``sinewatch schemas export DIR``), MCAP recordings embed them, and the codec in
:mod:`sinewatch.schemas.codec` produces and checks exactly these shapes.

JSON has no NaN: an undefined estimate is ``null``.
"""

from __future__ import annotations

from enum import Enum
from typing import Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictFloat, model_validator

FORMAT_VERSION = 1  # SampleBlock, ErrorReport, Status
FRAME_FORMAT_VERSION = 2  # SampleFrame: 2 added time_quality (a frame without it is still written as 1)
ESTIMATE_FORMAT_VERSION = 5  # Estimate: 2 added rocof_hz_per_s and std, 3 timestamp and valid, 4 fencing,
# 5 time_quality (see Estimate)

CHANNEL_PATTERN = r"^[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*$"


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid")


class SampleDtype(str, Enum):
    float32 = "float32"
    float64 = "float64"


class TimeQuality(_Message):
    """How far the time stamps of an input can be trusted, as its source states it: what an
    IEC 61850-9-2 merging unit says in ``smpSynch`` (IEC 61869-9), or a DAQ of its GPS lock.

    On the binary encodings it is one byte (a SampleFrame's header from format version 2, a
    SampleBlock's ``flags``): 0 = not stated; otherwise bit 7 set, bits 1-0 the ``sync``
    code (0 none, 1 local, 2 global: the ``smpSynch`` values), bit 2 ``holdover``, bits 6-3
    zero."""

    sync: Literal["none", "local", "global"] = Field(
        description="none: the sample clock is not synchronised; local: to a local area clock (not UTC-traceable); "
        "global: to a global area clock (a UTC-traceable PTP/GPS grandmaster)"
    )
    holdover: bool = Field(
        False,
        description="The source lost the time reference it had during the stream and its clock runs free since "
        "(with sync global or local: holding over; with none: past holdover, no longer traceable)",
    )


class SampleBlock(_Message):
    """A block of consecutive samples of one channel.

    ``samples`` is a list of rows: a plain list of numbers for a single-column block, or
    a list of equal-length lists when known inputs travel with the signal (column 0 is
    the measured signal, the others the inputs, see ``columns``).
    """

    format_version: Literal[1] = 1
    channel: str = Field(pattern=CHANNEL_PATTERN, max_length=256, description="Channel name")
    seq: int = Field(ge=0, lt=2**64, description="Sequence number of the block on its channel")
    t0_ns: int = Field(ge=-(2**63), lt=2**63, description="Time of the first sample, ns since the epoch")
    # strict and finite, as the binary header's float64: a string, a boolean, Infinity or
    # 1e309 is refused here, not later as an estimator's error
    sample_rate_hz: float = Field(gt=0, strict=True, allow_inf_nan=False, description="Sample rate, Hz")
    dtype: SampleDtype = Field(SampleDtype.float64, description="Sample type on the binary encoding")
    columns: int = Field(1, ge=1, le=255, description="Values per sample: 1, or 1 + number of inputs")
    unit: str | None = Field(None, max_length=64, description="Physical unit of column 0, e.g. V")
    samples: list[StrictFloat] | list[list[StrictFloat]] = Field(
        description="Samples, oldest first"
    )  # numbers only (no strings or booleans); NaN is a number, refused later as non_finite like a binary one


class SampleFrame(_Message):
    """C channels sampled at the same n instants, in one message (a multi-channel frame:
    what a DAQ card, an IEC 61850-9-2 merging unit or a COMTRADE record holds).

    ``samples`` is sample-major: row i holds every channel's value at sample i, in the
    order of ``channels``. Each channel is still a channel of its own everywhere else (its
    estimator, estimates, errors, status): the frame's ``seq`` and ``t0_ns`` are each
    channel's, as if its column had been sent alone as a SampleBlock.
    """

    format_version: Literal[1, 2] = 1
    seq: int = Field(ge=0, lt=2**64, description="Sequence number of the frame (each channel's block sequence)")
    t0_ns: int = Field(ge=-(2**63), lt=2**63, description="Time of the first sample, ns since the epoch")
    # strict and finite, as SampleBlock's (a string, a boolean or Infinity is a decode error)
    sample_rate_hz: float = Field(
        gt=0, strict=True, allow_inf_nan=False, description="Sample rate of every channel, Hz"
    )
    dtype: SampleDtype = Field(SampleDtype.float64, description="Sample type on the binary encoding")
    channels: list[Annotated[str, Field(pattern=CHANNEL_PATTERN, max_length=256)]] = Field(
        min_length=1, max_length=65535, description="Channel names, one per column, distinct"
    )
    samples: list[list[StrictFloat]] = Field(description="Rows of one value per channel, oldest first")
    time_quality: TimeQuality | None = Field(
        None,
        description="The time quality of every sample of the frame, as its source states it; null or absent: not "
        "stated (format version 2; a version 1 frame has none)",
    )

    @model_validator(mode="after")
    def _distinct(self) -> SampleFrame:
        if len(set(self.channels)) != len(self.channels):
            raise ValueError("channels: expected distinct names, got a repeated one")
        if self.time_quality is not None and self.format_version < 2:
            raise ValueError("time_quality: expected format_version 2, got it in a version 1 frame")
        return self


class Time(_Message):
    """A time as Foxglove (and ROS) write it: whole seconds and nanoseconds since the epoch.

    Both fit a JavaScript number exactly, where ``timestamp_ns`` (beyond 2^53) does not:
    a JavaScript reader takes ``sec + nsec / 1e9``, or ``BigInt(sec) * 1000000000n + BigInt(nsec)``."""

    sec: int = Field(description="Whole seconds since the epoch (floor, so negative before 1970)")
    nsec: int = Field(ge=0, lt=1_000_000_000, description="Nanoseconds past ``sec``")

    @classmethod
    def of(cls, ns: int) -> Time:
        sec, nsec = divmod(ns, 1_000_000_000)
        return cls(sec=sec, nsec=nsec)


def fill_time(msg: Any, ns: int, field: str = "timestamp") -> None:
    """Set (or check) the ``{sec, nsec}`` twin of a nanosecond timestamp."""
    t = getattr(msg, field)
    if t is None:
        setattr(msg, field, Time.of(ns))
    elif t.sec * 1_000_000_000 + t.nsec != ns:
        raise ValueError(f"{field}: expected {{sec, nsec}} equal to {ns} ns, got {t.sec} s + {t.nsec} ns")


class Diagnostics(_Message):
    converged: bool = Field(
        description="The estimate is settled: the estimator's own convergence test passed (each estimator's "
        "criterion: docs/validity.md) and, from format version 3, the estimate is valid"
    )
    valid: bool = Field(
        True,
        description="The signal the estimate describes is present now and has been for the estimator's memory "
        "(its window, or its settling time): false while the input is absent or collapsing (its one-cycle AC RMS "
        "at or below 0.1 of the recent level: an interruption or a sag below 0.1 pu, IEEE 1159), for one memory "
        "after it, before the estimator has seen one memory of signal, or when the estimate is undefined. An "
        "estimate with valid false is not a measurement (format version 3; docs/validity.md)",
    )
    residual_rms: float | None = Field(description="RMS one-step prediction error over the block")
    gap: bool = Field(False, description="Samples were missing before this block (sequence gap)")
    gap_blocks: int = Field(0, ge=0, description="How many blocks were missing before this one")
    restart: bool = Field(
        False, description="The sender restarted its sequence numbers (seq went back, time went forward)"
    )
    reset: bool = Field(False, description="The estimator was reset before this block")
    extras: dict[str, float | list[float | None] | None] = Field(
        default_factory=dict, description="Estimator-specific diagnostics at the last sample"
    )


class Uncertainty(_Message):
    """One standard deviation of each reported parameter, per component; null where the
    estimator cannot say (no sound derivation, or not yet converged)."""

    frequency_hz: list[float | None]
    amplitude: list[float | None]
    phase_rad: list[float | None]
    offset: float | None


class Fencing(_Message):
    """Who published an estimate: the shard and the term of its owner's election (an etcd
    revision, increasing with every election). A reader that has seen a newer term of a
    shard drops what an older term publishes after it (a deposed owner that has not noticed
    yet)."""

    shard: str = Field(description="The shard's shard_id")
    term: int = Field(ge=1, description="The election's term: the etcd revision that made this daemon the owner")


class Estimate(_Message):
    """The estimate at the last sample of one input block.

    y = offset + sum_k amplitude[k] * sin(phase_rad[k]); phase at ``timestamp_ns``.

    Version 2 added ``rocof_hz_per_s`` and ``std``; version 3 ``timestamp`` (``{sec, nsec}``,
    exact in JavaScript) and ``diagnostics.valid``; version 4 ``fencing`` (null from a daemon
    that owns its channels without an election); version 5 ``time_quality`` (the input's, null
    when it stated none). An earlier version is this message without
    the later fields and with its own ``format_version``, byte for byte what earlier builds
    wrote: replay renders estimates in the version of the recording it checks.
    """

    format_version: Literal[1, 2, 3, 4, 5] = 5
    channel: str
    seq: int = Field(description="Sequence number of the input block")
    timestamp_ns: int = Field(
        description="Time the estimate refers to, ns since the epoch: the block's last sample, or the report "
        "time k/Fs for an estimator that reports on a time grid (pmu)"
    )
    timestamp: Time | None = Field(
        None, description="timestamp_ns as {sec, nsec} (filled from timestamp_ns when not given; format version 3)"
    )
    n_samples: int = Field(description="Samples in the input block")
    estimator: str
    frequency_hz: list[float | None]
    amplitude: list[float | None]
    phase_rad: list[float | None]
    offset: float | None
    rocof_hz_per_s: list[float | None] | None = Field(
        None, description="Rate of change of frequency per component, Hz/s; null when the estimator does not track it"
    )
    std: Uncertainty | None = Field(None, description="Standard deviations of the estimates; null when unknown")
    diagnostics: Diagnostics
    fencing: Fencing | None = Field(
        None, description="The shard and election term of the daemon that published it (format version 4)"
    )
    time_quality: TimeQuality | None = Field(
        None,
        description="The time quality of the input block (or frame) the estimate was made from, as its source "
        "stated it (a SampleFrame of format version 2, a binary SampleBlock's flags); null when it stated none "
        "(format version 5)",
    )

    V2_FIELDS: ClassVar[frozenset[str]] = frozenset({"rocof_hz_per_s", "std"})
    V3_FIELDS: ClassVar[frozenset[str]] = frozenset({"timestamp"})
    V4_FIELDS: ClassVar[frozenset[str]] = frozenset({"fencing"})
    V5_FIELDS: ClassVar[frozenset[str]] = frozenset({"time_quality"})
    V3_DIAGNOSTICS: ClassVar[frozenset[str]] = frozenset({"valid"})

    @model_validator(mode="after")
    def _timestamp(self) -> Estimate:
        fill_time(self, self.timestamp_ns)
        return self


class ErrorKind(str, Enum):
    decode_error = "decode_error"
    unsupported_version = "unsupported_version"
    non_finite = "non_finite"
    empty_block = "empty_block"
    oversized_block = "oversized_block"
    sample_rate_change = "sample_rate_change"
    shape_mismatch = "shape_mismatch"
    duplicate = "duplicate"
    out_of_order = "out_of_order"
    channel_key_mismatch = "channel_key_mismatch"
    no_rule = "no_rule"
    estimator_error = "estimator_error"
    queue_overflow = "queue_overflow"
    unrecovered = "unrecovered"  # lost in transport, past the publisher's cache (Zenoh's recovery)
    channel_limit = "channel_limit"
    estimator_fault = "estimator_fault"
    sink_error = "sink_error"
    internal_error = "internal_error"


class ErrorReport(_Message):
    """Why an input was rejected (or data was lost). One per rejected input."""

    format_version: Literal[1] = 1
    key: str = Field(description="Zenoh key the input arrived on")
    channel: str | None = Field(description="Channel, when the payload could be decoded that far")
    seq: int | None = None
    kind: ErrorKind
    message: str
    count: int = Field(ge=1, description="Errors of this kind on this key so far, this one included")


class ChannelStatus(_Message):
    channel: str
    key: str
    estimator: str
    sample_rate_hz: float
    blocks: int
    samples: int
    errors: int
    gaps: int
    last_seq: int | None
    last_latency_us: float | None = Field(description="Receive-to-publish latency of the last block")
    converged: bool


class SinkStatus(_Message):
    """Health of one output (Zenoh publisher, MCAP recorder). A failed sink never stops
    estimation: its outputs are skipped (and counted) until it recovers."""

    name: str
    ok: bool = Field(description="The sink's last call succeeded")
    failures: int = Field(description="Calls that raised, since start")
    skipped: int = Field(description="Outputs not delivered to this sink while it was failed")
    recoveries: int = Field(description="Times the sink was reopened after a failure")
    last_error: str | None = Field(description="The last failure, as 'ExceptionType: message'")


class C37118ClientStatus(_Message):
    """One connected phasor data concentrator (or UDP destination) of the C37.118.2 server."""

    peer: str = Field(description="HOST:PORT of the client")
    transport: Literal["tcp", "udp"]
    streaming: list[int] = Field(description="ID codes whose data frames it has turned on")
    frames_sent: int = Field(description="Frames handed to its connection")
    frames_dropped: int = Field(description="Data frames dropped because its queue was full (a slow reader)")
    frames_queued: int = Field(0, description="Data frames waiting in its queue now")


class C37118Status(_Message):
    """The C37.118.2 server (present only when ``[c37118]`` is enabled)."""

    port: int
    clients: list[C37118ClientStatus]
    frames_built: int = Field(description="Data frames built (one per station per reporting time)")
    frames_incomplete: int = Field(description="Data frames sent with a missing channel (STAT data error 10)")
    frames_dropped: int = Field(description="Data frames dropped for slow clients, since start (all clients)")
    frames_late: int = Field(description="Estimates that came after their frame was sent (not sent)")
    commands: int = Field(description="Command frames accepted")
    commands_rejected: int = Field(description="Command frames rejected (bad CRC, unknown ID code, truncated, ...)")
    rejected_by_reason: dict[str, int] = Field(default_factory=dict)


class Status(_Message):
    """Periodic daemon status."""

    format_version: Literal[1] = 1
    daemon_id: str
    uptime_s: float
    blocks_received: int
    blocks_processed: int
    dropped: int = Field(description="Inputs dropped by the intake queue (drop policy only)")
    backpressure_waits: int = Field(description="Times the intake waited for queue space")
    unrecovered: int = Field(
        0, description="Blocks Zenoh reported missed and not recoverable from the publishers' caches"
    )
    errors: int
    errors_by_kind: dict[str, int] = Field(
        default_factory=dict, description="Rejected inputs and faults per ErrorReport kind"
    )
    queue_depth: int
    recording: str | None = Field(description="Current MCAP file, if recording")
    sinks: list[SinkStatus] = Field(default_factory=list, description="Health of each output")
    channels: list[ChannelStatus]
    c37118: C37118Status | None = Field(
        None, description="The C37.118.2 server's counters (absent when it is off; added within format version 1)"
    )


MESSAGE_MODELS: dict[str, type[BaseModel]] = {
    "SampleBlock": SampleBlock,
    "SampleFrame": SampleFrame,
    "Estimate": Estimate,
    "ErrorReport": ErrorReport,
    "Status": Status,
}

MESSAGE_VERSIONS: dict[str, int] = {
    "SampleBlock": FORMAT_VERSION,
    "SampleFrame": FRAME_FORMAT_VERSION,
    "Estimate": ESTIMATE_FORMAT_VERSION,
    "ErrorReport": FORMAT_VERSION,
    "Status": FORMAT_VERSION,
}
