"""sinewatch as a PMU, end to end on loopback: ``sinewatch serve --c37118 PORT`` with a
three-channel station, C37.118.1-style signals fed over real Zenoh, an independent
C37.118.2 client from PyPI (pyc37's command frames, pymu's parsing of CFG-2 and of the
data frames) and ``sinewatch tail --c37118`` both reading; every data frame's phasors,
FREQ and DFREQ equal the Estimates published on Zenoh at the same timestamps (to float32
rounding), 12 s of frames without a missing one. A client that connects, turns data on and
stops reading costs the daemon nothing (every estimate still published, the other client
still gets every frame) and its dropped frames are counted; malformed command frames are
rejected with a log line and a count, and the server goes on answering."""

from __future__ import annotations

import collections.abc  # pyc37 refers to collections.abc without importing it
import json
import signal
import socket
import struct
import subprocess
import threading
from typing import Any

import numpy as np
import pytest
from conftest import TIMEOUT, make_config, run_daemon, sinewatch, take

from sinewatch.clients import BlockPublisher, connect, subscribe_estimates, subscribe_status
from sinewatch.clients.c37118 import C37118Reader
from sinewatch.clients.session import free_loopback_port
from sinewatch.estimators import create
from sinewatch.scenarios import get as get_scenario
from sinewatch.schemas.c37118 import (
    Command,
    DataError,
    FrameSplitter,
    crc_ccitt,
    decode_frame,
    encode_command,
)
from sinewatch.schemas.codec import Block, encode_block_binary
from sinewatch.schemas.config import C37118Section, C37118Station, EstimatorRule, RecordingSection

pyc37 = pytest.importorskip("pyc37.frame")  # command frames (pymu's need a PyCRC that PyPI no longer has)
pymu_cfg = pytest.importorskip("pymu.pmuConfigFrame")
pymu_data = pytest.importorskip("pymu.pmuDataFrame")

assert collections.abc
T0_NS = 1_700_000_000 * 10**9 + 7_300_000  # off the 20 ms grid
BLOCK = 1000  # 0.1 s at 10 kHz
ID = 7
CHANNELS = ["pmu/pa", "pmu/pb", "pmu/pc"]
SCENARIOS = ["c37-50hz-ramp-up", "c37-50hz-pm-2hz", "c37-50hz-am-2hz"]  # a 1 Hz/s ramp, PM, AM
PARAMS = {"nominal_frequency_hz": 50, "reporting_rate_hz": 50}


def f32(v: float) -> float:
    return struct.unpack(">f", struct.pack(">f", v))[0]


def station_blocks(seconds: float = 12.0) -> list[list[Block]]:
    """Per channel, its blocks: three C37.118.1 test signals, 10 kHz, on one time base."""
    out = []
    for channel, name in zip(CHANNELS, SCENARIOS, strict=True):
        sc = get_scenario(name, duration_s=seconds)
        x, _ = sc.generate(seed=0)
        fs = sc.sample_rate_hz
        out.append(
            [
                Block(channel, i, T0_NS + round(i * BLOCK * 1e9 / fs), fs, x[i * BLOCK : (i + 1) * BLOCK])
                for i in range(len(x) // BLOCK)
            ]
        )
    return out


def report_times(blocks: list[Block]) -> list[int]:
    """The report times the pmu estimator gives for these blocks (run directly)."""
    est = create("pmu", blocks[0].sample_rate_hz, **PARAMS)
    times: list[int] = []
    for blk in blocks:
        rep = est.update(blk.samples, last_only=True, t0_ns=blk.t0_ns).reports
        if rep is not None:
            times += rep.timestamps_ns()
    return times


def publish_interleaved(pub: BlockPublisher, per_channel: list[list[Block]]) -> None:
    for i in range(len(per_channel[0])):
        for blocks in per_channel:
            pub.publish_raw(blocks[i].channel, encode_block_binary(blocks[i], "float64"))


def read_frame(f: Any) -> bytes:
    """One whole frame from a socket file (SYNC and FRAMESIZE first, then the rest)."""
    head = f.read(4)
    assert len(head) == 4, "connection closed"
    return head + f.read(int.from_bytes(head[2:4], "big") - 4)


def write_config(tmp_path, zenoh_port: int) -> str:
    path = tmp_path / "pmu.toml"
    path.write_text(
        f"""
daemon_id = "pmu-test"
status_interval_s = 0.2
[zenoh]
listen = ["tcp/127.0.0.1:{zenoh_port}"]
[recording]
enabled = false
[[rules]]
match = "sinewatch/in/pmu/**"
estimator = "pmu"
params = {{ nominal_frequency_hz = 50, reporting_rate_hz = 50 }}
[[c37118.stations]]
id_code = {ID}
name = "SINEWATCH A"
channels = {json.dumps(CHANNELS)}
data_rate = 50
time_synchronised = true
"""
    )
    return str(path)


def test_serve_c37118_frames_equal_the_zenoh_estimates(tmp_path):
    per_channel = station_blocks(12.0)
    times = report_times(per_channel[0])
    assert len(times) >= 500  # at least 10 s of frames at 50 frames/s
    zport, cport = free_loopback_port(), free_loopback_port()
    serve = subprocess.Popen(
        sinewatch("serve", "--config", write_config(tmp_path, zport), "--c37118", str(cport)),
        stderr=subprocess.PIPE,
        text=True,
    )
    tail = None
    try:
        assert serve.stderr is not None
        for line in serve.stderr:  # the server logs its port once it listens
            if "C37.118.2 server on" in line:
                assert f"127.0.0.1:{cport}" in line and "SINEWATCH A (ID 7, 3 channel(s))" in line
                break
        # the independent client: pyc37's command frames, pymu's parsers, over a plain socket
        pdc = socket.create_connection(("127.0.0.1", cport), timeout=TIMEOUT)
        f = pdc.makefile("rb")
        pdc.sendall(pyc37.CommandFrame(ID, "cfg2").convert2bytes())
        cfg = pymu_cfg.ConfigFrame(read_frame(f).hex().upper())
        cfg.finishParsing()
        st = cfg.stations[0]
        assert (cfg.num_pmu, st.stn.strip(), st.idcode_data, cfg.datarate) == (1, "SINEWATCH A", ID, 50)
        assert [c.strip() for c in st.channels] == ["pa", "pb", "pc"]
        assert cfg.time_base.baseDecStr == 1_000_000
        pdc.sendall(pyc37.CommandFrame(ID, "start").convert2bytes())
        # and sinewatch's own reader, as a user runs it
        tail = subprocess.Popen(
            sinewatch("tail", "--c37118", f"127.0.0.1:{cport}", "--id-code", str(ID), "--json", "--count", "5"),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        frames: list[bytes] = []
        reader = threading.Thread(target=lambda: frames.extend(read_frame(f) for _ in times))
        with connect([f"tcp/127.0.0.1:{zport}"]) as s:
            est = subscribe_estimates(s, "sinewatch/est/pmu/**")
            status = subscribe_status(s)
            # both clients have turned data on (the daemon's Status says so) before anything is fed
            while (msg := status.get(timeout=TIMEOUT)) is not None:
                clients = msg["c37118"]["clients"]
                if len(clients) == 2 and all(c["streaming"] == [ID] for c in clients):
                    break
            assert msg is not None
            reader.start()
            pub = BlockPublisher(s)
            assert pub.wait_for_subscriber(CHANNELS[0], TIMEOUT)
            publish_interleaved(pub, per_channel)
            estimates = take(est, 3 * len(times))
            reader.join(TIMEOUT * 3)
            # the first Status that counts every frame read (one queued before them says fewer)
            while (last_status := status.get(timeout=TIMEOUT)) is not None and last_status["c37118"][
                "frames_built"
            ] < len(times):
                pass
        tail_out, tail_err = tail.communicate(timeout=60)
    finally:
        serve.send_signal(signal.SIGINT)
        _, err = serve.communicate(timeout=60)
        if tail is not None and tail.poll() is None:
            tail.kill()
    assert serve.returncode == 0, err
    assert len(estimates) == 3 * len(times) and len(frames) == len(times)
    by_time: dict[int, dict[str, dict[str, Any]]] = {}
    for e in estimates:
        by_time.setdefault(e["timestamp_ns"], {})[e["channel"]] = e
    assert sorted(by_time) == times
    got_times = []
    for raw in frames:
        frame = pymu_data.DataFrame(raw.hex().upper(), cfg)
        t_ns = frame.soc.secCount * 10**9 + frame.fracsec * 1000  # TIME_BASE 1e6: microseconds
        got_times.append(t_ns)
        ests = by_time[t_ns]
        pmu = frame.pmus[0]
        for ph, ch in zip(pmu.phasors, CHANNELS, strict=True):
            extras = ests[ch]["diagnostics"]["extras"]
            assert ph.mag == f32(extras["synchrophasor_magnitude"])
            assert ph.rad == f32(extras["synchrophasor_angle_rad"])
        a = ests[CHANNELS[0]]
        assert pmu.freq == f32(a["frequency_hz"][0])
        assert pmu.dfreq * 100 == pytest.approx(f32(a["rocof_hz_per_s"][0]), rel=1e-12, abs=1e-12)  # pymu: / 100
        good = all(e["diagnostics"]["valid"] and not e["diagnostics"]["gap"] for e in ests.values())
        assert pmu.stat.dataError == ("GOOD" if good else "PMUERROR_NOVALUES")
        assert pmu.stat.pmuSync != "NOT_IN_SYNC" and pmu.stat.dataModified == "OTHER"
    # every report time, in order, none missing: 12 s of frames
    assert got_times == times and set(np.diff(got_times)) == {20_000_000}
    assert np.ptp(got_times) >= 10 * 10**9
    # FREQ and DFREQ are the first channel's: the ramp's 1 Hz/s in the middle of it
    mid = [
        pymu_data.DataFrame(raw.hex().upper(), cfg).pmus[0].dfreq * 100
        for raw, t in zip(frames, got_times, strict=True)
        if T0_NS + 3 * 10**9 < t < T0_NS + 9 * 10**9
    ]
    assert len(mid) == 300 and abs(np.median(mid) - 1.0) < 0.01
    assert last_status is not None and last_status["c37118"]["frames_built"] == len(times)
    assert last_status["c37118"]["frames_dropped"] == 0 and last_status["c37118"]["commands_rejected"] == 0
    # sinewatch tail --c37118: the station from CFG-2, then five frames as JSON
    assert tail.returncode == 0, tail_err
    assert "station 'SINEWATCH A' ID 7, 50 frames/s, 50 Hz, phasors pa, pb, pc" in tail_err
    rows = [json.loads(line) for line in tail_out.splitlines()]
    assert len(rows) == 5
    for row in rows:
        ests = by_time[row["time_ns"]]
        assert row["frequency_hz"] == f32(ests[CHANNELS[0]]["frequency_hz"][0])
        assert row["phasors"]["pb"] == [
            f32(ests["pmu/pb"]["diagnostics"]["extras"][k])
            for k in ("synchrophasor_magnitude", "synchrophasor_angle_rad")
        ]
        assert row["in_sync"] and row["time_quality"] == 0


def daemon_config(tmp_path, max_skew_s: float = 0.5, **section):
    station = C37118Station(id_code=ID, name="SINEWATCH A", channels=CHANNELS, data_rate=50, max_skew_s=max_skew_s)
    c37 = C37118Section(enabled=True, port=0, stations=[station], **section)
    return make_config(
        tmp_path,
        rules=[EstimatorRule(match="sinewatch/in/pmu/**", estimator="pmu", params=PARAMS)],
        recording=RecordingSection(enabled=False),
        c37118=c37,
    )


def test_a_stalled_client_costs_the_daemon_nothing_and_its_drops_are_counted(tmp_path):
    per_channel = station_blocks(30.0)
    times = report_times(per_channel[0])
    # a small per-client budget, so that the stalled client overflows within the run; one block
    # per turn of the event loop (as in real time), so that a reading client keeps up. The
    # station keeps its reporting rate with frames of invalid data (STAT error 11) once no
    # estimate has come for max_skew_s of wall-clock time: 0.5 s by default, which a loaded
    # machine can starve the publisher or the daemon for. Its reports are not what this test
    # is about, so the wait is longer than the run.
    config = daemon_config(tmp_path, max_skew_s=120.0, client_queue_frames=8, client_buffer_bytes=16384)
    config.limits.intake_batch = 1

    def client(daemon, ep):
        port = daemon.c37118.port
        stalled = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled.connect(("127.0.0.1", port))
        stalled.sendall(encode_command(ID, Command.DATA_ON))  # ... and never reads again
        with C37118Reader("127.0.0.1", port, id_code=ID, timeout_s=TIMEOUT) as good, connect([ep]) as s:
            good.config()
            good.start()
            est = subscribe_estimates(s, "sinewatch/est/pmu/**")
            status = subscribe_status(s)
            while (msg := status.get(timeout=TIMEOUT)) is not None:
                if sorted(len(c["streaming"]) for c in msg["c37118"]["clients"]) == [1, 1]:
                    break
            rows: list[dict[str, Any]] = []
            reader = threading.Thread(target=lambda: rows.extend(good.rows(count=len(times))))
            reader.start()
            pub = BlockPublisher(s)
            assert pub.wait_for_subscriber(CHANNELS[0], TIMEOUT)
            publish_interleaved(pub, per_channel)
            got = take(est, 3 * len(times))
            reader.join(TIMEOUT)
            stats = daemon.c37118.status()
            channel_stats = daemon.pipeline.channel_status()
            intake = daemon.intake.counters
        stalled.close()
        return got, rows, stats, channel_stats, intake

    (got, rows, stats, channel_stats, intake), daemon, code = run_daemon(config, client)
    assert code == 0
    # every estimate published on Zenoh, every frame to the client that reads
    assert len(got) == 3 * len(times) and [r["time_ns"] for r in rows] == times
    assert all(r["data_error"] == DataError.GOOD for r in rows[5:])
    assert intake.dropped == 0 and daemon.pipeline.counters.errors == 0
    assert all(c["gaps"] == 0 and c["errors"] == 0 for c in channel_stats)
    # the stalled client's frames were dropped and counted, not waited for
    stalled = [c for c in stats.clients if c.frames_dropped > 0]
    # each frame handed to its connection, dropped, or still in its queue (of at most 8)
    [s] = stalled
    assert s.frames_sent + s.frames_dropped + s.frames_queued == len(times) and s.frames_queued <= 8
    assert stats.frames_dropped == s.frames_dropped > 0
    assert stats.frames_built == len(times)


def test_malformed_command_frames_are_rejected_counted_and_logged(tmp_path, caplog):
    config = daemon_config(tmp_path, max_clients=2)
    good_cmd = encode_command(ID, Command.SEND_CFG2)
    bad_crc = good_cmd[:-1] + bytes([good_cmd[-1] ^ 0xFF])
    wrong_id = encode_command(ID + 1, Command.SEND_CFG2)
    no_cmd_word = bytes.fromhex("AA41 0010 0007 00000000 00000000")
    no_cmd_word += crc_ccitt(no_cmd_word).to_bytes(2, "big")
    unknown_cmd = encode_command(ID, 0x0007)
    data_frame_not_command = bytes.fromhex("AA01 0010 0007 00000000 00000000")
    data_frame_not_command += crc_ccitt(data_frame_not_command).to_bytes(2, "big")

    def ask_cfg2(sock: socket.socket, splitter: FrameSplitter) -> bytes:
        """Send a valid CFG-2 command and return the answer: by then everything sent before it
        on this connection has been handled (one connection's frames are handled in order)."""
        sock.sendall(good_cmd)
        frames: list[bytes] = []
        while not frames:
            data = sock.recv(65536)
            assert data, "server closed the connection"
            frames = splitter.feed(data)
        return frames[0]

    def hang_up(sock: socket.socket) -> None:
        """Close our side and wait for the server to close its own: by then it has let go."""
        sock.shutdown(socket.SHUT_WR)
        assert sock.recv(65536) == b""

    def client(daemon, ep):
        port = daemon.c37118.port
        with socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT) as sock:
            splitter = FrameSplitter()
            for bad in (bad_crc, wrong_id, no_cmd_word, unknown_cmd, data_frame_not_command, b"\x00\x01\x02junk"):
                sock.sendall(bad)
                cfg2 = decode_frame(ask_cfg2(sock, splitter))  # still answered after each
                assert (cfg2.frame_type.name, cfg2.id_code) == ("CFG2", ID)
            hang_up(sock)
        # past max_clients (2 here: the one above has closed, these two are in) a third is refused
        with (
            socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT) as one,
            socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT) as two,
        ):
            ask_cfg2(one, FrameSplitter())
            ask_cfg2(two, FrameSplitter())  # both served: both counted as clients now
            with socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT) as three:
                assert three.recv(1) == b""  # closed at once
            hang_up(one)
            hang_up(two)
        # a frame cut short by the client closing: counted when the server sees the end
        with socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT) as sock:
            sock.sendall(good_cmd[:9])
            sock.shutdown(socket.SHUT_WR)
            assert sock.recv(1) == b""  # the server closed its side: it has seen the end
        return daemon.c37118.status()

    stats, _, code = run_daemon(config, client)
    assert code == 0
    assert stats.rejected_by_reason == {
        "client_limit": 1,
        "command": 1,
        "crc": 1,
        "id_code": 1,
        "sync": 1,
        "truncated": 2,
        "type": 1,
    }
    assert stats.commands_rejected == 8 and stats.commands == 8
    logged = [r.getMessage() for r in caplog.records if r.name == "sinewatch.c37118"]
    assert any("rejected (crc): CHK: expected CRC-CCITT" in m for m in logged)
    assert any("rejected (id_code): IDCODE: expected one of [7], got 8" in m for m in logged)
    assert any("rejected (truncated): connection closed 9 byte(s) into a frame" in m for m in logged)
