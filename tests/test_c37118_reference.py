"""A C37.118.2 stream as the reference for a sinewatch channel (``sinewatch bench
pmu-reference``): the comparison's maths against known answers, and live on loopback with
the daemon's own C37.118.2 server as the "real" PMU. Compared with itself (the channel the
station serves), the error is float32 rounding; a P-class estimator on the same
amplitude-modulated signal differs from the M-class reference by far more than that, and
within what the classes' limits allow."""

from __future__ import annotations

import cmath
import math

import pytest
from conftest import TIMEOUT, make_config, run_daemon

from sinewatch.apps.bench.pmu_reference import collect_estimates, read_reference, score
from sinewatch.clients import BlockPublisher, connect, subscribe_estimates
from sinewatch.clients.c37118 import C37118Reader
from sinewatch.scenarios import get as get_scenario
from sinewatch.schemas.codec import Block, encode_block_binary
from sinewatch.schemas.config import C37118Section, C37118Station, EstimatorRule, RecordingSection

T = 1_700_000_000 * 10**9
BLOCK = 1000


def row(t_ns, mag, ang, f, rocof, *, polar=True, error=0):
    a, b = (mag, ang) if polar else (mag * math.cos(ang), mag * math.sin(ang))
    return {
        "time_ns": t_ns,
        "polar": polar,
        "phasors": {"VA": [a, b]},
        "frequency_hz": f,
        "rocof_hz_per_s": rocof,
        "data_error": error,
    }


def est(t_ns, mag, ang, f, rocof):
    return {
        "timestamp_ns": t_ns,
        "frequency_hz": [f],
        "rocof_hz_per_s": [rocof],
        "diagnostics": {"extras": {"synchrophasor_magnitude": mag, "synchrophasor_angle_rad": ang}},
    }


def test_score_against_known_errors():
    rows = [
        row(T, 1.0, 0.0, 50.0, 0.0),
        row(T + 20_000_000, 1.0, 0.5, 50.0, 0.0, polar=False),
        row(T + 40_000_000, 1.0, 0.0, 50.0, 0.0, error=2),  # flagged by the PMU: left out
        row(T + 60_000_000, 1.0, 0.0, 50.0, 0.0),  # no estimate at its time
    ]
    ests = [
        est(T, 1.01, 0.0, 50.002, 0.1),  # 1 % magnitude error: TVE 1 %
        est(T + 20_000_000, 1.0, 0.5 + 0.01, 49.999, -0.2),  # 0.01 rad: TVE 2 sin(0.005) = 0.99999 %
        est(T + 40_000_000, 9.0, 0.0, 50.0, 0.0),
    ]
    r = score(rows, ests, "VA", 50)
    assert (r["frames"], r["pairs"], r["flagged"], r["unmatched"]) == (4, 2, 1, 1)
    assert r["tve_pct"]["max"] == pytest.approx(1.0, rel=1e-12)
    assert r["tve_pct"]["mean"] == pytest.approx((1.0 + 200 * math.sin(0.005)) / 2, rel=1e-9)
    assert r["fe_hz"]["max"] == pytest.approx(0.002, rel=1e-9)
    assert r["rfe_hz_per_s"]["max"] == pytest.approx(0.2, rel=1e-12)
    assert abs(cmath.rect(1.0, 0.5) - complex(*rows[1]["phasors"]["VA"])) < 1e-15


def test_live_reference_from_the_daemons_own_c37118_server(tmp_path):
    sc = get_scenario("c37-50hz-am-2hz", duration_s=6.0)  # 10 % amplitude modulation at 2 Hz
    x, _ = sc.generate(seed=0)
    fs = sc.sample_rate_hz
    n = len(x) // BLOCK
    station = C37118Station(id_code=7, name="REF", channels=["ref/pa"], phasor_names=["VA"], time_synchronised=True)
    m_class = {"nominal_frequency_hz": 50, "reporting_rate_hz": 50, "performance_class": "M"}
    p_class = {**m_class, "performance_class": "P"}
    config = make_config(
        tmp_path,
        rules=[
            EstimatorRule(match="sinewatch/in/ref/**", estimator="pmu", params=m_class),
            EstimatorRule(match="sinewatch/in/cmp/**", estimator="pmu", params=p_class),
        ],
        recording=RecordingSection(enabled=False),
        c37118=C37118Section(enabled=True, port=0, stations=[station]),
    )

    def client(daemon, ep):
        with (
            connect([ep]) as s,
            subscribe_estimates(s, "sinewatch/est/ref/pa") as ref_est,
            subscribe_estimates(s, "sinewatch/est/cmp/pa") as cmp_est,
            C37118Reader("127.0.0.1", daemon.c37118.port, id_code=7, timeout_s=TIMEOUT) as pmu,
        ):
            pub = BlockPublisher(s)

            def feed():
                assert pub.wait_for_subscriber("ref/pa", TIMEOUT)
                for i in range(n):
                    for ch in ("ref/pa", "cmp/pa"):
                        blk = Block(ch, i, T + round(i * BLOCK * 1e9 / fs), fs, x[i * BLOCK : (i + 1) * BLOCK])
                        pub.publish_raw(ch, encode_block_binary(blk, "float64"))

            # the M-class reference reports once its window is full: 200 frames come within 6 s
            rows, name, nominal = read_reference(pmu, None, 200, confirm=True, on_start=feed)
            last = max(r["time_ns"] for r in rows)
            return (
                rows,
                name,
                score(rows, collect_estimates(ref_est, last, TIMEOUT), name, nominal),
                score(rows, collect_estimates(cmp_est, last, TIMEOUT), name, nominal),
            )

    (rows, name, itself, p), _, code = run_daemon(config, client)
    assert code == 0 and name == "VA" and len(rows) == 200
    assert all(r["time_ns"] % 20_000_000 == 0 for r in rows)
    # the channel the station serves, against its own frames: float32 rounding. The first
    # frames may say "do not use" (STAT 11: the estimate's valid is false until the estimator
    # has seen enough of the signal); they are left out of the comparison
    assert itself["pairs"] + itself["flagged"] == 200 and itself["flagged"] <= 5 and itself["unmatched"] == 0
    assert itself["tve_pct"]["max"] < 1e-4 and itself["fe_hz"]["max"] < 1e-5 and itself["rfe_hz_per_s"]["max"] < 1e-5
    # a P-class estimator of the same signal against the M-class reference: a real difference
    # (the classes' windows follow the modulation differently), thousands of times the rounding
    # above and within what the classes' own limits allow (TVE 3 % each against the truth)
    assert (p["pairs"], p["flagged"], p["unmatched"]) == (itself["pairs"], itself["flagged"], 0)
    assert 1000 * itself["tve_pct"]["max"] < p["tve_pct"]["max"] < 3.0
    assert p["fe_hz"]["max"] < 0.3 and p["rfe_hz_per_s"]["max"] < 14.0
