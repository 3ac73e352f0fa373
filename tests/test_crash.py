"""kill -9 under load: the recording loses at most its flush interval, and still replays.

``sinewatch serve`` runs as its own process; the test feeds it in lock step (each block
published once the previous estimate came back, so the test knows when the daemon had
handled each one), SIGKILLs it mid-stream, and reads the unfinished MCAP file: every input
handled more than ``flush_interval_s`` before the kill is in it, and replaying it
reproduces the recorded estimates bit for bit.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
from conftest import STARTUP_WAIT_S, TIMEOUT, make_config

from sinewatch.clients import BlockPublisher, JsonSubscription, connect, subscribe_estimates
from sinewatch.runtime.replay import read_recording, replay
from sinewatch.schemas.config import RecordingSection

FLUSH_S = 0.25
TIMER_SLACK_S = 0.15  # the flush timer fires on a loaded event loop: allow it this much lateness


def test_sigkill_under_load_loses_at_most_the_flush_interval(tmp_path):
    config = make_config(tmp_path, recording=RecordingSection(directory=tmp_path / "rec", flush_interval_s=FLUSH_S))
    cfg_file = tmp_path / "serve.json"
    cfg_file.write_text(json.dumps(config.model_dump(mode="json")))
    # One process: what a SIGKILL of the process holding the recorder loses (with workers, a
    # SIGKILL of the supervisor makes its workers drain: test_workers.py)
    serve = subprocess.Popen([sys.executable, "-m", "sinewatch", "serve", "--config", str(cfg_file), "--workers", "1"])
    handled_at: list[float] = []  # when each block's estimate came back
    try:
        with connect([config.zenoh.listen[0]], timeout_s=STARTUP_WAIT_S) as s:  # serve starting up
            with JsonSubscription(s, "sinewatch/status/**") as status:
                assert status.get(timeout=TIMEOUT) is not None  # the daemon is up
            est = subscribe_estimates(s)
            pub = BlockPublisher(s)
            assert pub.wait_for_subscriber("k/a", TIMEOUT)
            x = np.sin(2 * np.pi * 50.0 * np.arange(500) / 10_000.0)
            start = time.monotonic()
            # each block's estimate leaves by the idle release (the test waits for it before the
            # next block: 0.5-0.75 s, idle_release_s and its timer): at least three, so that the
            # first is settled however slow a loaded machine makes them
            while time.monotonic() - start < 3 * FLUSH_S + 1.0 or len(handled_at) < 3:
                pub.publish("k/a", x, 10_000.0)
                assert est.get(timeout=TIMEOUT) is not None
                handled_at.append(time.monotonic())
            serve.send_signal(signal.SIGKILL)
            killed_at = time.monotonic()
    finally:
        serve.kill()
        serve.wait()
    [path] = sorted((tmp_path / "rec").glob("*.mcap"))
    records = list(read_recording(path))
    assert records[-1][0] == "incomplete"  # no footer: the writer never finished
    inputs = sum(1 for kind, m in records if kind == "message" and m.role == "input")
    settled = sum(1 for t in handled_at if t < killed_at - FLUSH_S - TIMER_SLACK_S)
    assert settled > 0 and settled <= inputs <= len(handled_at)
    print(
        f"\nSIGKILL: {len(handled_at)} blocks handled, {inputs} recorded, "
        f"{len(handled_at) - inputs} lost (<= the last {FLUSH_S + TIMER_SLACK_S} s: {len(handled_at) - settled})"
    )
    result = replay([path])
    assert result.ok and result.incomplete_files == [path] and result.matched == result.recorded_estimates > 0
