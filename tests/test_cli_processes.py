"""The command line as a user runs it: `serve`, `feed` and `tail` as separate processes
talking over Zenoh on 127.0.0.1, then `replay` of what `serve` recorded."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

from conftest import make_config, replay_recording, serve_config_feed_tail, serve_feed_tail, sinewatch


def test_serve_feed_tail_replay(tmp_path):
    config = make_config(tmp_path)
    feed_err, lines, serve_err = serve_config_feed_tail(
        tmp_path, config, 10, ["--scenario", "demo-biased", "--channels", "2", "--duration", "2", "--block", "1000"]
    )
    assert "published 40 blocks" in feed_err
    assert len(lines) == 10 and {m["channel"] for m in lines} <= {"sim/demo-biased/0", "sim/demo-biased/1"}
    assert "drained: 40 inputs, 40 estimates, 0 errors" in serve_err
    assert "all 40 recorded estimates reproduced bit for bit" in replay_recording(tmp_path / "rec")


def test_feed_without_a_daemon_says_so(tmp_path):
    config = make_config(tmp_path)  # nothing listens on its port
    r = subprocess.run(
        sinewatch("feed", "--connect", config.zenoh.listen[0], "--wait", "1", "--duration", "0.1"),
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert r.returncode != 0
    assert "is the daemon running" in r.stderr or "could not open" in r.stderr


def test_deploy_pmu_config_serves_reports_on_the_time_grid(tmp_path):
    """deploy/pmu.toml as a user runs it: a C37-style feed in, reports every 20 ms of the
    epoch out (several per 100 ms block), each with ROCOF, and the recording replays."""
    from sinewatch.clients.session import free_loopback_port

    ep = f"tcp/127.0.0.1:{free_loopback_port()}"
    env = {
        **os.environ,
        "SINEWATCH__ZENOH__LISTEN": json.dumps([ep]),
        "SINEWATCH__RECORDING__DIRECTORY": str(tmp_path / "rec"),
    }
    deploy = Path(__file__).resolve().parents[1] / "deploy" / "pmu.toml"
    _, reports, _ = serve_feed_tail(
        ["--config", str(deploy)],
        ["--connect", ep, "--count", "40", "--json", "--timeout", "60", "--wait", "60"],
        ["--connect", ep, "--scenario", "c37-50hz-off-p2", "--prefix", "pmu", "--duration", "2", "--block", "1000"],
        serve_env=env,
    )
    assert len(reports) == 40 and {r["estimator"] for r in reports} == {"pmu"}
    assert all(r["timestamp_ns"] % 20_000_000 == 0 for r in reports)  # on the 50 frames/s grid
    times = [r["timestamp_ns"] for r in reports]
    assert times == sorted(times) and len({r["seq"] for r in reports}) < len(reports)  # several per block
    settled = [r for r in reports if r["diagnostics"]["converged"]]
    assert settled and all(abs(r["frequency_hz"][0] - 52.0) < 0.005 for r in settled)  # M-class FE limit
    assert all(r["rocof_hz_per_s"] is not None for r in settled)
    assert "recorded estimates reproduced bit for bit" in replay_recording(tmp_path / "rec")
