"""The pipeline builds each Estimate's bytes directly (no pydantic model on the hot path):
they must be the bytes of the pydantic model through ``encode_estimate``, in every format
version, for every shape of estimate (NaN and inf as null, no std, rocof, extras scalar and
vector, several components, gaps, resets, restarts), and for the tracks of every registered
estimator run through a real pipeline."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import make_config

from sinewatch.core.pipeline import Channel, NullSink, Pipeline, estimate_model
from sinewatch.estimators import available, get
from sinewatch.estimators.base import Track, TrackStd
from sinewatch.schemas.codec import TIME_QUALITY_JSON, Block, encode_block_binary, encode_estimate, json_string
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.messages import Estimate, Fencing

VERSIONS = (1, 2, 3, 4, 5)


def _reference(pipeline: Pipeline, ch: Channel, block: Block, track: Track, ts: int, t_last: int, gap, restart, reset):
    """The bytes as the pipeline built them before the fast path: the model, then encode_estimate."""
    converged = bool(track.converged[-1])
    valid = True
    if pipeline.estimate_version >= 3:
        lag = max(0, round((t_last - ts) * ch.sample_rate_hz / 1e9))
        valid = ch.presence.run_samples >= ch.valid_memory_samples + lag and bool(  # the rules in force
            np.all(np.isfinite(track.frequency_hz[-1])) and np.all(np.isfinite(track.amplitude[-1]))
        )
        converged = converged and valid
    model = estimate_model(ch, block, track, ts, converged, valid, gap, restart, reset, pipeline.fencing)
    return encode_estimate(model, pipeline.estimate_version), converged


def _values(rng: np.random.Generator, k: int, special: float) -> np.ndarray:
    """k values of every magnitude repr() writes differently (1e-05, 1e+16, -0.0, ...),
    with about one in four replaced by NaN, inf or -inf when ``special``."""
    mags = 10.0 ** rng.integers(-12, 20, size=k)
    x = rng.standard_normal(k) * mags
    x[rng.random(k) < 0.1] = -0.0
    x[rng.random(k) < 0.1] = 3.0  # integral: repr 3.0, not 3
    bad = rng.random(k) < special
    x[bad] = rng.choice([np.nan, np.inf, -np.inf], size=int(bad.sum()))
    return x


def _track(rng: np.random.Generator) -> Track:
    k = int(rng.integers(0, 4))
    n = int(rng.integers(1, 3))
    special = float(rng.choice([0.0, 0.3]))

    def rows(cols: int | None) -> np.ndarray:
        return np.stack([_values(rng, cols if cols is not None else 1, special) for _ in range(n)]).reshape(
            (n, cols) if cols is not None else (n,)
        )

    extras = {}
    for name in rng.choice(["a", "x_hat", "ü", 'q"uote'], size=int(rng.integers(0, 3)), replace=False):
        extras[str(name)] = rows(None) if rng.random() < 0.5 else rows(int(rng.integers(1, 4)))
    return Track(
        frequency_hz=rows(k),
        amplitude=rows(k),
        phase_rad=rows(k).astype(np.float32) if rng.random() < 0.2 else rows(k),
        offset=rows(None),
        converged=rng.random(n) < 0.5,
        residual_rms=float(_values(rng, 1, special)[0]),
        extras=extras,
        rocof_hz_per_s=rows(k) if rng.random() < 0.5 else None,
        std=TrackStd(rows(k), rows(k), rows(k), rows(None)) if rng.random() < 0.6 else None,
    )


@pytest.mark.parametrize("version", VERSIONS)
def test_the_fast_bytes_are_the_models_bytes_over_many_random_estimates(tmp_path, version):
    rng = np.random.default_rng(1234 + version)
    pipeline = Pipeline(make_config(tmp_path), [NullSink()], estimate_version=version)
    est = get("ges-kalman")(10_000.0, {"q": [1e-10, 1e-10, 1e-14, 1e-14], "r": 1e-4})
    names = ["a", "site-1/bus.2/V_a", "x" * 256]
    seen_null = seen_valid = seen_invalid = 0
    qualities = sorted(TIME_QUALITY_JSON)  # not stated, and every stated time quality (format 5)
    seen_quality: set[str] = set()
    for i in range(1500):
        ch = Channel(names[i % 3], "sinewatch/in/" + names[i % 3], est, 10_000.0)
        ch.presence.counters[2] = int(rng.choice([0, 10**9]))  # run length: absent, or long present
        seq = int(rng.choice([0, 7, 2**64 - 1]))
        t0 = int(rng.choice([0, -1, 1_763_900_000_123_456_789, 2**63 - 10**8, -(2**62)]))
        tq = qualities[i % len(qualities)]
        block = Block(ch.name, seq, t0, 10_000.0, np.zeros(int(rng.integers(1, 2000))), None, tq)
        track = _track(rng)
        gap = int(rng.choice([0, 0, 3]))
        restart, reset = bool(rng.random() < 0.2), bool(rng.random() < 0.2)
        ts = t0 + int(rng.integers(0, 10**6))
        # the fencing token of a clustered daemon (format 4), or none (a daemon that owns its keys alone)
        pipeline.set_fencing(None if i % 4 == 0 else Fencing(shard=names[i % 3], term=int(rng.integers(1, 2**62))))
        fast, conv = pipeline._estimate_payload(ch, block, track, ts, ts + 5_000, gap, restart, reset)
        ref, ref_conv = _reference(pipeline, ch, block, track, ts, ts + 5_000, gap, restart, reset)
        assert fast == ref, (i, fast, ref)
        assert conv == ref_conv
        msg = json.loads(fast)
        assert msg["format_version"] == version
        seen_null += b"null" in fast
        if version >= 4:
            assert msg["fencing"] == (None if i % 4 == 0 else pipeline.fencing.model_dump())
        if version >= 5:
            assert json.dumps(msg["time_quality"], separators=(",", ":")) == TIME_QUALITY_JSON[tq]
            seen_quality.add(TIME_QUALITY_JSON[tq])
        else:
            assert "time_quality" not in msg
        if version == 3:
            seen_valid += msg["diagnostics"]["valid"]
            seen_invalid += not msg["diagnostics"]["valid"]
            assert Estimate.model_validate(msg).model_dump(mode="json")["timestamp"] == msg["timestamp"]
    assert seen_null > 500  # the NaN/inf -> null path was exercised
    if version >= 5:  # null and the six stated qualities, each as the model writes it
        assert seen_quality == set(TIME_QUALITY_JSON.values()) and len(seen_quality) == 7
    if version == 3:
        assert seen_valid > 100 and seen_invalid > 100


def test_json_string_is_what_dumps_writes():
    for s in ["a/b", "ü", 'q"uote\\', "tab\there", "\u2028", "x" * 300]:
        assert json_string(s) == json.dumps(s, separators=(",", ":"))


class ComparingPipeline(Pipeline):
    """A real pipeline that also builds every estimate the model's way and compares."""

    compared = 0

    def _estimate_payload(self, ch, block, track, ts, t_last, gap, restart, reset, jump=False):
        assert not jump  # the blocks here are contiguous in time
        fast, conv = super()._estimate_payload(ch, block, track, ts, t_last, gap, restart, reset, jump)
        ref, ref_conv = _reference(self, ch, block, track, ts, t_last, gap, restart, reset)
        assert fast == ref, (ch.estimator.name, fast, ref)
        assert conv == ref_conv
        type(self).compared += 1
        return fast, conv


@pytest.mark.parametrize("name", available())
def test_every_estimators_estimates_are_the_models_bytes(tmp_path, name):
    cls = get(name)
    fs = cls.example_sample_rate_hz
    block = max(100, int(fs / 20))  # 50 ms: grid reporters (pmu) complete reports within 12 blocks
    x = cls.example_signal(block * 12, seed=3)
    compared0 = ComparingPipeline.compared
    for version in VERSIONS:
        rule = EstimatorRule(match="sinewatch/in/**", estimator=name, params=dict(cls.example_params))
        pipeline = ComparingPipeline(make_config(tmp_path, rules=[rule]), [NullSink()], estimate_version=version)
        for i in range(12):
            if i == 6:
                continue  # a gap: gap and gap_blocks in the estimate
            seq = i if i < 10 else i - 10  # seq back, time forward: a restart
            t0 = 1_763_900_000_000_000_000 + round(i * block * 1e9 / fs)
            blk = Block("c", seq, t0, fs, x[i * block : (i + 1) * block])
            pipeline.process("sinewatch/in/c", encode_block_binary(blk), "", t0)
        assert pipeline.counters.errors == 0, pipeline.counters.by_kind
    assert ComparingPipeline.compared > compared0
