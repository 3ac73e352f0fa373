"""Power quality: the IEC 61000-4-7 harmonic analyser against exact truth (class I limits),
symmetrical components and unbalance (IEC 61000-4-30 class A), the 150/180-cycle and
10-min aggregation against hand-computed values (with the 10-min resynchronisation), and
the messages' JSON round trips."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sinewatch.power_quality import (
    Aggregator,
    HarmonicAnalyser,
    WindowValues,
    channel_window_values,
    group_window_values,
    harmonics_report,
    phases_from_sequence,
    symmetrical_components,
    three_phase_report,
    window_sequence,
)
from sinewatch.power_quality.sequence import A
from sinewatch.scenarios.power_quality_iec import LIMITS, class_i_limit, get_pq, pq_names
from sinewatch.schemas.errors import InputError, ParameterError
from sinewatch.schemas.power_quality import (
    PQ_MESSAGE_MODELS,
    HarmonicsReport,
    PqAggregate,
    ThreePhaseReport,
    encode_pq,
    json_encoding,
)

NS = 1_000_000_000


def run(analyser: HarmonicAnalyser, y: np.ndarray, fs: float, block: int = 997, t0_ns: int = 0):
    windows = []
    for i in range(0, y.shape[0], block):
        windows += analyser.update(y[i : i + block], t0_ns + round(i * NS / fs))
    return windows


def analyse(name: str, **overrides):
    sc = get_pq(name, **overrides)
    y, _ = sc.generate()
    an = HarmonicAnalyser(sc.sample_rate_hz, nominal_frequency_hz=sc.nominal_frequency_hz, n_channels=sc.n_phases)
    return sc, run(an, y, sc.sample_rate_hz)


# ---- harmonics: IEC 61000-4-7 class I ----------------------------------------------------------

HARMONIC_FAMILIES = [
    f"pq-harmonics-{f}hz-{lvl}{off}" for f in (50, 60) for lvl in ("all", "low") for off in ("", "-m5", "-p5")
]


@pytest.mark.parametrize("name", HARMONIC_FAMILIES)
def test_harmonics_2_to_50_within_class_i(name):
    """Every harmonic 2..50 at once (1-10 %, or 0.1-0.9 % where the limit is 0.05 % of
    nominal), fundamental at nominal and +-5 %: every window, every order, THD."""
    sc, windows = analyse(name)
    truth = sc.pq_truth
    assert len(windows) >= 8
    limit = class_i_limit(truth.harmonic_rms[0, 1:], truth.harmonic_rms[0, 1])
    for w in windows:
        assert w.converged and w.n_cycles == (10 if sc.nominal_frequency_hz == 50 else 12)
        err = np.abs(w.harmonic_rms[0, 1:] - truth.harmonic_rms[0, 1:])
        # measured worst: 1.4e-4 of the limit (tests/test_power_quality.py; python -m sinewatch.power_quality.speed)
        assert np.all(err <= 0.01 * limit), (name, int(np.argmax(err / limit)) + 1, float(np.max(err / limit)))
        assert abs(w.thd[0] - truth.thd[0]) <= 0.01 * LIMITS["harmonic_relative"] * truth.thd[0]
        assert abs(w.frequency_hz - truth.frequency_hz) <= 1e-6
        # subgroups and groups hold the harmonic itself (no interharmonics in the signal)
        np.testing.assert_allclose(w.harmonic_subgroup_rms[0, 1:], truth.harmonic_rms[0, 1:], rtol=1e-3, atol=2e-6)
        np.testing.assert_allclose(w.harmonic_group_rms[0, 1:], truth.harmonic_rms[0, 1:], rtol=1e-3, atol=2e-6)
        assert np.max(w.interharmonic_centred_subgroup_rms) < 1e-4 * truth.harmonic_rms[0, 1]
        np.testing.assert_allclose(w.rms[0], math.sqrt(np.sum(truth.harmonic_rms[0] ** 2)), rtol=1e-5)


@pytest.mark.parametrize("f0", [50.0, 60.0])
@pytest.mark.parametrize("df", [-5.0, 0.0, 5.0])
@pytest.mark.parametrize("h", [2, 3, 7, 13, 25, 49, 50])
def test_single_harmonic_magnitude_and_phase(f0, df, h):
    sc, windows = analyse(f"pq-harmonic-{int(f0)}hz-single", harmonic=h, level=0.01, df_pct=df)
    w = windows[-1]
    true = sc.pq_truth.harmonic_rms[0, h]
    assert abs(w.harmonic_rms[0, h] - true) <= 0.01 * LIMITS["harmonic_relative"] * true
    # phase at the window end: 2 pi h f t_end + phi_h
    t_end = w.end_ns / NS
    expect = 2 * np.pi * h * sc.frequency_hz * t_end + sc.harmonic_phase[0, h]
    assert abs(np.angle(np.exp(1j * (w.harmonic_phase_rad[0, h] - expect)))) < 1e-3
    others = np.delete(w.harmonic_rms[0, 2:], h - 2)
    assert np.max(others) < 1e-5  # no leakage into the other orders


@pytest.mark.slow
@pytest.mark.parametrize("f0", [50.0, 60.0])
def test_every_single_harmonic_every_level_slow(f0):
    """The full sweep: each harmonic 2..50 alone at 1 %, 5 % and 10 %, f0 -5/0/+5 %."""
    worst = 0.0
    for h in range(2, 51):
        for level in (0.01, 0.05, 0.10):
            for df in (-5.0, 0.0, 5.0):
                sc, windows = analyse(f"pq-harmonic-{int(f0)}hz-single", harmonic=h, level=level, df_pct=df)
                true = sc.pq_truth.harmonic_rms[0]
                lim = class_i_limit(true[1:], 1.0)
                for w in windows:
                    worst = max(worst, float(np.max(np.abs(w.harmonic_rms[0, 1:] - true[1:]) / lim)))
    assert worst <= 0.01, worst


def test_groups_and_subgroups_follow_the_standard_bins():
    """An interharmonic between orders 5 and 6 (at 5.5 f, bin 55 of a 10-cycle window) lands
    in the interharmonic group and centred subgroup 5 and in no harmonic subgroup; one at
    5.1 f (bin 51) goes to harmonic group 5 and subgroup 5 (bins 49..51), not to the
    centred subgroup (bins 52..58). Tolerance 1e-8: the synchronisation (F) puts the
    interharmonic on its bin (measured leakage below 1e-13)."""
    fs, f = 10_000.0, 50.0
    t = np.arange(int(2 * fs)) / fs
    for ratio, in_isg, in_sg in ((5.5, True, False), (5.1, False, True)):
        y = math.sqrt(2) * np.sin(2 * np.pi * f * t) + math.sqrt(2) * 0.03 * np.sin(2 * np.pi * ratio * f * t + 0.2)
        w = run(HarmonicAnalyser(fs), y, fs)[-1]
        assert abs(w.interharmonic_group_rms[0, 5] - 0.03) < 1e-8
        assert abs(w.interharmonic_centred_subgroup_rms[0, 5] - (0.03 if in_isg else 0.0)) < 1e-8
        assert abs(w.harmonic_subgroup_rms[0, 5] - (0.03 if in_sg else 0.0)) < 1e-8
        # bin 55 is the half-weighted edge of groups 5 and 6 (50 Hz: bins 45..55, 55..65)
        assert abs(w.harmonic_group_rms[0, 5] - (0.03 if in_sg else 0.03 / math.sqrt(2))) < 1e-8
        assert w.harmonic_rms[0, 5] < 1e-8
        assert abs(w.thds[0] - (0.03 if in_sg else 0.0)) < 1e-8
    # the same edge at 60 Hz: an interharmonic at 5.5 f is bin 66,
    # exactly halfway: half its power in group 5, half in group 6
    fs, f = 10_000.0, 60.0
    t = np.arange(int(2 * fs)) / fs
    y = math.sqrt(2) * np.sin(2 * np.pi * f * t) + math.sqrt(2) * 0.04 * np.sin(2 * np.pi * 5.5 * f * t)
    w = run(HarmonicAnalyser(fs, nominal_frequency_hz=60.0), y, fs)[-1]
    assert abs(w.harmonic_group_rms[0, 5] - 0.04 / math.sqrt(2)) < 1e-4
    assert abs(w.harmonic_group_rms[0, 6] - 0.04 / math.sqrt(2)) < 1e-4


def test_thd_stops_at_the_40th_order():
    """IEC 61000-4-7 sets H = 40 for THD, THDG and THDS: a 1 % 45th harmonic is reported in
    ``harmonic_rms`` but adds nothing to them (before: THD read 1 % for a 0 % truth)."""
    fs, f = 10_000.0, 50.0
    t = np.arange(int(1 * fs)) / fs
    y = math.sqrt(2) * (
        np.sin(2 * np.pi * f * t) + 0.05 * np.sin(10 * np.pi * f * t) + 0.01 * np.sin(90 * np.pi * f * t)
    )
    for w in run(HarmonicAnalyser(fs), y, fs):
        assert abs(w.harmonic_rms[0, 45] - 0.01) < 1e-7
        for ratio in (w.thd[0], w.thdg[0], w.thds[0]):
            assert abs(ratio - 0.05) < 1e-7
    w = run(HarmonicAnalyser(fs, max_harmonic=30), y, fs)[-1]
    assert w.harmonic_rms.shape == (1, 31) and abs(w.thd[0] - 0.05) < 1e-7


# ---- interharmonics: IEC 61000-4-7 class I with the synchronisation they used to bias -------


def one_interharmonic(f0: float, ratio: float, level: float, phase: float, df: float = 0.0, seconds: float = 1.0):
    sc = get_pq(
        f"pq-interharmonic-{int(f0)}hz-single", ratio=ratio, level=level, phase=phase, df_pct=df, duration_s=seconds
    )
    y, _ = sc.generate()
    an = HarmonicAnalyser(sc.sample_rate_hz, nominal_frequency_hz=f0)
    return sc, run(an, y, sc.sample_rate_hz)


@pytest.mark.parametrize(("f0", "ratio", "level"), [(50.0, 2.5, 0.015), (50.0, 3.5, 0.01), (60.0, 2.5, 0.02)])
@pytest.mark.parametrize("phase", [0.0, 1.6, 2.6])
def test_an_interharmonic_does_not_move_the_window(f0, ratio, level, phase):
    """A 1.5 % interharmonic at 125 Hz (2.5 f at 50 Hz) used to bias the window's
    frequency by up to 1.5 mHz through the one-cycle phasors, smearing the fundamental
    into interharmonic group 1 (0.04 % of it at phase 2.6 rad, 0.76 of the class I limit
    of 0.05 % of nominal). Now: the frequency within 1e-6 Hz and group 1 below 1e-6 (the
    resampler's own error: 5e-7 Hz at 60 Hz, 10 kHz; 0 at 50 Hz)."""
    sc, windows = one_interharmonic(f0, ratio, level, phase)
    k = int(ratio)
    for w in windows:
        assert abs(w.frequency_hz - sc.frequency_hz) < 1e-6
        assert w.interharmonic_group_rms[0, 1] < 1e-6
        assert abs(w.interharmonic_group_rms[0, k] - level) < 1e-6
        assert abs(w.harmonic_rms[0, 1] - 1.0) < 1e-5  # the resampler: 1.9e-6 at 60 Hz


@pytest.mark.parametrize(("f0", "f1"), [(50.0, 49.7), (60.0, 60.2)])
def test_an_interharmonic_off_the_bins_does_not_move_the_window(f0, f1):
    """Interharmonics do not follow the fundamental: 5 % at frequencies off the window's
    bins (103.7, 180.1, 1234.5 and 2471.9 Hz, from just above the 2nd order to near the
    50th), three phases each: the window's frequency stays within 1e-5 Hz of the truth
    (measured worst 2.7e-6 Hz, at 103.7 Hz beside 60.2 Hz)."""
    fs = 10_000.0
    t = np.arange(int(1.2 * fs)) / fs
    for fi in (103.7, 180.1, 1234.5, 2471.9):
        for ph in (0.0, 1.0, 2.0):
            y = math.sqrt(2) * (np.sin(2 * np.pi * f1 * t + 0.4) + 0.05 * np.sin(2 * np.pi * fi * t + ph))
            for w in run(HarmonicAnalyser(fs, nominal_frequency_hz=f0), y, fs):
                assert abs(w.frequency_hz - f1) < 1e-5, (fi, ph, w.frequency_hz)


def worst_scores(name: str, **overrides) -> dict[str, float]:
    from sinewatch.apps.bench.pq_accuracy import sinewatch_scores

    sc = get_pq(name, **overrides)
    y, _ = sc.generate()
    return {k: v["ratio"] for k, v in sinewatch_scores(sc, y.reshape(y.shape[0], -1), sc.pq_truth).items()}


INTERHARMONIC_SUBSET = [
    "pq-interharmonics-50hz-5pct",
    "pq-interharmonics-50hz-1pct-m5",
    "pq-interharmonics-60hz-5pct-p5",
    "pq-interharmonics-60hz-3pct-m5",
    "pq-unbalance-50hz-u2-2pct-interharmonic-5pct-m5",
    "pq-unbalance-60hz-u2-2pct-interharmonic-5pct-p5",
]


@pytest.mark.parametrize("name", INTERHARMONIC_SUBSET)
def test_interharmonics_within_class_i(name):
    """Interharmonics 1-5 % (2.5 f, 13 + 2/N f, 49.5 f) with harmonics, or 5 % at 2.5 f
    with 2 % unbalance, at 50/60 Hz and +-5 %: every quantity the bench scores (harmonic
    subgroups and groups, interharmonic groups and centred subgroups, THD/THDG/THDS
    against a class I reading, frequency and u2/u0 against class A) within 1 % of its
    limit on every window (measured worst: 0.3 %; before, 141 % on interharmonic groups
    of the unbalance scenario at 50 Hz -5 %)."""
    scores = worst_scores(name, duration_s=1.0)
    assert {"harmonics", "interharmonic_groups", "thdg", "frequency"} <= set(scores)
    assert ("u2" in scores) == ("unbalance" in name)
    bad = {k: v for k, v in scores.items() if not v <= 0.01}
    assert not bad, bad


@pytest.mark.slow
@pytest.mark.parametrize("f0", [50.0, 60.0])
def test_every_interharmonic_position_and_level_slow(f0):
    """The full grid: one interharmonic at 1, 3 and 5 % in every interharmonic group 2..49
    (its middle, the bins next to the harmonics either side, and the second bin), f0
    -5/0/+5 %, every bench quantity within 1 % of its class I / class A limit."""
    n = 10 if f0 == 50.0 else 12
    worst = (0.0, "")
    for order in range(2, 50):
        for offset in (1, 2, n // 2, n - 1):
            for level in (0.01, 0.03, 0.05):
                for df in (-5.0, 0.0, 5.0):
                    ratio = order + offset / n
                    scores = worst_scores(
                        f"pq-interharmonic-{int(f0)}hz-single", ratio=ratio, level=level, df_pct=df, duration_s=0.6
                    )
                    key = max(scores, key=lambda k: scores[k])
                    if scores[key] > worst[0]:
                        worst = (scores[key], f"{key} at {ratio:g} f, {level:g}, {df:+g} %")
    assert worst[0] <= 0.01, worst


# ---- symmetrical components and unbalance: IEC 61000-4-30 class A ---------------------------


def test_fortescue_algebra():
    v = 1.3 * np.exp(0.4j)
    balanced = symmetrical_components(v, A * A * v, A * v)
    assert abs(balanced.positive - v) < 1e-15 and abs(balanced.negative) < 1e-15 and abs(balanced.zero) < 1e-15
    rng = np.random.default_rng(3)
    seq = rng.normal(size=(3, 5)) + 1j * rng.normal(size=(3, 5))
    sc = symmetrical_components(*phases_from_sequence(*seq))
    np.testing.assert_allclose(np.stack([sc.zero, sc.positive, sc.negative]), seq, atol=1e-14)
    # a textbook case: phase c missing (Vc = 0): V1 = V2 = ... |V2|/|V1| = 1/2
    one = symmetrical_components(1.0, A * A, 0.0)
    assert abs(one.u2 - 0.5) < 1e-15 and abs(one.u0 - 0.5) < 1e-15
    assert math.isnan(float(symmetrical_components(0.0, 0.0, 0.0).u2))


UNBALANCE = [
    f"pq-unbalance-{f}hz-u2-{u}pct{off}" for f in (50, 60) for u in ("0.5", "1", "2", "5") for off in ("", "-m5", "-p5")
] + [f"pq-unbalance-{f}hz-u2-2pct-harmonics{off}" for f in (50, 60) for off in ("", "-m5", "-p5")]


@pytest.mark.parametrize("name", UNBALANCE)
def test_unbalance_within_class_a(name):
    sc, windows = analyse(name)
    truth = sc.pq_truth
    assert truth.sequence_rms is not None and truth.u2 is not None and truth.u0 is not None
    v0, v1, v2 = truth.sequence_rms
    for w in windows:
        seq = window_sequence(w)
        # class A: u2 within 0.15 percentage points (measured worst: 3e-7 points)
        assert abs(float(seq.u2) - truth.u2) <= 0.01 * LIMITS["u2_absolute"]
        assert abs(float(seq.u0) - truth.u0) <= 0.01 * LIMITS["u2_absolute"]
        # sequence magnitudes within the class A magnitude limit (0.1 % of V1)
        for got, true in ((seq.positive, v1), (seq.negative, v2), (seq.zero, v0)):
            assert abs(abs(complex(got)) - abs(true)) <= 0.01 * LIMITS["magnitude_relative"] * abs(v1)
        # angles: the phasors are at the window end, the truth at t = 0
        rot = np.exp(1j * 2 * np.pi * sc.frequency_hz * w.end_ns / NS)
        assert abs(complex(seq.positive) - v1 * rot) < 1e-5
        assert abs(complex(seq.negative) - v2 * rot) < 1e-5
        assert abs(w.frequency_hz - truth.frequency_hz) <= 1e-3 * LIMITS["frequency_hz"]


def test_three_phase_report_and_group_values():
    _, windows = analyse("pq-unbalance-50hz-u2-2pct")
    w = windows[-1]
    z = w.fundamental_phasor
    rep = three_phase_report("feeder1", ["feeder1/va", "feeder1/vb", "feeder1/vc"], w.end_ns, z, w.frequency_hz)
    assert rep.u2 is not None and abs(rep.u2 - 0.02) < 1e-6
    assert rep.positive.magnitude_rms is not None and abs(rep.positive.magnitude_rms - 1.0) < 1e-5
    assert rep.phase_rms == pytest.approx(list(np.abs(z)))
    again = ThreePhaseReport.model_validate_json(encode_pq(rep))
    assert again == rep and encode_pq(again) == encode_pq(rep)
    missing = three_phase_report("g", ["a", "b", "c"], 0, [z[0], z[1], complex("nan")], 50.0, missing=["c"])
    assert missing.u2 is None and missing.phase_rms[2] is None and missing.missing == ["c"]
    json.loads(encode_pq(missing))  # null, not NaN
    gv = group_window_values(w)
    assert abs(gv.values["u2"] - 0.02) < 1e-6 and abs(gv.values["u0"] - 0.01) < 1e-6


# ---- streaming behaviour -------------------------------------------------------------------------


def test_block_cuts_state_round_trip_and_determinism():
    sc = get_pq("pq-unbalance-60hz-u2-2pct-harmonics-p5", noise_std=1e-3)
    y, _ = sc.generate(seed=4)
    fs = sc.sample_rate_hz
    ref = run(HarmonicAnalyser(fs, nominal_frequency_hz=60.0, n_channels=3), y, fs, block=10_000_000)
    for block in (1, 333, 4096):
        if block == 1:
            y1 = y[:9000]
            got = run(HarmonicAnalyser(fs, nominal_frequency_hz=60.0, n_channels=3), y1, fs, block=1)
            want = [w for w in ref if w.end_ns <= 9000 * NS / fs - 16 * NS / fs]
            got = got[: len(want)]
        else:
            got, want = run(HarmonicAnalyser(fs, nominal_frequency_hz=60.0, n_channels=3), y, fs, block=block), ref
        assert len(got) == len(want) > 0
        for a, b in zip(got, want, strict=True):
            assert a.start_ns == b.start_ns and a.end_ns == b.end_ns and a.frequency_hz == b.frequency_hz
            assert np.array_equal(a.harmonic_rms, b.harmonic_rms) and np.array_equal(a.thd, b.thd)
    # a snapshot taken mid-window restores the exact continuation
    an = HarmonicAnalyser(fs, nominal_frequency_hz=60.0, n_channels=3)
    first = an.update(y[:7777], 0)
    snap = json.loads(json.dumps(an.get_state()))
    other = HarmonicAnalyser(fs, nominal_frequency_hz=60.0, n_channels=3)
    other.set_state(snap)
    t1 = round(7777 * NS / fs)
    rest_a, rest_b = an.update(y[7777:], t1), other.update(y[7777:], t1)
    assert [w.end_ns for w in first + rest_a] == [w.end_ns for w in ref]
    assert all(np.array_equal(a.harmonic_rms, b.harmonic_rms) for a, b in zip(rest_a, rest_b, strict=True))
    with pytest.raises(ParameterError):
        HarmonicAnalyser(fs, nominal_frequency_hz=50.0, n_channels=3).set_state(snap)


def test_windows_are_contiguous_and_resynchronise_on_the_10_min_tick():
    """Start 1.05 s before a 10-min tick: the windows follow one another without gap, the
    one holding the tick runs to its end (overlap 1) and the next starts on the tick."""
    sc = get_pq("pq-unbalance-50hz-u2-1pct-p5")
    fs = sc.sample_rate_hz
    y, _ = sc.generate()
    t0 = 600 * NS - 1_050_000_000
    windows = run(HarmonicAnalyser(fs, nominal_frequency_hz=50.0, n_channels=3), y, fs, t0_ns=t0)
    ticks = [i for i, w in enumerate(windows) if w.resync]
    assert len(ticks) == 1
    k = ticks[0]
    assert windows[k].start_ns == 600 * NS
    assert windows[k - 1].start_ns < 600 * NS < windows[k - 1].end_ns
    for i in range(1, len(windows)):
        if i != k:
            assert abs(windows[i].start_ns - windows[i - 1].end_ns) <= 1
        # every window spans N cycles of the measured frequency
        w = windows[i]
        assert abs((w.end_ns - w.start_ns) / NS - 10 / w.frequency_hz) < 2e-9
    assert windows[0].start_ns == t0 + round(16 * NS / fs)  # the interpolator's R samples


def test_time_discontinuity_restarts_the_analysis():
    fs = 10_000.0
    sc = get_pq("pq-harmonics-50hz-all")
    y, _ = sc.generate()
    an = HarmonicAnalyser(fs)
    before = an.update(y[:5000], 0)
    after = an.update(y[5000:], round(5000 * NS / fs) + 7 * NS)  # 7 s missing
    assert before and after and after[0].gap and not any(w.gap for w in after[1:] + before)
    assert after[0].start_ns == round(5000 * NS / fs) + 7 * NS + round(16 * NS / fs)


def test_parameters_and_inputs_are_checked():
    with pytest.raises(ParameterError, match="reference_channel"):
        HarmonicAnalyser(10_000.0, n_channels=3, reference_channel=3)
    with pytest.raises(ParameterError, match="sample_rate_hz"):
        HarmonicAnalyser(5_000.0)  # harmonic 50 of 57.5 Hz is beyond 0.4 fs
    with pytest.raises(ParameterError, match="invalid parameters"):
        HarmonicAnalyser(10_000.0, nominal_frequency_hz=55.0)
    with pytest.raises(ParameterError, match="invalid parameters"):
        HarmonicAnalyser(10_000.0, bogus=1)
    an = HarmonicAnalyser(10_000.0, n_channels=3)
    with pytest.raises(InputError, match=r"expected shape \(N, 3\)"):
        an.update(np.zeros(100), 0)
    with pytest.raises(InputError, match="finite"):
        an.update(np.full((10, 3), np.nan), 0)
    # a dead channel: no fundamental, THD undefined (null on the wire), no crash
    w = run(HarmonicAnalyser(10_000.0), np.zeros(6000), 10_000.0)
    assert w and math.isnan(w[0].thd[0])
    assert harmonics_report(w[0], "dead", 0, 50.0).thd is None


# ---- aggregation: IEC 61000-4-30 -------------------------------------------------------------


def _window(start_s: float, length_s: float, v: float, f: float = 50.0) -> WindowValues:
    return WindowValues(
        start_ns=round(start_s * NS),
        end_ns=round((start_s + length_s) * NS),
        n_cycles=10,
        values={"rms": v, "frequency_hz": f, "thd": v / 100.0},
        arrays={"h": np.array([v, 2 * v])},
    )


def test_150_cycle_aggregate_by_hand():
    agg = Aggregator("ch")
    out = []
    freqs = [50.0 + 0.01 * i for i in range(15)]
    for i in range(15):
        out += agg.add(_window(10.0 + 0.2 * i, 0.2, float(i + 1), freqs[i]))
    assert len(out) == 1
    a = out[0]
    # sqrt((1 + 4 + ... + 225) / 15) = sqrt(1240 / 15)
    assert a.interval == "150/180-cycle" and a.complete and a.n_windows == 15
    assert a.values["rms"] == pytest.approx(math.sqrt(1240 / 15), rel=1e-15)
    assert a.values["thd"] == pytest.approx(math.sqrt(1240 / 15) / 100, rel=1e-14)
    # frequency: 150 cycles over sum(10 / f_i) seconds
    assert a.values["frequency_hz"] == pytest.approx(150.0 / sum(10.0 / f for f in freqs), rel=1e-15)
    assert a.arrays["h"] == pytest.approx([math.sqrt(1240 / 15), 2 * math.sqrt(1240 / 15)], rel=1e-15)
    assert a.start_ns == 10 * NS and a.timestamp_ns == 13 * NS
    assert PqAggregate.model_validate_json(encode_pq(a)) == a


def test_10_min_aggregate_and_resynchronisation_by_hand():
    """Windows of 0.2 s from 599.05 s: the one from 599.85 to 600.05 s holds the tick
    (overlap 1) and ends the first 10-min interval; the next starts at 600 s. The
    150/180-cycle interval in progress at the tick goes on with the new stream's windows
    until it has 15 (overlap 2, IEC 61000-4-30 class A), while a new one starts at 600 s."""
    agg = Aggregator("ch")
    out = []
    starts = [599.05 + 0.2 * i for i in range(5)]  # 599.05 .. 599.85
    for i, s in enumerate(starts):
        out += agg.add(_window(s, 0.2, float(i + 1)))
    assert out == []
    # the first window after the tick starts on it: the 10-s value of 590..600 s and the 10-min one
    out += agg.add(_window(600.0, 0.2, 10.0))
    ten_s, ten = out
    assert ten_s.interval == "10-s" and ten_s.start_ns == 590 * NS and ten_s.timestamp_ns == 600 * NS
    assert not ten_s.complete and ten_s.values == {"frequency_hz": 50.0}  # the stream began at 599.05 s
    assert ten.interval == "10-min" and ten.timestamp_ns == 600 * NS and ten.start_ns == 0
    assert ten.n_windows == 5 and not ten.complete  # the stream began inside the interval
    assert ten.values["rms"] == pytest.approx(math.sqrt(55 / 5), rel=1e-15)
    # a whole 10-min interval from the tick: 3000 windows of 0.2 s, values 1, 2, 3, 1, 2, 3, ...
    out = []
    for i in range(1, 3000):
        out += agg.add(_window(600.0 + 0.2 * i, 0.2, float(i % 3 + 1)))
    out += agg.add(_window(1200.0, 0.2, 1.0))  # the next interval's first window closes it
    shorts = [a for a in out if a.interval == "150/180-cycle"]
    tens = [a for a in out if a.interval == "10-min"]
    vals = [10.0] + [float(i % 3 + 1) for i in range(1, 3000)]
    # overlap 2: the interval of 599.05 s took 10 more windows, from the new stream, to 602.0 s
    first = shorts[0]
    assert first.start_ns == round(599.05 * NS) and first.timestamp_ns == 602 * NS
    assert first.n_windows == 15 and first.complete
    expect = [1.0, 2.0, 3.0, 4.0, 5.0, *vals[:10]]
    assert first.values["rms"] == pytest.approx(math.sqrt(sum(v * v for v in expect) / 15), rel=1e-14)
    assert len(shorts) == 201 and all(a.complete for a in shorts) and len(tens) == 1
    assert shorts[1].start_ns == 600 * NS  # resynchronised on the tick
    assert shorts[1].values["rms"] == pytest.approx(math.sqrt(sum(v * v for v in vals[:15]) / 15), rel=1e-14)
    ten = tens[0]
    assert ten.complete and ten.n_windows == 3000 and ten.timestamp_ns == 1200 * NS
    assert ten.values["rms"] == pytest.approx(math.sqrt(sum(v * v for v in vals) / 3000), rel=1e-13)
    assert ten.values["frequency_hz"] == pytest.approx(50.0, rel=1e-15)
    ten_s = [a for a in out if a.interval == "10-s"]
    assert [a.start_ns for a in ten_s] == [(600 + 10 * k) * NS for k in range(60)]
    assert all(a.complete and a.n_windows == 50 and a.values["frequency_hz"] == 50.0 for a in ten_s)


def _cycles_truth(windows: list[tuple[float, float]], k: int) -> float:
    """IEC 61000-4-30 5.1 by enumeration: the whole cycles of windows (start s, f Hz; 10
    cycles each) inside [10k, 10k + 10) s, their count over their summed duration."""
    count, duration = 0, 0.0
    for start, f in windows:
        for j in range(10):
            a, b = start + j / f, start + (j + 1) / f
            if 10 * k <= a and b <= 10 * k + 10 + 1e-12:
                count += 1
                duration += 1 / f
    return count / duration


def test_10_s_frequency_counts_whole_cycles_within_the_clock_interval():
    """Windows of 10 cycles at a wandering frequency (49.9 Hz +- 0.05), from 3.0 s: each
    10-s value is the whole cycles inside its interval over their duration (cycles that
    cross a 10-s tick dropped), the first incomplete (the stream starts inside it); a hole
    in the stream makes the values around it incomplete."""
    agg = Aggregator("ch")
    windows, t = [], 3.0
    for i in range(200):
        f = 49.9 + 0.05 * math.sin(0.3 * i)
        windows.append((t, f))
        t += 10.0 / f
    out = []
    for start, f in windows:
        out += agg.add(_window(start, 10.0 / f, 1.0, f))
    ten_s = [a for a in out if a.interval == "10-s"]
    assert [a.start_ns for a in ten_s] == [0, 10 * NS, 20 * NS, 30 * NS]  # 40..43 s still open
    assert [a.complete for a in ten_s] == [False, True, True, True]
    for k, a in enumerate(ten_s):
        assert a.values["frequency_hz"] == pytest.approx(_cycles_truth(windows, k), rel=1e-12)
        assert a.values["frequency_hz"] != pytest.approx(49.9, rel=1e-9)  # it does wander
    rest = agg.flush()
    assert [a.interval for a in rest][:1] == ["10-s"] and not rest[0].complete
    # a hole of 1 s at 15 s: the 10-s value of 10..20 s is incomplete, the next ones are not
    agg, out = Aggregator("ch"), []
    for i in range(150):
        start = 0.2 * i + (1.0 if 0.2 * i >= 15.0 else 0.0)
        out += agg.add(_window(start, 0.2, 1.0))
    ten_s = [a for a in out if a.interval == "10-s"]
    assert [(a.start_ns // NS, a.complete) for a in ten_s] == [(0, True), (10, False), (20, True)]


def test_overlap_1_cycles_are_counted_once_in_the_10_s_value():
    """At the 10-min tick the window in progress (599.85 s, here at 50.5 Hz, to 600.048 s)
    overlaps the new stream's first window (600.0 s): its cycles past the tick give way,
    so the 10-s value of 600..610 s holds the new stream's 500 cycles at 50 Hz only."""
    agg, out = Aggregator("ch"), []
    for i in range(4):
        out += agg.add(_window(599.05 + 0.2 * i, 0.2, 1.0))
    out += agg.add(_window(599.85, 10 / 50.5, 1.0, 50.5))
    for i in range(60):
        out += agg.add(_window(600.0 + 0.2 * i, 0.2, 1.0))
    [a] = [a for a in out if a.interval == "10-s" and a.start_ns == 600 * NS]
    assert a.complete and a.values["frequency_hz"] == 50.0


def test_an_aggregator_state_of_an_earlier_build_restores():
    """A snapshot written before the 10-s, 2-h and overlap-2 state existed (only the
    150/180-cycle and 10-min accumulators): its intervals go on, the new ones start afresh."""
    a = Aggregator("ch")
    for i in range(7):
        a.add(_window(10.0 + 0.2 * i, 0.2, 2.0))
    legacy = {k: v for k, v in a.get_state().items() if k in ("short", "long", "long_index", "last_end")}
    b = Aggregator("ch")
    b.set_state(json.loads(json.dumps(legacy)))
    out = [x for i in range(7, 15) for x in b.add(_window(10.0 + 0.2 * i, 0.2, 2.0))]
    [short] = [x for x in out if x.interval == "150/180-cycle"]
    assert short.complete and short.n_windows == 15 and short.values["rms"] == 2.0


def test_2_h_aggregate_of_twelve_10_min_values():
    """IEC 61000-4-30 2-h interval: the RMS of the twelve 10-min values (each counting
    once, whatever its number of windows), on the 2-h clock; here with a 1-s "10-min"
    interval (so a 12-s "2-h" one) to keep the stream short."""
    agg, out = Aggregator("ch", tick_s=1.0), []
    t, k = 0.0, 0
    while t < 24.0 - 1e-9:
        n = 5 if k % 2 else 4  # windows per 1-s interval: 4 x 0.25 s or 5 x 0.2 s
        for _ in range(n):
            out += agg.add(_window(t, 1.0 / n, float(k + 1), 50.0))
            t = round(t + 1.0 / n, 9)
        k += 1
    out += agg.add(_window(24.0, 0.2, 1.0))
    two_h = [a for a in out if a.interval == "2-h"]
    assert [(a.start_ns, a.timestamp_ns) for a in two_h] == [(0, 12 * NS), (12 * NS, 24 * NS)]
    assert all(a.n_windows == 12 and a.complete for a in two_h)
    for j, a in enumerate(two_h):
        vals = [float(12 * j + i + 1) for i in range(12)]
        assert a.values["rms"] == pytest.approx(math.sqrt(sum(v * v for v in vals) / 12), rel=1e-14)
        assert a.values["frequency_hz"] == pytest.approx(50.0, rel=1e-14)
        assert a.arrays["h"][1] == pytest.approx(2 * math.sqrt(sum(v * v for v in vals) / 12), rel=1e-14)
    assert PqAggregate.model_validate_json(encode_pq(two_h[1])) == two_h[1]
    # a stream that starts inside the first 10-min interval: that 2-h value is incomplete
    agg, out = Aggregator("ch", tick_s=1.0), []
    for i in range(2, 13 * 5):
        out += agg.add(_window(0.2 * i, 0.2, 1.0))
    [a] = [a for a in out if a.interval == "2-h"]
    assert a.n_windows == 12 and not a.complete and a.values["rms"] == pytest.approx(1.0, rel=1e-15)
    # the state carries a 2-h interval in progress across a restore, exactly
    a1, a2 = Aggregator("ch", tick_s=1.0), Aggregator("ch", tick_s=1.0)
    stream = [_window(0.25 * i, 0.25, float(i % 7 + 1)) for i in range(100)]
    o1 = [x for w in stream for x in a1.add(w)]
    o2 = [x for w in stream[:37] for x in a2.add(w)]
    restored = Aggregator("ch", tick_s=1.0)
    restored.set_state(json.loads(json.dumps(a2.get_state())))
    o2 += [x for w in stream[37:] for x in restored.add(w)]
    assert [encode_pq(x) for x in o1] == [encode_pq(x) for x in o2]


def test_aggregation_gaps_and_undefined_values():
    agg = Aggregator("ch")
    out = []
    for i in range(4):
        out += agg.add(_window(10.0 + 0.2 * i, 0.2, 2.0))
    out += agg.add(_window(20.0, 0.2, float("nan")))  # discontinuous and undefined
    ten_s, short = out  # the 10-s value of 10..20 s (a hole in it), the 150/180-cycle one cut short
    assert ten_s.interval == "10-s" and not ten_s.complete and ten_s.n_windows == 4
    assert short.interval == "150/180-cycle" and not short.complete and short.n_windows == 4
    rest = agg.flush()
    assert [a.interval for a in rest] == ["10-s", "150/180-cycle", "10-min", "2-h"]
    assert rest[0].values["frequency_hz"] == 50.0 and rest[0].n_windows == 1 and not rest[0].complete
    assert rest[1].values["rms"] is None and rest[1].n_windows == 1
    assert rest[2].values["rms"] == pytest.approx(2.0) and not rest[2].complete
    assert rest[3].values["rms"] == pytest.approx(2.0) and not rest[3].complete and rest[3].n_windows == 1
    with pytest.raises(ParameterError):
        Aggregator("x", windows_per_interval=0)


def test_analyser_to_aggregates_across_a_tick():
    """End to end: a three-phase stream across the 10-min tick, through the analyser and two
    aggregators (a channel and the group): the aggregates hold the truth."""
    sc = get_pq("pq-unbalance-50hz-u2-2pct-harmonics-m5", duration_s=6.0)
    fs = sc.sample_rate_hz
    y, _ = sc.generate()
    windows = run(HarmonicAnalyser(fs, n_channels=3), y, fs, t0_ns=600 * NS - 2 * NS)
    ch, grp = Aggregator("feeder1/va"), Aggregator("feeder1")
    out_ch, out_grp = [], []
    for w in windows:
        out_ch += ch.add(channel_window_values(w, 0))
        out_grp += grp.add(group_window_values(w))
    tens = [a for a in out_grp if a.interval == "10-min"]
    assert len(tens) == 1 and tens[0].timestamp_ns == 600 * NS
    truth = sc.pq_truth
    for a in out_grp + out_ch:
        assert a.values["frequency_hz"] == pytest.approx(truth.frequency_hz, abs=1e-6)
    assert [a.start_ns for a in out_ch if a.interval == "10-s"] == [590 * NS]  # 600..610 s still open
    out_grp = [a for a in out_grp if a.interval != "10-s"]
    out_ch = [a for a in out_ch if a.interval != "10-s"]
    for a in out_grp:
        assert a.values["u2"] == pytest.approx(truth.u2, abs=1e-6)
    for a in out_ch:
        assert a.values["thd"] == pytest.approx(truth.thd[0], rel=1e-5)
        assert a.arrays["harmonic_subgroup_rms"][5] == pytest.approx(truth.harmonic_rms[0, 5], rel=1e-4)
    after = [a for a in out_ch if a.interval == "150/180-cycle" and a.start_ns >= 600 * NS]
    assert after and after[0].start_ns == 600 * NS


# ---- messages ----------------------------------------------------------------------------------


def test_harmonics_report_round_trip_and_schemas():
    _, windows = analyse("pq-harmonics-60hz-all-m5")
    rep = harmonics_report(windows[-1], "feeder1/va", 0, 60.0)
    assert rep.n_cycles == 12 and len(rep.harmonic_rms) == 51 and len(rep.interharmonic_centred_subgroup_rms) == 51
    raw = encode_pq(rep)
    again = HarmonicsReport.model_validate_json(raw)
    assert again == rep and encode_pq(again) == raw
    assert rep.timestamp_ns == windows[-1].end_ns
    assert json_encoding("HarmonicsReport") == "application/json;sinewatch/HarmonicsReport@2"
    t = json.loads(raw)["timestamp"]  # {sec, nsec}: exact in JavaScript, where timestamp_ns is not
    assert t["sec"] * 10**9 + t["nsec"] == rep.timestamp_ns and 0 <= t["nsec"] < 10**9
    v1 = json.loads(encode_pq(rep, version=1))  # what the first build wrote, for replaying its recordings
    assert v1["format_version"] == 1 and "timestamp" not in v1
    for name, model in PQ_MESSAGE_MODELS.items():
        schema = model.model_json_schema()
        assert schema["title"] == name and schema["additionalProperties"] is False
    with pytest.raises(ValueError):
        HarmonicsReport.model_validate({**rep.model_dump(), "extra": 1})


def test_scenario_registry_is_separate_and_complete():
    from sinewatch import scenarios

    names = pq_names()
    assert len(names) == 70 and not set(names) & set(scenarios.names())
    with pytest.raises(ParameterError):
        get_pq("pq-nothing")
    sc = get_pq("pq-unbalance-60hz-u2-5pct-m5", noise_std=0.01)
    a, _ = sc.generate(seed=1)
    b = np.concatenate([sc.stream(1).read(100)[0], sc.stream(1).read(1)[0]])
    assert a.shape == (sc.n_samples, 3) and np.isfinite(a).all()
    assert np.array_equal(a[:100], sc.stream(1).read(100)[0]) and b.shape == (101, 3)
    assert sc.pq_truth.frequency_hz == pytest.approx(57.0)
