"""A Zenoh router restarted under a running daemon: nothing lost within the history.

A real router process (a Zenoh session in router mode, started and SIGKILLed by the test)
sits between a gateway (BlockPublisher) and the daemon, both Zenoh clients of it. Blocks
published while the router is down stay in the publisher's cache; when the router is back,
the daemon's recovering subscriber fetches them, so every block is estimated once and in
order. Past the publisher's history, the loss is flagged on the next estimate (gap,
gap_blocks) and counted in Status (unrecovered).
"""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator

import numpy as np
import pytest
from conftest import TIMEOUT, make_config, run_daemon

from sinewatch.clients import BlockPublisher, JsonSubscription, connect
from sinewatch.clients.session import free_loopback_port
from sinewatch.runtime.replay import read_recording, replay
from sinewatch.schemas.config import ZenohSection

ROUTER = """
import sys, threading, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"router"')
conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:%s"]' % sys.argv[1])
conf.insert_json5("scouting/multicast/enabled", "false")
session = zenoh.open(conf)
print("ready", flush=True)
threading.Event().wait()
"""


@contextlib.contextmanager
def router(port: int) -> Iterator[subprocess.Popen[str]]:
    proc = subprocess.Popen([sys.executable, "-c", ROUTER, str(port)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        yield proc
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()


def _signal(n: int) -> list[np.ndarray]:
    t = np.arange(n * 500) / 10_000.0
    x = np.sin(2 * np.pi * 50.0 * t)
    return [x[i * 500 : (i + 1) * 500] for i in range(n)]


def _status_after(status: JsonSubscription, accounted: int) -> dict | None:
    """The first Status in which ``accounted`` inputs are either processed or reported lost
    for good (the last one seen if that does not come within TIMEOUT: Status keeps coming)."""
    deadline = time.monotonic() + TIMEOUT
    msg = None
    while time.monotonic() < deadline and (msg := status.get(timeout=TIMEOUT)) is not None:
        if msg["blocks_processed"] + msg["unrecovered"] >= accounted:
            break
    return msg


@pytest.mark.parametrize(("history", "during_outage"), [(1024, 40), (8, 40)])
def test_a_router_restart_loses_nothing_within_the_history(tmp_path, history, during_outage):
    port = free_loopback_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    config = make_config(tmp_path, zenoh=ZenohSection(mode="client", listen=[], connect=[endpoint]))
    before, after = 20, 20
    blocks = _signal(before + during_outage + after)
    with router(port) as first:

        def client(daemon, _ep):
            with connect([endpoint]) as s, JsonSubscription(s, "sinewatch/status/**") as status:
                pub = BlockPublisher(s, history=history)
                assert pub.wait_for_subscriber("rr/a", TIMEOUT)
                for x in blocks[:before]:
                    pub.publish("rr/a", x, 10_000.0)
                assert _status_after(status, before) is not None
                first.send_signal(signal.SIGKILL)  # the router dies mid-stream
                first.wait()
                assert pub.wait_for_matching("rr/a", False, TIMEOUT)  # Zenoh has seen the link drop
                for x in blocks[before : before + during_outage]:
                    pub.publish("rr/a", x, 10_000.0)
                unmatched = pub.unmatched
                with router(port):  # ... and comes back on the same endpoint
                    assert pub.wait_for_subscriber("rr/a", TIMEOUT)
                    for x in blocks[before + during_outage :]:
                        pub.publish("rr/a", x, 10_000.0)
                    last = _status_after(status, len(blocks))
                return unmatched, last

        (unmatched, last), daemon, code = run_daemon(config, client)
    assert code == 0 and last is not None
    ch = daemon.pipeline.channels["rr/a"]
    assert last["blocks_processed"] >= ch.blocks, last
    assert unmatched == during_outage  # the publisher says what it could not deliver then
    if history >= during_outage:  # everything recovered: each block once, in order, no gap
        assert (ch.blocks, ch.last_seq, ch.gaps) == (len(blocks), len(blocks) - 1, 0)
        assert last["unrecovered"] == 0
    else:  # past the cache: what was not recovered is a flagged gap, and Zenoh says how many
        # (how much of the cache is recovered depends on timing: at most `history` blocks)
        assert ch.last_seq == len(blocks) - 1 and ch.gaps >= 1
        assert before + after <= ch.blocks <= before + history + after
        assert last["unrecovered"] == len(blocks) - ch.blocks
        # ... and told on the key at once, in an ErrorReport whose count is the blocks lost so far: the record of
        # a loss that no later block follows (a stream's last blocks)
        recorded = [m for path in daemon.recording_paths for kind, m in read_recording(path) if kind == "message"]
        reports = [json.loads(m.payload) for m in recorded if m.role == "error"]
        counts = [r["count"] for r in reports if r.get("kind") == "unrecovered" and r["key"] == "sinewatch/in/rr/a"]
        assert counts and counts[-1] == last["unrecovered"], counts
    assert replay(daemon.recording_paths).ok
