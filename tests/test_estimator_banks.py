"""Estimator banks (``sinewatch.estimators.bank.update_bank``) against the single-channel path.

The contract: after ``update_bank(ests, x)``, every ``ests[c]`` holds exactly the state, and
``tracks[c]`` exactly the bits, of ``ests[c].update(x[:, c])``, whatever the bank's size and
the channel's position in it. Each channel here has its own signal (its own seed) and its own
history (channels joined the bank at different times), so a bank that mixed channels up, read
a neighbour's state or rounded one step differently would show in some channel's bits.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from sinewatch.estimators import available, get
from sinewatch.estimators.bank import NO_BANK, bank_of, update_bank
from sinewatch.estimators.base import Estimator, Track
from sinewatch.estimators.lanes import host_vector_bits
from sinewatch.schemas.errors import InputError

NAMES = sorted(available())
N = 240  # samples per channel: enough to cross windows and decimation steps, fast to check
# blocks of uneven sizes (one of a single sample), alternately every row and the last row only
BLOCKS = ((0, 97, False), (97, 98, True), (98, 170, True), (170, N, False))
T0_NS = 1_700_000_000_000_000_000


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return (
        a.shape == b.shape
        and a.dtype == b.dtype
        and np.ascontiguousarray(a).tobytes() == np.ascontiguousarray(b).tobytes()
    )


def assert_tracks_bitwise(a: Track, b: Track, where: str) -> None:
    for f in ("frequency_hz", "amplitude", "phase_rad", "offset", "converged"):
        assert _same_bits(getattr(a, f), getattr(b, f)), f"{where}: {f}"
    assert np.float64(a.residual_rms).tobytes() == np.float64(b.residual_rms).tobytes(), f"{where}: residual_rms"
    assert set(a.extras) == set(b.extras), where
    for k in a.extras:
        assert _same_bits(a.extras[k], b.extras[k]), f"{where}: extras[{k}]"
    for f in ("rocof_hz_per_s",):
        x, y = getattr(a, f), getattr(b, f)
        assert (x is None) == (y is None) and (x is None or _same_bits(x, y)), f"{where}: {f}"
    assert (a.std is None) == (b.std is None), where
    if a.std is not None and b.std is not None:
        for f in ("frequency_hz", "amplitude", "phase_rad", "offset"):
            assert _same_bits(getattr(a.std, f), getattr(b.std, f)), f"{where}: std.{f}"
    assert (a.reports is None) == (b.reports is None), where


def assert_states_bitwise(a: Estimator, b: Estimator, where: str) -> None:
    assert list(a._state) == list(b._state), where
    for k in a._state:
        assert _same_bits(a._state[k], b._state[k]), f"{where}: state {k}"


def _channels(name: str, size: int) -> tuple[np.ndarray, list[Estimator], list[Estimator]]:
    """``size`` channels, each with its own seed and its own history (channel c has been fed
    c % 3 earlier blocks), as two identical sets of estimators: one for the single-channel path,
    one for the bank."""
    cls = get(name)
    x = np.stack([cls.example_signal(N + 2 * 50, seed=100 + c) for c in range(size)], axis=1)
    singles, banked = [], []
    for c in range(size):
        pair = [cls.example(), cls.example()]
        for est in pair:
            for b in range(c % 3):
                est.update(np.ascontiguousarray(x[N + 50 * b : N + 50 * (b + 1), c]))
        singles.append(pair[0])
        banked.append(pair[1])
    return np.ascontiguousarray(x[:N]), singles, banked


@pytest.mark.parametrize("size", [1, 3, 8, 64])
@pytest.mark.parametrize("name", NAMES)
def test_bank_matches_single_channel_bit_for_bit(name: str, size: int) -> None:
    x, singles, banked = _channels(name, size)
    for a, b, last_only in BLOCKS:
        t0 = T0_NS + a * 1_000_000
        expected = [
            est.update(np.ascontiguousarray(x[a:b, c]), last_only=last_only, t0_ns=t0) for c, est in enumerate(singles)
        ]
        got = update_bank(banked, x[a:b], last_only=last_only, t0_ns=t0)
        assert len(got) == size
        for c in range(size):  # every position in the bank
            where = f"{name} bank {size} position {c} block {a}:{b} last_only={last_only}"
            assert_tracks_bitwise(expected[c], got[c], where)
            assert_states_bitwise(singles[c], banked[c], where)


@pytest.mark.parametrize("name", NAMES)
def test_state_round_trips_after_a_bank_call(name: str) -> None:
    """A snapshot taken after a bank call restores an estimator that continues exactly as the
    banked one does (the scattered state arrays are each channel's own, complete)."""
    x, _, banked = _channels(name, 3)
    update_bank(banked, x[:150])
    cls = get(name)
    restored = [cls.from_state(json.loads(json.dumps(e.get_state()))) for e in banked]
    after_bank = update_bank(banked, x[150:])
    after_restore = [e.update(np.ascontiguousarray(x[150:, c])) for c, e in enumerate(restored)]
    for c in range(3):
        assert_tracks_bitwise(after_restore[c], after_bank[c], f"{name} channel {c}")
        assert_states_bitwise(restored[c], banked[c], f"{name} channel {c}")


def test_every_registered_estimator_has_a_bank_or_says_why() -> None:
    missing = [n for n in NAMES if bank_of(get(n)) is None and not NO_BANK.get(n)]
    assert not missing, f"estimators with neither a compiled bank nor a reason in NO_BANK: {missing}"
    stale = [n for n in NO_BANK if n not in NAMES or bank_of(get(n)) is not None]
    assert not stale, f"NO_BANK lists estimators that are not registered or have a bank: {stale}"


@pytest.mark.parametrize("name", NAMES)
def test_a_non_finite_column_rejects_the_call_and_changes_no_channel(name: str) -> None:
    x, _, banked = _channels(name, 3)
    bad = x[:50].copy()
    bad[7, 1] = np.nan
    before = [{k: v.copy() for k, v in e._state.items()} for e in banked]
    with pytest.raises(InputError) as info:
        update_bank(banked, bad)
    assert info.value.kind == "non_finite"
    for e, s in zip(banked, before, strict=True):
        assert all(_same_bits(e._state[k], s[k]) for k in s)


def test_a_bank_of_different_parameters_is_refused() -> None:
    cls = get("sogi-fll")
    ests = [cls.example(), cls(cls.example_sample_rate_hz, {"nominal_frequency_hz": 60.0})]
    with pytest.raises(ValueError, match=r"estimators\[1\]"):
        update_bank(ests, np.zeros((8, 2)))


def test_bench_kernels_bank_reports_every_estimator_and_why_below_target(tmp_path, capsys) -> None:
    """``sinewatch bench kernels --bank N``: every estimator's bank measured beside its single
    channel and the streaming FFT, and every bank below the target says why (no timing asserted)."""
    import argparse

    from sinewatch.apps.bench import kernels

    out_json = tmp_path / "k.json"
    names = ["sogi-fll", "pmu"]
    args = argparse.Namespace(estimators=",".join(names), block=[256], seconds=0.02, bank=3, json=out_json)
    assert kernels.run(args) == 0
    printed = " ".join(capsys.readouterr().out.split())  # the console wraps long lines
    results = json.loads(out_json.read_text())
    assert results["bank_channels"] == 3
    cpu, bits = host_vector_bits()  # the host the ratios were measured on, printed and kept
    assert results["host"] == {"cpu": cpu, "vector_bits": bits} and bits in (128, 256, 512)
    assert f"Kernels compiled for {cpu}: {bits}-bit vectors" in printed
    for name in names:
        r = results["estimators"][name]["256"]
        assert r["bank3_bank"] > 0 and r["bank3_single"] > 0 and r["bank3_fft_stream"] > 0
        if r["bank3_bank_vs_fft"] < kernels.BANK_TARGET:
            why = NO_BANK.get(name) or get(name).bank_note
            assert f"bank note: {name}'s bank 3" in printed
            assert " ".join(why.split())[:60] in printed


BANKED = [n for n in NAMES if bank_of(get(n)) is not None]


def _step_alike(
    name: str, singles: list[Estimator], banked: list[Estimator], x: np.ndarray, last_only: bool
) -> list[Track]:
    """Block ``x`` (one column a channel) through each single estimator and through the bank,
    compared bit for bit (tracks and states); the single path's tracks."""
    expected = [e.update(np.ascontiguousarray(x[:, c]), last_only=last_only) for c, e in enumerate(singles)]
    got = update_bank(banked, x, last_only=last_only)
    for c in range(len(singles)):
        where = f"{name} channel {c} of {len(singles)}, {x.shape[0]} samples, last_only={last_only}"
        assert_tracks_bitwise(expected[c], got[c], where)
        assert_states_bitwise(singles[c], banked[c], where)
    return expected


@pytest.mark.parametrize("name", BANKED)
def test_compiled_bank_matches_single_channel_over_long_staggered_histories(name: str) -> None:
    """Nine channels (a full group of lanes and one more, alone in the next) whose histories
    differ by thousands of samples, so that within one call some channels are still in their
    start transient and others settled: ges-kalman's bank then runs lanes whose start
    covariance T (U3) is still propagated beside lanes where it is already zero, and the step
    that switches between the two inside a block."""
    cls = get(name)
    size = 9
    x = np.stack([cls.example_signal(20_000, seed=7 + c) for c in range(size)], axis=1)
    singles, banked = [cls.example() for _ in range(size)], [cls.example() for _ in range(size)]
    for c in range(1, size):
        for est in (singles[c], banked[c]):
            est.update(np.ascontiguousarray(x[: c * 1500, c]))
    pos = 10_000
    mixed = []  # per call: whether some channel's T (U3) is still live and another's zero
    for n, last_only in ((3000, True), (2500, False), (4000, True), (500, False)):
        _step_alike(name, singles, banked, x[pos : pos + n], last_only)
        pos += n
        if name == "ges-kalman":
            traces = [e._state["unc"][0] + e._state["unc"][5] for e in banked]
            mixed.append(any(t == 0.0 for t in traces) and any(t != 0.0 for t in traces))
    if name == "ges-kalman":  # the case the test is for happened
        assert mixed[0], "expected lanes with T live beside lanes with T zero after the first call"


def _regimes(seed: int, n: int, fs: float) -> np.ndarray:
    """A signal that takes kkl-biased through every branch of its inverse map: a tone with an
    offset (converged), a step in frequency and offset (a jump), the offset alone (undefined,
    the settled mean reported), silence, a vanishing tone, and noise; each channel's pieces in
    its own order and lengths."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    pieces = [
        0.5 + np.sin(2 * np.pi * 50 * t + 0.3) + 0.01 * rng.standard_normal(n),
        -1.0 + 2.0 * np.sin(2 * np.pi * 61 * t),
        np.full(n, 0.7),
        np.zeros(n),
        1e-200 * np.sin(2 * np.pi * 50 * t),
        rng.standard_normal(n),
    ]
    order = rng.permutation(len(pieces))
    lengths = rng.integers(n // 8, n // 3, size=len(pieces))
    return np.concatenate([pieces[i][: lengths[i]] for i in order])[:n]


def test_kkl_biased_bank_matches_single_channel_through_every_branch_of_the_inverse_map() -> None:
    """kkl-biased's bank evaluates every step for all lanes and selects where the single
    kernel branches (mu = 0 or not, the Schur complement, x3 > 0, below Nyquist, the settled
    offset while undefined): nine channels, each through those regimes at its own times, bit
    for bit; the single path is checked to have visited converged, defined-but-not-converged,
    offset-only and fully undefined samples, so the branches the test is for were taken."""
    cls = get("kkl-biased")
    fs, n, size = cls.example_sample_rate_hz, 24_000, 9
    x = np.stack([_regimes(300 + c, n, fs) for c in range(size)], axis=1)
    singles, banked = [cls.example() for _ in range(size)], [cls.example() for _ in range(size)]
    seen = {"converged": 0, "defined": 0, "offset only": 0, "undefined": 0}
    pos = 0
    for step, last_only in ((5000, False), (3000, True), (7000, False), (9000, False)):
        for tr in _step_alike("kkl-biased", singles, banked, x[pos : pos + step], last_only):
            freq_ok, off_ok = np.isfinite(tr.frequency_hz), np.isfinite(tr.offset)
            seen["converged"] += int(tr.converged.sum())
            seen["defined"] += int((freq_ok & ~tr.converged).sum())
            seen["offset only"] += int((~freq_ok & off_ok).sum())
            seen["undefined"] += int((~freq_ok & ~off_ok).sum())
        pos += step
    assert all(v > 0 for v in seen.values()), seen


def test_sogi_fll_bank_matches_single_channel_through_silence_and_the_clamps() -> None:
    """sogi-fll's step selects where it once branched (the FLL held below min_amplitude, the
    flush of what decays to subnormals in silence, the frequency clamps), and its bank runs the
    step for 8 lanes as one vector: nine channels, each through tone, steps, silence, a 1e-200
    tone and noise at its own times, bit for bit; the single path is checked to have held its
    FLL (frequency NaN) and to have run locked, so the selects' both sides were taken."""
    cls = get("sogi-fll")
    fs, n, size = cls.example_sample_rate_hz, 12_000, 9
    x = np.stack([_regimes(500 + c, n, fs) for c in range(size)], axis=1)
    singles, banked = [cls.example() for _ in range(size)], [cls.example() for _ in range(size)]
    held = locked = 0
    pos = 0
    for step, last_only in ((2500, False), (1500, True), (4000, False), (4000, False)):
        for tr in _step_alike("sogi-fll", singles, banked, x[pos : pos + step], last_only):
            held += int(np.isnan(tr.frequency_hz).sum())
            locked += int(tr.converged.sum())
        pos += step
    assert held > 0 and locked > 0, (held, locked)


def test_sogi_fll_lane_loops_of_either_vector_width_step_alike() -> None:
    """sogi-fll's bank compiles one of two lane loops, by the host's vector width: 8 lanes in a
    loop (one AVX-512 vector) or lanes i and i + 4 in one body (two 256-bit vectors). Both run
    here, whatever the host, from the same work array through tone, silence and the clamps, and
    leave it the same bit for bit after every sample; both sides of the FLL's hold were taken."""
    from sinewatch.estimators import sogi_fll as sf

    cls = get("sogi-fll")
    est = cls.example()
    c = tuple(float(v) for v in est._constants[0])
    a_min2 = c[6] * c[6]
    L = sf.LANES
    x = np.stack([_regimes(900 + ln, 12_000, cls.example_sample_rate_hz) for ln in range(L)], axis=1)
    wide = np.zeros(sf._ROWS * L)
    for i, v in enumerate(est._initial_state()["x"]):
        wide[i * L : (i + 1) * L] = v
    halves = wide.copy()
    held = live = 0
    for k in range(x.shape[0]):
        row = (sf._RY + k % 2) * L  # the kernel's sample row for sample k
        wide[row : row + L] = halves[row : row + L] = x[k]
        sf._bank_lanes_512(wide, k, c)
        sf._bank_lanes_256(halves, k, c)
        # (row _RYV, after the shared rows, is the two-vector loop's own copy of the sample)
        assert wide[: sf._RYV * L].tobytes() == halves[: sf._RYV * L].tobytes(), f"sample {k}"
        amp2 = wide[sf._RAMP2 * L : (sf._RAMP2 + 1) * L]
        held += int((amp2 <= a_min2).sum())
        live += int((amp2 > a_min2).sum())
    assert held > 0 and live > 0, (held, live)


def _pmu_signal(seed: int, n: int, fs: float) -> np.ndarray:
    """A tone near 50 Hz (its own frequency, phase, amplitude, offset, ramp and noise per
    seed) that steps in magnitude and phase part way, so that (T) sees transitions."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    f = 49.5 + rng.uniform(0, 1.0) + rng.uniform(-0.2, 0.2) * t
    phase = 2 * np.pi * np.cumsum(f) / fs + rng.uniform(0, 2 * np.pi)
    step = np.where(t > rng.uniform(0.4, 0.8) * t[-1], 1.1, 1.0)
    x = rng.uniform(0.5, 2.0) * step * np.sin(phase + 0.1 * (step - 1.0)) + rng.uniform(-0.1, 0.1)
    return x + 0.01 * rng.standard_normal(n)


def _pmu_step_alike(
    singles: list[Estimator], banked: list[Estimator], blk: np.ndarray, last_only: bool, t0: int | None, where: str
) -> list[Track]:
    """Block ``blk`` (one column a channel, first sample at ``t0``) through each single pmu and
    through the bank, compared bit for bit: tracks, reports, states and (T); the single path's
    tracks."""
    expected = [e.update(np.ascontiguousarray(blk[:, c]), last_only=last_only, t0_ns=t0) for c, e in enumerate(singles)]
    got = update_bank(banked, blk, last_only=last_only, t0_ns=t0)
    for c, (a, b) in enumerate(zip(expected, got, strict=True)):
        at = f"{where} channel {c}"
        assert_tracks_bitwise(a, b, at)
        assert a.reports is not None and b.reports is not None, at
        assert _same_bits(a.reports.index, b.reports.index), at
        assert_tracks_bitwise(a.reports.track, b.reports.track, at + " reports")
        assert_states_bitwise(singles[c], banked[c], at)
        assert _same_bits(singles[c]._transition, banked[c]._transition), at + " (T)"
    return expected


@pytest.mark.parametrize(
    ("params", "fs"),
    [
        ({"nominal_frequency_hz": 50, "reporting_rate_hz": 50}, 10_000.0),
        # an oscillator off f0 (the reports' angles turned back to the nominal cosine)
        ({"nominal_frequency_hz": 50, "reporting_rate_hz": 25}, 9_999.33),
        # 'auto': undecided channels run one by one, decided ones in the bank
        ({"nominal_frequency_hz": "auto", "performance_class": "P"}, 10_000.0),
    ],
)
def test_pmu_bank_matches_single_channel_on_its_grid(params: dict, fs: float) -> None:
    """pmu's lane-major bank, bit for bit with the single path, with reports in every call:
    eleven channels, of which seven started together (lanes in lock step: one group of
    eight padded by one) and four joined one at a time (each a group of its own); timed
    blocks of uneven sizes, one of them after a gap in time (every channel re-anchors and
    (T) starts over), the last one untimed."""
    cls = get("pmu")
    size, n = 11, 40_000
    x = np.stack([_pmu_signal(500 + c, n, fs) for c in range(size)], axis=1)
    singles, banked = [cls(fs, params) for _ in range(size)], [cls(fs, params) for _ in range(size)]
    t_start = T0_NS + 123_456
    for c in range(7, size):  # joined earlier, each at its own time: a history of its own
        for est in (singles[c], banked[c]):
            est.update(np.ascontiguousarray(x[: 997 * (c - 6), c]), t0_ns=t_start - 997 * (c - 6) * round(1e9 / fs))
    pos, t0, reports = 0, t_start, 0
    for step, last_only, gap_ns in (
        (4000, True, 0),
        (3001, False, 0),
        (9000, True, 0),
        (8000, True, 2 * 10**9),
        (7000, False, 0),
        (4500, True, None),
    ):
        t0 = None if gap_ns is None else t0 + gap_ns
        expected = _pmu_step_alike(singles, banked, x[pos : pos + step], last_only, t0, f"pmu {params}, {pos}:")
        reports += sum(e.reports.n_reports for e in expected if e.reports is not None)
        pos += step
        if t0 is not None:
            t0 += round(step * 1e9 / fs)
    assert reports > 20 * size  # the reports the test is for were made
    assert any(bool(np.any(e.reports.track.converged)) for e in expected)


def test_pmu_bank_of_a_frame_in_lock_step_builds_its_tracks_at_once(monkeypatch) -> None:
    """A frame's channels, anchored together, share one group of lanes and the same number of
    reports: their Tracks are built by ``grid_tracks`` for the whole frame (checked: it ran in
    every call), each bit for bit the single path's, reports included (an oscillator off f0 at
    9999.33 Hz: the reports' angles are also referred to the nominal cosine per channel)."""
    from sinewatch.estimators import _pmu_bank

    calls = []
    batch = _pmu_bank.grid_tracks
    monkeypatch.setattr(_pmu_bank, "grid_tracks", lambda *a: calls.append(1) or batch(*a))
    cls = get("pmu")
    params, fs = {"nominal_frequency_hz": 50, "reporting_rate_hz": 50}, 9_999.33
    size = 8
    x = np.stack([_pmu_signal(700 + c, 5000, fs) for c in range(size)], axis=1)
    singles, banked = [cls(fs, params) for _ in range(size)], [cls(fs, params) for _ in range(size)]
    pos, t0, reports = 0, T0_NS + 777, 0
    for step, last_only in ((1500, True), (1200, False), (2300, True)):
        expected = _pmu_step_alike(singles, banked, x[pos : pos + step], last_only, t0, f"pmu at {fs} Hz, {pos}:")
        reports += sum(e.reports.n_reports for e in expected if e.reports is not None)
        pos += step
        t0 += round(step * 1e9 / fs)
    assert len(calls) == 3 and reports > 8 * size


@pytest.mark.parametrize(
    ("params", "path"),
    [
        # a fractional period: four-tap delay lines (the lanes' nt = 4 branch)
        ({"frequencies_hz": [50.0, 150.0], "period_s": 0.05013, "fractional_delay": True}, "_bank_lanes"),
        # five lines: ten states, more than the lanes' work array holds
        ({"frequencies_hz": [50.0, 110.0, 150.0, 250.0, 350.0], "period_s": 0.05}, "_bank_any"),
        # a plant that is not a bank of 2 x 2 blocks (a damped mode and a real one)
        ({"preset": "plant", "A": [[-5.0, 0.0, 0.0], [0.0, 0.0, 314.159], [0.0, -314.159, -1.0]],
          "C": [1.0, 1.0, 0.0], "period_s": 0.05}, "_bank_any"),
    ],
)  # fmt: skip
def test_grip_mixing_bank_matches_single_channel_on_every_kernel_path(params: dict, path: str, monkeypatch) -> None:
    """grip-mixing's bank takes the vector lanes for a bank of oscillators of at most eight
    states with one or four taps, and each channel through the single kernel otherwise: each
    path bit for bit with the single channel, for nine channels of which six started together
    (one group of lanes, padded) and three joined one at a time (groups of their own)."""
    from sinewatch.estimators import grip_mixing_kernels as gk

    fs, size = 4000.0, 9
    cls = get("grip-mixing")
    x = np.stack([cls.example_signal(3000, seed=40 + c) for c in range(size)], axis=1)
    singles, banked = [cls(fs, params) for _ in range(size)], [cls(fs, params) for _ in range(size)]
    for c in range(6, size):
        for est in (singles[c], banked[c]):
            est.update(np.ascontiguousarray(x[: 37 * (c - 5), c]))
    iconst = banked[0]._iconst  # the compiled dispatch's test, so the case is the path it names
    n_taps = int(iconst[3])
    lanes = bool(iconst[10 + n_taps]) and int(iconst[0]) <= gk.NMAX and n_taps in (1, 4)
    assert ("_bank_lanes" if lanes else "_bank_any") == path
    pos = 200
    for n, last_only in ((700, True), (1, False), (900, False), (1000, True)):
        _step_alike("grip-mixing", singles, banked, x[pos : pos + n], last_only)
        pos += n
