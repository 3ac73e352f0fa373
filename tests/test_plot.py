"""``sinewatch plot``: one PNG of a channel of two recordings; its size and pixels show
that it drew the panels, the recordings' colours, the input and the shaded gaps."""

from __future__ import annotations

import matplotlib.image
import numpy as np
import pytest
from test_compare_track import OTHER
from test_replay_window import record

from sinewatch.apps.cli import main
from sinewatch.apps.plot import COLOURS, GAP_COLOUR, INPUT_COLOUR, gap_spans, plot
from sinewatch.core.window import Window
from sinewatch.runtime.replay import replay


def rgb(hex_colour: str, alpha: float = 1.0) -> np.ndarray:
    """The colour as drawn over white with ``alpha``, 0-255."""
    c = np.array([int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)], dtype=float)
    return np.round(255 - alpha * (255 - c))


def count(image: np.ndarray, colour: np.ndarray, box: tuple[int, int, int, int] | None = None) -> int:
    if box is not None:
        left, top, right, bottom = box
        image = image[top:bottom, left:right]
    return int(np.sum(np.all(np.abs(image[..., :3] - colour) <= 1.5, axis=-1)))


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    d = tmp_path_factory.mktemp("plot")
    original = record(d, n_blocks=60)
    rerun = d / "rerun.mcap"
    replay([original], rules=[OTHER], out=rerun)
    return original, rerun


def test_the_png_shows_both_recordings_the_input_and_the_gaps(recordings, tmp_path):
    out = tmp_path / "faulty.png"
    r = plot(list(recordings), "win/demo-faulty-sensor", out, window=Window.parse("+0.6s", "+1.6s"))
    # 25 blocks in the window, one dropped (seq 45): 24 estimates each, the NaN block 30 rejected
    assert r.estimates == [23, 23]
    image = matplotlib.image.imread(out)[..., :3] * 255
    assert image.shape[:2] == (r.size_px[1], r.size_px[0]) == (1020, 1200)
    assert out.stat().st_size > 50_000
    white = np.all(image > 250, axis=-1)
    for name, (left, top, right, bottom) in r.axes_px.items():
        inside = ~white[top + 3 : bottom - 3, left + 3 : right - 3]
        assert inside.mean() > 0.01, f"panel {name} is empty"
    legend_band = (0, 0, r.size_px[0], r.axes_px["signal"][1])  # above the first panel
    for colour in (COLOURS[0], COLOURS[1], INPUT_COLOUR):
        assert count(image, rgb(colour), legend_band) > 20, f"legend lacks {colour}"
    assert count(image, rgb(INPUT_COLOUR), r.axes_px["signal"]) > 500  # the input samples
    for panel in ("frequency", "amplitude"):  # both recordings' estimates, in their colours
        assert count(image, rgb(COLOURS[0]), r.axes_px[panel]) > 100
        assert count(image, rgb(COLOURS[1]), r.axes_px[panel]) > 100
    gap = rgb(GAP_COLOUR, 0.18)  # shaded where block 45 is missing and block 30 was rejected
    assert count(image, gap, r.axes_px["rocof"]) > 500 and count(image, gap, legend_band) > 20


def test_gap_spans_are_missing_and_rejected_blocks():
    x = np.zeros(400)
    bad = x.copy()
    bad[3] = np.nan
    blocks = [(0, 0, 10_000.0, x), (1, 40_000_000, 10_000.0, bad), (1, 40_000_000, 10_000.0, bad)]
    blocks += [(3, 120_000_000, 10_000.0, x)]
    assert gap_spans(blocks) == [(40_000_000, 80_000_000), (80_000_000, 120_000_000)]


def test_plot_names_the_channels_when_the_channel_is_not_recorded(recordings, tmp_path, capsys):
    assert main(["plot", str(recordings[0]), "--channel", "nope", "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "--channel: expected one of win/demo-biased, win/demo-faulty-sensor" in err and "got 'nope'" in err
