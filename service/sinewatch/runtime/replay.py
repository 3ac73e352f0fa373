"""Replay: the daemon's pipeline fed from an MCAP recording instead of Zenoh.

``replay(paths)`` reads the recorded inputs in file order, runs them through a fresh
:class:`~sinewatch.core.pipeline.Pipeline` built from the config recorded in the file (and
the channel snapshot, for a file that starts after a rotation) and checks that every
recorded output (every role but inputs, errors and status: estimates, and the
power-quality harmonics, three_phase and pq_aggregate messages) is reproduced byte for
byte, in order, per topic. With ``rules`` it re-runs another
estimator or other parameters instead, and ``out`` writes a new recording, so two
algorithms can be compared on the same data.

The reader is a single streaming pass (``mcap.stream_reader``), so a file whose writer
was killed (no summary, no footer) still replays: every complete chunk is used and the
result says the file was incomplete.

Why one module of a little over 800 lines: reading a recording, comparing its outputs and
the two replay loops (a whole run, and a window from the snapshot before it) share the
recording's private conventions (roles, topics, the formats each file was written in);
apart, each would need them exported to the others.
"""

from __future__ import annotations

import json
import logging
import struct
from collections import defaultdict, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, DataEnd, Message, Metadata
from mcap.stream_reader import StreamReader

from sinewatch.core.comtrade_file import ComtradeError, ComtradeRecord, interleaved_blocks, read_comtrade
from sinewatch.core.pipeline import NullSink, Pipeline, Sink
from sinewatch.core.window import ChannelFilter, Window
from sinewatch.outputs.recorder import ESTIMATOR_DEFAULTS_VERSION, METADATA_NAME, SNAPSHOT_NAME, McapRecorder
from sinewatch.outputs.track import TRACK_ROLE, TrackingPipeline, TrackWriter
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, encode_block_binary
from sinewatch.schemas.config import EstimatorRule, SinewatchConfig
from sinewatch.schemas.errors import InputError, SinewatchError
from sinewatch.schemas.frame import Frame, decode_input
from sinewatch.schemas.input_record import INPUT_MESSAGE_ENCODING, decode_input_record
from sinewatch.schemas.messages import ESTIMATE_FORMAT_VERSION, Fencing
from sinewatch.schemas.power_quality import PQ_FORMAT_VERSION, PQ_ROLES

log = logging.getLogger("sinewatch.runtime.replay")


def _defaults_then(cls: type, version: int) -> dict[str, Any]:
    """The defaults an estimator had in a file of defaults version ``version`` that differ from
    today's: its ``defaults_by_version`` (per version v, the defaults of files older than v;
    the oldest wins where two name one key), else ``defaults_before`` (files older than 2)."""
    table: dict[int, dict[str, Any]] = getattr(cls, "defaults_by_version", None) or {
        2: getattr(cls, "defaults_before", {})
    }
    then: dict[str, Any] = {}
    for v in sorted(table, reverse=True):  # newest first, so that an older value overrides
        if version < v:
            then.update(table[v])
    return then


def recorded_config(metadata: dict[str, str]) -> SinewatchConfig:
    """The config a recording was made with, each rule's ``params`` completed with the
    defaults its estimator had then: a default an estimator changed since (its
    ``defaults_before``, for files older than ``ESTIMATOR_DEFAULTS_VERSION``) is set
    explicitly, so the file replays bit for bit."""
    from sinewatch.estimators import get
    from sinewatch.schemas.errors import UnknownEstimatorError

    config = SinewatchConfig.model_validate(json.loads(metadata["config"]))
    version = int(metadata.get("estimator_defaults_version", "1"))
    if version >= ESTIMATOR_DEFAULTS_VERSION:
        return config
    rules = []
    for rule in config.rules:
        try:
            before = _defaults_then(get(rule.estimator), version)
        except UnknownEstimatorError:  # refused where the pipeline builds the rule, as before
            before = {}
        missing = {k: v for k, v in before.items() if k not in rule.params}
        rules.append(rule.model_copy(update={"params": {**missing, **rule.params}}) if missing else rule)
    return config.model_copy(update={"rules": rules})


class ReplayError(SinewatchError, ValueError):
    """The file cannot be replayed (not a sinewatch recording, no inputs, ...)."""


@dataclass
class RecordedMessage:
    role: str
    topic: str
    zenoh_encoding: str
    payload: bytes
    log_time_ns: int


NOT_COMPARED_ROLES = frozenset({"input", "error", "status", TRACK_ROLE, ""})  # every other role is an output


@dataclass
class Mismatch:
    topic: str
    index: int  # position among this topic's outputs
    recorded: bytes | None
    produced: bytes | None
    role: str = "estimate"

    def describe(self) -> str:
        if self.recorded is None:
            return f"{self.topic} #{self.index}: produced {self.role} output the recording does not have"
        if self.produced is None:
            return f"{self.topic} #{self.index}: recorded {self.role} output was not reproduced"
        return f"{self.topic} #{self.index}: " + ", ".join(diff_fields(self.recorded, self.produced))


@dataclass
class ReplayResult:
    paths: list[Path]
    inputs: int = 0
    recorded_estimates: int = 0
    produced_estimates: int = 0
    matched: int = 0
    mismatches: list[Mismatch] = field(default_factory=list)  # the first max_mismatches
    recorded_errors: int = 0
    produced_errors: int = 0
    incomplete_files: list[Path] = field(default_factory=list)
    compared: bool = True
    uncompared_tail: int = 0  # estimates past the end of an incomplete recording
    final: dict[str, tuple[bytes | None, bytes | None]] = field(default_factory=dict)  # estimates only
    out_paths: list[Path] = field(default_factory=list)
    # every output role but "estimate" (e.g. harmonics, three_phase, pq_aggregate): counts by role
    recorded_other: dict[str, int] = field(default_factory=dict)
    produced_other: dict[str, int] = field(default_factory=dict)
    matched_other: dict[str, int] = field(default_factory=dict)
    # COMTRADE: channels shorter than their estimator's window (no estimate could be valid)
    short_channels: list[str] = field(default_factory=list)
    # a window or channel filter (_replay_window_run)
    window: str = ""  # the window in words; "" for a whole replay
    warmup_inputs: int = 0  # inputs run between the snapshot (or run start) and the window, not compared
    started_from: str = ""  # "snapshot at +S s", "run start"
    track_rows: int = 0
    track_path: Path | None = None

    @property
    def ok(self) -> bool:
        if self.short_channels:
            return False
        if not self.compared:
            return True
        return (
            not self.mismatches
            and self.matched == self.recorded_estimates
            and all(self.matched_other.get(role, 0) == n for role, n in self.recorded_other.items())
        )


def diff_fields(a: bytes, b: bytes) -> list[str]:
    """Field-level differences between two Estimate JSON payloads."""
    try:
        x, y = json.loads(a), json.loads(b)
    except ValueError:
        return ["payloads differ and are not JSON"]
    out = []
    for k in sorted(set(x) | set(y)):
        if k == "diagnostics" and isinstance(x.get(k), dict) and isinstance(y.get(k), dict):
            for d in sorted(set(x[k]) | set(y[k])):
                if x[k].get(d) != y[k].get(d):
                    out.append(f"diagnostics.{d}: recorded {x[k].get(d)!r} != replayed {y[k].get(d)!r}")
        elif x.get(k) != y.get(k):
            out.append(f"{k}: recorded {x.get(k)!r} != replayed {y.get(k)!r}")
    return out or ["byte-level difference only (formatting)"]


MCAP_MAGIC = b"\x89MCAP0\r\n"


def check_recording(path: Path) -> None:
    """Raise ReplayError unless ``path`` is a readable file that starts as an MCAP file does."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise ReplayError(
            f"{path}: expected an MCAP recording, got {(exc.strerror or type(exc).__name__).lower()}"
        ) from None
    if head != MCAP_MAGIC:
        got = "an empty file" if not head else f"a file starting {head!r}"
        raise ReplayError(f"{path}: expected an MCAP recording (starting {MCAP_MAGIC!r}), got {got}")


def read_recording(
    path: Path,
    on_progress: Callable[[int], None] | None = None,
    *,
    from_snapshot_before_ns: int | None = None,
    roles: frozenset[str] | None = None,
) -> Iterator[tuple[str, Any]]:
    """Yield ("metadata", dict), ("snapshot", dict) and ("message", RecordedMessage) in file
    order; ("incomplete", reason) last if the file ends early. ``roles``: only the messages of
    channels with these roles (the others are skipped undecoded: an input's protobuf decoding
    is most of a read).

    ``from_snapshot_before_ns``: in a finished file (one with a summary), skip what comes
    before its latest state snapshot logged at or before that time (:func:`seek_point`):
    the metadata, then that snapshot and everything after it."""
    channels: dict[int, Channel] = {}
    point = None if from_snapshot_before_ns is None else seek_point(path, from_snapshot_before_ns)
    with open(path, "rb") as f:
        if point is not None:
            offset, channels, metadata = point
            for item in metadata:
                yield "metadata", item
            f.seek(offset)
        reader = StreamReader(f, skip_magic=point is not None, validate_crcs=True)
        try:
            for n, record in enumerate(reader.records):
                if isinstance(record, DataEnd):
                    break  # the summary repeats schemas and channels: nothing new there
                if isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message):
                    channel = channels[record.channel_id]
                    if roles is None or channel.metadata.get("role", "") in roles:
                        yield "message", recorded_message(channel, record)
                elif isinstance(record, Metadata) and record.name == METADATA_NAME:
                    yield "metadata", dict(record.metadata)
                elif isinstance(record, Attachment) and record.name == SNAPSHOT_NAME:
                    yield "snapshot", json.loads(record.data)
                if on_progress is not None and n % 512 == 0:
                    on_progress(f.tell())
        except (McapError, EOFError, ValueError, KeyError, struct.error) as exc:  # struct: cut inside a record header
            yield "incomplete", f"{type(exc).__name__}: {exc}"
        if on_progress is not None:
            on_progress(f.tell())


def read_window(
    path: Path, window: Window, on_progress: Callable[[int], None] | None = None
) -> Iterator[tuple[str, Any]]:
    """:func:`read_recording`'s items, the messages outside ``window`` left out; reading stops
    at the first message past its end (``export``, ``compare`` and ``plot`` read this way)."""
    for kind, item in read_recording(path, on_progress):
        if kind == "message":
            window.anchor(item.log_time_ns)
            if window.after(item.log_time_ns):
                return
            if window.before(item.log_time_ns):
                continue
        yield kind, item


def recorded_message(channel: Channel, message: Message) -> RecordedMessage:
    """A message as the daemon saw it: an input recorded as an InputBlock (protobuf) gives back
    the bytes and the Zenoh encoding it arrived with; every other message (and an input of a
    recording of an earlier build: its raw payload) is as recorded, under its channel's
    Zenoh encoding."""
    payload, encoding = message.data, channel.metadata.get("zenoh_encoding", "")
    if channel.message_encoding == INPUT_MESSAGE_ENCODING:
        payload, encoding = decode_input_record(payload)
    return RecordedMessage(channel.metadata.get("role", ""), channel.topic, encoding, payload, message.log_time)


def seek_point(path: Path, before_ns: int) -> tuple[int, dict[int, Channel], list[dict[str, str]]] | None:
    """Where to start reading a finished recording for a window from ``before_ns``: the
    offset of its latest snapshot logged at or before then (the snapshots written every
    ``recording.snapshot_interval_s`` are logged at the input they precede), the file's
    channels and its sinewatch metadata, all from the summary; None without a summary or
    such a snapshot (then the file is read from its start)."""
    with open(path, "rb") as f:
        try:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is None:
                return None
            snapshots = [a for a in summary.attachment_indexes if a.name == SNAPSHOT_NAME and a.log_time <= before_ns]
            if not snapshots:
                return None
            metadata = [dict(m.metadata) for m in reader.iter_metadata() if m.name == METADATA_NAME]
        except (McapError, EOFError, ValueError, KeyError, struct.error):
            return None
    return max(snapshots, key=lambda a: a.offset).offset, dict(summary.channels), metadata


def first_log_time(path: Path) -> int | None:
    """The log time of a finished recording's first message (its summary's), else None."""
    with open(path, "rb") as f:
        try:
            summary = make_reader(f).get_summary()
        except (McapError, EOFError, ValueError, KeyError, struct.error):
            return None
    if summary is None or summary.statistics is None or not summary.statistics.message_count:
        return None
    return int(summary.statistics.message_start_time)


class _Comparator(NullSink):
    """Collects what the replayed pipeline produces, per topic, in order: estimates and
    every other output (``on_output``, by the role its message kind is recorded under)."""

    def __init__(self) -> None:
        self.estimates: dict[str, deque[bytes]] = defaultdict(deque)  # every output topic
        self.roles: dict[str, str] = {}  # topic -> role
        self.produced = 0
        self.produced_other: dict[str, int] = defaultdict(int)
        self.errors = 0
        self.other_outputs = True  # False: the recording has none (recording.power_quality off)
        self.active = True  # False: a window's warm-up, whose outputs are not compared
        # the channels compared (a frame runs whole: its other channels' outputs are dropped)
        self.select: ChannelFilter | None = None

    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
        if not self.active or (self.select is not None and not self.select.matches_topic(key)):
            return
        self.estimates[key].append(payload)
        self.roles[key] = "estimate"
        self.produced += 1

    def on_output(self, kind: str, key: str, payload: bytes, log_time_ns: int) -> None:
        if not self.other_outputs or not self.active:
            return
        if self.select is not None and not self.select.matches_topic(key):
            return
        role = PQ_ROLES.get(kind, kind)
        self.estimates[key].append(payload)
        self.roles[key] = role
        self.produced_other[role] += 1

    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None:
        if self.active:
            self.errors += 1


def replay(
    paths: list[Path],
    *,
    rules: list[EstimatorRule] | None = None,
    out: Path | None = None,
    on_progress: Callable[[Path, int], None] | None = None,
    max_mismatches: int = 1000,
    window: Window | None = None,
    channels: ChannelFilter | None = None,
    track: Path | bool = False,
) -> ReplayResult:
    """Replay recordings; see the module docstring. ``paths`` may hold several runs (the
    files of each worker process of ``serve --workers``, of a restarted worker, of other
    daemons): each run (:func:`split_runs`) replays through a pipeline of its own, as it was
    recorded, and the results add up. With ``out`` and several runs, run k > 1 is written
    to ``out`` with ``-run<k>`` before its suffix.

    ``window`` and ``channels`` narrow the replay to a time window and some channels
    (:func:`_replay_window_run`); ``track`` also writes every sample's estimate of those
    channels (:mod:`sinewatch.outputs.track`): ``True`` into ``out``, a path into a Parquet file."""
    for path in paths:
        check_recording(path)
    runs = split_runs(paths)
    narrowed = (window is not None and window.bounded) or (channels is not None and not channels.everything)
    if narrowed or track:
        if len(runs) > 1 and (out is not None or isinstance(track, Path)):
            raise ReplayError(
                f"a window, channel filter or track of several runs: expected one run, got {len(runs)} "
                "(replay each daemon's files on their own)"
            )
        results = [
            _replay_window_run(
                _Run(run, rules, out, on_progress, max_mismatches),
                window=Window(window.start, window.end) if window is not None else Window(),
                channels=channels or ChannelFilter(),
                track=track,
            )
            for run in runs
        ]
        return results[0] if len(results) == 1 else merge_results(paths, results)
    if len(runs) == 1:
        return _replay_run(_Run(paths, rules, out, on_progress, max_mismatches))
    results = [
        _replay_run(_Run(run, rules, _run_out(out, k), on_progress, max_mismatches))
        for k, run in enumerate(runs, start=1)
    ]
    return merge_results(paths, results)


def file_identity(path: Path) -> tuple[str, int]:
    """(daemon id, index of the file in its run) from a recording's sinewatch metadata."""
    for kind, item in read_recording(path):
        if kind == "metadata":
            return json.loads(item["config"]).get("daemon_id", ""), int(item.get("file_index", "0"))
        if kind in ("message", "incomplete"):
            break
    raise ReplayError(f"{path}: no sinewatch metadata at its start; expected a file written by sinewatch")


def _follows_outage(path: Path) -> bool:
    """The file a recorder started after a failed write (a full disk): the one before it
    lost its tail, so this file's snapshot, not replay's state, is where it starts."""
    for kind, item in read_recording(path):
        if kind == "metadata":
            return bool(item.get("follows_outage") == "true")
        if kind in ("message", "incomplete"):
            break
    return False


def split_runs(paths: list[Path]) -> list[list[Path]]:
    """The runs among ``paths``: a daemon's files whose indices follow each other, in the
    order given. A file of another daemon (a worker process has an id of its own), or one
    whose index does not follow its daemon's previous file (a new run of it, e.g. a worker
    restarted from its state), or one started after a failed write, starts another run."""
    runs: list[list[Path]] = []
    open_runs: dict[str, tuple[int, list[Path]]] = {}  # daemon id -> (its last file index, its run)
    for path in paths:
        daemon_id, index = file_identity(path)
        last = open_runs.get(daemon_id)
        if last is not None and index == last[0] + 1 and not _follows_outage(path):
            last[1].append(path)
            open_runs[daemon_id] = (index, last[1])
        else:
            run = [path]
            runs.append(run)
            open_runs[daemon_id] = (index, run)
    return runs


def merge_results(paths: list[Path], results: list[ReplayResult]) -> ReplayResult:
    """One result for several runs: counts added, lists joined."""
    merged = ReplayResult(paths=list(paths), compared=all(r.compared for r in results))
    for r in results:
        for name in ("inputs", "recorded_estimates", "produced_estimates", "matched", "recorded_errors"):
            setattr(merged, name, getattr(merged, name) + getattr(r, name))
        merged.produced_errors += r.produced_errors
        merged.uncompared_tail += r.uncompared_tail
        merged.mismatches.extend(r.mismatches)
        merged.incomplete_files.extend(r.incomplete_files)
        merged.out_paths.extend(r.out_paths)
        merged.final.update(r.final)
        for mine, theirs in (
            (merged.recorded_other, r.recorded_other),
            (merged.produced_other, r.produced_other),
            (merged.matched_other, r.matched_other),
        ):
            for role, n in theirs.items():
                mine[role] = mine.get(role, 0) + n
    return merged


# (no validity version: a re-run's follows its config, as the daemon's and its recorder's do)
_CURRENT_VERSIONS = {
    "estimate_version": ESTIMATE_FORMAT_VERSION,
    "pq_version": PQ_FORMAT_VERSION,
}


def _recorded_versions(metadata: dict[str, str], rules: list[EstimatorRule] | None) -> dict[str, int]:
    """The Pipeline's version arguments for a file: a check runs in the recording's own
    formats and validity rules (files of earlier builds have no key: 1); a re-run with other
    ``rules`` in today's, its validity rules those its recorded config asks for (``report_in_block``:
    version 6, else 5), which its output file then says."""
    if rules is not None:
        return _CURRENT_VERSIONS
    return {
        "estimate_version": int(metadata.get("estimate_format_version", "1")),
        "pq_version": int(metadata.get("pq_format_version", "1")),
        "validity_version": int(metadata.get("validity_rules_version", "1")),
    }


def _run_out(out: Path | None, k: int) -> Path | None:
    """Where run ``k`` (from 1) of several is written: ``out``, then ``out`` with ``-run<k>``."""
    return None if out is None else out if k == 1 else out.with_name(f"{out.stem}-run{k}{out.suffix}")


@dataclass(frozen=True)
class _Run:
    """One run's files and what both replay loops take with them: the rules to re-run with
    (None: check the recording), where to write, progress, and how many mismatches to keep."""

    paths: list[Path]
    rules: list[EstimatorRule] | None
    out: Path | None
    on_progress: Callable[[Path, int], None] | None
    max_mismatches: int

    def result(self) -> ResultBuilder:
        return ResultBuilder(self.paths, compare=self.rules is None, max_mismatches=self.max_mismatches)

    def progress(self, path: Path) -> Callable[[int], None] | None:
        """``on_progress`` for one of the run's files (None: no progress wanted)."""
        on_progress = self.on_progress
        return None if on_progress is None else lambda pos: on_progress(path, pos)


def _replay_run(run: _Run) -> ReplayResult:
    """Replay one run's files, in order."""
    paths, rules, out = run.paths, run.rules, run.out
    result = run.result()
    pipeline: Pipeline | None = None
    recorder: McapRecorder | None = None
    comparator = _Comparator()
    pending_snapshot: dict[str, Any] | None = None
    config: SinewatchConfig | None = None
    versions = _CURRENT_VERSIONS
    last_log_ns = 0
    for file_no, path in enumerate(paths):
        progress = run.progress(path)
        for kind, item in read_recording(path, progress):
            if kind == "metadata":
                if config is None:
                    config = recorded_config(item)
                    versions = _recorded_versions(item, rules)
            elif kind == "snapshot":
                # A later file's snapshot is the state replay has reached by then, unless
                # no input came before it: the files of a standby before its takeover hold
                # status only, and the takeover's state is in this one. So are the snapshots
                # written every recording.snapshot_interval_s (for windows): not restored.
                if (file_no == 0 and pipeline is None) or result.r.inputs == 0:
                    pending_snapshot = item
                    if pipeline is not None:
                        pipeline.restore(item)
                elif pipeline is not None and "fencing" in item:  # a new term from this file on (a takeover)
                    pipeline.set_fencing(Fencing.model_validate(item["fencing"]))
            elif kind == "incomplete":
                log.warning("%s ends early (%s): replayed its complete chunks", path, item)
                result.r.incomplete_files.append(path)
            elif kind == "message":
                if pipeline is None:
                    if config is None:
                        raise ReplayError(
                            f"{path}: no sinewatch metadata before the first message; "
                            "expected a file written by sinewatch"
                        )
                    comparator.other_outputs = config.recording.power_quality
                    sinks: list[Sink] = [comparator]
                    if out is not None:
                        rec_config = config if rules is None else config.model_copy(update={"rules": rules})
                        recorder = McapRecorder(rec_config, path=out)
                        sinks.append(recorder)
                    pipeline = Pipeline(
                        config,
                        sinks,
                        rules=rules,
                        **versions,
                    )
                    if pending_snapshot is not None:
                        pipeline.restore(pending_snapshot)
                result.message(item, pipeline, comparator)
                last_log_ns = item.log_time_ns
    if rules is not None and pipeline is not None:
        # re-estimated: the input's end, as a daemon's drain, publishes what is still held back
        pipeline.release_held(last_log_ns)
    if recorder is not None:
        recorder.close()
        result.r.out_paths = list(recorder.paths)
    if pipeline is None:
        raise ReplayError(f"{', '.join(map(str, paths))}: no recorded messages to replay")
    if result.r.inputs == 0:
        raise ReplayError("the recording has no inputs (recording.inputs was off?): nothing to replay")
    result.finish(comparator)
    return result.r


class _Gate(NullSink):
    """A sink that passes everything on to ``sink`` while :attr:`active` (a window's
    recorder: the warm-up before the window is not recorded)."""

    def __init__(self, sink: McapRecorder) -> None:
        self.sink = sink
        self.sink_name = sink.sink_name
        self.active = False

    def on_input(self, key: str, payload: bytes, encoding: str, log_time_ns: int) -> None:
        if self.active:
            self.sink.on_input(key, payload, encoding, log_time_ns)

    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
        if self.active:
            self.sink.on_estimate(key, payload, log_time_ns)

    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None:
        if self.active:
            self.sink.on_error(key, payload, log_time_ns)

    def on_output(self, kind: str, key: str, payload: bytes, log_time_ns: int) -> None:
        if self.active:
            self.sink.on_output(kind, key, payload, log_time_ns)


class _InputChannels:
    """The channel name of a recorded input (its block's), by topic: a key carries one
    channel, so each topic is decoded once; an input that does not decode is taken by its
    topic's tail."""

    def __init__(self, channels: ChannelFilter) -> None:
        self.filter = channels
        self._by_topic: dict[str, bool] = {}

    def selected(self, m: RecordedMessage) -> bool:
        """A block of a selected channel, or a multi-channel frame with one among its
        channels (the whole frame is run: its channels advance together)."""
        if self.filter.everything:
            return True
        hit = self._by_topic.get(m.topic)
        if hit is not None:
            return hit
        try:
            decoded = decode_input(m.payload, m.zenoh_encoding)
        except InputError:
            return self.filter.matches_topic(m.topic)
        if isinstance(decoded, Frame):  # a frame's layout may change from one to the next: not cached
            return any(self.filter.matches(name) for name in decoded.channels)
        hit = self._by_topic[m.topic] = self.filter.matches(decoded.channel)
        return hit


# _replay_window_run and _replay_run stay two loops: a window starts from the snapshot before
# it, holds the inputs in between and gates what is compared and recorded, where a whole run
# feeds every input as it comes; one loop with both behind flags would read as neither.
def _replay_window_run(
    run: _Run,
    *,
    window: Window,
    channels: ChannelFilter,
    track: Path | bool,
) -> ReplayResult:
    """Replay the part of one run's files in ``window`` on the ``channels`` selected.

    A check (no ``rules``) starts from the latest state snapshot at or before the window's
    start (a file's start, or one written every ``recording.snapshot_interval_s``): the
    inputs after it and before the window are kept, not run, until the window begins;
    then the pipeline is restored from the snapshot and runs them (the warm-up: outputs
    neither compared nor recorded), then the window, whose outputs are compared with the
    recorded ones. A re-run with other ``rules`` cannot start from a snapshot of other
    estimators: it runs the run from its start, the part before the window as warm-up.
    The inputs of channels not selected are skipped, and so are the outputs recorded on
    topics that do not end in a selected channel's name. Reading stops at the window's end.

    ``out`` records the window only, its first file starting with the snapshot of the
    window's start, so that it replays on its own."""
    paths, rules, out = run.paths, run.rules, run.out
    result = run.result()
    comparator = _Comparator()
    comparator.active = False
    comparator.select = None if channels.everything else channels
    inputs = _InputChannels(channels)
    config: SinewatchConfig | None = None
    versions = _CURRENT_VERSIONS
    snapshot: dict[str, Any] | None = None
    snapshot_at: int | None = None  # its log time: that of the first message after it
    snapshot_pending = False
    held: list[RecordedMessage] = []  # selected inputs since the snapshot, before the window
    pipeline: Pipeline | None = None
    gate: _Gate | None = None
    recorder: McapRecorder | None = None
    tracker: TrackWriter | None = None
    in_window = False
    done = False

    def build() -> Pipeline:
        nonlocal gate, recorder, tracker
        assert config is not None
        comparator.other_outputs = config.recording.power_quality
        sinks: list[Sink] = [comparator]
        built: list[Pipeline] = []
        if out is not None:
            rec_config = config if rules is None else config.model_copy(update={"rules": rules})
            recorder = McapRecorder(rec_config, path=out, snapshot=lambda: built[0].snapshot())
            recorder.attach_first_snapshot = True  # the window's first file replays on its own
            gate = _Gate(recorder)
            sinks.append(gate)
        kwargs: dict[str, Any] = dict(rules=rules, **versions)
        if track:
            if track is True and recorder is None:
                raise ReplayError("--track: expected --out (a recording to write the track into) or a .parquet path")
            tracker = TrackWriter(recorder=recorder, parquet=track if isinstance(track, Path) else None)
            made: Pipeline = TrackingPipeline(config, sinks, writer=tracker, channels=channels, **kwargs)
        else:
            made = Pipeline(config, sinks, **kwargs)
        built.append(made)
        return made

    def enter_window(p: Pipeline) -> None:
        nonlocal in_window
        in_window = True
        comparator.active = True
        if gate is not None:
            gate.active = True
        if isinstance(p, TrackingPipeline):
            p.active = True

    for path in paths:
        if done:
            break
        progress = run.progress(path)
        if window.origin_ns is None and (first := first_log_time(path)) is not None:
            window.anchor(first)
        # a check skips what comes before the latest snapshot before its window, unread
        seek = window.start_ns if rules is None and pipeline is None else None
        for kind, item in read_recording(path, progress, from_snapshot_before_ns=seek):
            if kind == "metadata":
                if config is None:
                    config = recorded_config(item)
                    versions = _recorded_versions(item, rules)
            elif kind == "snapshot":
                # a check before its window starts from the latest; a re-run from the run's first only
                if pipeline is None and (rules is None or (snapshot is None and path == paths[0])):
                    snapshot, snapshot_pending = item, True
                    held.clear()
            elif kind == "incomplete":
                log.warning("%s ends early (%s): replayed its complete chunks", path, item)
                result.r.incomplete_files.append(path)
            elif kind == "message":
                m: RecordedMessage = item
                if config is None:
                    raise ReplayError(
                        f"{path}: no sinewatch metadata before the first message; expected a file written by sinewatch"
                    )
                window.anchor(m.log_time_ns)
                if snapshot_pending:
                    snapshot_at, snapshot_pending = m.log_time_ns, False
                if window.after(m.log_time_ns):
                    done = True
                    break
                if m.role == "input":
                    if not inputs.selected(m):
                        continue
                elif not channels.everything and not channels.matches_topic(m.topic):
                    continue
                if window.before(m.log_time_ns):
                    if m.role != "input":
                        continue
                    if rules is None:  # held until the window: a later snapshot may make them unneeded
                        held.append(m)
                        continue
                    if pipeline is None:
                        pipeline = _start(build(), snapshot)
                    pipeline.process(m.topic, m.payload, m.zenoh_encoding, m.log_time_ns)
                    result.r.warmup_inputs += 1
                    continue
                # the pipeline starts at the window's first input: a standby's status-only files
                # before it leave the snapshot of its takeover to start from
                if pipeline is None and m.role != "input":
                    if m.role == "error":
                        result.r.recorded_errors += 1
                    continue
                if pipeline is None:
                    pipeline = _start(build(), snapshot)
                if not in_window:
                    for h in held:
                        pipeline.process(h.topic, h.payload, h.zenoh_encoding, h.log_time_ns)
                    result.r.warmup_inputs += len(held)
                    held.clear()
                    enter_window(pipeline)
                    origin = window.origin_ns or 0
                    result.r.started_from = (
                        "run start"
                        if snapshot is None
                        else f"snapshot at +{((snapshot_at or origin) - origin) / 1e9:.3f} s"
                    )
                result.message(m, pipeline, comparator)
    if recorder is not None:
        recorder.close()
        result.r.out_paths = list(recorder.paths)
    if tracker is not None:
        tracker.close()
        result.r.track_rows = tracker.rows
        result.r.track_path = tracker.parquet
    if config is None:
        raise ReplayError(f"{', '.join(map(str, paths))}: no sinewatch metadata; expected a file written by sinewatch")
    if pipeline is None or not in_window:
        raise ReplayError(
            f"{', '.join(map(str, paths))}: expected inputs in the window ({window.describe()}) "
            f"on the channels selected ({channels.describe()}), got none"
        )
    result.r.window = window.describe() if window.bounded else ""
    result.finish(comparator)
    return result.r


def _start(pipeline: Pipeline, snapshot: dict[str, Any] | None) -> Pipeline:
    if snapshot is not None:
        pipeline.restore(snapshot)
    return pipeline


def replay_comtrade(
    path: Path,
    *,
    rules: list[EstimatorRule] | None = None,
    out: Path | None = None,
    block_size: int = 1000,
) -> ReplayResult:
    """Run a COMTRADE record (:mod:`sinewatch.core.comtrade_file`) through a fresh pipeline, as
    ``sinewatch feed --comtrade`` would send it to a daemon: each analog channel in blocks of
    ``block_size`` samples (float64) on ``sinewatch/in/CHANNEL``, with ``rules`` (default: the
    default config's). Nothing is compared (there is no recorded estimate); ``out`` records
    inputs and outputs to a new MCAP file, which replays bit for bit. A channel shorter than
    its estimator's window is named in ``short_channels`` (the result is then not ``ok``);
    when every channel is, :class:`ComtradeError` says so (after ``out`` is written)."""
    record = read_comtrade(path)
    config = SinewatchConfig(daemon_id="sinewatch-comtrade")
    if rules is not None:
        config = config.model_copy(update={"rules": rules})
    prefix = config.keys.input.removesuffix("/**")
    result = ResultBuilder([path], compare=False, max_mismatches=0)
    comparator = _Comparator()
    comparator.other_outputs = config.recording.power_quality
    sinks: list[Sink] = [comparator]
    recorder = McapRecorder(config, path=out) if out is not None else None
    if recorder is not None:
        sinks.append(recorder)
    pipeline = Pipeline(config, sinks)
    for block in interleaved_blocks(record, block_size):
        payload = encode_block_binary(block, "float64")
        message = RecordedMessage("input", f"{prefix}/{block.channel}", BLOCK_BINARY_ENCODING, payload, block.t0_ns)
        result.message(message, pipeline, comparator)
    if recorder is not None:
        recorder.close()
        result.r.out_paths = list(recorder.paths)
    result.finish(comparator)
    result.r.short_channels = _short_channels(record, pipeline)
    if result.r.short_channels and len(result.r.short_channels) == len(record.channels):
        raise ComtradeError(f"{path}: {'; '.join(result.r.short_channels)}: no estimate can be valid")
    return result.r


def _short_channels(record: ComtradeRecord, pipeline: Pipeline) -> list[str]:
    """The record's channels shorter than the window (``memory_samples``) of the estimator
    the rules gave them, each as 'CHANNEL: expected at least N samples (ESTIMATOR's window
    at RATE Hz), got M'."""
    out = []
    for c in record.channels:
        ch = pipeline.channels.get(c.channel)
        if ch is None:
            continue
        need = ch.estimator.memory_samples
        if len(c.samples) < need:
            out.append(
                f"{c.channel}: expected at least {need} samples ({ch.estimator.name}'s window at "
                f"{c.sample_rate_hz:g} Hz, {need / c.sample_rate_hz:.3g} s), got {len(c.samples)}"
            )
    return out


class ResultBuilder:
    def __init__(self, paths: list[Path], *, compare: bool, max_mismatches: int) -> None:
        self.r = ReplayResult(paths=list(paths), compared=compare)
        self.max_mismatches = max_mismatches
        self.counts: dict[str, int] = defaultdict(int)

    def message(self, m: RecordedMessage, pipeline: Pipeline, comparator: _Comparator) -> None:
        r = self.r
        if m.role == "input":
            r.inputs += 1
            pipeline.process(m.topic, m.payload, m.zenoh_encoding, m.log_time_ns)
        elif m.role == "error":
            r.recorded_errors += 1
        elif m.role not in NOT_COMPARED_ROLES:
            estimate = m.role == "estimate"
            if estimate:
                r.recorded_estimates += 1
            else:
                r.recorded_other[m.role] = r.recorded_other.get(m.role, 0) + 1
            if estimate and not comparator.estimates[m.topic]:
                # recorded with nothing produced yet: only the daemon's drain and its idle
                # release publish an estimate after a channel's last input (Pipeline.release_held,
                # release_idle), so release that channel here too
                pipeline.release_held(m.log_time_ns, m.topic)
            produced = comparator.estimates[m.topic].popleft() if comparator.estimates[m.topic] else None
            index = self.counts[m.topic]
            self.counts[m.topic] += 1
            if estimate:
                r.final[m.topic] = (m.payload, produced)
            if not r.compared:
                return
            if produced == m.payload:
                if estimate:
                    r.matched += 1
                else:
                    r.matched_other[m.role] = r.matched_other.get(m.role, 0) + 1
            elif len(r.mismatches) < self.max_mismatches:
                r.mismatches.append(Mismatch(m.topic, index, m.payload, produced, m.role))

    def finish(self, comparator: _Comparator) -> None:
        r = self.r
        r.produced_errors = comparator.errors
        r.produced_estimates = comparator.produced
        r.produced_other = dict(comparator.produced_other)
        for topic, extra in comparator.estimates.items():  # produced, never recorded
            if r.incomplete_files:  # their records were cut off with the file's tail
                r.uncompared_tail += len(extra)
                continue
            role = comparator.roles.get(topic, "estimate")
            for payload in extra:
                if role == "estimate":
                    r.final[topic] = (r.final.get(topic, (None, None))[0], payload)
                if r.compared and len(r.mismatches) < self.max_mismatches:
                    r.mismatches.append(Mismatch(topic, self.counts[topic], None, payload, role))
                self.counts[topic] += 1
