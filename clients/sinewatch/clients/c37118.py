"""A reader of IEEE C37.118.2 streams (a minimal phasor data concentrator over TCP).

    from sinewatch.clients.c37118 import C37118Reader

    with C37118Reader("127.0.0.1", 4712, id_code=7) as pmu:
        cfg = pmu.config()            # CFG-2
        pmu.start()                   # turn data frames on
        for row in pmu.rows(count=50):
            print(row["time_ns"], row["frequency_hz"], row["phasors"])

It reads any PMU that speaks C37.118.2 (sinewatch's own server or a real one: integer or
float formats, several PMUs per frame); ``sinewatch tail --c37118 HOST:PORT`` wraps it.
Frames are decoded by :mod:`sinewatch.schemas.c37118`.
"""

from __future__ import annotations

import socket
from collections.abc import Iterator
from types import TracebackType
from typing import Any

from sinewatch.schemas.c37118 import (
    Command,
    ConfigFrame,
    DataFrame,
    Frame,
    FrameError,
    FrameSplitter,
    FrameType,
    decode_config,
    decode_data,
    decode_frame,
    encode_command,
    time_ns,
)

DEFAULT_PORT = 4712  # the port C37.118.2 Annex names for TCP/UDP


def parse_host_port(text: str, default_port: int = DEFAULT_PORT) -> tuple[str, int]:
    """``HOST:PORT`` (or ``HOST``) to (host, port)."""
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, default_port
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"expected HOST:PORT with a port 1-65535, got {text!r}")
    return host.strip("[]"), int(port)


class C37118Reader:
    """One TCP connection to a PMU (or PDC): commands out, frames in."""

    def __init__(self, host: str, port: int = DEFAULT_PORT, *, id_code: int, timeout_s: float = 10.0) -> None:
        self.host, self.port, self.id_code = host, port, id_code
        self._sock = socket.create_connection((host, port), timeout=timeout_s)
        self._splitter = FrameSplitter()
        self._frames: list[bytes] = []
        self._held: list[Frame] = []  # frames read while waiting for another kind
        self.cfg: ConfigFrame | None = None
        self.rejected = 0  # frames that failed their CRC or could not be decoded

    # ---- commands -------------------------------------------------------------------------------
    def command(self, cmd: int) -> None:
        self._sock.sendall(encode_command(self.id_code, cmd))

    def start(self, *, confirm: bool = False) -> None:
        """Turn data frames on (a configuration must have been read: :meth:`config`).

        With ``confirm``, also ask for the header and wait for it: a PMU handles one
        connection's commands in order, so once the header is here data is on (data frames
        that came first are kept). Not every PMU sends a header: off by default."""
        self.command(Command.DATA_ON)
        if confirm:
            self.command(Command.SEND_HDR)
            self.next_frame(FrameType.HEADER, keep_others=True)

    def stop(self) -> None:
        self.command(Command.DATA_OFF)

    def config(self, version: int = 2) -> ConfigFrame:
        """Ask for CFG-1, -2 or -3 and return it (CFG-2 is also kept to decode data frames)."""
        cmd = {1: Command.SEND_CFG1, 2: Command.SEND_CFG2, 3: Command.SEND_CFG3}[version]
        want = {1: FrameType.CFG1, 2: FrameType.CFG2, 3: FrameType.CFG3}[version]
        self.command(cmd)
        frame = self.next_frame(want)
        cfg = decode_config(frame)
        if version == 2 or self.cfg is None:
            self.cfg = cfg
        return cfg

    def header(self) -> str:
        self.command(Command.SEND_HDR)
        return self.next_frame(FrameType.HEADER).body.decode("ascii", "replace")

    # ---- frames ---------------------------------------------------------------------------------
    def next_frame(self, frame_type: FrameType | None = None, *, keep_others: bool = False) -> Frame:
        """The next frame that passes its CRC (of ``frame_type``; others are skipped, or kept
        for later calls with ``keep_others``)."""
        for i, held in enumerate(self._held):
            if frame_type is None or held.frame_type is frame_type:
                return self._held.pop(i)
        while True:
            while not self._frames:
                data = self._sock.recv(65536)
                if not data:
                    raise ConnectionError(f"{self.host}:{self.port} closed the connection")
                self._frames += self._splitter.feed(data)
            raw = self._frames.pop(0)
            try:
                frame = decode_frame(raw)
            except FrameError:
                self.rejected += 1
                continue
            if frame_type is None or frame.frame_type is frame_type:
                return frame
            if keep_others:
                self._held.append(frame)

    def data_frames(self, count: int | None = None) -> Iterator[DataFrame]:
        """Data frames, decoded with the last configuration read."""
        if self.cfg is None:
            raise RuntimeError("data frames: expected a configuration first (call config())")
        n = 0
        while count is None or n < count:
            frame = self.next_frame(FrameType.DATA)
            try:
                yield decode_data(frame, self.cfg)
            except FrameError:
                self.rejected += 1
                continue
            n += 1

    def rows(self, count: int | None = None) -> Iterator[dict[str, Any]]:
        """One dict per PMU per data frame (see :func:`data_rows`)."""
        assert self.cfg is not None or count == 0
        for frame in self.data_frames(count):
            assert self.cfg is not None
            yield from data_rows(self.cfg, frame)

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> C37118Reader:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def data_rows(cfg: ConfigFrame, frame: DataFrame) -> list[dict[str, Any]]:
    """A data frame as plain values: per PMU its station, ID code, time (ns since the epoch),
    STAT (and its data error, sync and data-modified bits), phasors by name (magnitude and
    angle, or real and imaginary as the format says), FREQ (Hz) and DFREQ (Hz/s)."""
    t = time_ns(frame.soc, frame.fracsec & 0xFFFFFF, cfg.time_base)
    out = []
    for p, d in zip(cfg.pmus, frame.pmus, strict=True):
        out.append(
            {
                "station": p.station,
                "id_code": p.id_code,
                "time_ns": t,
                "time_quality": (frame.fracsec >> 24) & 0x0F,
                "stat": d.stat,
                "data_error": int(d.data_error),
                "in_sync": d.in_sync,
                "data_modified": d.data_modified,
                "polar": p.format.polar,
                "phasors": {name: list(ph) for name, ph in zip(p.phasor_names, d.phasors, strict=True)},
                "frequency_hz": d.freq_hz,
                "rocof_hz_per_s": d.dfreq_hz_per_s,
                **({"analogs": dict(zip(p.analog_names, d.analogs, strict=True))} if d.analogs else {}),
                **({"digitals": d.digitals} if d.digitals else {}),
            }
        )
    return out


__all__ = ["DEFAULT_PORT", "C37118Reader", "data_rows", "parse_host_port"]
