"""The command line as a user runs it: `serve`, `feed` and `tail` as separate processes
talking over Zenoh on 127.0.0.1, then `replay` of what `serve` recorded."""

from __future__ import annotations

import json
import subprocess

from conftest import make_config, replay_recording, serve_feed_tail, sinewatch


def test_serve_feed_tail_replay(tmp_path):
    config = make_config(tmp_path)
    ep = config.zenoh.listen[0]
    cfg_file = tmp_path / "serve.json"
    cfg_file.write_text(json.dumps(config.model_dump(mode="json")))
    feed_err, lines, serve_err = serve_feed_tail(
        ["--config", str(cfg_file)],
        ["--connect", ep, "--count", "10", "--json", "--timeout", "60", "--wait", "60"],
        ["--connect", ep, "--scenario", "demo-biased", "--channels", "2", "--duration", "2", "--block", "1000"],
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
