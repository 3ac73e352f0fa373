"""``replay --track``: every sample's estimate, not one per block.

The pipeline asks each estimator for the last row of its track only (``last_only``); a
replay with ``--track`` asks the estimators of the selected channels for every row (the
kernel runs the same samples either way and its last row is the same bits: the
estimator conformance tests check it) and writes each row out, with the estimator's own
per-sample signals (``Track.extras``: e.g. an observer's internal state, the switching
signals of a multi-sine estimator), its standard deviations and ROCOF where it has them,
and the input sample itself.

Columns, one row per sample (``K`` components, ``C`` input columns):

* ``channel``, ``estimator``, ``seq`` (the block's), ``sample`` (index in the block),
  ``timestamp_ns`` (``t0_ns + round(i * 1e9 / sample_rate_hz)``, as ``export --samples``),
  ``input_0`` .. ``input_{C-1}``;
* ``frequency_hz_k``, ``amplitude_k``, ``phase_rad_k`` for k < K, ``offset``,
  ``converged``, ``residual_rms`` (the block's);
* ``rocof_hz_per_s_k`` and ``std_frequency_hz_k``, ``std_amplitude_k``,
  ``std_phase_rad_k``, ``std_offset`` when the estimator reports them;
* ``extras.NAME`` for a per-sample extra of one column, ``extras.NAME_j`` for column j of
  a wider one.

Written as Parquet (one file, the union of every channel's columns, null where a channel
has no such column; needs pyarrow, the ``export`` extra), or into the replay's output
recording as one JSON message per sample on ``sinewatch/track/CHANNEL`` (role
``track``, with its JSON Schema, so Foxglove plots any column), logged at the block's log
time minus the time from the sample to the block's last sample.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from sinewatch.core.pipeline import Channel, Pipeline
from sinewatch.core.window import ChannelFilter
from sinewatch.estimators.base import Track
from sinewatch.schemas.codec import Block
from sinewatch.schemas.errors import SinewatchError

TRACK_PREFIX = "sinewatch/track"
TRACK_ROLE = "track"
TRACK_SCHEMA_NAME = "sinewatch.TrackRow"
TRACK_SCHEMA: dict[str, Any] = {
    "title": "TrackRow",
    "description": "One sample's estimate and the estimator's per-sample signals (sinewatch replay --track)",
    "type": "object",
    "properties": {
        "channel": {"type": "string"},
        "estimator": {"type": "string"},
        "seq": {"type": "integer"},
        "sample": {"type": "integer"},
        "timestamp": {
            "type": "object",
            "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
        },
        "timestamp_ns": {"type": "integer"},
        "input": {"type": "array", "items": {"type": ["number", "null"]}},
        "frequency_hz": {"type": "array", "items": {"type": ["number", "null"]}},
        "amplitude": {"type": "array", "items": {"type": ["number", "null"]}},
        "phase_rad": {"type": "array", "items": {"type": ["number", "null"]}},
        "offset": {"type": ["number", "null"]},
        "converged": {"type": "boolean"},
        "residual_rms": {"type": ["number", "null"]},
        "rocof_hz_per_s": {"type": ["array", "null"], "items": {"type": ["number", "null"]}},
        "std": {"type": ["object", "null"]},
        "extras": {"type": "object"},
    },
}


class TrackError(SinewatchError, ValueError):
    """``--track`` cannot be done as asked (no output to write it to, a missing extra)."""


class JsonRecorder(Protocol):
    """Where track rows go in a recording (:meth:`sinewatch.outputs.recorder.McapRecorder.record_json`)."""

    def record_json(
        self, topic: str, role: str, schema_name: str, schema: bytes, payload: bytes, log_time_ns: int
    ) -> None: ...


def track_columns(track: Track, samples: np.ndarray, t0_ns: int, sample_rate_hz: float) -> dict[str, np.ndarray]:
    """The columns (module docstring) of one block's full track, without channel, estimator
    and seq; every array has one row per sample."""
    n = track.n_samples
    cols: dict[str, np.ndarray] = {
        "sample": np.arange(n, dtype=np.int64),
        "timestamp_ns": t0_ns + np.round(np.arange(n) * (1e9 / sample_rate_hz)).astype(np.int64),
    }
    x = samples.reshape(n, -1)
    for j in range(x.shape[1]):
        cols[f"input_{j}"] = np.asarray(x[:, j], dtype=np.float64)
    for name in ("frequency_hz", "amplitude", "phase_rad"):
        values = getattr(track, name)
        for k in range(values.shape[1]):
            cols[f"{name}_{k}"] = values[:, k]
    cols["offset"] = track.offset
    cols["converged"] = np.asarray(track.converged, dtype=np.bool_)
    cols["residual_rms"] = np.full(n, track.residual_rms)
    if track.rocof_hz_per_s is not None:
        rocof = track.rocof_hz_per_s.reshape(n, -1)
        for k in range(rocof.shape[1]):
            cols[f"rocof_hz_per_s_{k}"] = rocof[:, k]
    if track.std is not None:
        for name in ("frequency_hz", "amplitude", "phase_rad"):
            values = getattr(track.std, name)
            for k in range(values.shape[1]):
                cols[f"std_{name}_{k}"] = values[:, k]
        cols["std_offset"] = track.std.offset
    for name, values in track.extras.items():
        v = np.asarray(values)
        if v.ndim == 1:
            cols[f"extras.{name}"] = v
        else:
            flat = v.reshape(n, -1)
            for j in range(flat.shape[1]):
                cols[f"extras.{name}_{j}"] = flat[:, j]
    return cols


def _value(v: Any) -> Any:
    """A JSON value: finite floats as they are, NaN/Inf as null, numpy scalars as Python's."""
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    f = float(v)
    return f if math.isfinite(f) else None


def track_messages(channel: str, estimator: str, seq: int, cols: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """One JSON message (:data:`TRACK_SCHEMA`) per row of ``cols``."""
    n = len(cols["sample"])
    grouped: dict[str, list[str]] = defaultdict(list)
    for name in cols:
        for prefix in ("input", "frequency_hz", "amplitude", "phase_rad", "rocof_hz_per_s"):
            if name.startswith(prefix + "_") and name[len(prefix) + 1 :].isdigit():
                grouped[prefix].append(name)
    std_names = [c for c in cols if c.startswith("std_")]
    extra_names = [c for c in cols if c.startswith("extras.")]
    lists = {k: np.asarray(v).tolist() for k, v in cols.items()}
    out = []
    for i in range(n):
        t = int(lists["timestamp_ns"][i])
        msg: dict[str, Any] = {
            "channel": channel,
            "estimator": estimator,
            "seq": seq,
            "sample": i,
            "timestamp": {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000},
            "timestamp_ns": t,
        }
        for prefix in ("input", "frequency_hz", "amplitude", "phase_rad"):
            msg[prefix] = [_value(lists[c][i]) for c in grouped[prefix]]
        msg["offset"] = _value(lists["offset"][i])
        msg["converged"] = bool(lists["converged"][i])
        msg["residual_rms"] = _value(lists["residual_rms"][i])
        msg["rocof_hz_per_s"] = [_value(lists[c][i]) for c in grouped["rocof_hz_per_s"]] or None
        msg["std"] = {c.removeprefix("std_"): _value(lists[c][i]) for c in std_names} or None
        msg["extras"] = {c.removeprefix("extras."): _value(lists[c][i]) for c in extra_names}
        out.append(msg)
    return out


class TrackWriter:
    """Collects the rows of the tracked blocks; writes them to a recording as they come
    (``recorder``) or to one Parquet file at :meth:`close` (``parquet``)."""

    def __init__(self, *, recorder: JsonRecorder | None = None, parquet: Path | None = None) -> None:
        if (recorder is None) == (parquet is None):
            raise TrackError("--track: expected one output, a recording (--out) or a .parquet path")
        if parquet is not None:
            _pyarrow()
        self.recorder = recorder
        self.parquet = parquet
        self.rows = 0
        self.blocks = 0
        self.channels: set[str] = set()
        self._blocks: list[dict[str, np.ndarray]] = []  # the Parquet file's rows, a block at a time
        self._schema_bytes = json.dumps(TRACK_SCHEMA).encode()

    def add(self, ch: Channel, block: Block, track: Track, log_time_ns: int) -> None:
        cols = track_columns(track, block.samples, block.t0_ns, block.sample_rate_hz)
        n = track.n_samples
        self.rows += n
        self.blocks += 1
        self.channels.add(ch.name)
        if self.recorder is not None:
            t_last = int(cols["timestamp_ns"][-1])
            topic = f"{TRACK_PREFIX}/{ch.name}"
            for msg in track_messages(ch.name, ch.estimator.name, block.seq, cols):
                log_time = log_time_ns - (t_last - msg["timestamp_ns"])
                payload = json.dumps(msg, separators=(",", ":"), allow_nan=False).encode()
                self.recorder.record_json(topic, TRACK_ROLE, TRACK_SCHEMA_NAME, self._schema_bytes, payload, log_time)
            return
        cols = {
            "channel": np.array([ch.name] * n, dtype=object),
            "estimator": np.array([ch.estimator.name] * n, dtype=object),
            "seq": np.full(n, block.seq, dtype=np.int64),
            **cols,
        }
        self._blocks.append(cols)

    def close(self) -> None:
        """Write the Parquet file: the union of the blocks' columns, in order of first use."""
        if self.parquet is None:
            return
        pa, pq = _pyarrow()
        names = list(dict.fromkeys(name for cols in self._blocks for name in cols))
        arrays = []
        for name in names:
            like = next(cols[name] for cols in self._blocks if name in cols)
            parts = [cols.get(name, _nulls(like, len(cols["sample"]))) for cols in self._blocks]
            missing = np.concatenate([np.full(len(cols["sample"]), name not in cols) for cols in self._blocks])
            arrays.append(pa.array(np.concatenate(parts), mask=missing if missing.any() else None))
        pq.write_table(pa.Table.from_arrays(arrays, names=names), self.parquet, compression="zstd")


def _nulls(like: np.ndarray, n: int) -> np.ndarray:
    """n missing values in a column of ``like``'s kind: NaN for floats, None otherwise."""
    if like.dtype.kind == "f":
        return np.full(n, np.nan)
    return np.array([None] * n, dtype=object)


def _pyarrow() -> tuple[Any, Any]:
    try:
        import pyarrow as pa  # type: ignore[import-untyped,import-not-found,unused-ignore]
        import pyarrow.parquet as pq  # type: ignore[import-untyped,import-not-found,unused-ignore]
    except ImportError:
        raise TrackError(
            "--track FILE.parquet: expected pyarrow to be installed, got no pyarrow "
            "(install the extra: pip install 'sinewatch[export]')"
        ) from None
    return pa, pq


class TrackingPipeline(Pipeline):
    """A :class:`Pipeline` whose selected channels' estimators return their whole track
    while :attr:`active`; each accepted block's rows go to ``writer``. The estimates are
    the last rows, the same bits as the plain pipeline's."""

    def __init__(self, *args: Any, writer: TrackWriter, channels: ChannelFilter, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.writer = writer
        self.track_filter = channels
        self.active = False
        self._pending: dict[str, Track] = {}
        self._log_time_ns = 0

    def process(
        self, key: str, payload: bytes, encoding: str, log_time_ns: int, received_ns: int | None = None
    ) -> None:
        self._log_time_ns = log_time_ns
        super().process(key, payload, encoding, log_time_ns, received_ns)

    def _channel_for(self, key: str, block: Block) -> Channel:
        ch = super()._channel_for(key, block)
        if self.track_filter.matches(ch.name):
            self._wrap(ch)
        return ch

    def _wrap(self, ch: Channel) -> None:
        """Route ``ch.estimator.update`` through the full track (an instance attribute over
        the method: the estimator object, its state and its snapshot stay what they are)."""
        est = ch.estimator
        if "update" in vars(est):
            return
        original: Callable[..., Track] = est.update
        pending = self._pending

        def update(samples: np.ndarray, *, last_only: bool = False, t0_ns: int | None = None) -> Track:
            if not self.active:
                return original(samples, last_only=last_only, t0_ns=t0_ns)
            full = original(samples, last_only=False, t0_ns=t0_ns)
            pending[ch.name] = full
            return full.last() if last_only else full

        setattr(est, "update", update)  # noqa: B010 (an instance attribute shadowing the method, on purpose)

    def _accept(
        self, ch: Channel, block: Block, gap_blocks: int, restart: bool, reset: bool, jump: bool = False
    ) -> None:
        super()._accept(ch, block, gap_blocks, restart, reset, jump)
        track = self._pending.pop(ch.name, None)
        if track is not None:
            self.writer.add(ch, block, track, self._log_time_ns)


__all__ = ["TRACK_PREFIX", "TRACK_ROLE", "TrackError", "TrackWriter", "TrackingPipeline", "track_columns"]
