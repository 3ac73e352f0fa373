"""``sinewatch replay``: progress bar, result table and exit code around :func:`replay`."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from rich.console import Console
from rich.table import Table

from sinewatch.apps.console import byte_progress, check_output_dir, make_console, print_table
from sinewatch.core.comtrade_file import is_comtrade
from sinewatch.core.window import ChannelFilter, Window
from sinewatch.estimators import check_rules
from sinewatch.runtime.replay import ReplayResult, check_recording, replay, replay_comtrade
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.errors import ConfigError


def run_replay(args: argparse.Namespace) -> int:
    console = make_console()
    rules = None
    if args.estimator:
        rules = [EstimatorRule(match=args.match, estimator=args.estimator, params=dict(args.param))]
        check_rules(rules)
    elif args.param:
        raise ConfigError(f"--param: expected with --estimator, got {len(args.param)} without it")
    if args.out is not None:
        check_output_dir(args.out.parent, "--out")
    window = Window.parse(getattr(args, "start", None), getattr(args, "end", None))
    channels = ChannelFilter.of(getattr(args, "channels", None))
    track = _track_target(args)
    if any(is_comtrade(p) for p in args.paths):
        if len(args.paths) > 1:
            raise ConfigError(f"replay of COMTRADE: expected one .cfg or .cff file, got {len(args.paths)} paths")
        if window.bounded or not channels.everything or track:
            raise ConfigError(
                "--start, --end, --channels, --track: expected an MCAP recording, got COMTRADE "
                "(replay it with --out first, then the recording)"
            )
        result = replay_comtrade(args.paths[0], rules=rules, out=args.out)
        report(console, result)
        for text in result.short_channels:
            console.print(f"[red]too short: {text}: its estimates are not valid[/red]", soft_wrap=True)
        return 0 if result.ok else 1
    for path in args.paths:
        check_recording(path)
    # The pipeline logs each rejected input; a replay repeats the recorded ones: keep it quiet,
    # for this replay only (a caller in the same process, a daemon or a test, keeps its warnings).
    pipeline_log = logging.getLogger("sinewatch.core.pipeline")
    level = pipeline_log.level
    pipeline_log.setLevel(logging.ERROR)
    try:
        return _replay_recordings(args, console, rules, window, channels, track)
    finally:
        pipeline_log.setLevel(level)


def _replay_recordings(
    args: argparse.Namespace,
    console: Console,
    rules: list[EstimatorRule] | None,
    window: Window,
    channels: ChannelFilter,
    track: Path | bool,
) -> int:
    total = sum(p.stat().st_size for p in args.paths)
    done_before = {p: sum(q.stat().st_size for q in args.paths[:i]) for i, p in enumerate(args.paths)}
    with byte_progress(console, "replaying", disable=args.no_progress) as progress:
        task = progress.add_task("replay", total=total)
        result = replay(
            args.paths,
            rules=rules,
            out=args.out,
            on_progress=lambda path, pos: progress.update(task, completed=done_before[path] + pos),
            window=window,
            channels=channels,
            track=track,
        )
    report(console, result)
    return 0 if result.ok else 1


def _track_target(args: argparse.Namespace) -> Path | bool:
    """``--track``: True (into --out), a Parquet path, or False."""
    track = getattr(args, "track", False)
    if track is True:
        if args.out is None:
            raise ConfigError("--track: expected --out (the recording to write the track into) or --track FILE.parquet")
        return True
    if not track:
        return False
    path = Path(track)
    if path.suffix != ".parquet":
        raise ConfigError(f"--track: expected a .parquet path (or no value, with --out), got {track!r}")
    check_output_dir(path.parent if str(path.parent) else Path("."), "--track")
    return path


def report(console: Console, r: ReplayResult) -> None:
    if r.window:
        console.print(
            f"window: {r.window or 'whole recording'}; started from the {r.started_from or 'run start'}, "
            f"{r.warmup_inputs} inputs before the window run, not compared"
        )
    for path in r.incomplete_files:
        console.print(f"[yellow]{path} was not finished (writer killed?): its complete chunks were replayed[/yellow]")
    console.print(
        f"{r.inputs} inputs replayed; {r.produced_estimates} estimates produced, "
        f"{r.recorded_estimates} recorded; errors: {r.produced_errors} produced, {r.recorded_errors} recorded"
    )
    if r.compared:
        if r.ok:
            console.print(f"[green]OK: all {r.matched} recorded estimates reproduced bit for bit[/green]")
            if r.recorded_other:
                others = ", ".join(f"{n} {role}" for role, n in sorted(r.recorded_other.items()))
                console.print(f"[green]OK: all other recorded outputs ({others}) reproduced bit for bit[/green]")
        else:
            console.print(
                f"[red]MISMATCH: {r.matched} of {r.recorded_estimates} estimates reproduced"
                + "".join(
                    f", {r.matched_other.get(role, 0)} of {n} {role}" for role, n in sorted(r.recorded_other.items())
                )
                + f"; {len(r.mismatches)} differ[/red]"
            )
            by_topic: dict[str, int] = {}
            for m in r.mismatches:
                by_topic[m.topic] = by_topic.get(m.topic, 0) + 1
            for topic, n in sorted(by_topic.items()):
                first = next(m for m in r.mismatches if m.topic == topic)
                console.print(f"  {topic}: {n} differ; first: {first.describe()}")
        if r.uncompared_tail:
            console.print(f"  ({r.uncompared_tail} estimates past the end of the unfinished file not compared)")
    else:
        table = Table(title="last estimate per channel: recorded vs re-run")
        for col in ("channel", "recorded", "re-run"):
            table.add_column(col)
        for topic, (rec, new) in sorted(r.final.items()):
            table.add_row(topic, _brief(rec), _brief(new))
        print_table(console, table)
    for path in r.out_paths:
        console.print(f"new recording: {path}")
    if r.track_rows:
        where = r.track_path or "the new recording (sinewatch/track/CHANNEL)"
        console.print(f"track: {r.track_rows} rows (one per sample) in {where}")


def _brief(payload: bytes | None) -> str:
    if payload is None:
        return "-"
    m = json.loads(payload)

    def f(v: float | None) -> str:
        return "nan" if v is None else f"{v:.4f}"

    return (
        f"{m['estimator']} f={','.join(map(f, m['frequency_hz']))} A={','.join(map(f, m['amplitude']))} "
        f"off={f(m['offset'])} conv={m['diagnostics']['converged']}"
    )
