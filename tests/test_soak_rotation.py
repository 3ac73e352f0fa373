"""Recording memory across file rotations, 200 channels: ``sinewatch bench soak`` with a
new MCAP file every 50 s for 5 minutes (six files), the daemon's RSS every 10 s. The bench
fails when RSS after the first rotation rises more than 5 % above its first sample after
it (a rising floor: a leak); this prints the RSS of each file (its highest and lowest)."""

from __future__ import annotations

import json

import pytest

from sinewatch.apps.cli import main

ROTATE_S = 50.0
ARGS = ["--channels", "200", "--rate", "2000", "--block", "1024", "--duration", "300", "--interval", "10"]


def rss_per_file(samples: list[dict], rotate_s: float) -> list[tuple[float, float]]:
    """(lowest, highest) RSS MB of the samples taken during each file."""
    files: dict[int, list[float]] = {}
    for s in samples:
        files.setdefault(int(s["t_s"] // rotate_s), []).append(s["rss_mb"])
    return [(min(v), max(v)) for _, v in sorted(files.items())]


@pytest.mark.slow
def test_rss_is_flat_across_rotations_at_200_channels(tmp_path):
    out = tmp_path / "soak.json"
    code = main(["bench", "soak", *ARGS, "--rotate-seconds", str(ROTATE_S), "--json", str(out)])
    result = json.loads(out.read_text())
    per_file = rss_per_file(result["samples"], ROTATE_S)
    print("\nRSS MB per file (lowest, highest):", [(round(lo, 1), round(hi, 1)) for lo, hi in per_file])
    assert len(per_file) >= 5  # several rotations crossed
    assert code == 0, f"RSS grew {100 * result['rss_growth_after_warmup']:.1f} % after the first rotation"
