"""The C37.118.2 server's station logic without sockets (frames built from Estimates: phasors,
FREQ/DFREQ, STAT data error, sync and time quality bits, missing channels after max_skew_s),
its config section, and its UDP side (commanded and spontaneous) on loopback."""

from __future__ import annotations

import asyncio
import json
import math
import socket

import pytest
from conftest import TIMEOUT, make_config, run_daemon
from test_c37118_served import CHANNELS, ID, PARAMS, f32, publish_interleaved, report_times, station_blocks

from sinewatch.apps.cli import main as cli_main
from sinewatch.clients import BlockPublisher, connect, subscribe_estimates
from sinewatch.outputs.c37118_server import C37118Server, Station, synchrophasor
from sinewatch.runtime.daemon import Daemon
from sinewatch.schemas.c37118 import (
    Command,
    DataError,
    FrameType,
    decode_config,
    decode_data,
    decode_frame,
    encode_command,
)
from sinewatch.schemas.config import (
    C37118Section,
    C37118Station,
    EstimatorRule,
    RecordingSection,
    SinewatchConfig,
    load_config,
)
from sinewatch.schemas.errors import ConfigError

T = 1_700_000_000 * 10**9  # a whole second


def estimate(
    channel: str, t_ns: int, *, mag=1.0, angle=0.5, f=50.01, rocof=0.02, valid=True, gap=False, tq=None
) -> dict:
    return {
        "time_quality": tq,
        "channel": channel,
        "timestamp_ns": t_ns,
        "frequency_hz": [f],
        "amplitude": [mag * math.sqrt(2)],
        "phase_rad": [0.0],
        "rocof_hz_per_s": [rocof],
        "diagnostics": {
            "valid": valid,
            "gap": gap,
            "extras": {"synchrophasor_magnitude": mag, "synchrophasor_angle_rad": angle},
        },
    }


def station(**kw) -> Station:
    cfg = dict(id_code=ID, name="ST", channels=["a", "b", "c"], data_rate=50, max_skew_s=0.05)
    cfg.update(kw)
    return Station(C37118Station(**cfg), 1_000_000)


def decode(st: Station, raw: bytes):
    frame = decode_frame(raw)
    return frame, decode_data(frame, st.cfg2).pmus[0]


def test_a_frame_once_every_channel_has_reported_its_time():
    st = station()
    assert st.add(0, estimate("a", T, mag=1.0, angle=0.1)) == []
    assert st.add(2, estimate("c", T, mag=3.0, angle=0.3)) == []
    [raw] = st.add(1, estimate("b", T, mag=2.0, angle=-0.2, f=49.99, rocof=-1.0))
    frame, pmu = decode(st, raw)
    assert (frame.soc, frame.fraction, frame.id_code) == (T // 10**9, 0, ID)
    assert pmu.phasors == [(1.0, f32(0.1)), (2.0, f32(-0.2)), (3.0, f32(0.3))]
    assert (pmu.freq_hz, pmu.dfreq_hz_per_s) == (f32(50.01), f32(0.02))  # the first channel's
    assert pmu.data_error is DataError.GOOD and not pmu.data_modified
    # the clock is not declared UTC-traceable: STAT bit 13, unlocked > 1000 s, FRACSEC quality F
    assert not pmu.in_sync and (pmu.stat >> 4) & 0b11 == 0b11 and (pmu.stat >> 6) & 0b111 == 7
    assert frame.time_quality == 0xF


def test_time_synchronised_station_says_so():
    st = station(time_synchronised=True, pmu_time_quality=3)
    frames = [f for i, ch in enumerate("abc") for f in st.add(i, estimate(ch, T + 20_000_000))]
    frame, pmu = decode(st, frames[0])
    assert pmu.in_sync and (pmu.stat >> 4) & 0b11 == 0 and (pmu.stat >> 6) & 0b111 == 3
    assert frame.time_quality == 0 and frame.fraction == 20_000


GLOBAL, LOCAL, NONE = ({"sync": s, "holdover": False} for s in ("global", "local", "none"))
LOST = {"sync": "none", "holdover": True}


def _time_bits(raw: bytes, st: Station) -> tuple[bool, int, int, int]:
    """(in sync, FRACSEC time quality code, STAT bits 8-6, STAT bits 5-4) of a data frame."""
    frame, pmu = decode(st, raw)
    assert (pmu.stat >> 13) & 1 == (not pmu.in_sync)
    return pmu.in_sync, frame.time_quality, (pmu.stat >> 6) & 0b111, (pmu.stat >> 4) & 0b11


@pytest.mark.parametrize("declared", [False, True])
def test_the_estimates_time_quality_sets_stat_and_fracsec_whatever_the_station_declares(declared):
    """C37.118.2-2011: STAT bit 13 (sync), bits 8-6 (PMU time quality, Table 7), bits 5-4
    (unlocked time, Table 6), FRACSEC bits 27-24 (time quality code, Tables 3 and 4) from the
    estimates' time quality; the declaration only where no estimate states one."""
    st = station(time_synchronised=declared, pmu_time_quality=2)
    bits = []
    for k, tq in enumerate([GLOBAL, LOCAL, NONE, None, GLOBAL]):
        t = T + k * 20_000_000
        [raw] = [f for i, ch in enumerate("abc") for f in st.add(i, estimate(ch, t, tq=tq))]
        bits.append(_time_bits(raw, st))
    not_traceable = (False, 0xF, 0b111, 0b11)  # never locked in this stream: unlocked > 1000 s
    declared_bits = (True, 0x0, 2, 0b00) if declared else not_traceable
    assert bits == [(True, 0x0, 2, 0b00), not_traceable, not_traceable, declared_bits, (True, 0x0, 2, 0b00)]
    # the configuration frame's FRACSEC says the last data frame's code
    assert decode_frame(st.config_frame(FrameType.CFG2, T)).time_quality == 0x0


def test_a_lost_synchronisation_counts_its_unlocked_time_in_table_6_s_ranges():
    st = station(time_synchronised=True, data_rate=1)
    got = {}
    for s in (0, 1, 9, 10, 99, 100, 1000, 1001):
        t = T + s * 10**9
        [raw] = [f for i, ch in enumerate("abc") for f in st.add(i, estimate(ch, t, tq=LOST))]
        got[s] = _time_bits(raw, st)
    # 00 below 10 s, 01 from 10 s to below 100 s, 10 from 100 s to 1000 s, 11 beyond
    assert {s: b[3] for s, b in got.items()} == {0: 0, 1: 0, 9: 0, 10: 1, 99: 1, 100: 2, 1000: 2, 1001: 3}
    assert {b[:3] for b in got.values()} == {(False, 0xF, 0b111)}
    # locked again: in sync at once, and a new loss counts from its own start
    t = T + 1002 * 10**9
    [raw] = [f for i, ch in enumerate("abc") for f in st.add(i, estimate(ch, t, tq=GLOBAL))]
    assert _time_bits(raw, st) == (True, 0x0, 7, 0b00)
    [raw] = [f for i, ch in enumerate("abc") for f in st.add(i, estimate(ch, t + 10**9, tq=LOST))]
    assert _time_bits(raw, st)[3] == 0b00


def test_a_frame_says_the_worst_time_quality_of_its_channels():
    st = station(time_synchronised=True)
    frames = st.add(0, estimate("a", T, tq=GLOBAL)) + st.add(1, estimate("b", T, tq=LOST))
    frames += st.add(2, estimate("c", T, tq=GLOBAL))
    [raw] = frames
    assert _time_bits(raw, st) == (False, 0xF, 0b111, 0b00)


@pytest.mark.parametrize(
    ("flags", "error"),
    [
        ({"gap": True}, DataError.PMU_ERROR_NO_INFO),  # estimated across missing samples
        ({"valid": False}, DataError.PMU_ERROR),  # not a measurement
        ({"valid": False, "gap": True}, DataError.PMU_ERROR),
    ],
)
def test_stat_data_error_follows_the_estimates(flags, error):
    st = station()
    st.add(0, estimate("a", T))
    st.add(1, estimate("b", T, **flags))
    [raw] = st.add(2, estimate("c", T))
    assert decode(st, raw)[1].data_error is error


def test_a_missing_channel_is_sent_as_absent_data_after_max_skew():
    st = station()  # max_skew_s = 50 ms: a frame waits until another channel is 2.5 reports past it
    out = []
    for k in range(4):
        t = T + k * 20_000_000
        out += st.add(0, estimate("a", t))
        if k != 1:
            out += st.add(1, estimate("b", t))
        out += st.add(2, estimate("c", t))
    # k = 0 complete; k = 1 waits (b missing) until a channel reaches t1 + 60 ms (k = 4)
    assert [decode_frame(r).fraction for r in out] == [0]
    out += st.add(0, estimate("a", T + 4 * 20_000_000))
    assert [decode_frame(r).fraction for r in out] == [0, 20_000, 40_000, 60_000]
    pmu = decode(st, out[1])[1]
    assert pmu.data_error is DataError.TEST_OR_ABSENT
    assert math.isnan(pmu.phasors[1][0]) and pmu.phasors[0] == (1.0, f32(0.5))
    assert decode(st, out[2])[1].data_error is DataError.GOOD
    assert (st.built, st.incomplete) == (4, 1)
    # b's estimate for k = 1 arriving now is late: not sent again, counted
    assert st.add(1, estimate("b", T + 20_000_000)) == [] and st.late == 1


def test_rectangular_format_and_config_frames():
    st = station(phasor_format="rectangular", phasor_type="current", nominal_frequency_hz=60, data_rate=60)
    frames = [f for i, ch in enumerate("abc") for f in st.add(i, estimate(ch, T, mag=2.0, angle=math.pi / 3))]
    pmu = decode(st, frames[0])[1]
    assert pmu.phasors[0] == (f32(2 * math.cos(math.pi / 3)), f32(2 * math.sin(math.pi / 3)))
    for kind in (FrameType.CFG1, FrameType.CFG2, FrameType.CFG3):
        cfg = decode_config(decode_frame(st.config_frame(kind, T)))
        p = cfg.pmus[0]
        assert (cfg.frame_type, cfg.data_rate, p.station, p.nominal_frequency_hz) == (kind, 60, "ST", 60)
        assert p.phasor_names == ["a", "b", "c"] and not p.format.polar
        if kind is FrameType.CFG3:
            assert [s.type_code for s in p.phscale] == [0b1000] * 3  # current
        else:
            assert p.phunit == [1 << 24] * 3  # current
    header = decode_frame(st.header_frame(T)).body.decode()
    assert "channels a, b, c" in header and "not UTC-traceable" in header


def test_synchrophasor_of_an_estimator_without_one():
    """x = A sin(psi) with psi = 2 pi f0 t + theta is A cos(2 pi f0 t + theta - pi/2): the
    synchrophasor is (A / sqrt 2, theta - pi/2), whatever t (C37.118.1 eq. (1)-(2))."""
    theta = 0.7
    for t_ns in (T, T + 7_300_000, T + 123_456_789_012):
        psi = 2 * math.pi * ((50 * t_ns) % 10**9) / 1e9 + theta
        est = {
            "timestamp_ns": t_ns,
            "amplitude": [2.0],
            "phase_rad": [psi],
            "diagnostics": {"extras": {}},
        }
        mag, ang = synchrophasor(est, 50)
        assert mag == pytest.approx(2 / math.sqrt(2), rel=1e-15)
        assert ang == pytest.approx(theta - math.pi / 2, abs=1e-12)
    assert synchrophasor({**est, "amplitude": [None]}, 50) is None


def test_config_section_is_validated():
    st = {"id_code": 1, "name": "A", "channels": ["x"]}
    with pytest.raises(ValueError, match="unique id_code"):
        C37118Section(stations=[st, {**st, "channels": ["y"]}])
    with pytest.raises(ValueError, match="at least one station"):
        C37118Section(enabled=True)
    with pytest.raises(ValueError, match="one per channel"):
        C37118Station(**st, phasor_names=["p", "q"])
    with pytest.raises(ValueError, match="distinct"):
        C37118Station(id_code=1, name="A", channels=["x", "x"])
    with pytest.raises(ValueError, match="HOST:PORT"):
        C37118Section(udp_destinations=["nowhere"])
    with pytest.raises(ValueError):
        C37118Station(id_code=65535, name="A", channels=["x"])  # 0 and 65535 are reserved
    with pytest.raises(ValueError):
        C37118Station(id_code=1, name="a name longer than 16", channels=["x"])
    assert SinewatchConfig().c37118.enabled is False  # off by default


def test_config_file_and_config_show(tmp_path, capsys):
    path = tmp_path / "c.toml"
    path.write_text(
        '[c37118]\nenabled = true\nport = 4713\n[[c37118.stations]]\nid_code = 9\nname = "B"\nchannels = ["pmu/x"]\n'
    )
    cfg = load_config(path, env={})
    assert cfg.c37118.stations[0].id_code == 9 and cfg.c37118.port == 4713
    assert cli_main(["config", "show", "--config", str(path)]) == 0
    shown = json.loads(capsys.readouterr().out)["c37118"]
    assert shown["enabled"] and shown["stations"][0]["channels"] == ["pmu/x"]
    bad = tmp_path / "bad.toml"
    bad.write_text("[c37118]\nenabled = true\n")
    with pytest.raises(ConfigError, match="at least one station"):
        load_config(bad, env={})
    # serve --c37118 PORT without stations: an error that says what to configure
    plain = tmp_path / "plain.toml"
    plain.write_text('daemon_id = "plain"\n')
    assert cli_main(["serve", "--config", str(plain), "--c37118", "4714"]) == 2
    assert "configure [[c37118.stations]]" in capsys.readouterr().err


def test_udp_commanded_and_spontaneous(tmp_path):
    per_channel = station_blocks(3.0)
    times = report_times(per_channel[0])
    spont = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    spont.bind(("127.0.0.1", 0))
    spont.settimeout(TIMEOUT)
    c37 = C37118Section(
        enabled=True,
        port=0,
        udp_destinations=[f"127.0.0.1:{spont.getsockname()[1]}"],
        stations=[C37118Station(id_code=ID, name="U", channels=CHANNELS, time_synchronised=True)],
    )
    config = make_config(
        tmp_path,
        rules=[EstimatorRule(match="sinewatch/in/pmu/**", estimator="pmu", params=PARAMS)],
        recording=RecordingSection(enabled=False),
        c37118=c37,
    )

    def client(daemon, ep):
        server: C37118Server = daemon.c37118
        pdc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        pdc.settimeout(TIMEOUT)
        pdc.connect(("127.0.0.1", server.port))
        pdc.send(encode_command(ID, Command.SEND_CFG2))
        cfg = decode_config(decode_frame(pdc.recv(65536)))
        pdc.send(encode_command(ID, Command.DATA_ON))
        pdc.send(encode_command(ID, Command.SEND_HDR))  # answered after DATA_ON was handled
        assert decode_frame(pdc.recv(65536)).frame_type is FrameType.HEADER
        with connect([ep]) as s:
            est = subscribe_estimates(s, "sinewatch/est/pmu/**")
            pub = BlockPublisher(s)
            assert pub.wait_for_subscriber(CHANNELS[0], TIMEOUT)
            publish_interleaved(pub, per_channel)
            got = [est.get(timeout=TIMEOUT) for _ in range(3 * len(times))]
            commanded = [decode_data(decode_frame(pdc.recv(65536)), cfg) for _ in times]
            spontaneous = [decode_data(decode_frame(spont.recv(65536)), cfg) for _ in times]
        pdc.send(encode_command(ID, Command.DATA_OFF))
        pdc.send(encode_command(ID, Command.SEND_CFG1))
        assert decode_frame(pdc.recv(65536)).frame_type is FrameType.CFG1
        return got, commanded, spontaneous, server.status()

    (got, commanded, spontaneous, stats), _, code = run_daemon(config, client)
    assert code == 0 and all(g is not None for g in got)
    want = {(e["timestamp_ns"], e["channel"]): e for e in got}
    for frames in (commanded, spontaneous):
        assert [f.soc * 10**9 + (f.fracsec & 0xFFFFFF) * 1000 for f in frames] == times
        for f in frames:
            t = f.soc * 10**9 + (f.fracsec & 0xFFFFFF) * 1000
            assert f.pmus[0].freq_hz == f32(want[(t, CHANNELS[0])]["frequency_hz"][0])
    assert stats.clients == []  # DATA_OFF: the UDP client is gone
    assert stats.commands == 5 and stats.commands_rejected == 0


def test_a_port_in_use_is_a_config_error_not_a_crash(tmp_path):
    busy = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    config = make_config(
        tmp_path,
        recording=RecordingSection(enabled=False),
        c37118=C37118Section(enabled=True, port=port, stations=[C37118Station(id_code=ID, name="B", channels=["x"])]),
    )
    with pytest.raises(ConfigError, match=f"expected to listen on 127.0.0.1:{port}"):
        asyncio.run(Daemon(config, install_signal_handlers=False).run())
    busy.close()
