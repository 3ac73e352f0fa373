"""Publishing SampleBlocks and multi-channel SampleFrames."""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
import zenoh
import zenoh.ext

from sinewatch.schemas import codec
from sinewatch.schemas import frame as frames
from sinewatch.schemas.codec import Block
from sinewatch.schemas.frame import Frame

DEFAULT_HISTORY_BLOCKS = 1024
HEARTBEAT_S = 0.5


class _ChannelPublisher:
    """One channel's Zenoh publishers: an AdvancedPublisher that puts the blocks and keeps
    the last ``history`` of them in a cache (with sample-miss detection, so a subscriber
    that lost some, e.g. while a router restarted, asks for them again), and a plain
    publisher on the same key that only watches whether any subscriber matches."""

    def __init__(self, session: zenoh.Session, key: str, encoding: str, history: int) -> None:
        self.key = key
        self.data = zenoh.ext.declare_advanced_publisher(
            session,
            key,
            encoding=zenoh.Encoding(encoding),
            congestion_control=zenoh.CongestionControl.BLOCK,
            cache=zenoh.ext.CacheConfig(history),
            sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=HEARTBEAT_S, sporadic_heartbeat=None),
            publisher_detection=True,
        )
        self.watch = session.declare_publisher(key, encoding=zenoh.Encoding(encoding))

    @property
    def matching(self) -> bool:
        # zenoh 1.10 returns a MatchingStatus here, though its stub says bool
        return bool(self.watch.matching_status.matching)  # type: ignore[attr-defined]

    def undeclare(self) -> None:
        self.data.undeclare()
        self.watch.undeclare()


class BlockPublisher:
    """Publishes blocks of samples on ``{prefix}/{channel}``.

    Sequence numbers and first-sample timestamps are kept per channel (both can be given
    explicitly). Publishers use ``CongestionControl.BLOCK``: when the daemon cannot keep
    up, ``publish`` waits instead of silently dropping (Zenoh's default DROP lost 3-54 %
    of messages under load here).

    Delivery through outages: each channel's last ``history`` blocks stay in a Zenoh cache,
    and a daemon subscribing with recovery (its default) fetches the blocks it missed, e.g.
    while a Zenoh router restarted. ``unmatched`` counts blocks published while no subscriber
    matched their key: they were not delivered then, and reach the daemon only if it
    recovers them from the cache (the newest ``history`` per channel); past that the daemon
    flags the gap. Blocks put between a link failing and Zenoh noticing it are not counted
    (nothing tells the publisher yet); they are in the cache all the same.
    """

    def __init__(
        self,
        session: zenoh.Session,
        *,
        prefix: str = "sinewatch/in",
        encoding: str = "binary",
        dtype: str = "float32",
        t0_ns: int | None = None,
        history: int = DEFAULT_HISTORY_BLOCKS,
    ) -> None:
        if encoding not in ("binary", "json"):
            raise ValueError(f"encoding: expected 'binary' or 'json', got {encoding!r}")
        if history < 1:
            raise ValueError(f"history: expected at least 1 block, got {history}")
        self.session = session
        self.prefix = prefix.rstrip("/")
        self.encoding = encoding
        self.dtype = dtype
        self.history = history
        self._start_ns = time.time_ns() if t0_ns is None else t0_ns
        self._publishers: dict[str, _ChannelPublisher] = {}
        self._frame_publishers: dict[str, _ChannelPublisher] = {}  # by frame name
        self._next_seq: dict[str, int] = {}
        self._next_t0: dict[str, int] = {}
        self.published = 0
        self.unmatched = 0

    def key(self, channel: str) -> str:
        return f"{self.prefix}/{channel}"

    def _publisher(self, channel: str) -> _ChannelPublisher:
        return self._declared(self._publishers, channel, codec.BLOCK_BINARY_ENCODING, codec.BLOCK_JSON_ENCODING)

    def _frame_publisher(self, name: str) -> _ChannelPublisher:
        return self._declared(self._frame_publishers, name, frames.FRAME_BINARY_ENCODING, frames.FRAME_JSON_ENCODING)

    def _declared(
        self, publishers: dict[str, _ChannelPublisher], name: str, binary: str, json: str
    ) -> _ChannelPublisher:
        """``name``'s publisher on ``{prefix}/{name}``, declared on first use."""
        pub = publishers.get(name)
        if pub is None:
            encoding = binary if self.encoding == "binary" else json
            pub = publishers[name] = _ChannelPublisher(self.session, self.key(name), encoding, self.history)
        return pub

    def _put(self, pub: _ChannelPublisher, payload: bytes, encoding: str | None) -> None:
        if not pub.matching:
            self.unmatched += 1
        if encoding is None:
            pub.data.put(payload)
        else:
            pub.data.put(payload, encoding=zenoh.Encoding(encoding))
        self.published += 1

    def _advance(self, slot: str, seq: int | None, t0_ns: int | None, n: int, sample_rate_hz: float) -> tuple[int, int]:
        """The seq and first-sample time of ``slot``'s next message of ``n`` samples (given ones
        win), and the counters moved on past it."""
        seq = self._next_seq.get(slot, 0) if seq is None else seq
        t0 = self._next_t0.get(slot, self._start_ns) if t0_ns is None else t0_ns
        self._next_seq[slot] = seq + 1
        self._next_t0[slot] = t0 + round(n * 1e9 / sample_rate_hz)
        return seq, t0

    def wait_for_subscriber(self, channel: str, timeout: float = 10.0) -> bool:
        """Block until something (the daemon) subscribes to this channel's key."""
        return self.wait_for_matching(channel, True, timeout)

    def wait_for_matching(self, channel: str, matching: bool, timeout: float = 10.0) -> bool:
        """Block until Zenoh says a subscriber does (or no longer does) match this channel's
        key; False on timeout. A dead link is noticed when Zenoh sees it drop, not at once."""
        return self._wait(self._publisher(channel), matching, timeout)

    @staticmethod
    def _wait(pub: _ChannelPublisher, matching: bool, timeout: float) -> bool:
        reached = threading.Event()

        def on_status(status: zenoh.MatchingStatus) -> None:
            if status.matching == matching:
                reached.set()

        listener = pub.watch.declare_matching_listener(on_status)
        try:
            return pub.matching == matching or reached.wait(timeout)
        finally:
            listener.undeclare()

    def block(
        self,
        channel: str,
        samples: np.ndarray,
        sample_rate_hz: float,
        *,
        seq: int | None = None,
        t0_ns: int | None = None,
        unit: str | None = None,
    ) -> Block:
        """The Block that ``publish`` would send (advances the channel's seq and time)."""
        samples = np.asarray(samples)
        seq, t0 = self._advance(channel, seq, t0_ns, samples.shape[0], sample_rate_hz)
        return Block(channel, seq, t0, float(sample_rate_hz), samples, unit)

    def encode(self, block: Block) -> bytes:
        if self.encoding == "binary":
            return codec.encode_block_binary(block, self.dtype)
        return codec.encode_block_json(block)

    def publish(self, channel: str, samples: np.ndarray, sample_rate_hz: float, **kw: Any) -> Block:
        block = self.block(channel, samples, sample_rate_hz, **kw)
        self.publish_raw(channel, self.encode(block))
        return block

    def publish_raw(self, channel: str, payload: bytes, encoding: str | None = None) -> None:
        """Send a payload as is, optionally with another Zenoh encoding than the
        publisher's (tests use it for hostile input)."""
        self._put(self._publisher(channel), payload, encoding)

    # ---- multi-channel frames ------------------------------------------------------------
    def frame(
        self,
        name: str,
        channels: list[str] | tuple[str, ...],
        samples: np.ndarray,
        sample_rate_hz: float,
        *,
        seq: int | None = None,
        t0_ns: int | None = None,
        time_quality: int = 0,
    ) -> Frame:
        """The Frame that ``publish_frame`` would send (advances the frame's seq and time).
        ``samples`` is (n, C): column c is ``channels[c]``; ``time_quality`` the byte of
        :func:`sinewatch.schemas.codec.time_quality_byte` (0: not stated, a version 1 frame)."""
        samples = np.asarray(samples)
        if samples.ndim != 2 or samples.shape[1] != len(channels):
            raise ValueError(
                f"samples: expected shape (n, {len(channels)}) (one column per channel), got {samples.shape}"
            )
        slot = "\n" + name  # a frame's own counters: no channel name holds a newline
        seq, t0 = self._advance(slot, seq, t0_ns, samples.shape[0], sample_rate_hz)
        return Frame(tuple(channels), seq, t0, float(sample_rate_hz), samples, time_quality)

    def encode_frame(self, frame: Frame) -> bytes:
        if self.encoding == "binary":
            return frames.encode_frame_binary(frame, self.dtype)
        return frames.encode_frame_json(frame)

    def frame_encoding(self, frame: Frame) -> str:
        """The Zenoh encoding ``encode_frame(frame)`` is sent with: format version 2 with a
        time quality, else 1 (what the frame publisher is declared with)."""
        return frames.frame_encoding(frame, self.encoding == "binary")

    def publish_frame(
        self, name: str, channels: list[str] | tuple[str, ...], samples: np.ndarray, sample_rate_hz: float, **kw: Any
    ) -> Frame:
        """Publish C channels sampled at the same instants as one SampleFrame on
        ``{prefix}/{name}``; each channel's key is ``{prefix}/{channel}`` for the daemon's
        rules, estimates and errors, as if it had been published alone."""
        frame = self.frame(name, channels, samples, sample_rate_hz, **kw)
        encoding = None if frame.version == 1 else self.frame_encoding(frame)
        self.publish_frame_raw(name, self.encode_frame(frame), encoding)
        return frame

    def publish_frame_raw(self, name: str, payload: bytes, encoding: str | None = None) -> None:
        self._put(self._frame_publisher(name), payload, encoding)

    def wait_for_frame_subscriber(self, name: str, timeout: float = 10.0) -> bool:
        """Block until something (the daemon) subscribes to this frame's key."""
        return self._wait(self._frame_publisher(name), True, timeout)

    def close(self) -> None:
        for pub in (*self._publishers.values(), *self._frame_publishers.values()):
            pub.undeclare()
        self._publishers.clear()
        self._frame_publishers.clear()
