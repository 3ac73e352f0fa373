"""The C37.118.2 server on loopback: idle TCP connections cannot hold every client slot, and
a station whose inputs stop keeps sending data frames at its reporting rate, flagged invalid
in STAT (data error 11, "PMU error, do not use values"), until its estimates come back."""

from __future__ import annotations

import asyncio
import json
import math

from conftest import TIMEOUT
from test_c37118_station import T, estimate

from sinewatch.outputs.c37118_server import C37118Server
from sinewatch.schemas.c37118 import Command, DataError, decode_config, decode_data, decode_frame, encode_command
from sinewatch.schemas.config import C37118Section, C37118Station

ID = 7
RATE = 50
PERIOD_NS = 10**9 // RATE


async def read_frame(reader: asyncio.StreamReader) -> bytes:
    head = await asyncio.wait_for(reader.readexactly(4), TIMEOUT)
    return head + await asyncio.wait_for(reader.readexactly(int.from_bytes(head[2:4], "big") - 4), TIMEOUT)


def estimate_payload(t_ns: int) -> bytes:
    return json.dumps(estimate("a", t_ns), separators=(",", ":")).encode()  # as the daemon writes it


def frame_time_ns(f) -> int:
    return f.soc * 10**9 + (f.fracsec & 0xFFFFFF) * 1000


def section(**kw) -> C37118Section:
    return C37118Section(
        enabled=True,
        port=0,
        stations=[C37118Station(id_code=ID, name="L", channels=["a"], data_rate=RATE, max_skew_s=0.05)],
        **kw,
    )


def test_idle_connections_are_closed_and_a_pdc_then_connects():
    async def main():
        server = C37118Server(section(max_clients=2, idle_timeout_s=0.3))
        await server.start()
        try:
            idle = [await asyncio.open_connection("127.0.0.1", server.port) for _ in range(2)]
            # they hold both slots: a PDC now is refused (closed at once)
            r, w = await asyncio.open_connection("127.0.0.1", server.port)
            assert await asyncio.wait_for(r.read(), TIMEOUT) == b""
            w.close()
            # the idle ones are closed by the server: they read the end of the stream
            for r, _w in idle:
                assert await asyncio.wait_for(r.read(), TIMEOUT) == b""
            # and a PDC that asks gets its answer
            r, w = await asyncio.open_connection("127.0.0.1", server.port)
            w.write(encode_command(ID, Command.SEND_CFG2))
            cfg = decode_config(decode_frame(await read_frame(r)))
            w.close()
            for _r, iw in idle:
                iw.close()
            return cfg, dict(server.rejected)
        finally:
            await server.stop()

    cfg, rejected = asyncio.run(main())
    assert cfg.pmus[0].station == "L"
    assert rejected == {"client_limit": 1, "idle": 2}


def test_stopped_inputs_keep_the_reporting_rate_with_stat_invalid():
    async def main():
        server = C37118Server(section())
        await server.start()
        try:
            r, w = await asyncio.open_connection("127.0.0.1", server.port)
            w.write(encode_command(ID, Command.DATA_ON) + encode_command(ID, Command.SEND_CFG2))
            cfg = decode_config(decode_frame(await read_frame(r)))  # DATA_ON was handled before
            for k in range(5):
                server.on_estimate("sinewatch/est/a", estimate_payload(T + k * PERIOD_NS), 0)
            good = [decode_data(decode_frame(await read_frame(r)), cfg) for _ in range(5)]
            # the inputs stop: the frames go on
            stopped = [decode_data(decode_frame(await read_frame(r)), cfg) for _ in range(10)]
            # the inputs come back (later in data time than any frame sent): good frames again
            back_t = frame_time_ns(stopped[-1]) + 100 * PERIOD_NS
            server.on_estimate("sinewatch/est/a", estimate_payload(back_t), 0)
            while True:
                f = decode_data(decode_frame(await read_frame(r)), cfg)
                if frame_time_ns(f) == back_t:
                    break
            w.close()
            return good, stopped, f
        finally:
            await server.stop()

    good, stopped, back = asyncio.run(main())
    assert [frame_time_ns(f) for f in good] == [T + k * PERIOD_NS for k in range(5)]
    assert all(f.pmus[0].stat >> 14 == DataError.GOOD for f in good)
    # on the same grid, one period apart, no frame missing
    assert [frame_time_ns(f) for f in stopped] == [T + k * PERIOD_NS for k in range(5, 15)]
    for f in stopped:
        assert f.pmus[0].stat >> 14 == DataError.PMU_ERROR
        assert all(math.isnan(v) for v in f.pmus[0].phasors[0])
    assert back.pmus[0].stat >> 14 == DataError.GOOD
