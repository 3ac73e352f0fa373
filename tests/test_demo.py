"""`sinewatch demo` in-process: every channel gets estimates, the recording replays."""

from __future__ import annotations

import asyncio
import io

from rich.console import Console

from sinewatch.demo import run_demo
from sinewatch.replay import replay


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
        assert name in text
    [path] = list(tmp_path.glob("*.mcap"))
    assert f"sinewatch replay {path}" in text.replace("\n", "")
    assert replay([path]).ok
