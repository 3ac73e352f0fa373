"""The configuration: one pydantic model tree, unknown keys rejected everywhere.

Defaults work out of the box and are safe: a Zenoh peer listening on loopback only,
multicast scouting off, every channel estimated by the default rule (``pmu``, C37.118.1 M class, its nominal frequency found from the signal), recording on.
Loaded from a TOML or JSON file plus ``SINEWATCH__SECTION__KEY`` environment variables by
:func:`load_config`; printed back by ``sinewatch config show``.

Precedence: defaults < file (TOML or JSON, by extension) < environment. Environment
variables are ``SINEWATCH__<SECTION>__<KEY>=value`` (double underscores separate levels,
names are case-insensitive, values are parsed as JSON when they parse, else taken as
strings), e.g. ``SINEWATCH__ZENOH__MODE=client`` or
``SINEWATCH__ZENOH__CONNECT='["tcp/10.0.0.1:7447"]'``. ``SINEWATCH_CONFIG`` names a file
when ``--config`` is not given. Unknown keys are rejected, from either source.
"""

from __future__ import annotations

import json
import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from sinewatch.schemas.errors import ConfigError

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7450"


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class ZenohSection(_Section):
    mode: Literal["peer", "client", "router"] = Field("peer", description="Zenoh session mode")
    listen: list[str] = Field(
        default_factory=lambda: [DEFAULT_ENDPOINT],
        description="Endpoints to listen on (loopback by default; [] for none)",
    )
    connect: list[str] = Field(default_factory=list, description="Endpoints to connect to (routers or peers)")
    multicast_scouting: bool = Field(False, description="Zenoh multicast scouting (off unless asked for)")
    shared_memory: bool | None = Field(None, description="Zenoh shared memory transport (None: Zenoh's default)")
    recovery: bool = Field(
        True,
        description="Subscribe with Zenoh's sample recovery: blocks missed (e.g. while a router restarts) are "
        "fetched again from the publishers' caches (BlockPublisher keeps its last 1024 per channel)",
    )
    raw: dict[str, Any] = Field(
        default_factory=dict,
        description="Passthrough of raw Zenoh config keys (JSON5 paths), e.g. {'transport/link/tx/lease': 5000}",
    )

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        for ep in v:
            if "/" not in ep:
                raise ValueError(f"endpoint: expected PROTO/ADDRESS such as {DEFAULT_ENDPOINT}, got {ep!r}")
        return v


class KeysSection(_Section):
    """The key layout. Inputs, estimates, errors and status live under their own prefixes."""

    input: str = Field("sinewatch/in/**", description="Key expression subscribed for SampleBlocks")
    estimates_prefix: str = Field("sinewatch/est", description="Estimates go to PREFIX/<channel>")
    errors_prefix: str = Field("sinewatch/err", description="ErrorReports go to PREFIX/<channel or _unknown>")
    status_key: str = Field("sinewatch/status", description="Status messages go to KEY/<daemon_id>")
    admin_prefix: str = Field(
        "sinewatch/admin",
        description="Cluster keys: PREFIX/<daemon_id>/channels (queryable: what a daemon owns), "
        "PREFIX/shard/<shard_id>/{active,standby}/<daemon_id> (liveliness), PREFIX/shard/<shard_id>/snapshot",
    )
    pq_prefix: str = Field(
        "sinewatch/pq",
        description="Power quality: HarmonicsReports go to PREFIX/harmonics/<channel>, PqAggregates to "
        "PREFIX/agg/<channel>, ThreePhaseReports to PREFIX/group/<group>",
    )


#: The default rule's estimator and, when a rule names neither an estimator nor parameters,
#: its parameters: the IEEE C37.118.1 M-class synchrophasor estimator (``pmu``) reporting at
#: the nominal frequency (50 or 60 reports a second), that frequency found from the signal
#: (its first 0.2 s), so 50 and 60 Hz systems are both measured with no setting. Each estimate
#: is at its report time, the instant it describes. Measured in docs/accuracy.md, "The default
#: rule" (``sinewatch bench compliance --estimator default-rule``).
DEFAULT_ESTIMATOR = "pmu"
DEFAULT_PARAMS: dict[str, Any] = {"nominal_frequency_hz": "auto"}


class EstimatorRule(_Section):
    """Channels whose input key matches ``match`` get ``estimator`` with ``params``.

    A rule that names neither ``estimator`` nor ``params`` is the default rule:
    ``pmu`` with :data:`DEFAULT_PARAMS` (C37.118.1 M class at the nominal frequency's reporting rate,
    that frequency found from the signal: right for 50 and 60 Hz mains with harmonics and noise at
    any sample rate from 1 to 50 kHz, whole hertz or not). A rule that names an estimator
    without ``params`` gets that estimator's own defaults (``sinewatch estimators``).

    ``params`` is checked against the estimator's own parameter model by
    :func:`sinewatch.estimators.check_rules`, which the daemon runs before it starts and
    ``sinewatch config check`` runs on demand: validating or printing a config here never
    imports an estimator (nor numba)."""

    match: str = Field("sinewatch/in/**", description="Key expression matched against the input key")
    estimator: str = Field(
        DEFAULT_ESTIMATOR, description="Registered estimator name (sinewatch estimators); default pmu"
    )
    params: dict[str, Any] = Field(
        default_factory=dict,
        description="Estimator parameters; when neither estimator nor params is given, the default "
        "rule's: pmu with nominal_frequency_hz = 'auto' (50 or 60 Hz from the signal)",
    )

    @model_validator(mode="before")
    @classmethod
    def _default_rule(cls, data: Any) -> Any:
        if isinstance(data, Mapping) and "estimator" not in data and "params" not in data:
            return {**data, "params": dict(DEFAULT_PARAMS)}
        return data


class HarmonicsRule(_Section):
    """Channels whose input key matches ``match`` also get an IEC 61000-4-7 harmonic analyser
    (one HarmonicsReport per 10/12-cycle window) and, with ``aggregate``, the IEC 61000-4-30
    150/180-cycle and 10-min aggregates of its window values. First matching rule wins."""

    match: str = Field(description="Key expression matched against the input key")
    nominal_frequency_hz: Literal[50, 60] = Field(50, description="50 Hz: 10-cycle windows; 60 Hz: 12-cycle windows")
    max_harmonic: int = Field(
        50, ge=2, le=50, description="Highest harmonic order reported (THD stops at min(40, this), IEC 61000-4-7)"
    )
    aggregate: bool = Field(True, description="Publish the 150/180-cycle and 10-min aggregates too")


class ThreePhaseGroup(_Section):
    """Three channels taken together: one ThreePhaseReport (phasors, symmetrical components,
    u2, u0) per estimate timestamp the phases share. A phase whose estimate for a timestamp
    has not come once another phase's data time is more than ``max_skew_s`` past it is
    reported missing (null phasor, named in ``missing``)."""

    name: str = Field(pattern=r"^[A-Za-z0-9_.\-/]+$", description="Group name; reports go to PQ_PREFIX/group/<name>")
    phases: list[str] = Field(min_length=3, max_length=3, description="Channel names of phase a, b, c")
    max_skew_s: float = Field(
        0.5, gt=0, allow_inf_nan=False, description="How far (data time) a phase may lag before it counts as missing"
    )
    aggregate_nominal_frequency_hz: Literal[50, 60] | None = Field(
        None,
        description="When set: the three phases' samples are also analysed on one IEC 61000-4-7 10/12-cycle "
        "window grid (synchronised to phase a) and u2, u0, the sequence magnitudes and the frequency are "
        "aggregated over 150/180 cycles and 10 min (IEC 61000-4-30), on PQ_PREFIX/agg/<name>",
    )

    @field_validator("phases")
    @classmethod
    def _distinct(cls, v: list[str]) -> list[str]:
        if len(set(v)) != 3:
            raise ValueError(f"phases: expected three different channels, got {v}")
        return v


class PowerQualitySection(_Section):
    """Power quality on top of the channel estimators (off unless configured)."""

    harmonics: list[HarmonicsRule] = Field(
        default_factory=list, description="Channels analysed for harmonics (IEC 61000-4-7) and aggregated"
    )
    groups: list[ThreePhaseGroup] = Field(default_factory=list, description="Three-phase groups")

    @field_validator("groups")
    @classmethod
    def _one_group_per_channel(cls, v: list[ThreePhaseGroup]) -> list[ThreePhaseGroup]:
        names = [g.name for g in v]
        if len(set(names)) != len(names):
            raise ValueError(f"groups: expected unique names, got {names}")
        seen: dict[str, str] = {}
        for g in v:
            for ch in g.phases:
                if ch in seen:
                    raise ValueError(
                        f"groups: expected each channel in one group, got {ch!r} in {seen[ch]!r} and {g.name!r}"
                    )
                seen[ch] = g.name
        return v


class C37118Station(_Section):
    """One PMU as a phasor data concentrator sees it: one ID code, one data stream, one phasor
    per channel (the channel estimator's synchrophasor: the ``pmu`` estimator's, or one derived
    from any estimator's amplitude and phase). FREQ and DFREQ are the first channel's."""

    id_code: int = Field(ge=1, le=65534, description="IDCODE of the data stream (unique per station)")
    name: str = Field(pattern=r"^[ -~]{1,16}$", description="Station name (STN): 1-16 printable ASCII characters")
    channels: list[str] = Field(
        min_length=1, max_length=64, description="Channel names (as in the Estimates), one phasor each, in order"
    )
    phasor_names: list[str] | None = Field(
        None, description="Phasor channel names (CHNAM, 16 ASCII characters); default: the channel names' last part"
    )
    phasor_type: Literal["voltage", "current"] = Field("voltage", description="PHUNIT type of every phasor")
    nominal_frequency_hz: Literal[50, 60] = Field(50, description="FNOM")
    data_rate: int = Field(
        50, ge=1, le=200, description="Frames per second (DATA_RATE): the channels' reporting rate (pmu estimator)"
    )
    phasor_format: Literal["polar", "rectangular"] = Field(
        "polar", description="Phasors as 32-bit floats, magnitude (RMS) and angle (rad), or real and imaginary"
    )
    max_skew_s: float = Field(
        0.5,
        gt=0,
        allow_inf_nan=False,
        description="A frame waits for every channel's estimate of its time until another channel is this far "
        "(data time) past it; then it is sent with the missing phasors NaN and STAT data error 10 (absent data)",
    )
    time_synchronised: bool = Field(
        False,
        description="For estimates whose input stated no time quality (Estimate time_quality null): the "
        "gateways' sample clocks are traceable to UTC (GPS/PTP): STAT sync bit 0 and FRACSEC time quality 0; "
        "otherwise STAT bit 13 (not in sync), unlocked > 1000 s and time quality 0xF. A stated time quality "
        "(e.g. a merging unit's smpSynch) sets them itself",
    )
    pmu_time_quality: int = Field(
        7,
        ge=0,
        le=7,
        description="STAT bits 8-6 (C37.118.2-2011 Table 7) while the time is locked: 7 = time error unknown "
        "or > 10 ms",
    )

    @field_validator("channels")
    @classmethod
    def _distinct_channels(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError(f"channels: expected distinct channel names, got {v}")
        return v

    @model_validator(mode="after")
    def _names(self) -> C37118Station:
        if self.phasor_names is not None and len(self.phasor_names) != len(self.channels):
            raise ValueError(
                f"phasor_names: expected one per channel ({len(self.channels)}), got {len(self.phasor_names)}"
            )
        return self


class C37118Section(_Section):
    """An IEEE C37.118.2-2011 server (sinewatch as a PMU; off by default): each station answers
    command frames over TCP (and UDP) on ``port`` and streams data frames at its rate."""

    enabled: bool = Field(False, description="Serve C37.118.2 (also: sinewatch serve --c37118 PORT)")
    host: str = Field("127.0.0.1", description="Address to listen on (loopback by default)")
    port: int = Field(4712, ge=0, le=65535, description="TCP and UDP port for command frames (0: any free port)")
    time_base: int = Field(1_000_000, ge=1, lt=1 << 24, description="TIME_BASE: FRACSEC counts 1/TIME_BASE s")
    client_queue_frames: int = Field(
        256, ge=1, description="Frames queued per client; past that a slow client's frames are dropped and counted"
    )
    max_clients: int = Field(
        32, ge=1, description="TCP connections and UDP streaming clients at once; more are refused and counted"
    )
    idle_timeout_s: float = Field(
        10.0,
        gt=0,
        allow_inf_nan=False,
        description="A TCP client that sends no command for this long while no data is on for it is disconnected "
        "(counted as rejected, reason idle): idle connections cannot hold every client slot",
    )
    client_buffer_bytes: int = Field(
        65536,
        ge=1024,
        description="Per TCP client: socket send buffer and write-buffer high-water mark; with the queue, what a "
        "client that stops reading may hold before its frames are dropped",
    )
    udp_destinations: list[str] = Field(
        default_factory=list,
        description="HOST:PORT destinations of spontaneous UDP data frames (every station, no command needed)",
    )
    stations: list[C37118Station] = Field(default_factory=list, description="The stations (PMUs) served")

    @field_validator("udp_destinations")
    @classmethod
    def _destinations(cls, v: list[str]) -> list[str]:
        for d in v:
            host, _, port = d.rpartition(":")
            if not host or not port.isdigit() or not 0 < int(port) < 65536:
                raise ValueError(f"udp_destinations: expected HOST:PORT, got {d!r}")
        return v

    @model_validator(mode="after")
    def _stations(self) -> C37118Section:
        ids = [s.id_code for s in self.stations]
        if len(set(ids)) != len(ids):
            raise ValueError(f"stations: expected unique id_code values, got {ids}")
        if self.enabled and not self.stations:
            raise ValueError("stations: expected at least one station when enabled")
        return self


class RecordingSection(_Section):
    enabled: bool = True
    directory: Path = Field(Path("sinewatch-runs"), description="Where MCAP files are written")
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    chunk_size_bytes: int = Field(1 << 20, ge=1024)
    rotate_bytes: int | None = Field(1 << 30, ge=1 << 16, description="Start a new file past this size")
    rotate_seconds: float | None = Field(3600.0, gt=0, description="Start a new file after this long")
    flush_interval_s: float = Field(
        1.0, gt=0, description="Close the open chunk this often: a crash loses at most this much"
    )
    # 60 s: a window's warm-up is at most a minute of its channels' data, while each
    # snapshot is built on the daemon's event loop (1.4 MB of JSON for 1000 ges-kalman
    # channels): rarer snapshots keep that off the latency
    snapshot_interval_s: float | None = Field(
        60.0,
        gt=0,
        description="Also write the state of every channel this often (log time; at an input) so that a "
        "window of the file replays from the snapshot before it; None: at file starts only",
    )
    inputs: bool = True
    estimates: bool = True
    power_quality: bool = Field(True, description="Record HarmonicsReports, ThreePhaseReports and PqAggregates")
    errors: bool = True
    status: bool = True


class ClusterSection(_Section):
    """Several daemons behind Zenoh routers: each owns a shard of the channels. With
    ``etcd`` set, the daemons of one shard elect its owner on an etcd lease: the owner
    publishes only while it can prove its lease alive, and every estimate carries the
    election's term (the fencing token); the others stand by and take over when the
    lease expires. Without ``etcd`` a daemon owns its shard alone (no standby).

    A shard is the key space the daemon subscribes to (``keys.input``, e.g.
    ``sinewatch/in/site1/**``), optionally cut further by ``shard = "i/N"``: the daemon then
    owns the input keys whose CRC-32 (of the UTF-8 key) modulo N is i - 1, so N daemons with
    ``1/N`` .. ``N/N`` split any set of keys with no overlap and no gap (each still receives
    every key of ``keys.input`` from Zenoh and drops the others' before decoding: prefer
    disjoint ``keys.input`` where the key layout allows it). The active daemon of a shard
    puts the state of its channels on PREFIX/shard/<shard_id>/snapshot every
    ``snapshot_interval_s``; its standbys keep the latest and watch its liveliness token."""

    shard: str | None = Field(
        None,
        pattern=r"^[1-9][0-9]*/[1-9][0-9]*$",
        description="i/N: own the input keys whose CRC-32 mod N is i-1; unset: every key of keys.input",
    )
    shard_id: str | None = Field(
        None,
        pattern=r"^[A-Za-z0-9_.\-]+$",
        description="Name shared by a shard's active daemon and its standbys (default: from keys.input and shard)",
    )
    role: Literal["active", "standby"] = Field(
        "active",
        description="active: campaign for the shard at once; standby: campaign once the shard has had an owner "
        "for a lease TTL (so the intended owner wins a cold start); needs etcd",
    )
    snapshot_interval_s: float = Field(1.0, gt=0, description="How often the active daemon publishes its state")
    etcd: str | None = Field(
        None,
        pattern=r"^[A-Za-z0-9_.\-\[\]:]+:[0-9]+$",
        description="host:port of the etcd server that elects each shard's owner; unset: no election, this daemon "
        "owns its shard alone",
    )
    lease_ttl_s: int = Field(
        3,
        ge=2,
        le=60,
        description="TTL of the owner's etcd lease, whole seconds (etcd's unit; it grants no less than 2 with its "
        "default timings). A deposed owner stops publishing within it; its successor takes over after it",
    )

    @model_validator(mode="after")
    def _standby_needs_etcd(self) -> ClusterSection:
        if self.role == "standby" and self.etcd is None:
            raise ValueError(
                "cluster.role: expected 'active' without cluster.etcd (a standby takes over through an etcd "
                "election), got 'standby'"
            )
        return self

    @field_validator("shard")
    @classmethod
    def _in_range(cls, v: str | None) -> str | None:
        if v is not None:
            i, n = (int(x) for x in v.split("/"))
            if not 1 <= i <= n:
                raise ValueError(f"shard: expected i/N with 1 <= i <= N, got {v!r}")
        return v


class WorkersSection(_Section):
    """Estimator worker processes (``serve --workers N``). With more than one, ``sinewatch
    serve`` is a supervisor: it hosts the Zenoh endpoints (a router session on
    ``zenoh.listen``) and runs N worker processes, each a whole pipeline (intake, estimators,
    publisher, its own MCAP recording) for the input keys a stable hash assigns it
    (CRC-32 of the key, independent of ``cluster.shard``), so each channel's state lives in
    one process and its estimates stay in order. A worker that dies is restarted from the
    last state it published (every ``cluster.snapshot_interval_s``); what it missed is
    flagged as a gap on the next estimates."""

    count: int = Field(
        1,
        ge=0,
        le=256,
        description="Worker processes; 1 (default): estimate in the serving process; 0: one per core. Each worker "
        "receives every block from Zenoh: on 2 cores with the publisher beside it, 2 workers sustained less than 1 "
        "(sinewatch bench e2e --workers 2)",
    )
    index: int | None = Field(
        None, ge=1, description="Set by the supervisor in each worker's config (1..count); leave unset"
    )
    resume_from: str | None = Field(
        None, description="Set by the supervisor when it restarts a worker: the state snapshot to resume from"
    )
    stall_s: float = Field(
        10.0,
        gt=0,
        allow_inf_nan=False,
        description="A worker whose event loop has not turned for this long is restarted",
    )
    restart_backoff_s: float = Field(
        1.0, gt=0, allow_inf_nan=False, description="Wait before restarting a worker that died soon after its start"
    )

    @model_validator(mode="after")
    def _index_in_range(self) -> WorkersSection:
        if self.index is not None and not 1 <= self.index <= max(self.count, 1):
            raise ValueError(f"workers.index: expected 1..{self.count}, got {self.index}")
        return self


class LimitsSection(_Section):
    max_payload_bytes: int = Field(16 << 20, ge=64)
    max_json_payload_bytes: int = Field(
        256 << 10,
        ge=64,
        description="A JSON block larger than this is refused before it is parsed (oversized_block): parsing "
        "holds the event loop, 50-180 ns a byte, so every channel would wait (a binary block costs nothing to "
        "decode); 256 KiB is about 13,000 samples",
    )
    max_block_samples: int = Field(1_000_000, ge=1)
    max_channels: int = Field(10_000, ge=1)
    queue_capacity: int = Field(8192, ge=1, description="Input blocks waiting for the estimators")
    queue_policy: Literal["block", "drop"] = Field(
        "block", description="block: back-pressure to Zenoh (no loss); drop: drop and count the newest"
    )
    intake_batch: int = Field(256, ge=1, description="Blocks handed to the event loop at once")


class FoxgloveSection(_Section):
    """Live view in Foxglove (``serve --foxglove PORT``): a Foxglove WebSocket server
    (the ``foxglove-sdk`` package, ``pip install 'sinewatch[foxglove]'``) streams the
    estimates, errors, status and power-quality messages on their Zenoh keys as topics,
    one plottable summary per input block on ``sinewatch/samples/<channel>``, and the log on
    ``sinewatch/log`` (``foxglove.Log``). Off unless a port is given. It never slows the
    daemon: each client has a bounded backlog (oldest dropped), and the input summaries are
    made on a worker thread behind a bounded queue (newest dropped and counted), at most
    ``input_rate_hz`` of them a second."""

    port: int | None = Field(None, ge=0, le=65535, description="WebSocket port (None: off; 0: any free port)")
    host: str = Field("127.0.0.1", description="Address to listen on (loopback by default)")
    inputs: bool = Field(True, description="Publish a summary of each input block (min, max, mean, RMS, samples)")
    input_points: int = Field(
        64, ge=1, le=100_000, description="At most this many samples per input summary (every k-th sample)"
    )
    input_rate_hz: float = Field(
        200.0,
        gt=0,
        allow_inf_nan=False,
        description="Input summaries per second at most, all channels together (one second's worth may come at "
        "once); past it blocks are skipped and counted: the summaries' cost has a ceiling",
    )
    queue: int = Field(
        1024, ge=1, description="Input blocks waiting for the summary worker; past it they are dropped and counted"
    )
    backlog: int = Field(1024, ge=1, description="Messages buffered per client; a slow client loses the oldest")
    max_topics: int = Field(4096, ge=1, description="Topics advertised at most (further ones are counted, not sent)")
    websocket_v1: bool = Field(
        True,
        description="Also answer clients asking for subprotocol foxglove.websocket.v1 (Lichtblick, PlotJuggler, "
        "Foxglove Studio before the SDK): a relay on the port in front of the SDK's server, which speaks only "
        "foxglove.sdk.v1 (the same protocol, renamed); false: the SDK's server on the port itself",
    )


class MetricsSection(_Section):
    """Prometheus metrics and a health endpoint (``serve --metrics PORT``): ``/metrics``
    (the ``prometheus-client`` package, ``pip install 'sinewatch[metrics]'``) and
    ``/healthz`` (JSON; 200 while the event loop turns and every sink is ok, else 503).
    Off unless a port is given."""

    port: int | None = Field(None, ge=0, le=65535, description="HTTP port (None: off; 0: any free port)")
    host: str = Field("127.0.0.1", description="Address to listen on (loopback by default)")
    stall_s: float = Field(
        5.0, gt=0, allow_inf_nan=False, description="/healthz fails once the event loop has not turned for this long"
    )


class SinewatchConfig(_Section):
    daemon_id: str = Field("sinewatch", pattern=r"^[A-Za-z0-9_.\-]+$")
    zenoh: ZenohSection = Field(default_factory=ZenohSection)
    keys: KeysSection = Field(default_factory=KeysSection)
    rules: list[EstimatorRule] = Field(
        default_factory=lambda: [EstimatorRule()],
        description="First matching rule wins; a channel no rule matches is rejected (no_rule)",
    )
    on_gap: Literal["coast", "reset"] = Field(
        "coast",
        description="After a sequence gap: coast (keep the state, flag the gap) or reset the estimator",
    )
    hold_estimates: bool = Field(
        True,
        description="Hold each estimate until the signal-presence detector has read its onset latency past "
        "the estimate's window (a third of a nominal cycle: 6.1 ms at 50 Hz, 5.1 ms at 60 Hz at 10 kHz), so that "
        "no estimate whose window holds the start of an interruption is published valid. An estimate at a "
        "block's last sample then leaves with the channel's next block, or idle_release_s after it (not "
        "valid: unconfirmed); a takeover publishes the held estimates of the state it restores under its own term "
        "(those its predecessor published are dropped). Costs the default rule 6 ms of reporting latency at 50 Hz "
        "(97 of C37.118.1's 100 ms). false: published at once; valid may then be wrong in the third of a cycle "
        "before the detector reads an onset",
    )
    report_in_block: bool = Field(
        False,
        description="With hold_estimates: report each block's estimate at the sample the signal-presence "
        "detector has read its onset latency L past (L samples before the block's last: 6.1 ms at 50 Hz, "
        "10 kHz), so that the block itself confirms it and it leaves at once instead of with the next block "
        "(validity rules version 6; its timestamp_ns is that sample's). A block of L samples or fewer, and an "
        "estimator reporting on a time grid (pmu), report and hold as without it",
    )
    idle_release_s: float = Field(
        0.5,
        gt=0,
        le=3600,
        description="With hold_estimates: a channel with no block for this long publishes the estimates it "
        "holds, not valid (nothing confirmed their windows): a feed that pauses or ends is not left waiting",
    )
    power_quality: PowerQualitySection = Field(default_factory=PowerQualitySection)
    c37118: C37118Section = Field(default_factory=C37118Section)
    cluster: ClusterSection = Field(default_factory=ClusterSection)
    recording: RecordingSection = Field(default_factory=RecordingSection)
    limits: LimitsSection = Field(default_factory=LimitsSection)
    workers: WorkersSection = Field(default_factory=WorkersSection)
    foxglove: FoxgloveSection = Field(default_factory=FoxgloveSection)
    metrics: MetricsSection = Field(default_factory=MetricsSection)
    status_interval_s: float = Field(1.0, gt=0)
    sink_retry_s: float = Field(
        1.0,
        gt=0,
        description="After an output fails (disk full, session closed), retry it this often; estimation goes on",
    )


# ---- loading: defaults < file < environment ---------------------------------------------------
ENV_PREFIX = "SINEWATCH__"
ENV_FILE = "SINEWATCH_CONFIG"


def load_config(path: str | Path | None = None, env: Mapping[str, str] | None = None) -> SinewatchConfig:
    env = os.environ if env is None else env
    path = path or env.get(ENV_FILE)
    data: dict[str, Any] = read_config_file(Path(path)) if path else {}
    _merge(data, env_overrides(env))
    try:
        return SinewatchConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"invalid configuration{f' in {path}' if path else ''}:\n{_explain(exc)}") from None


def read_config_file(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"config file {path}: {exc.strerror}") from None
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            data = tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"config file {path}: not valid {path.suffix.lstrip('.') or 'TOML'}: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path}: expected a table at the top, got {type(data).__name__}")
    return data


def env_overrides(env: Mapping[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, raw in env.items():
        if not name.upper().startswith(ENV_PREFIX):
            continue
        path = [p.lower() for p in name[len(ENV_PREFIX) :].split("__")]
        if not all(path):
            raise ConfigError(f"environment variable {name}: empty level in the name")
        try:
            value: Any = json.loads(raw)
        except ValueError:
            value = raw
        node = out
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"environment variable {name}: {part} is not a section")
        node[path[-1]] = value
    return out


def _merge(base: dict[str, Any], over: Mapping[str, Any]) -> None:
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(base.get(k), dict):
            _merge(base[k], v)
        else:
            base[k] = v


def _explain(exc: ValidationError) -> str:
    lines = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "(top)"
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        lines.append(f"  {loc}: {msg}")
    return "\n".join(lines)


def config_to_json(config: SinewatchConfig) -> str:
    return json.dumps(config.model_dump(mode="json"), indent=2)
