"""COMTRADE files (IEEE Std C37.111-1999 and C37.111-2013) as sinewatch channels.

A COMTRADE record is a configuration file (``.cfg``: station, channels with their scaling
``a * x + b`` and unit, sample rates, start time, data format) beside a data file
(``.dat``: ASCII, or BINARY / BINARY32 / FLOAT32 in 2013), or both in one ``.cff`` (2013).
Reading is done by python-comtrade (``comtrade`` on PyPI, David Parrini; MIT): it reads
the 1991, 1999 and 2013 revisions in all four data formats and the CFF container, and
applies each channel's scaling; it needs nothing but the standard library (numpy when
present). ``pip install 'sinewatch[comtrade]'``.

Each **analog** channel becomes a sinewatch channel ``PREFIX/STATION/CHANNEL`` (names
reduced to the characters a channel name allows), at the file's recorded sample rate,
starting at the record's start time plus the first sample's time. A record with several
sample-rate segments (``nrates`` > 1) gives one channel per segment (``.../CHANNEL/seg2``...),
since a sinewatch channel keeps one rate (the first sample of a segment comes one period
of its own rate after the last of the one before, as python-comtrade reads it). A record
with timestamps only (``samp`` = 0) is refused: a channel needs a fixed rate. Status
(digital) channels are not estimated and are left out. The start time is read as UTC (the 1999 revision has no time zone field).
The text files are read as UTF-8, or as Latin-1 when they are not valid UTF-8
(:func:`text_encoding`: older relays write Latin-1 names).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from sinewatch.schemas.codec import Block
from sinewatch.schemas.errors import SinewatchError
from sinewatch.schemas.frame import Frame

COMTRADE_SUFFIXES = (".cfg", ".cff")


class ComtradeError(SinewatchError, ValueError):
    """The file is not a COMTRADE record this reader can use."""


@dataclass
class ComtradeChannel:
    channel: str  # the sinewatch channel name
    name: str  # the channel id in the file
    unit: str | None
    sample_rate_hz: float
    t0_ns: int
    samples: np.ndarray  # float64, scaled (a * x + b)

    def blocks(self, block_size: int) -> Iterator[Block]:
        """The channel as consecutive Blocks of ``block_size`` samples (seq 0, 1, ...); the
        time of each block's first sample is t0 + round(i * 1e9 / rate)."""
        for seq, start in enumerate(range(0, len(self.samples), block_size)):
            t0 = self.t0_ns + round(start * 1e9 / self.sample_rate_hz)
            yield Block(self.channel, seq, t0, self.sample_rate_hz, self.samples[start : start + block_size], self.unit)


@dataclass
class ComtradeRecord:
    path: Path
    station: str
    rev_year: str
    data_format: str
    channels: list[ComtradeChannel]


def interleaved_blocks(record: ComtradeRecord, block_size: int) -> list[Block]:
    """Every channel's blocks in the order of their times (channels interleaved as sampled)."""
    items = [(b.t0_ns, i, b) for i, ch in enumerate(record.channels) for b in ch.blocks(block_size)]
    return [b for _, _, b in sorted(items, key=lambda item: (item[0], item[1]))]


def interleaved_frames(record: ComtradeRecord, block_size: int) -> list[tuple[str, Frame]]:
    """The record as multi-channel frames, in the order of their times: the analog channels
    sampled together (one rate segment: same rate, start and length) go in one frame of
    ``block_size`` samples each, named ``<first channel's prefix>.frame<k>`` with dots for
    slashes (one key chunk). Returns (frame name, Frame) pairs; seq 0, 1, ... per frame."""
    groups: dict[tuple[float, int, int], list[ComtradeChannel]] = {}
    for ch in record.channels:
        groups.setdefault((ch.sample_rate_hz, ch.t0_ns, len(ch.samples)), []).append(ch)
    items = []
    for k, ((fs, t0_ns, n), members) in enumerate(groups.items()):
        name = f"{members[0].channel.rsplit('/', 1)[0].replace('/', '.')}.frame{k}"
        names = tuple(ch.channel for ch in members)
        data = np.stack([ch.samples for ch in members], axis=1)
        for seq, start in enumerate(range(0, n, block_size)):
            t0 = t0_ns + round(start * 1e9 / fs)
            items.append((t0, k, name, Frame(names, seq, t0, fs, data[start : start + block_size])))
    items.sort(key=lambda item: (item[0], item[1]))
    return [(name, frame) for _, _, name, frame in items]


def is_comtrade(path: Path) -> bool:
    return path.suffix.lower() in COMTRADE_SUFFIXES


def _library() -> Any:
    try:
        import comtrade  # type: ignore[import-untyped,import-not-found,unused-ignore]
    except ImportError:
        raise ComtradeError(
            "COMTRADE: expected the comtrade package to be installed, got none "
            "(install the extra: pip install 'sinewatch[comtrade]')"
        ) from None
    return comtrade


_NOT_IN_NAME = re.compile(r"[^A-Za-z0-9_.\-]+")


def channel_part(text: str) -> str:
    """``text`` as one level of a channel name: other characters become '-'."""
    return _NOT_IN_NAME.sub("-", text.strip()).strip("-") or "_"


def read_comtrade(path: Path, prefix: str = "comtrade") -> ComtradeRecord:
    """Read a COMTRADE record (``.cfg`` with its ``.dat`` beside it, or a ``.cff``)."""
    if not is_comtrade(path):
        raise ComtradeError(f"{path}: expected a COMTRADE .cfg or .cff file, got a {path.suffix or 'suffixless'} file")
    if not path.is_file():
        raise ComtradeError(f"{path}: expected a COMTRADE file, got no such file")
    lib = _library()
    record = lib.Comtrade(use_numpy_arrays=True, use_double_precision=True)
    try:
        record.load(str(path), encoding=text_encoding(path))
    except FileNotFoundError as exc:
        raise ComtradeError(f"{path}: expected its data file {exc.filename}, got no such file") from None
    except Exception as exc:  # noqa: BLE001 (the reader raises ValueError, IndexError, struct.error, ...)
        raise ComtradeError(f"{path}: expected a COMTRADE record, got {type(exc).__name__}: {exc}") from None
    cfg = record.cfg
    if cfg.analog_count == 0:
        raise ComtradeError(f"{path}: expected at least one analog channel, got none")
    station = channel_part(cfg.station_name)
    time = np.asarray(record.time, dtype=np.float64)
    start = _epoch_ns(cfg.start_timestamp)
    segments = _segments(cfg, len(time), path)
    channels = []
    used: set[str] = set()
    for ch, values in zip(cfg.analog_channels, record.analog, strict=True):
        base = f"{channel_part(prefix)}/{station}/{channel_part(ch.name)}"
        while base in used:  # two channels of one name: number the later ones
            base += "_"
        used.add(base)
        data = np.asarray(values, dtype=np.float64)
        for k, (rate, first, stop) in enumerate(segments):
            name = base if len(segments) == 1 else f"{base}/seg{k + 1}"
            channels.append(
                ComtradeChannel(
                    channel=name,
                    name=ch.name.strip(),
                    unit=ch.uu.strip() or None,
                    sample_rate_hz=rate,
                    t0_ns=start + round(float(time[first]) * 1e9),
                    samples=data[first:stop],
                )
            )
    return ComtradeRecord(path, cfg.station_name.strip(), str(cfg.rev_year), str(cfg.ft).upper(), channels)


def text_encoding(path: Path) -> str:
    """The encoding of a record's text files (``.cfg`` and, beside it, ``.hdr`` and
    ``.inf``): UTF-8 (C37.111-2013 clause 6; a byte-order mark is skipped) when they all
    decode as UTF-8, else Latin-1, which older relays write (C37.111-1999 says ASCII and
    their names carry o-umlauts and micro signs) and which decodes any byte. A ``.cff``
    is read by the library as UTF-8 whatever this says."""
    texts = [path, *(path.with_suffix(s) for s in (".hdr", ".inf", ".HDR", ".INF"))]
    for p in texts:
        if p.is_file():
            try:
                p.read_bytes().decode("utf-8")
            except UnicodeDecodeError:
                return "latin-1"
    return "utf-8-sig"


def _segments(cfg: Any, n: int, path: Path) -> list[tuple[float, int, int]]:
    """(rate, first index, end index) of each sample-rate segment."""
    out = []
    first = 0
    for rate, endsamp in cfg.sample_rates:
        stop = min(int(endsamp), n)
        if float(rate) <= 0:
            raise ComtradeError(
                f"{path}: expected a sample rate (samp > 0), got samp = {rate} (timestamps only): "
                "sinewatch channels need a fixed rate"
            )
        if stop > first:
            out.append((float(rate), first, stop))
        first = stop
    if not out:
        raise ComtradeError(f"{path}: expected samples, got none")
    return out


def _epoch_ns(stamp: datetime) -> int:
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=UTC)
    delta = stamp - datetime(1970, 1, 1, tzinfo=UTC)
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1_000
