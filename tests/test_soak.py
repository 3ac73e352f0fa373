"""Soak: the daemon under steady real-time load for minutes (`make test-slow`)."""

from __future__ import annotations

import resource

import pytest
from conftest import make_config, run_daemon

from sinewatch.apps.feed import Feed, make_channels
from sinewatch.clients import BlockPublisher, connect, subscribe_estimates
from sinewatch.runtime.replay import replay
from sinewatch.scenarios.demo import DEMO_CHANNELS
from sinewatch.schemas.config import RecordingSection


@pytest.mark.slow
def test_two_minutes_of_eight_channels_lose_nothing_and_replay(tmp_path):
    seconds = 120.0
    config = make_config(tmp_path, recording=RecordingSection(directory=tmp_path / "rec", rotate_seconds=45.0))

    def client(_daemon, ep):
        with connect([ep]) as s:
            est = subscribe_estimates(s)
            pub = BlockPublisher(s)
            channels = make_channels(DEMO_CHANNELS, prefix="soak", duration_s=seconds)
            for c in channels:
                assert pub.wait_for_subscriber(c.channel, 20)
            rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            sent = Feed(pub, channels, block_size=1000, realtime=True).run(seconds)
            rejected = sum(c.faults_injected.get("nan", 0) + c.faults_injected.get("duplicate", 0) for c in channels)
            got = 0
            while got < sent - rejected and est.get(timeout=20) is not None:
                got += 1
            return sent, rejected, got, rss_before

    (sent, rejected, got, rss_before), daemon, code = run_daemon(config, client)
    assert code == 0 and got == sent - rejected
    rss_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    assert rss_after - rss_before < 100_000  # KiB: no growth with time beyond buffers
    paths = daemon.recording_paths
    assert len(paths) >= 3
    assert replay(paths[-1:]).ok and replay(paths).ok
