"""Replay: the daemon's pipeline fed from an MCAP recording instead of Zenoh.

``replay(paths)`` reads the recorded inputs in file order, runs them through a fresh
:class:`~sinewatch.pipeline.Pipeline` built from the config recorded in the file (and
the channel snapshot, for a file that starts after a rotation) and checks that every
recorded output (every role but inputs, errors and status: estimates, and the
power-quality harmonics, three_phase and pq_aggregate messages) is reproduced byte for
byte, in order, per topic. With ``rules`` it re-runs another
estimator or other parameters instead, and ``out`` writes a new recording, so two
algorithms can be compared on the same data.

The reader is a single streaming pass (``mcap.stream_reader``), so a file whose writer
was killed (no summary, no footer) still replays: every complete chunk is used and the
result says the file was incomplete.
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
from mcap.records import Attachment, Channel, DataEnd, Message, Metadata
from mcap.stream_reader import StreamReader

from sinewatch.comtrade_file import ComtradeError, ComtradeRecord, interleaved_blocks, read_comtrade
from sinewatch.pipeline import NullSink, Pipeline, Sink
from sinewatch.recorder import METADATA_NAME, SNAPSHOT_NAME, McapRecorder
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, encode_block_binary
from sinewatch.schemas.config import EstimatorRule, SinewatchConfig
from sinewatch.schemas.errors import SinewatchError
from sinewatch.schemas.messages import ESTIMATE_FORMAT_VERSION, Fencing
from sinewatch.schemas.power_quality import PQ_FORMAT_VERSION, PQ_ROLES

log = logging.getLogger("sinewatch.replay")


class ReplayError(SinewatchError, ValueError):
    """The file cannot be replayed (not a sinewatch recording, no inputs, ...)."""


@dataclass
class RecordedMessage:
    role: str
    topic: str
    zenoh_encoding: str
    payload: bytes
    log_time_ns: int


NOT_COMPARED_ROLES = frozenset({"input", "error", "status", ""})  # every other role is an output


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
    recorded_errors: int = 0
    produced_errors: int = 0
    mismatches: list[Mismatch] = field(default_factory=list)
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


def read_recording(path: Path, on_progress: Callable[[int], None] | None = None) -> Iterator[tuple[str, Any]]:
    """Yield ("metadata", dict), ("snapshot", dict) and ("message", RecordedMessage) in file
    order; ("incomplete", reason) last if the file ends early."""
    channels: dict[int, Channel] = {}
    with open(path, "rb") as f:
        reader = StreamReader(f, validate_crcs=True)
        try:
            for n, record in enumerate(reader.records):
                if isinstance(record, DataEnd):
                    break  # the summary repeats schemas and channels: nothing new there
                if isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message):
                    ch = channels[record.channel_id]
                    yield (
                        "message",
                        RecordedMessage(
                            ch.metadata.get("role", ""),
                            ch.topic,
                            ch.metadata.get("zenoh_encoding", ""),
                            record.data,
                            record.log_time,
                        ),
                    )
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

    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self.estimates[key].append(payload)
        self.roles[key] = "estimate"
        self.produced += 1

    def on_output(self, kind: str, key: str, payload: bytes, log_time_ns: int) -> None:
        if not self.other_outputs:
            return
        role = PQ_ROLES.get(kind, kind)
        self.estimates[key].append(payload)
        self.roles[key] = role
        self.produced_other[role] += 1

    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self.errors += 1


def replay(
    paths: list[Path],
    *,
    rules: list[EstimatorRule] | None = None,
    out: Path | None = None,
    on_progress: Callable[[Path, int], None] | None = None,
    max_mismatches: int = 1000,
) -> ReplayResult:
    """Replay recordings; see the module docstring. ``paths`` may hold several runs (the
    files of each worker process of ``serve --workers``, of a restarted worker, of other
    daemons): each run (:func:`split_runs`) replays through a pipeline of its own, as it was
    recorded, and the results add up. With ``out`` and several runs, run k > 1 is written
    to ``out`` with ``-run<k>`` before its suffix."""
    for path in paths:
        check_recording(path)
    runs = split_runs(paths)
    if len(runs) == 1:
        return _replay_run(paths, rules=rules, out=out, on_progress=on_progress, max_mismatches=max_mismatches)
    results = [
        _replay_run(
            run,
            rules=rules,
            out=None if out is None else out if k == 1 else out.with_name(f"{out.stem}-run{k}{out.suffix}"),
            on_progress=on_progress,
            max_mismatches=max_mismatches,
        )
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


def _replay_run(
    paths: list[Path],
    *,
    rules: list[EstimatorRule] | None,
    out: Path | None,
    on_progress: Callable[[Path, int], None] | None,
    max_mismatches: int,
) -> ReplayResult:
    """Replay one run's files, in order."""
    result = ResultBuilder(paths, compare=rules is None, max_mismatches=max_mismatches)
    pipeline: Pipeline | None = None
    recorder: McapRecorder | None = None
    comparator = _Comparator()
    pending_snapshot: dict[str, Any] | None = None
    config: SinewatchConfig | None = None
    estimate_version = ESTIMATE_FORMAT_VERSION
    pq_version = PQ_FORMAT_VERSION
    for file_no, path in enumerate(paths):
        progress = (lambda pos, p=path: on_progress(p, pos)) if on_progress else None
        for kind, item in read_recording(path, progress):
            if kind == "metadata":
                if config is None:
                    config = SinewatchConfig.model_validate(json.loads(item["config"]))
                    # check in the recording's own format (files of earlier builds have no key: 1)
                    if rules is None:
                        estimate_version = int(item.get("estimate_format_version", "1"))
                        pq_version = int(item.get("pq_format_version", "1"))
            elif kind == "snapshot":
                # A later file's snapshot is the state replay has reached by then, unless
                # no input came before it: the files of a standby before its takeover hold
                # status only, and the takeover's state is in this one.
                if file_no == 0 or result.r.inputs == 0:
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
                        config, sinks, rules=rules, estimate_version=estimate_version, pq_version=pq_version
                    )
                    if pending_snapshot is not None:
                        pipeline.restore(pending_snapshot)
                result.message(item, pipeline, comparator)
    if recorder is not None:
        recorder.close()
        result.r.out_paths = list(recorder.paths)
    if pipeline is None:
        raise ReplayError(f"{', '.join(map(str, paths))}: no recorded messages to replay")
    if result.r.inputs == 0:
        raise ReplayError("the recording has no inputs (recording.inputs was off?): nothing to replay")
    result.finish(comparator)
    return result.r


def replay_comtrade(
    path: Path,
    *,
    rules: list[EstimatorRule] | None = None,
    out: Path | None = None,
    block_size: int = 1000,
) -> ReplayResult:
    """Run a COMTRADE record (:mod:`sinewatch.comtrade_file`) through a fresh pipeline, as
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
