"""Power quality served by the daemon: three-phase groups, IEC 61000-4-7 harmonics and
IEC 61000-4-30 aggregates on Zenoh, recorded and replayed bit for bit.

Truth comes from the power-quality scenarios (:mod:`sinewatch.scenarios.power_quality_iec`),
whose signals are sums of sines with exactly known RMS values, phases and sequence
components; limits from :mod:`sinewatch.power_quality.limits` (IEC 61000-4-30 class A for
u2: 0.15 percentage points; IEC 61000-4-7 class I for harmonics).
"""

from __future__ import annotations

import json
import os
import queue
from pathlib import Path

import numpy as np
import pytest
from conftest import TIMEOUT, FakeClock, make_config, replay_recording, run_daemon, serve_feed_tail

from sinewatch.apps.feed import make_channels
from sinewatch.clients import BlockPublisher, connect
from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.outputs.recorder import McapRecorder
from sinewatch.power_quality.limits import LIMITS, class_i_limit
from sinewatch.runtime.replay import replay
from sinewatch.scenarios.power_quality_iec import get_pq
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import (
    EstimatorRule,
    HarmonicsRule,
    PowerQualitySection,
    RecordingSection,
    SinewatchConfig,
    ThreePhaseGroup,
)
from sinewatch.schemas.errors import ConfigError
from sinewatch.schemas.power_quality import HarmonicsReport, PqAggregate, ThreePhaseReport, json_encoding

SCENARIO = "pq-unbalance-50hz-u2-2pct-harmonics-m5"  # u2 = 2 %, 5th/7th/11th/3rd harmonics, f = 47.5 Hz
IPDFT_50 = {"nominal_frequency_hz": 50.0, "window_cycles": 10}
T0_NS = 598_000_000_000  # 2 s before a 10-min tick of absolute time: the run crosses it
BLOCK = 1000  # samples, 0.1 s at 10 kHz
MODELS = {"HarmonicsReport": HarmonicsReport, "ThreePhaseReport": ThreePhaseReport, "PqAggregate": PqAggregate}
REPO = Path(__file__).resolve().parents[1]


def pq_config(tmp_path: Path, phases: list[str], **overrides) -> SinewatchConfig:
    return make_config(
        tmp_path,
        rules=[EstimatorRule(match="sinewatch/in/**", estimator="ipdft", params=IPDFT_50)],
        power_quality=PowerQualitySection(
            harmonics=[HarmonicsRule(match="sinewatch/in/**", nominal_frequency_hz=50)],
            groups=[ThreePhaseGroup(name="feeder1", phases=phases, max_skew_s=0.25, aggregate_nominal_frequency_hz=50)],
        ),
        **overrides,
    )


class Outputs(NullSink):
    """Every power-quality output of a pipeline, raw, in order."""

    def __init__(self) -> None:
        self.out: list[tuple[str, str, bytes]] = []

    def on_output(self, kind: str, key: str, payload: bytes, log_time_ns: int) -> None:
        self.out.append((kind, key, payload))


class OutputsErrorsEstimates(Outputs):
    """The power-quality outputs, the errors (decoded) and how many estimates."""

    def __init__(self) -> None:
        super().__init__()
        self.errors: list[dict] = []
        self.estimates = 0

    def on_error(self, key, payload, log_time_ns):
        self.errors.append(json.loads(payload))

    def on_estimate(self, key, payload, log_time_ns):
        self.estimates += 1


def phase_blocks(n_blocks: int, prefix: str = "pq") -> tuple[list[list[Block]], list[str]]:
    """Blocks of the three phases of SCENARIO (what `sinewatch feed` cuts), per round."""
    channels = make_channels([SCENARIO], prefix=prefix)
    names = [c.channel for c in channels]
    rounds = []
    for i in range(n_blocks):
        rounds.append(
            [Block(c.channel, i, T0_NS + i * BLOCK * 100_000, 10_000.0, c.stream.read(BLOCK)[0]) for c in channels]
        )
    return rounds, names


def check_accuracy(outputs: list[tuple[str, str, dict]], names: list[str]) -> dict[str, float]:
    """Assert the reports against the scenario's truth; return the worst error / limit."""
    truth = get_pq(SCENARIO).pq_truth
    groups = [m for kind, _, m in outputs if kind == "ThreePhaseReport"]
    harmonics = [m for kind, _, m in outputs if kind == "HarmonicsReport"]
    # group: settled once the 10-cycle estimator window has filled (0.21 s: from the 3rd block)
    settled = [g for g in groups if g["timestamp_ns"] >= T0_NS + 300_000_000]
    assert settled and all(g["missing"] == [] for g in groups)
    u2_err = max(abs(g["u2"] - truth.u2) for g in settled)
    u0_err = max(abs(g["u0"] - truth.u0) for g in settled)
    v1_err = max(abs(g["positive"]["magnitude_rms"] - abs(truth.sequence_rms[1])) for g in settled)
    assert u2_err <= LIMITS["u2_absolute"]  # IEC 61000-4-30 class A: 0.15 percentage points
    assert u0_err <= LIMITS["u2_absolute"]
    assert v1_err <= LIMITS["magnitude_relative"] * abs(truth.sequence_rms[1])
    assert all(abs(g["frequency_hz"] - truth.frequency_hz) <= LIMITS["frequency_hz"] for g in settled)
    # harmonics: every order of every window of every phase within class I
    worst = 0.0
    for p, name in enumerate(names):
        reports = [h for h in harmonics if h["channel"] == name]
        assert len(reports) >= 15
        lim = class_i_limit(truth.harmonic_rms[p], truth.harmonic_rms[p, 1])
        for h in reports:
            c = np.array(h["harmonic_rms"], dtype=float)
            ratio = np.abs(c[1:] - truth.harmonic_rms[p, 1:]) / lim[1:]
            worst = max(worst, float(ratio.max()))
            assert abs(h["thd"] - truth.thd[p]) <= LIMITS["harmonic_relative"] * truth.thd[p]
    assert worst <= 1.0
    return {"u2_pp": 100 * u2_err, "harmonic_over_limit": worst}


def test_live_daemon_groups_harmonics_aggregates_recorded_and_replayed(tmp_path):
    rounds, names = phase_blocks(60)  # 6 s of signal: 28 windows per phase, a 10-min tick at 2 s
    config = pq_config(tmp_path, names)
    reference = Outputs()  # what a pipeline given exactly these blocks says
    ref_pipeline = Pipeline(config, [reference])
    for blocks in rounds:
        for b in blocks:
            ref_pipeline.process(f"sinewatch/in/{b.channel}", encode_block_binary(b), BLOCK_BINARY_ENCODING, 0)
    expected = reference.out

    def client(_daemon, ep):
        got: queue.Queue[tuple[str, str, bytes]] = queue.Queue()
        with connect([ep]) as s:
            sub = s.declare_subscriber(
                "sinewatch/pq/**", lambda x: got.put((str(x.key_expr), str(x.encoding), x.payload.to_bytes()))
            )
            pub = BlockPublisher(s, dtype="float64")
            assert all(pub.wait_for_subscriber(n, TIMEOUT) for n in names)
            for blocks in rounds:
                for b in blocks:
                    pub.publish_raw(b.channel, encode_block_binary(b))
            out = []
            while len(out) < len(expected):
                try:
                    out.append(got.get(timeout=TIMEOUT))
                except queue.Empty:
                    break
            sub.undeclare()
            return out

    received, daemon, code = run_daemon(config, client)
    assert code == 0
    # the daemon said on Zenoh exactly what the reference pipeline says, byte for byte, per key
    assert len(received) == len(expected)
    by_key: dict[str, list[bytes]] = {}
    for key, encoding, payload in received:
        kind = json.loads(payload).keys()
        model = (
            "HarmonicsReport" if "harmonic_rms" in kind else "ThreePhaseReport" if "group" in kind else "PqAggregate"
        )
        assert encoding == json_encoding(model)
        MODELS[model].model_validate_json(payload)  # valid against its schema
        by_key.setdefault(key, []).append(payload)
    ref_by_key: dict[str, list[bytes]] = {}
    for _kind, key, payload in expected:
        ref_by_key.setdefault(key, []).append(payload)
    assert by_key == ref_by_key
    assert set(by_key) == {
        "sinewatch/pq/group/feeder1",
        "sinewatch/pq/agg/feeder1",
        *(f"sinewatch/pq/harmonics/{n}" for n in names),
        *(f"sinewatch/pq/agg/{n}" for n in names),
    }
    decoded = [(kind, key, json.loads(p)) for kind, key, p in expected]
    check_accuracy(decoded, names)
    assert sum(kind == "ThreePhaseReport" for kind, _, _ in decoded) == 60  # one per timestamp
    aggs = [m for kind, _, m in decoded if kind == "PqAggregate"]
    short = [a for a in aggs if a["interval"] == "150/180-cycle"]
    ten_min = [a for a in aggs if a["interval"] == "10-min"]
    # the tick at 600 s closes a 10-min interval (incomplete: the stream started at 598 s); the
    # 150/180-cycle one in progress goes on with the new stream's windows to its 15 (overlap 2)
    # while new ones start at the tick; per phase and for the group
    assert {a["timestamp_ns"] for a in ten_min} == {600_000_000_000} and len(ten_min) == 4
    assert all(not a["complete"] for a in ten_min)
    complete = [a for a in short if a["complete"]]
    assert all(a["n_windows"] == 15 for a in complete)
    overlap_2 = [a for a in complete if a["start_ns"] < 600_000_000_000]
    assert sorted(a["source"] for a in overlap_2) == sorted([*names, "feeder1"])
    assert all(a["timestamp_ns"] > 600_000_000_000 for a in overlap_2)
    assert {a["source"] for a in complete if a["start_ns"] == 600_000_000_000} == {*names, "feeder1"}
    ten_s = [a for a in aggs if a["interval"] == "10-s"]  # 590..600 s, incomplete (from 598 s)
    assert len(ten_s) == 4 and all(a["start_ns"] == 590_000_000_000 and not a["complete"] for a in ten_s)
    truth = get_pq(SCENARIO).pq_truth
    for a in complete:  # aggregated frequency (cycles / duration), THD and u2 (RMS of the window values)
        assert abs(a["values"]["frequency_hz"] - truth.frequency_hz) <= LIMITS["frequency_hz"]
        if a["source"] == "feeder1":
            assert abs(a["values"]["u2"] - truth.u2) <= LIMITS["u2_absolute"]
            assert abs(a["values"]["u0"] - truth.u0) <= LIMITS["u2_absolute"]
            assert abs(a["values"]["positive_rms"] - abs(truth.sequence_rms[1])) <= 1e-3 * abs(truth.sequence_rms[1])
        else:
            p = names.index(a["source"])
            assert abs(a["values"]["thd"] - truth.thd[p]) <= LIMITS["harmonic_relative"] * truth.thd[p]

    # recorded with a role and a JSON Schema per kind; the recording replays bit for bit
    [path] = daemon.recording_paths
    result = replay([path])
    assert result.ok and result.inputs == 180 and result.matched == 180
    n_kind = {k: sum(kind == k for kind, _, _ in expected) for k in MODELS}
    assert (
        result.recorded_other
        == result.matched_other
        == {
            "harmonics": n_kind["HarmonicsReport"],
            "three_phase": n_kind["ThreePhaseReport"],
            "pq_aggregate": n_kind["PqAggregate"],
        }
    )


def record_and_replay(config, recorder, rounds):
    """Run the rounds of phase blocks through a pipeline that records to ``recorder`` (round i
    logged at i + 1 ns), close the files and replay them."""
    pipeline = Pipeline(config, [recorder])
    for i, blocks in enumerate(rounds):
        for b in blocks:
            pipeline.process(f"sinewatch/in/{b.channel}", encode_block_binary(b), BLOCK_BINARY_ENCODING, i + 1)
    pipeline.release_held(len(rounds) + 1)  # the input's end, as the daemon's drain
    recorder.close()
    return replay(recorder.paths)


def test_replay_catches_a_changed_pq_output(tmp_path):
    """The comparator covers the new roles: a recording whose harmonics differ fails."""
    rounds, names = phase_blocks(12)
    config = pq_config(tmp_path, names, recording=RecordingSection(directory=tmp_path / "rec"))
    recorder = McapRecorder(config)
    original = recorder.on_output
    seen = {"n": 0}

    def tampered(kind, key, payload, log_time_ns):
        if kind == "HarmonicsReport":
            seen["n"] += 1
            if seen["n"] == 3:
                payload = payload.replace(b'"converged":true', b'"converged":false')
        original(kind, key, payload, log_time_ns)

    recorder.on_output = tampered
    result = record_and_replay(config, recorder, rounds)
    assert not result.ok and result.matched == 36
    [m] = result.mismatches
    assert m.role == "harmonics" and m.topic.startswith("sinewatch/pq/harmonics/")
    assert "converged: recorded False != replayed True" in m.describe()


def test_a_recording_without_pq_messages_replays(tmp_path):
    """recording.power_quality = false: the messages are published, not recorded; replay
    compares the estimates and does not count the unrecorded messages as mismatches."""
    rounds, names = phase_blocks(12)
    config = pq_config(tmp_path, names, recording=RecordingSection(directory=tmp_path / "rec", power_quality=False))
    recorder = McapRecorder(config)
    result = record_and_replay(config, recorder, rounds)
    assert result.ok and result.matched == 36 and result.recorded_other == {} and result.produced_other == {}


def test_a_phase_that_stops_is_reported_missing_after_the_skew_bound(tmp_path):
    rounds, names = phase_blocks(20)
    config = pq_config(tmp_path, names)  # max_skew_s = 0.25: 2.5 blocks of 0.1 s
    out = Outputs()
    pipeline = Pipeline(config, [out])
    for i, blocks in enumerate(rounds):
        for b in blocks:
            if b.channel == names[2] and i >= 10:
                continue  # phase c stops after block 9
            pipeline.process(f"sinewatch/in/{b.channel}", encode_block_binary(b), BLOCK_BINARY_ENCODING, 0)
        stamp = T0_NS + i * 100_000_000 + 99_900_000  # the estimates' timestamp (last sample)
        groups = [json.loads(p) for kind, _, p in out.out if kind == "ThreePhaseReport"]
        # all timestamps up to this one are out, except those within the bound of the newest
        if i < 10:
            assert groups[-1]["timestamp_ns"] == stamp and len(groups) == i + 1
        else:
            # the last complete one (block 9), or the newest one 3 blocks behind (0.3 s > 0.25 s)
            assert groups[-1]["timestamp_ns"] == max(T0_NS + 999_900_000, stamp - 300_000_000)
    groups = [json.loads(p) for kind, _, p in out.out if kind == "ThreePhaseReport"]
    assert [g["missing"] for g in groups[:10]] == [[]] * 10
    for g in groups[10:]:
        assert g["missing"] == [names[2]] and g["phase_rms"][2] is None and g["phase_angle_rad"][2] is None
        assert g["u2"] is None and g["positive"]["magnitude_rms"] is None
        assert g["phase_rms"][0] is not None and g["frequency_hz"] is not None
    # a late estimate for a timestamp already reported is dropped, not reported twice
    late = rounds[10][2]
    pipeline.process(f"sinewatch/in/{late.channel}", encode_block_binary(late), BLOCK_BINARY_ENCODING, 0)
    assert pipeline.pq.groups["feeder1"].late == 1
    assert len([1 for kind, _, _ in out.out if kind == "ThreePhaseReport"]) == len(groups)


def test_rotated_recording_replays_alone_with_the_pq_state_in_its_snapshot(tmp_path):
    """A file that starts after a rotation carries the analysers', aggregators' and the
    group's state: replayed on its own, it reproduces its harmonics, aggregates and
    group reports bit for bit (windows, aggregates and groups straddle the rotation)."""
    rounds, names = phase_blocks(40)
    config = pq_config(
        tmp_path,
        names,
        recording=RecordingSection(directory=tmp_path / "rec", rotate_seconds=1.35, rotate_bytes=None),
    )
    clock = FakeClock()
    recorder = McapRecorder(config, snapshot=lambda: pipeline.snapshot(), clock=clock)
    pipeline = Pipeline(config, [recorder])
    for i, blocks in enumerate(rounds):
        for j, b in enumerate(blocks):
            if j == 2 and i in (13, 14):
                continue  # phase c late across the rotation: the group has pending timestamps
            pipeline.process(f"sinewatch/in/{b.channel}", encode_block_binary(b), BLOCK_BINARY_ENCODING, 3 * i + j + 1)
        clock.now += 0.1
    recorder.close()
    assert len(recorder.paths) >= 3
    for path in recorder.paths[1:]:
        result = replay([path])
        assert result.ok, [m.describe() for m in result.mismatches[:3]]
        assert result.recorded_other["harmonics"] > 0 and result.recorded_other["three_phase"] > 0
    # and the whole run in one go
    assert replay(recorder.paths).ok


def test_groups_config_is_checked():
    with pytest.raises(ConfigError, match="three different channels"):
        _load({"power_quality": {"groups": [{"name": "g", "phases": ["a", "b", "a"]}]}})
    with pytest.raises(ConfigError, match="each channel in one group"):
        _load(
            {
                "power_quality": {
                    "groups": [{"name": "g", "phases": ["a", "b", "c"]}, {"name": "h", "phases": ["d", "e", "a"]}]
                }
            }
        )
    with pytest.raises(ConfigError, match="nominal_frequency_hz"):
        _load({"power_quality": {"harmonics": [{"match": "sinewatch/in/**", "nominal_frequency_hz": 55}]}})


def _load(data: dict) -> SinewatchConfig:
    from sinewatch.schemas.config import load_config

    env = {f"SINEWATCH__POWER_QUALITY__{k.upper()}": json.dumps(v) for k, v in data["power_quality"].items()}
    return load_config(None, env)


def test_feed_serve_tail_processes_with_the_deploy_config(tmp_path):
    """`sinewatch serve --config deploy/power-quality.toml` (port and directory moved by the
    environment), `sinewatch feed --scenario pq-unbalance-50hz-u2-2pct-harmonics` and
    `sinewatch tail 'sinewatch/pq/**'` as processes; then `sinewatch replay`."""
    ep = make_config(tmp_path).zenoh.listen[0]
    env = {
        **os.environ,
        "SINEWATCH__ZENOH__LISTEN": json.dumps([ep]),
        "SINEWATCH__RECORDING__DIRECTORY": str(tmp_path / "rec"),
    }
    feed_err, lines, serve_err = serve_feed_tail(
        ["--config", str(REPO / "deploy" / "power-quality.toml")],
        ["sinewatch/pq/**", "--connect", ep, "--count", "40", "--json", "--timeout", "60", "--wait", "60"],
        ["--connect", ep, "--scenario", "pq-unbalance-50hz-u2-2pct-harmonics", "--duration", "2", "--block", "1000"],
        serve_env=env,
    )
    assert "published 60 blocks" in feed_err  # 20 blocks x 3 phases
    assert len(lines) == 40
    groups = [m for m in lines if "group" in m]
    harmonics = [m for m in lines if "harmonic_rms" in m]
    assert groups and harmonics
    assert all(g["group"] == "feeder1" and g["missing"] == [] for g in groups)
    truth = get_pq("pq-unbalance-50hz-u2-2pct-harmonics").pq_truth
    late = [g for g in groups if g["u2"] is not None][-1]
    assert abs(late["u2"] - truth.u2) <= LIMITS["u2_absolute"]
    assert "drained: 60 inputs, 60 estimates, 0 errors" in serve_err
    stdout = replay_recording(tmp_path / "rec")
    assert "all 60 recorded estimates reproduced bit for bit" in stdout
    assert "all other recorded outputs (" in stdout and "three_phase)" in stdout


def test_tail_prints_each_pq_message_on_one_line(tmp_path):
    """`sinewatch tail 'sinewatch/pq/**'` without --json: one readable line per message."""
    from sinewatch.apps.cli import format_estimate

    rounds, names = phase_blocks(40)
    out = Outputs()
    pipeline = Pipeline(pq_config(tmp_path, names), [out])
    for blocks in rounds:
        for b in blocks:
            pipeline.process(f"sinewatch/in/{b.channel}", encode_block_binary(b), BLOCK_BINARY_ENCODING, 0)
    lines = {kind: format_estimate(json.loads(p)) for kind, _, p in out.out}
    assert set(lines) == set(MODELS)
    assert f"{names[2]} harmonics f=47.5000Hz" in lines["HarmonicsReport"] and " h5=" in lines["HarmonicsReport"]
    assert "feeder1 three-phase f=47.5000Hz V1=1.0000 u2=2.000% u0=1.000%" in lines["ThreePhaseReport"]
    aggregates = [format_estimate(json.loads(p)) for kind, _, p in out.out if kind == "PqAggregate"]
    # at the tick: the 10-s frequency value, then the 10-min one; the 150/180-cycle interval in
    # progress finishes later, with the new stream's windows (overlap 2)
    assert f"600.0000 {names[0]} 10-s n=10 (incomplete) frequency_hz=47.5000" in aggregates[0]
    assert f"600.0000 {names[0]} 10-min n=10 (incomplete) frequency_hz=47.5000" in aggregates[1]
    assert "thd=6.2" in aggregates[1]
    assert any(f"{names[0]} 150/180-cycle n=15 frequency_hz=47.5000" in a and "thd=6.2" in a for a in aggregates)


@pytest.mark.parametrize(
    "scenario", ["pq-unbalance-60hz-u2-2pct-harmonics-m5", "pq-unbalance-50hz-u2-0.5pct-p5", "pq-harmonics-60hz-all-p5"]
)
def test_stage_accuracy_at_60_hz_and_off_nominal(tmp_path, scenario):
    """Through the pipeline's stage (what the daemon runs, as the live test shows byte for
    byte): 12-cycle windows at 60 Hz, +-5 % off nominal, u2 from 0.5 %, all 49 harmonics."""
    sc = get_pq(scenario)
    truth = sc.pq_truth
    f0 = int(truth.nominal_frequency_hz)
    channels = make_channels([scenario], prefix="acc")
    names = [c.channel for c in channels]
    config = make_config(
        tmp_path,
        rules=[
            EstimatorRule(match="sinewatch/in/**", estimator="ipdft", params={**IPDFT_50, "nominal_frequency_hz": f0})
        ],
        power_quality=PowerQualitySection(
            harmonics=[HarmonicsRule(match="sinewatch/in/**", nominal_frequency_hz=f0)],
            groups=[ThreePhaseGroup(name="g", phases=names)] if len(names) == 3 else [],
        ),
    )
    out = Outputs()
    pipeline = Pipeline(config, [out])
    for i in range(30):
        for c in channels:
            b = Block(c.channel, i, T0_NS + i * 100_000_000, 10_000.0, c.stream.read(BLOCK)[0])
            pipeline.process(f"sinewatch/in/{c.channel}", encode_block_binary(b), BLOCK_BINARY_ENCODING, 0)
    msgs = [(kind, json.loads(p)) for kind, _, p in out.out]
    groups = [m for kind, m in msgs if kind == "ThreePhaseReport" and m["timestamp_ns"] >= T0_NS + 300_000_000]
    assert bool(groups) == (len(names) == 3)
    for g in groups:
        assert abs(g["u2"] - truth.u2) <= LIMITS["u2_absolute"] and g["missing"] == []
    for p, name in enumerate(names):
        reports = [m for kind, m in msgs if kind == "HarmonicsReport" and m["channel"] == name]
        assert len(reports) >= 10 and all(r["n_cycles"] == (10 if f0 == 50 else 12) for r in reports)
        lim = class_i_limit(truth.harmonic_rms[p], truth.harmonic_rms[p, 1])
        for r in reports:
            err = np.abs(np.array(r["harmonic_rms"][1:], dtype=float) - truth.harmonic_rms[p, 1:])
            assert np.all(err <= lim[1:])


def test_harmonics_at_a_rate_too_low_are_refused_once_and_estimation_goes_on(tmp_path):
    config = pq_config(tmp_path, ["x/a", "x/b", "x/c"])
    keep = OutputsErrorsEstimates()
    pipeline = Pipeline(config, [keep])
    t = np.arange(500) / 5_000.0
    for i in range(5):  # 5 kHz: the 50th harmonic of 57.5 Hz is beyond 0.4 fs
        x = np.sin(2 * np.pi * 50.0 * (t + i * 0.1))
        b = Block("slow", i, T0_NS + i * 100_000_000, 5_000.0, x)
        pipeline.process("sinewatch/in/slow", encode_block_binary(b), BLOCK_BINARY_ENCODING, 0)
    pipeline.release_held(0)  # the input's end: the estimates held back for the presence detector
    assert keep.estimates == 5 and keep.out == []
    [err] = keep.errors
    assert err["kind"] == "estimator_error" and err["channel"] == "slow" and err["seq"] == 0
    assert "harmonics off for channel 'slow'" in err["message"] and "7331.25" in err["message"]


def test_group_aggregates_at_a_rate_below_harmonic_range_come_from_the_fundamental(tmp_path):
    """A three-phase group's aggregates (u2, u0, sequence magnitudes, frequency) need only the
    fundamental: at 4 kHz, too slow for harmonics to the 50th, the group still aggregates, each
    phase's estimate is published, and nothing is reported as an error; the per-channel harmonics
    are refused once each, as above."""
    fs, n = 4_000.0, 400  # 0.1 s blocks
    truth = get_pq(SCENARIO).pq_truth
    channels = make_channels([SCENARIO], prefix="slow", sample_rate_hz=fs)
    names = [c.channel for c in channels]
    config = make_config(
        tmp_path,
        rules=[EstimatorRule(match="sinewatch/in/**", estimator="ipdft", params=IPDFT_50)],
        power_quality=PowerQualitySection(
            groups=[ThreePhaseGroup(name="feeder1", phases=names, max_skew_s=0.25, aggregate_nominal_frequency_hz=50)],
        ),
    )

    keep = OutputsErrorsEstimates()
    pipeline = Pipeline(config, [keep])
    for i in range(40):  # 4 s: 18 windows, one complete 150-cycle aggregate
        for c in channels:
            b = Block(c.channel, i, T0_NS + i * 100_000_000, fs, c.stream.read(n)[0])
            pipeline.process(f"sinewatch/in/{c.channel}", encode_block_binary(b), BLOCK_BINARY_ENCODING, 0)
    pipeline.release_held(0)  # the input's end: the estimates held back for the presence detector
    assert keep.errors == [] and keep.estimates == 120
    aggs = [json.loads(p) for kind, _, p in keep.out if kind == "PqAggregate"]
    complete = [a for a in aggs if a["interval"] == "150/180-cycle" and a["complete"]]
    assert complete and all(a["source"] == "feeder1" for a in complete)
    for a in complete:
        assert abs(a["values"]["u2"] - truth.u2) <= LIMITS["u2_absolute"]
        assert abs(a["values"]["frequency_hz"] - truth.frequency_hz) <= LIMITS["frequency_hz"]


def test_group_window_analysis_below_its_least_rate_is_a_parameter_error():
    from sinewatch.power_quality.stage import _group_params
    from sinewatch.schemas.errors import ParameterError

    assert _group_params(50, 10_000.0).max_harmonic == 50  # unchanged where the rate carries the 50th
    assert _group_params(50, 4_000.0).max_harmonic == 26  # (26 + 1) x 57.5 Hz <= 1600 Hz < 28 x 57.5
    with pytest.raises(ParameterError, match=r"expected >= 431.25 Hz .* got 400"):
        _group_params(50, 400.0)
