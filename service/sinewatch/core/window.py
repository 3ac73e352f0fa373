"""Windows and channel filters over a recording: what ``replay``, ``export``, ``compare``
and ``plot`` take as ``--start``/``--end`` and ``--channels``.

Times are a recording's log times (the MCAP ``log_time`` of each message: when the daemon
received an input; its estimates carry the same log time; Foxglove's timeline). A window
is half-open, ``[start, end)``; either end may be left open. A time is written as

* ``+2.5s``, ``+2500ms``, ``+2500000us``, ``+2500000000ns``, ``+1.5min`` or ``+2.5``
  (seconds): relative to the recording's start, the log time of its first message (for
  several files of one run, the first file's; for ``compare`` and ``plot``, the first
  recording's, since a re-run of some channels starts at their first input);
* ``2026-11-26T16:57:03.25Z`` (ISO 8601; without a zone, UTC): absolute;
* ``1764176223250000000``: absolute, integer ns since the Unix epoch.

A channel filter is a list of globs (``fnmatch``, case-sensitive: ``*`` also matches
``/``) matched against channel names, e.g. ``demo/demo-faulty-sensor`` or ``'demo/*'``;
an empty list selects every channel.
"""

from __future__ import annotations

import fnmatch
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from decimal import Decimal

from sinewatch.schemas.errors import SinewatchError

_UNITS_NS = {"ns": 1, "us": 1_000, "ms": 1_000_000, "s": 1_000_000_000, "min": 60_000_000_000, "": 1_000_000_000}
_RELATIVE = re.compile(r"^\+\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*(ns|us|ms|s|min|)$")
_EPOCH_NS = re.compile(r"^[0-9]{10,}$")  # ns since the epoch: 10+ digits (1e9 ns is 1970-01-01T00:00:01)


class WindowError(SinewatchError, ValueError):
    """A window or channel filter that cannot be understood or selects nothing."""


@dataclass(frozen=True)
class TimeSpec:
    """A time as written on the command line: ``relative`` ns after the recording's start,
    or ``absolute`` ns since the epoch (exactly one is set)."""

    text: str
    relative_ns: int | None = None
    absolute_ns: int | None = None

    def resolve(self, origin_ns: int) -> int:
        return origin_ns + self.relative_ns if self.relative_ns is not None else int(self.absolute_ns or 0)


def parse_time(text: str, option: str = "--start") -> TimeSpec:
    """A :class:`TimeSpec` from ``text`` (syntax in the module docstring)."""
    s = text.strip()
    m = _RELATIVE.match(s)
    if m:
        exact = Decimal(m.group(1)) * _UNITS_NS[m.group(2)]  # the regex admits only decimal numbers
        return TimeSpec(text, relative_ns=int(exact.to_integral_value()))
    if _EPOCH_NS.match(s):
        return TimeSpec(text, absolute_ns=int(s))
    try:
        t = datetime.fromisoformat(s)
    except ValueError:
        raise WindowError(
            f"{option}: expected +SECONDS[s|ms|us|ns|min] (after the recording's start), an ISO 8601 time "
            f"or integer ns since the epoch, got {text!r}"
        ) from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    delta = t - datetime(1970, 1, 1, tzinfo=UTC)
    ns = (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1_000
    return TimeSpec(text, absolute_ns=ns)


@dataclass
class Window:
    """``[start, end)`` in log time, resolved against the recording's start at its first
    message (:meth:`anchor`)."""

    start: TimeSpec | None = None
    end: TimeSpec | None = None
    origin_ns: int | None = None
    start_ns: int | None = None  # resolved; None: from the first message
    end_ns: int | None = None  # resolved; None: to the last

    @classmethod
    def parse(cls, start: str | None, end: str | None) -> Window:
        w = cls(
            None if start is None else parse_time(start, "--start"), None if end is None else parse_time(end, "--end")
        )
        if w.start is not None and w.end is not None:
            both_relative = w.start.relative_ns is not None and w.end.relative_ns is not None
            both_absolute = w.start.absolute_ns is not None and w.end.absolute_ns is not None
            if (both_relative or both_absolute) and w.end.resolve(0) <= w.start.resolve(0):
                raise WindowError(f"--end: expected a time after --start {start!r}, got {end!r}")
        return w

    @property
    def bounded(self) -> bool:
        return self.start is not None or self.end is not None

    def anchor(self, origin_ns: int) -> None:
        """Resolve the window against the recording's first log time (once)."""
        if self.origin_ns is not None:
            return
        self.origin_ns = origin_ns
        self.start_ns = None if self.start is None else self.start.resolve(origin_ns)
        self.end_ns = None if self.end is None else self.end.resolve(origin_ns)

    def before(self, log_time_ns: int) -> bool:
        return self.start_ns is not None and log_time_ns < self.start_ns

    def after(self, log_time_ns: int) -> bool:
        return self.end_ns is not None and log_time_ns >= self.end_ns

    def contains(self, log_time_ns: int) -> bool:
        return not self.before(log_time_ns) and not self.after(log_time_ns)

    def describe(self) -> str:
        """The window in words, for titles and reports."""
        if not self.bounded:
            return "whole recording"
        parts = []
        for name, spec, ns in (("from", self.start, self.start_ns), ("to", self.end, self.end_ns)):
            if spec is None:
                continue
            if ns is not None and self.origin_ns is not None:
                parts.append(f"{name} +{(ns - self.origin_ns) / 1e9:.3f} s")
            else:
                parts.append(f"{name} {spec.text}")
        return " ".join(parts)


@dataclass
class ChannelFilter:
    """Channel-name globs; empty selects every channel. Topics (MCAP channel names, Zenoh
    keys) are selected when they end in ``/<a selected channel>``."""

    globs: list[str] = field(default_factory=list)
    _names: dict[str, bool] = field(default_factory=dict, repr=False)
    _topics: dict[str, bool] = field(default_factory=dict, repr=False)

    @classmethod
    def of(cls, globs: str | Iterable[str] | None) -> ChannelFilter:
        if globs is None:
            return cls()
        items = [globs] if isinstance(globs, str) else list(globs)
        return cls([g for g in items if g not in ("", "*")] if "*" not in items else [])

    @property
    def everything(self) -> bool:
        return not self.globs

    def matches(self, channel: str) -> bool:
        hit = self._names.get(channel)
        if hit is None:
            hit = self._names[channel] = self.everything or any(fnmatch.fnmatchcase(channel, g) for g in self.globs)
        return hit

    def matches_topic(self, topic: str) -> bool:
        """True when some tail of ``topic`` after a ``/`` is a selected channel name."""
        hit = self._topics.get(topic)
        if hit is None:
            hit = self.everything or any(self.matches(topic[i + 1 :]) for i, c in enumerate(topic) if c == "/")
            self._topics[topic] = hit
        return hit

    def describe(self) -> str:
        return "every channel" if self.everything else ", ".join(self.globs)


__all__ = ["ChannelFilter", "TimeSpec", "Window", "WindowError", "parse_time"]
