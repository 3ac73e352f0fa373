"""`sinewatch demo` in-process: every channel gets estimates, the recording replays."""

from __future__ import annotations

import asyncio
import io

from rich.console import Console

from sinewatch.apps.demo import run_demo
from sinewatch.runtime.replay import replay


def test_demo_runs_end_to_end_and_its_recording_replays(tmp_path):
    out = io.StringIO()
    console = Console(file=out, width=160, force_terminal=False)
    code = asyncio.run(
        run_demo(["demo-biased", "kkl-demo", "rocof-demo"], duration_s=1.5, record_dir=tmp_path, console=console)
    )
    text = out.getvalue()
    assert code == 0
    assert "Summary: 45 blocks in, 45 estimates out, 0 rejected" in text
    for name in ("biased", "kkl-demo", "rocof-demo"):
        [row] = [line for line in text.splitlines() if line.startswith(name) and " est " in line]
        # the table's conv column: the newest valid estimate, not the not-valid ones the drain releases
        assert row.split()[-3] == "yes", row
    [path] = list(tmp_path.glob("*.mcap"))
    assert f"sinewatch replay {path}" in text.replace("\n", "")
    assert replay([path]).ok


def test_demo_serves_each_channel_with_its_scenarios_suggested_estimator(tmp_path):
    from sinewatch import scenarios
    from sinewatch.apps.demo import demo_config
    from sinewatch.apps.feed import make_channels
    from sinewatch.scenarios.demo import DEMO_CHANNELS

    assert len(DEMO_CHANNELS) == 8 and all("demo" in scenarios.get(n).tags for n in DEMO_CHANNELS)
    channels = make_channels([*DEMO_CHANNELS, "kkl-demo"], prefix="demo")
    config = demo_config(channels, 7447, tmp_path, record=False)
    assert [r.match for r in config.rules] == [f"sinewatch/in/demo/{n}" for n in [*DEMO_CHANNELS, "kkl-demo"]]
    by_match = {r.match: (r.estimator, r.params) for r in config.rules}
    assert by_match["sinewatch/in/demo/demo-mains-harmonics"] == ("ipdft", {"nominal_frequency_hz": 50.0})
    assert by_match["sinewatch/in/demo/kkl-demo"] == ("kkl", {"f_min_hz": 45.0, "f_max_hz": 65.0})
    assert by_match["sinewatch/in/demo/demo-noisy-60hz"] == (
        "ges-kalman",
        {"q": [1e-10, 1e-10, 1e-15, 1e-15], "r": 5e-3},
    )
