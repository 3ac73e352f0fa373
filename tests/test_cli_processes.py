"""The command line as a user runs it: `serve`, `feed` and `tail` as separate processes
talking over Zenoh on 127.0.0.1, then `replay` of what `serve` recorded."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

from conftest import make_config


def sinewatch(*args: str) -> list[str]:
    return [sys.executable, "-m", "sinewatch", *args]


def test_serve_feed_tail_replay(tmp_path):
    config = make_config(tmp_path)
    ep = config.zenoh.listen[0]
    cfg_file = tmp_path / "serve.json"
    cfg_file.write_text(json.dumps(config.model_dump(mode="json")))
    serve = subprocess.Popen(sinewatch("serve", "--config", str(cfg_file)), stderr=subprocess.PIPE, text=True)
    try:
        tail = subprocess.Popen(
            sinewatch("tail", "--connect", ep, "--count", "10", "--json", "--timeout", "60", "--wait", "60"),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert tail.stderr.readline().startswith("tail: subscribed to")  # before anything is fed
        feed = subprocess.run(
            sinewatch(
                "feed",
                "--connect",
                ep,
                "--scenario",
                "demo-biased",
                "--channels",
                "2",
                "--duration",
                "2",
                "--block",
                "1000",
                "--fast",
                "--wait",
                "60",
            ),
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert feed.returncode == 0, feed.stderr
        assert "published 40 blocks" in feed.stderr
        out, _ = tail.communicate(timeout=120)
        lines = [json.loads(line) for line in out.splitlines()]
        assert len(lines) == 10 and {m["channel"] for m in lines} <= {"sim/demo-biased/0", "sim/demo-biased/1"}
    finally:
        serve.send_signal(signal.SIGINT)
        _, err = serve.communicate(timeout=60)
    assert serve.returncode == 0, err
    assert "drained: 40 inputs, 40 estimates, 0 errors" in err
    [mcap] = list((tmp_path / "rec").glob("*.mcap"))
    replay = subprocess.run(
        sinewatch("replay", str(mcap), "--no-progress"), capture_output=True, text=True, timeout=120, check=False
    )
    assert replay.returncode == 0, replay.stdout + replay.stderr
    assert "all 40 recorded estimates reproduced bit for bit" in replay.stdout


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
