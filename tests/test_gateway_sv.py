"""``sinewatch gateway sv``: IEC 61850-9-2LE sampled values (4 currents + 4 voltages, INT32
and a quality word each, 4000 samples/s) from a pcap file the test writes with open61850's
encoder and pcap writer, then from the same library's publisher on a veth pair. The gateway's
frames against the byte values sent (scaling, time from smpCnt, the counter's wrap, a lost
and a repeated counter, an invalid quality word, an unsynchronised stretch), then a real
daemon's estimates of them against the known waveforms."""

from __future__ import annotations

import itertools
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import make_config, run_daemon, take

from sinewatch.clients import connect, subscribe_errors, subscribe_estimates
from sinewatch.clients.subscriber import JsonSubscription
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.frame import Frame

sv = pytest.importorskip("open61850.sv", reason="the sv extra (open61850) is not installed")
pcap = pytest.importorskip("open61850.pcap")
svp = pytest.importorskip("open61850.sv_publisher")

from sinewatch.apps.gateway import GatewayOptions, SvGateway  # noqa: E402

RATE = 4000
START = 1_700_000_000  # the UTC second of the first sample
F = 49.97  # off nominal, so a frequency error shows
I_PEAK, V_PEAK, I_LAG = 400.0, 9000.0, 30.0  # amperes and volts (9-2LE: 1 mA, 10 mV per count)
LATENCY_NS = 120_000  # a frame is captured this long after its sample was taken
SV_ID = "MU01"
N = 256  # samples per frame: 4000/256 is not whole, so frames straddle the counter's wrap

# the events, as (second, smpCnt) from START
LOST = (1, 1000)  # this sample is never sent
REPEATED = (1, 2000)  # this sample is sent twice
BAD_QUALITY = (1, 3000)  # VA's quality word says invalid
UNSYNCED = 2  # this whole second says smpSynch = 0 (none)
SECONDS = 5  # the counter wraps inside a frame in seconds 0-1 and 3-4


def _stream(smp_synch: int) -> svp.SvStream:
    waves = svp.three_phase(i_peak=I_PEAK, v_peak=V_PEAK, freq_hz=F, i_lag_deg=I_LAG, layout="4I4U")
    return svp.SvStream(
        sv_id=SV_ID, app_id=0x4000, dst_mac="01:0c:cd:04:00:01", src_mac="02:00:00:00:00:01", waves=waves,
        smp_synch=smp_synch, dat_set="MU01LD0/LLN0$PhsMeas1",
    )  # fmt: skip


def write_capture(path: Path) -> list[tuple[int, int, bytes]]:
    """A 9-2LE capture of SECONDS seconds with the events above; returns what was sent:
    (second, smpCnt, frame bytes) in capture order."""
    synced, unsynced = _stream(sv.SMP_SYNCH_GLOBAL), _stream(sv.SMP_SYNCH_NONE)
    t_synced, t_unsynced = svp.build_template(synced, 1, RATE), svp.build_template(unsynced, 1, RATE)
    sent = []
    with pcap.PcapWriter(path) as w:
        for s in range(SECONDS):
            for c in range(RATE):
                if (s, c) == LOST:
                    continue
                stream, template = (unsynced, t_unsynced) if s == UNSYNCED else (synced, t_synced)
                frame = svp.render_frame(template, stream, START + s, c, RATE)
                if (s, c) == BAD_QUALITY:
                    frame = _set_quality(frame, template, channel=4, quality=0x1)  # validity 01: invalid
                copies = 2 if (s, c) == REPEATED else 1
                for _ in range(copies):
                    w.write(frame, timestamp=((START + s) * 10**9 + c * 250_000 + LATENCY_NS) / 1e9)
                    sent.append((s, c, frame))
    return sent


def _set_quality(frame: bytes, template: svp.Template, channel: int, quality: int) -> bytes:
    b = bytearray(frame)
    at = template.sample_offsets[0] + 8 * channel + 4
    b[at : at + 4] = quality.to_bytes(4, "big")
    return bytes(b)


def truth(channel: str, k: np.ndarray) -> np.ndarray:
    """The waveform each channel carries, in amperes or volts, at sample k (from START):
    the publisher's own formula (the phase taken per second, see ``Wave.value``)."""
    phase = {"IA": -I_LAG, "IB": -I_LAG - 120, "IC": -I_LAG - 240, "VA": 0.0, "VB": -120.0, "VC": -240.0}
    peak = V_PEAK if channel.startswith("V") else I_PEAK
    second, c = np.divmod(k, RATE)
    cycles = np.array([math.fmod(F * int(START + s), 1.0) for s in second]) + F * c / RATE
    return peak * np.sin(2 * np.pi * cycles + np.radians(phase[channel]))


def gateway_frames(path: Path, n: int = N) -> tuple[list[Frame], SvGateway]:
    frames: list[Frame] = []
    gw = SvGateway(GatewayOptions(rate=RATE, samples=n), lambda name, f: frames.append(f))
    for captured in pcap.read_pcap(path):
        gw.feed(captured.data, round(captured.timestamp * 1e9))
    gw.flush()
    return frames, gw


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("sv") / "mu01.pcap"
    write_capture(path)
    return path


@pytest.fixture(scope="module")
def decoded(capture) -> tuple[list[Frame], SvGateway]:
    """The capture through the gateway in this process, frames of N (decoded once)."""
    return gateway_frames(capture)


def test_the_gateway_s_frames_carry_the_values_sent_at_the_times_of_their_sample_counters(decoded):
    frames, gw = decoded
    [stats] = gw.summary()["streams"]
    assert stats == {
        "sv_id": SV_ID,
        "samples": SECONDS * RATE - 1,  # the lost one; the repeat dropped
        "frames": len(frames),
        "lost": 1,
        "lost_events": 1,
        "repeated": 1,
        "bad_quality": 1,
        "unsynchronised": RATE,
        "synch_changes": 2,
        "rejected": 0,
        "time_quality": {"sync": "global", "holdover": False},  # at the end: synchronised again
    }
    assert all(
        f.channels == tuple(f"MU01/{c}" for c in ("IA", "IB", "IC", "IN", "VA", "VB", "VC", "VN")) for f in frames
    )
    # the values: each synchronised sample against the waveform at its sample time, to the
    # 9-2LE count (1 mA, 10 mV: half a count of rounding)
    for f in frames:
        k = (f.t0_ns - START * 10**9) // 250_000 + np.arange(f.n_samples)
        if k[0] // RATE == UNSYNCED:
            continue
        for c, name in enumerate(("IA", "IB", "IC", None, "VA", "VB", "VC")):
            if name is None:
                continue
            x = f.samples[:, c]
            ok = np.isfinite(x)
            tol = 0.0005 if name.startswith("I") else 0.005
            assert np.max(np.abs(x[ok] - truth(name, k[ok]))) <= tol + 1e-9, (name, f.seq)
    nan = [
        (f.seq, int(np.argwhere(np.isnan(f.samples))[0][0]), int(np.argwhere(np.isnan(f.samples))[0][1]))
        for f in frames
        if np.isnan(f.samples).any()
    ]
    assert len(nan) == 1 and nan[0][2] == 4  # VA, one sample, only there
    bad = next(f for f in frames if np.isnan(f.samples).any())
    assert bad.t0_ns + nan[0][1] * 250_000 == (START + BAD_QUALITY[0]) * 10**9 + BAD_QUALITY[1] * 250_000


def test_wrap_loss_repeat_and_unsynchronised_stretch_are_flagged_as_documented(decoded):
    frames, _ = decoded
    seqs = [f.seq for f in frames]
    skips = [(a, b) for a, b in itertools.pairwise(seqs) if b != a + 1]
    # one skip each: the lost sample, the repeated one, into and out of the unsynchronised second
    assert len(skips) == 4 and all(b == a + 2 for a, b in skips)
    by_seq = {f.seq: f for f in frames}
    for a, b in skips:
        fa, fb = by_seq[a], by_seq[b]
        end_a = fa.t0_ns + fa.n_samples * 250_000
        cut = ((fb.t0_ns - START * 10**9) // 10**9, (fb.t0_ns % 10**9) // 250_000)
        if cut == (LOST[0], LOST[1] + 1):
            assert fb.t0_ns - end_a == 250_000  # the one sample missing
        elif cut == (REPEATED[0], REPEATED[1] + 1):
            assert fb.t0_ns == end_a  # nothing missing: the repeat was dropped, the cut flags it
    # the counter's wrap inside a frame is no gap: frames straddling a second are continuous
    straddling = [f for f in frames if f.t0_ns // 10**9 != (f.t0_ns + (f.n_samples - 1) * 250_000) // 10**9]
    assert len(straddling) == 2
    for f in straddling:
        nxt = by_seq.get(f.seq + 1)
        if nxt is not None:
            assert nxt.t0_ns == f.t0_ns + f.n_samples * 250_000
    # each frame carries its samples' smpSynch as a time quality: global (0x82), and in the
    # unsynchronised second none with holdover (0x84: it was global before, the clock runs free)
    assert {f.time_quality for f in frames if (f.t0_ns // 10**9) - START == UNSYNCED} == {0x84}
    assert {f.time_quality for f in frames if (f.t0_ns // 10**9) - START != UNSYNCED} == {0x82}
    # synchronised frames sit on the UTC second's grid; the unsynchronised second is timed by
    # the capture's clock (its first sample's arrival), 120 us off that grid (to the 1 us
    # open61850's float capture times keep at this epoch)
    for f in frames:
        second = (f.t0_ns // 10**9) - START
        offset = (f.t0_ns - START * 10**9) % 250_000
        if second == UNSYNCED:
            assert abs(offset - LATENCY_NS) < 1000, (f.seq, offset)
        else:
            assert offset == 0, (f.seq, second)


def test_every_smp_synch_value_becomes_the_frames_time_quality_and_each_change_is_reported():
    """smpSynch per IEC 61850-9-2 Ed. 2.1: 0 none, 1 local, 2 global, 5-254 a local clock by
    its number, 3/4/255 reserved (none). A drop sets holdover, a rise clears it; a frame never
    holds two time qualities; each change goes to the callback once."""
    from sinewatch.apps.gateway import StreamSpec, SvStreamDecoder, sync_code

    assert [sync_code(v) for v in (0, 1, 2, 3, 4, 5, 254, 255)] == [0, 1, 2, 0, 0, 1, 1, 0]
    dec = SvStreamDecoder(StreamSpec("MU9"), rate=RATE, n_samples=10)
    stretches = [(0, 20), (1, 20), (2, 20), (0, 20), (5, 20), (2, 20), (3, 20)]
    expected = [0x80, 0x81, 0x82, 0x84, 0x81, 0x82, 0x84]  # none, local, global, none since a drop, ...
    frames, k = [], 0
    for synch, count in stretches:
        for _ in range(count):
            frames += dec.push(START * 10**9 + k * 250_000, k % RATE, synch, bytes(64))
            k += 1
    frames += dec.flush()
    assert [f.time_quality for f in frames] == [q for q in expected for _ in range(2)]  # 20 samples: 2 frames
    assert dec.stats.synch_changes == 6 and dec.time_quality == 0x84
    # each change ends a frame and skips a seq (a gap of one for the daemon), as a change of smpSynch always did
    assert [b.seq - a.seq for a, b in itertools.pairwise(frames)] == [1, 2] * 6 + [1]
    # through the gateway: the changes of the capture reported, as (svID, old byte, new byte)
    capture_frames = []
    changes = []
    gw = SvGateway(GatewayOptions(rate=RATE, samples=N), lambda name, f: capture_frames.append(f),
                   lambda sv_id, old, new, t: changes.append((sv_id, old, new, t)))  # fmt: skip
    stream = _stream(sv.SMP_SYNCH_GLOBAL)
    unsynced = _stream(sv.SMP_SYNCH_NONE)
    templates = {0: svp.build_template(stream, 1, RATE), 2: svp.build_template(unsynced, 1, RATE)}
    for s in range(3):
        for c in range(0, RATE, 400):  # every 400th sample is enough to follow smpSynch (seen as lost ones)
            st, tpl = (unsynced, templates[2]) if s == 1 else (stream, templates[0])
            gw.feed(svp.render_frame(tpl, st, START + s, c, RATE), (START + s) * 10**9 + c * 250_000 + LATENCY_NS)
    assert [(sv_id, old, new) for sv_id, old, new, _ in changes] == [
        (SV_ID, 0x00, 0x82), (SV_ID, 0x82, 0x84), (SV_ID, 0x84, 0x82),
    ]  # fmt: skip
    assert changes[1][3] == (START + 1) * 10**9 + LATENCY_NS  # when: the first unsynchronised sample's arrival


def test_frames_of_80_samples_and_a_filter_that_matches_nothing(capture):
    frames, _ = gateway_frames(capture, n=80)
    assert all(f.n_samples <= 80 for f in frames) and sum(f.n_samples for f in frames) == SECONDS * RATE - 1
    other = SvGateway(GatewayOptions(rate=RATE, sv_ids=("MU99",)), lambda name, f: None)
    for captured in pcap.read_pcap(capture):
        other.feed(captured.data, round(captured.timestamp * 1e9))
    assert other.streams == {} and other.filtered == SECONDS * RATE  # every ASDU, the repeat in, the lost out
    other.feed(b"\x01" * 40, 0)
    assert other.not_sv == 1


IPDFT = {"nominal_frequency_hz": 50.0, "window_cycles": 10}


def check_three_phase(estimates: list[dict], channels=("VA", "VB", "VC"), peak=V_PEAK, phases=(0.0, -120.0, -240.0)):
    """The last estimate of each phase: frequency within 5 mHz, magnitude within 0.1 %, the
    angles between the phases within 0.1 degree of the waveform's."""
    last = {}
    for e in estimates:
        last[e["channel"]] = e
    got = [last[f"{SV_ID}/{c}"] for c in channels]
    assert len({e["timestamp_ns"] for e in got}) == 1  # one frame: the same instant
    for e in got:
        assert abs(e["frequency_hz"][0] - F) < 0.005, e
        assert abs(e["amplitude"][0] - peak) / peak < 0.001, e
    for k in (1, 2):
        d = math.degrees(got[0]["phase_rad"][0] - got[k]["phase_rad"][0])
        expected = phases[0] - phases[k]
        assert abs((d - expected + 180) % 360 - 180) < 0.1, (k, d)


def test_a_daemon_estimates_the_gateway_s_frames_from_the_pcap(tmp_path, capture, decoded):
    rules = [EstimatorRule(match="sinewatch/in/**", estimator="ipdft", params=IPDFT)]
    config = make_config(tmp_path, rules=rules)
    frames, _ = decoded
    expected = 8 * len(frames) - 1  # every channel of every frame, but VA's NaN block

    def client(_daemon, ep):
        with connect([ep]) as s:
            est = subscribe_estimates(s)
            err = subscribe_errors(s)
            status = JsonSubscription(s, "sinewatch/gateway/sv/**")
            r = subprocess.run(
                [sys.executable, "-m", "sinewatch", "gateway", "sv", "--pcap", str(capture), "--connect", ep,
                 "--samples", str(N), "--rate", str(RATE), "--wait", "30"],
                capture_output=True, text=True, timeout=300, check=False,
            )  # fmt: skip
            final = None  # the gateway's last status: every sample counted
            for final in status.iter(timeout=30):
                if final["samples"] == SECONDS * RATE - 1:
                    break
            return r, take(est, expected), take(err, 1), final

    (r, got, errors, status), _daemon, code = run_daemon(config, client)
    # the gateway's live status key: its last message the final counts
    assert status is not None and status["_key"] == "sinewatch/gateway/sv/MU01"
    assert (status["samples"], status["lost"], status["repeated"], status["synch_changes"]) == (
        SECONDS * RATE - 1, 1, 1, 2,
    )  # fmt: skip
    assert status["synchronised"] is True and status["time_quality"] == {"sync": "global", "holdover": False}
    assert r.returncode == 0, r.stderr
    # each change of smpSynch reported by the gateway, on stderr by default
    assert r.stderr.count("stream MU01: time quality") == 3, r.stderr
    assert "{'sync': 'global', 'holdover': False} -> {'sync': 'none', 'holdover': True}" in r.stderr
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["published"] == len(frames) and summary["streams"][0]["lost"] == 1
    assert code == 0 and len(got) == expected
    assert [(e["kind"], e["channel"]) for e in errors] == [("non_finite", "MU01/VA")]
    va = sorted((e for e in got if e["channel"] == "MU01/VA"), key=lambda e: e["seq"])
    ib = sorted((e for e in got if e["channel"] == "MU01/IB"), key=lambda e: e["seq"])
    # IB: a gap at each of the four cuts; VA: also after its refused block
    assert sum(e["diagnostics"]["gap"] for e in ib) == 4
    assert sum(e["diagnostics"]["gap"] for e in va) == 5
    check_three_phase(got)
    check_three_phase(got, ("IA", "IB", "IC"), I_PEAK, (-I_LAG, -I_LAG - 120, -I_LAG - 240))
    # smpSynch reaches every estimate: 2 as global, the second of 0 as none since a loss (holdover)
    by_second: dict[int, set] = {}
    for e in got:
        assert e["format_version"] == 5
        tq = e["time_quality"]
        by_second.setdefault(e["timestamp_ns"] // 10**9 - START, set()).add((tq["sync"], tq["holdover"]))
    assert by_second == {s: {("none", True)} if s == UNSYNCED else {("global", False)} for s in range(SECONDS)}


# ---- live: open61850's publisher on one end of a veth pair, the gateway on the other --------
def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30, check=False)


@pytest.fixture
def veth():
    """A veth pair: one end in a network namespace of its own (the merging unit's side),
    the other here (the gateway's); skipped where they cannot be created (not root, no
    ``ip``, a container without the capability)."""
    import os
    import shutil

    if shutil.which("ip") is None:
        pytest.skip("no `ip` command to create a network namespace and a veth pair")
    tag = f"{os.getpid() % 100000}"
    ns, here, there = f"swsv{tag}", f"swg{tag}", f"swm{tag}"
    made = _ip("netns", "add", ns)
    if made.returncode != 0:
        pytest.skip(f"cannot create a network namespace: {made.stderr.strip()}")
    try:
        steps = [
            ("link", "add", here, "type", "veth", "peer", "name", there),
            ("link", "set", there, "netns", ns),
            ("link", "set", here, "up"),
            ("-n", ns, "link", "set", there, "up"),
        ]
        for step in steps:
            r = _ip(*step)
            if r.returncode != 0:
                pytest.skip(f"cannot set up the veth pair (ip {' '.join(step)}): {r.stderr.strip()}")
        yield ns, here, there
    finally:
        _ip("link", "del", here)
        _ip("netns", "del", ns)


def _live(tmp_path, veth, seconds: float) -> None:
    import re

    ns, here, there = veth
    rules = [EstimatorRule(match="sinewatch/in/**", estimator="ipdft", params=IPDFT)]
    config = make_config(tmp_path, rules=rules)

    def client(_daemon, ep):
        with connect([ep]) as s:
            est = subscribe_estimates(s)
            gateway = subprocess.Popen(
                [sys.executable, "-m", "sinewatch", "gateway", "sv", "--iface", here, "--connect", ep,
                 "--samples", "80", "--rate", str(RATE), "--idle", "3", "--wait", "30"],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            )  # fmt: skip
            try:
                assert gateway.stderr is not None
                line = gateway.stderr.readline()  # waits until its socket is bound
                assert "listening on" in line, line + gateway.stderr.read()
                publisher = subprocess.run(
                    ["ip", "netns", "exec", ns, sys.executable, "-m", "open61850.sv_publisher", there,
                     "02:00:00:00:00:02", "01:0c:cd:04:00:02", SV_ID, "--appid", "0x4001", "--conf-rev", "1",
                     "--smp-synch", "2", "--rate", str(RATE), "--asdus", "1", "--layout", "4I4U",
                     "--freq", str(F), "--i-peak", str(I_PEAK), "--v-peak", str(V_PEAK), "--phase", str(I_LAG),
                     "--engine", "python", "--duration", str(seconds)],
                    capture_output=True, text=True, timeout=seconds + 60, check=False,
                )  # fmt: skip
                out, err = gateway.communicate(timeout=seconds + 120)  # it stops 3 s after the bus goes silent
            finally:
                if gateway.poll() is None:
                    gateway.kill()
                    gateway.wait()
            summary = json.loads(out.strip().splitlines()[-1])
            return publisher, summary, err, take(est, 8 * summary["published"])

    (publisher, summary, err, got), _daemon, code = run_daemon(config, client)
    assert publisher.returncode == 0, publisher.stderr
    stats = re.search(r"frames_sent=(\d+), send_errors=(\d+)", publisher.stderr)
    assert stats, publisher.stderr
    sent, send_errors = int(stats.group(1)), int(stats.group(2))
    [stream] = summary["streams"]
    assert send_errors == 0 and sent >= seconds * RATE * 0.9
    # no lost frame: every frame sent was decoded, in order, none missing or repeated
    assert (stream["samples"], stream["lost"], stream["repeated"], stream["bad_quality"]) == (sent, 0, 0, 0), err
    assert stream["unsynchronised"] == 0 and summary["undecodable"] == 0
    assert code == 0 and len(got) == 8 * summary["published"]
    assert not any(e["diagnostics"]["gap"] for e in got)
    # times from smpSynch = global: every estimate on the 4000/s grid of the UTC second
    assert all(e["timestamp_ns"] % 250_000 == 0 for e in got)
    check_three_phase(got)
    check_three_phase(got, ("IA", "IB", "IC"), I_PEAK, (-I_LAG, -I_LAG - 120, -I_LAG - 240))


def test_live_from_a_publisher_on_a_veth_pair(tmp_path, veth):
    _live(tmp_path, veth, seconds=2.0)


@pytest.mark.slow
def test_live_ten_seconds_without_a_lost_frame(tmp_path, veth):
    _live(tmp_path, veth, seconds=10.0)


def test_bench_gateway_runs_its_three_ways_and_zenoh_delivers_every_frame(tmp_path):
    """The bench's bookkeeping (no timing asserted): every SV frame goes through each way,
    and the subscriber counts every SampleFrame the gateway put (4000 samples / 80)."""
    import argparse

    from sinewatch.apps.bench.gateway import run

    out = tmp_path / "bench.json"
    args = argparse.Namespace(streams=1, seconds=1, rate=RATE, samples=80, json=out)
    assert run(args) == 0
    result = json.loads(out.read_text())
    assert [r["way"] for r in result["results"]] == ["decode (open61850)", "gateway", "gateway + Zenoh"]
    assert all(r["frames"] == RATE for r in result["results"])
    assert result["results"][2]["zenoh_frames"] == RATE // 80


def test_the_deploy_example_serves_the_merging_unit_as_a_pmu_and_a_power_quality_meter(tmp_path, capture):
    """deploy/sv-merging-unit.toml on the gateway's frames: C37.118.2 data frames of the three
    voltages (RMS within 0.1 %, 120 degrees apart within 0.1, frequency within 5 mHz, STAT
    in sync as the example declares) and the three-phase group's reports (balanced: u2 ~ 0)."""
    import threading

    from sinewatch.clients.c37118 import C37118Reader
    from sinewatch.clients.session import free_loopback_port
    from sinewatch.schemas.config import ZenohSection, load_config

    example = load_config(Path(__file__).resolve().parents[1] / "deploy" / "sv-merging-unit.toml", {})
    c_port = free_loopback_port()
    config = example.model_copy(
        update={
            "zenoh": ZenohSection(listen=[f"tcp/127.0.0.1:{free_loopback_port()}"]),
            "c37118": example.c37118.model_copy(update={"port": c_port}),
            "recording": example.recording.model_copy(update={"enabled": False}),
        }
    )

    def client(_daemon, ep):
        rows: list[dict] = []
        with connect([ep]) as s, C37118Reader("127.0.0.1", c_port, id_code=61, timeout_s=60) as pmu:
            groups = JsonSubscription(s, "sinewatch/pq/group/**")
            pmu.config()
            pmu.start()
            reader = threading.Thread(target=lambda: rows.extend(pmu.rows(count=150)), daemon=True)
            reader.start()
            r = subprocess.run(
                [sys.executable, "-m", "sinewatch", "gateway", "sv", "--pcap", str(capture), "--connect", ep,
                 "--wait", "30"],
                capture_output=True, text=True, timeout=300, check=False,
            )  # fmt: skip
            reader.join(timeout=120)
            return r, list(rows), take(groups, 100)

    (r, rows, groups), _daemon, code = run_daemon(config, client)
    assert r.returncode == 0, r.stderr
    assert code == 0 and len(rows) == 150 and len(groups) == 100
    good = [row for row in rows if row["data_error"] == 0]
    # STAT and FRACSEC from the merging unit's smpSynch (the estimates' time quality; the example's
    # time_synchronised only for inputs that state none), in the frames the PDC socket read. Every
    # row made of estimates (data error 00 or 01) is either in sync (bit 13 clear, FRACSEC code 0,
    # unlocked 00, the station's PMU time quality) or not (bit 13 set, code 0xF: Table 4, time not
    # reliable; PMU time quality 111: Table 7, unknown; unlocked 00: the loss was less than 10 s
    # before, Table 6). A report takes the time quality of the block that completed it, so the
    # pmu's reports up to its latency (< 0.2 s) before a change take the new one: the rows not in
    # sync are those of the unsynchronised second, give or take that latency.
    pmu_tq = example.c37118.stations[0].pmu_time_quality
    measured = [row for row in rows if row["data_error"] in (0, 1)]
    bits = {
        (row["in_sync"], row["time_quality"], (row["stat"] >> 6) & 0b111, (row["stat"] >> 4) & 0b11) for row in measured
    }
    assert bits == {(True, 0, pmu_tq, 0b00), (False, 0xF, 0b111, 0b00)}, bits
    s2 = (START + UNSYNCED) * 10**9
    not_in_sync = [row["time_ns"] for row in measured if not row["in_sync"]]
    in_sync = [row["time_ns"] for row in measured if row["in_sync"]]
    assert all(s2 - 200_000_000 <= t < s2 + 10**9 for t in not_in_sync), not_in_sync
    assert not any(s2 <= t < s2 + 800_000_000 for t in in_sync), in_sync
    assert len(not_in_sync) > 10 and len(in_sync) > 10
    last = good[-1]
    mags = [last["phasors"][p][0] for p in ("VA", "VB", "VC")]
    angles = [math.degrees(last["phasors"][p][1]) for p in ("VA", "VB", "VC")]
    assert all(abs(m - V_PEAK / math.sqrt(2)) / (V_PEAK / math.sqrt(2)) < 0.001 for m in mags), mags
    for k in (1, 2):
        assert abs((angles[0] - angles[k] - 120 * k + 180) % 360 - 180) < 0.1, angles
    assert abs(last["frequency_hz"] - F) < 0.005, last
    assert groups[-1]["u2"] is not None and groups[-1]["u2"] < 1e-3, groups[-1]


def _head(capture: Path, path: Path, count: int) -> Path:
    """The first ``count`` frames of a capture, as a capture of their own."""
    with pcap.PcapWriter(path) as w:
        for frame in itertools.islice(pcap.read_pcap(capture), count):
            w.write(frame)
    return path


def test_malformed_sv_is_counted_never_raised_and_other_streams_go_on(capture):
    good = [c.data for c in itertools.islice(pcap.read_pcap(capture), 4)]
    got: list[Frame] = []
    gw = SvGateway(GatewayOptions(rate=RATE, samples=2), lambda name, f: got.append(f))
    gw.feed(good[0], START * 10**9)
    gw.feed(good[0][:60], START * 10**9)  # cut: its Length field says more (open61850: not an SV frame)
    broken = bytearray(good[1])
    broken[22] = 0x61  # the SavPdu tag ([APPLICATION 0] = 0x60) after the 14 + 8 header bytes
    gw.feed(bytes(broken), START * 10**9 + 250_000)
    seven = svp.SvStream(sv_id=SV_ID, app_id=0x4000, dst_mac="01:0c:cd:04:00:01", src_mac="02:00:00:00:00:01",
                         waves=[svp.Wave(1.0, scale=1000)] * 7, smp_synch=2)  # fmt: skip
    gw.feed(svp.render_frame(svp.build_template(seven, 1, RATE), seven, START, 1, RATE), START * 10**9 + 250_000)
    high = svp.render_frame(svp.build_template(_stream(2), 1, 8000), _stream(2), START, 5000, 8000)
    gw.feed(high, START * 10**9 + 625_000_000)  # smpCnt 5000: beyond the 4000 a second
    gw.feed(good[1], START * 10**9 + 250_000 + LATENCY_NS)
    assert (gw.not_sv, gw.undecodable, gw.streams[SV_ID].stats.rejected) == (1, 1, 2)
    assert len(got) == 1 and got[0].n_samples == 2 and got[0].seq == 0  # samples 0 and 1, unharmed


def test_realtime_reads_the_same_frames_at_the_capture_s_pace(tmp_path, capture):
    import threading

    from sinewatch.apps.gateway import pcap_frames

    short = _head(capture, tmp_path / "short.pcap", 400)  # 0.1 s of traffic
    stop = threading.Event()
    assert list(pcap_frames(str(short), realtime=True, stop=stop)) == list(
        pcap_frames(str(short), realtime=False, stop=stop)
    )


def test_a_cut_capture_publishes_what_was_complete_then_says_so(tmp_path, capture):
    short = _head(capture, tmp_path / "short.pcap", 1000)
    cut = tmp_path / "cut.pcap"
    cut.write_bytes(short.read_bytes()[:-10])  # the last record cut, as a killed capture leaves it
    config = make_config(tmp_path, rules=[EstimatorRule(match="sinewatch/in/**", estimator="ipdft", params=IPDFT)])

    def client(_daemon, ep):
        with connect([ep]) as s:
            est = subscribe_estimates(s)
            r = subprocess.run(
                [sys.executable, "-m", "sinewatch", "gateway", "sv", "--pcap", str(cut), "--connect", ep,
                 "--samples", "100", "--wait", "30"],
                capture_output=True, text=True, timeout=300, check=False,
            )  # fmt: skip
            return r, take(est, 8 * 10)

    (r, got), _daemon, code = run_daemon(config, client)
    assert r.returncode == 2 and code == 0
    assert r.stderr.strip().splitlines()[-1].startswith("sinewatch: error: --pcap ") and "expected a pcap" in r.stderr
    [stream] = json.loads(r.stdout.strip().splitlines()[-1])["streams"]
    assert stream["samples"] == 999 and stream["frames"] == 10  # 9 frames of 100, then the 99 complete
    assert len(got) == 80


def test_two_asdus_a_frame_at_4800_per_second_as_iec_61869_9_sends_them(tmp_path):
    """Several ASDUs in one Ethernet frame (IEC 61869-9; 60 Hz, 4800/s, 2 a frame): every
    sample is taken, in order, on the 4800/s grid of the UTC second, none lost."""
    rate = 4800
    stream = _stream(sv.SMP_SYNCH_GLOBAL)
    template = svp.build_template(stream, 2, rate)
    path = tmp_path / "two.pcap"
    with pcap.PcapWriter(path) as w:
        for c in range(0, rate, 2):  # a frame leaves with its last sample
            w.write(svp.render_frame(template, stream, START, c, rate), (START * 10**9 + (c + 1) * 10**9 // rate) / 1e9)
    frames: list[Frame] = []
    gw = SvGateway(GatewayOptions(rate=rate, samples=160), lambda name, f: frames.append(f))
    for captured in pcap.read_pcap(path):
        gw.feed(captured.data, round(captured.timestamp * 1e9))
    gw.flush()
    stats = gw.streams[SV_ID].stats
    assert (stats.samples, stats.lost, stats.repeated, stats.rejected) == (rate, 0, 0, 0)
    assert [f.seq for f in frames] == list(range(rate // 160))
    assert [f.t0_ns for f in frames] == [START * 10**9 + round(k * 160 * 1e9 / rate) for k in range(rate // 160)]
    va = np.concatenate([f.samples[:, 4] for f in frames])
    expected = [svp.sample_values(stream, START, c, rate)[4] * 0.01 for c in range(rate)]
    assert np.array_equal(va, np.asarray(expected))


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        ([], "expected exactly one of --pcap FILE or --iface NAME"),
        (["--pcap", "x.pcap", "--iface", "eth0"], "expected exactly one of --pcap FILE or --iface NAME"),
        (["--pcap", "x.pcap", "--channels", "MU01=a,b"], "--channels: expected SVID=NAME,... with 8 names"),
        (["--pcap", "x.pcap", "--channels", "MU01=a,b,c,d,e,f,g,h i"], "--channels: expected SVID=NAME,..."),
        (["--pcap", "x.pcap", "--dst-mac", "01:0c:cd"], "--dst-mac: expected six hex octets"),
    ],
)
def test_gateway_mistakes_are_one_line_saying_what_was_expected(capsys, argv, says):
    from sinewatch.apps.cli import main

    assert main(["gateway", "sv", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0]
