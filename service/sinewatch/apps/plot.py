"""``sinewatch plot FILE [FILE...] --channel NAME [--start T] [--end T]``: one PNG of one
channel, for a bug report or a first look.

Panels on one time axis (data time: the blocks' sample times, in seconds after the first
sample plotted):

1. the input samples (grey; from the first recording that has them) and, for each
   recording in its own colour, the estimated signal ``offset + sum_k A_k sin(phase_k)``
   over each block, from the block's estimate (at its last sample) carried back over the
   block's samples at its frequency;
2. frequency (Hz), 3. amplitude and 4. ROCOF (Hz/s) of each estimate, with a band of one
   standard deviation where the estimator reports it;
5. per recording, when its estimates were valid (``diagnostics.valid``) and converged.

Gaps (blocks missing from the sequence) and rejected inputs (a block with a non-finite
sample, a duplicate) are shaded red on every panel; the times the first recording's
estimates were not valid, grey. Needs matplotlib (``pip install 'sinewatch[plots]'``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from sinewatch.core.window import Window
from sinewatch.runtime.replay import check_recording, read_window
from sinewatch.schemas.codec import Block
from sinewatch.schemas.errors import InputError, SinewatchError
from sinewatch.schemas.frame import Frame, decode_input

COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf")  # tab10, red left out
INPUT_COLOUR = "#8c8c8c"
GAP_COLOUR = "#d62728"
INVALID_COLOUR = "#7f7f7f"
DPI = 100


class PlotError(SinewatchError, ValueError):
    """The plot cannot be made as asked (no such channel, no matplotlib)."""


@dataclass
class Series:
    """One recording's view of the channel."""

    path: Path
    estimator: str = ""
    blocks: list[tuple[int, int, float, np.ndarray]] = field(default_factory=list)  # seq, t0_ns, rate, column 0
    estimates: list[dict[str, Any]] = field(default_factory=list)
    channels_seen: set[str] = field(default_factory=set)


def read_series(path: Path, channel: str, window: Window) -> Series:
    """The channel's input blocks and estimates in ``window`` of the recording at ``path``."""
    check_recording(path)
    s = Series(path)
    for kind, item in read_window(path, window):
        if kind != "message":
            continue
        if item.role == "estimate":
            msg = json.loads(item.payload)
            s.channels_seen.add(msg["channel"])
            if msg["channel"] == channel:
                s.estimates.append(msg)
                s.estimator = msg["estimator"]
        elif item.role == "input":
            block = _channel_block(item.payload, item.zenoh_encoding, channel)
            if block is not None:
                x = block.samples.reshape(block.n_samples, -1)[:, 0].astype(np.float64)
                s.blocks.append((block.seq, block.t0_ns, block.sample_rate_hz, x))
    return s


def _channel_block(payload: bytes, encoding: str, channel: str) -> Block | None:
    """The channel's block in a recorded input: the block itself, or its column of a
    multi-channel frame; None for another channel's input or one that does not decode."""
    try:
        decoded = decode_input(payload, encoding)
    except InputError:
        return None
    if isinstance(decoded, Frame):
        return decoded.block(decoded.channels.index(channel)) if channel in decoded.channels else None
    return decoded if decoded.channel == channel else None


def _arr(values: list[Any]) -> np.ndarray:
    return np.array([math.nan if v is None else float(v) for v in values], dtype=np.float64)


def _component(msgs: list[dict[str, Any]], name: str, k: int = 0, std: bool = False) -> np.ndarray:
    out = []
    for m in msgs:
        src = (m.get("std") or {}) if std else m
        v = src.get(name)
        if isinstance(v, list):
            v = v[k] if k < len(v) else None
        out.append(v)
    return _arr(out)


def gap_spans(blocks: list[tuple[int, int, float, np.ndarray]]) -> list[tuple[int, int]]:
    """(start, end) data times, ns, with no accepted input: missing blocks between two
    received ones, and blocks with a non-finite sample (rejected). Duplicates are skipped."""
    spans: list[tuple[int, int]] = []
    last_seq: int | None = None
    last_end: int | None = None
    for seq, t0, rate, x in blocks:
        if last_seq is not None and seq <= last_seq:
            continue  # a duplicate (or older): rejected, adds nothing
        end = t0 + round(len(x) * 1e9 / rate)
        if last_end is not None and t0 > last_end + round(0.5e9 / rate):
            spans.append((last_end, t0))
        if not np.isfinite(x).all():
            spans.append((t0, end))
        last_seq, last_end = seq, end
    return spans


def _spans(times: np.ndarray, flags: np.ndarray) -> list[tuple[float, float]]:
    """Runs of True in ``flags`` as (start, end) times, each run ending at the next time."""
    out = []
    start = None
    for i, f in enumerate(flags):
        if f and start is None:
            start = times[i - 1] if i > 0 else times[i]
        if not f and start is not None:
            out.append((start, times[i - 1]))
            start = None
    if start is not None:
        out.append((start, times[-1]))
    return out


@dataclass
class PlotResult:
    path: Path
    size_px: tuple[int, int]
    axes_px: dict[str, tuple[int, int, int, int]]  # panel -> (left, top, right, bottom), image pixels
    colours: list[str]
    estimates: list[int]


def plot(
    paths: list[Path], channel: str, out: Path, *, window: Window | None = None, width_in: float = 12.0
) -> PlotResult:
    """Draw the PNG (module docstring) and return where its panels are."""
    try:
        import matplotlib
    except ImportError:
        raise PlotError(
            "plot: expected matplotlib to be installed, got no matplotlib (pip install 'sinewatch[plots]')"
        ) from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    window = window or Window()
    first_window = Window(window.start, window.end)
    series = [read_series(paths[0], channel, first_window)]
    for path in paths[1:]:  # relative times are the first recording's: a re-run may start later
        other = Window(window.start, window.end)
        if first_window.origin_ns is not None:
            other.anchor(first_window.origin_ns)
        series.append(read_series(path, channel, other))
    if not any(s.estimates for s in series):
        seen = sorted(set().union(*(s.channels_seen for s in series)))
        listed = ", ".join(seen[:8]) + (", ..." if len(seen) > 8 else "")
        raise PlotError(f"--channel: expected one of {listed or 'the recorded channels'}, got {channel!r}")
    inputs = next((s.blocks for s in series if s.blocks), [])
    first_t = [b[1] for b in inputs[:1]] + [int(s.estimates[0]["timestamp_ns"]) for s in series if s.estimates]
    t_origin = min(first_t)
    rate = inputs[0][2] if inputs else None

    def secs(ns: Any) -> Any:
        return (np.asarray(ns, dtype=np.float64) - t_origin) / 1e9

    height = width_in * 0.85
    fig, axes = plt.subplots(
        5, 1, figsize=(width_in, height), sharex=True, gridspec_kw={"height_ratios": [3, 2, 2, 2, 1]}
    )
    ax_sig, ax_f, ax_a, ax_r, ax_v = axes
    # gaps and rejected inputs, on every panel
    for a, b in gap_spans(inputs):
        for ax in axes:
            ax.axvspan(float(secs(a)), float(secs(b)), color=GAP_COLOUR, alpha=0.18, lw=0)
    # the input
    for _seq, t0, r, x in inputs:
        t = secs(t0 + np.round(np.arange(len(x)) * (1e9 / r)))
        ax_sig.plot(t, x, color=INPUT_COLOUR, lw=2.4, zorder=1)  # wide: the estimates run over it
    colours = []
    for i, s in enumerate(series):
        colour = COLOURS[i % len(COLOURS)]
        colours.append(colour)
        if not s.estimates:
            continue
        t = secs([m["timestamp_ns"] for m in s.estimates])
        style = "-" if i == 0 else "--"
        if rate is not None:
            _reconstruction(ax_sig, s.estimates, rate, secs, colour, style)
        gaps = np.array([bool(m["diagnostics"].get("gap")) for m in s.estimates])
        for ax, name in ((ax_f, "frequency_hz"), (ax_a, "amplitude"), (ax_r, "rocof_hz_per_s")):
            k_max = max(len(m.get(name) or []) for m in s.estimates)
            for k in range(k_max):
                tb, y = _broken(t, _component(s.estimates, name, k), gaps)
                ax.plot(tb, y, color=colour, lw=1.4, ls=style)
                if name != "rocof_hz_per_s":
                    _, sd = _broken(t, _component(s.estimates, name, k, std=True), gaps)
                    if np.isfinite(sd).any():
                        ax.fill_between(tb, y - sd, y + sd, color=colour, alpha=0.25, lw=0)
        valid = np.array([bool(m["diagnostics"].get("valid", m["diagnostics"]["converged"])) for m in s.estimates])
        converged = np.array([bool(m["diagnostics"]["converged"]) for m in s.estimates])
        level = len(series) - 1 - i
        for lo, hi in _spans(t, valid):
            ax_v.broken_barh([(lo, hi - lo)], (level + 0.05, 0.4), color=colour)
        for lo, hi in _spans(t, converged):
            ax_v.broken_barh([(lo, hi - lo)], (level + 0.5, 0.4), color=colour, alpha=0.5)
        if i == 0:
            for lo, hi in _spans(t, ~valid):
                for ax in axes[:4]:
                    ax.axvspan(lo, hi, color=INVALID_COLOUR, alpha=0.12, lw=0)
    _labels(axes, series, t_origin)
    handles: list[Any] = [matplotlib.lines.Line2D([], [], color=INPUT_COLOUR, lw=1.2, label="input samples")]
    for i, s in enumerate(series):
        handles.append(
            matplotlib.lines.Line2D(
                [], [], color=colours[i], lw=2.5, ls="-" if i == 0 else "--", label=f"{_tag(i)}: {_short(s)}"
            )
        )
    handles += [
        Patch(color=colours[0], alpha=0.25, label="± 1 std (where reported)"),
        Patch(color=GAP_COLOUR, alpha=0.18, label="gap / rejected input"),
        Patch(color=INVALID_COLOUR, alpha=0.12, label="A not valid"),
    ]
    fig.legend(handles=handles, loc="upper center", ncol=3, bbox_to_anchor=(0.5, 0.965), fontsize=9)
    span = "" if not window.bounded else f", window {_window_text(window)}"
    fig.suptitle(f"{channel}{span}", fontsize=13, y=0.995)
    fig.tight_layout(rect=(0, 0, 1, 0.925))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=DPI)
    width_px, height_px = fig.canvas.get_width_height()
    boxes = {}
    for name, ax in zip(("signal", "frequency", "amplitude", "rocof", "validity"), axes, strict=True):
        x0, y0, x1, y1 = ax.get_window_extent().extents
        boxes[name] = (round(x0), round(height_px - y1), round(x1), round(height_px - y0))
    plt.close(fig)
    return PlotResult(out, (width_px, height_px), boxes, colours, [len(s.estimates) for s in series])


def _broken(t: np.ndarray, y: np.ndarray, gaps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``t`` and ``y`` with a NaN point before each estimate after a gap: the line stops at
    the gap instead of bridging it."""
    at = np.flatnonzero(gaps)
    return np.insert(t, at, np.nan), np.insert(y, at, np.nan)


def _tag(i: int) -> str:
    """A, B, C, ...: the recordings in the order given."""
    return chr(ord("A") + i) if i < 26 else f"#{i + 1}"


def _short(s: Series, keep: int = 40) -> str:
    name = s.path.name if len(s.path.name) <= keep else s.path.name[: keep // 2 - 1] + "…" + s.path.name[-keep // 2 :]
    return f"{name} ({s.estimator or 'no estimates'})"


def _window_text(window: Window) -> str:
    return f"{window.start.text if window.start else 'start'} .. {window.end.text if window.end else 'end'}"


def _reconstruction(ax: Any, estimates: list[dict[str, Any]], rate: float, secs: Any, colour: str, style: str) -> None:
    """``offset + sum_k A_k sin(phase_k + 2 pi f_k (t - t_e))`` over each estimate's block
    (its ``n_samples`` up to its time ``t_e``): one line, broken between blocks."""
    ts, ys = [], []
    for m in estimates:
        n = int(m["n_samples"])
        dt = (np.arange(n) - (n - 1)) / rate  # seconds before the estimate's time
        y = np.full(n, np.nan if m["offset"] is None else float(m["offset"]))
        for f, a, ph in zip(m["frequency_hz"], m["amplitude"], m["phase_rad"], strict=False):
            if None in (f, a, ph):
                y[:] = np.nan
                continue
            y += a * np.sin(ph + 2 * np.pi * f * dt)
        ts.append(secs(m["timestamp_ns"]) + dt)
        ys.append(y)
        ts.append(np.array([np.nan]))
        ys.append(np.array([np.nan]))
    ax.plot(np.concatenate(ts), np.concatenate(ys), color=colour, lw=0.9, ls=style, zorder=3)


def _labels(axes: Any, series: list[Series], t_origin: int) -> None:
    ax_sig, ax_f, ax_a, ax_r, ax_v = axes
    ax_sig.set_ylabel("signal (input units)")
    ax_f.set_ylabel("frequency (Hz)")
    ax_a.set_ylabel("amplitude (input units)")
    ax_r.set_ylabel("ROCOF (Hz/s)")
    ax_v.set_yticks(
        [len(series) - 1 - i + off for i in range(len(series)) for off in (0.25, 0.7)],
        [f"{_tag(i)} {what}" for i in range(len(series)) for what in ("valid", "converged")],
        fontsize=8,
    )
    ax_v.set_ylim(0, len(series))
    start = datetime.fromtimestamp(t_origin / 1e9, tz=UTC).isoformat(timespec="milliseconds")
    ax_v.set_xlabel(f"time (s) after {start} (the first sample plotted)")
    for ax in axes:
        ax.grid(True, alpha=0.3)


def run_plot(args: Any) -> int:
    from sinewatch.apps.console import check_output_dir

    out = args.out or args.paths[0].with_name(args.channel.replace("/", "_") + ".png")
    check_output_dir(out.parent, "--out")
    result = plot(args.paths, args.channel, out, window=Window.parse(args.start, args.end), width_in=args.width)
    print(f"{result.path} ({result.size_px[0]}x{result.size_px[1]} px; estimates: {result.estimates})")
    return 0


__all__ = ["PlotError", "PlotResult", "gap_spans", "plot", "run_plot"]
