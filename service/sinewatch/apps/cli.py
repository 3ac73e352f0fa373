"""The ``sinewatch`` command line.

sinewatch demo                      the whole path on loopback, with a live table
sinewatch serve --config FILE       run the daemon
sinewatch config show [--config F]  print the effective configuration
sinewatch schemas export DIR        write the JSON Schemas
sinewatch estimators                list estimators and their parameters
sinewatch feed [...]                publish simulated sample blocks
sinewatch gateway sv [...]          IEC 61850-9-2 sampled values (interface or pcap) as frames
sinewatch tail [KEYEXPR]            print estimates as they arrive
sinewatch replay RUN.mcap [...]     replay a recording (bit-exact check, or re-run)
sinewatch export RUN.mcap [...]     the recording's estimates (and samples) as CSV or Parquet
sinewatch compare A.mcap B.mcap     two recordings of the same inputs, channel by channel
sinewatch plot RUN.mcap [...]       one channel's input and estimates as a PNG
sinewatch status                    which daemon owns which channels (shards, standbys)
sinewatch router [--listen EP]      a Zenoh router (from the eclipse-zenoh wheel)
sinewatch bench kernels|e2e|accuracy|scenarios|gateway|...

Why one module of about 900 lines: it is the table of contents of the command line. Each
command here is a few lines that check its arguments and hand over to the module that does
the work, imported when the command runs (so ``sinewatch config show`` loads no estimator);
the parser beside them is one ``build_parser``. Split by command, the commands would need
the connection and waiting helpers they share one layer down, which is the client library's
place, not the CLI's.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any, NoReturn, cast

from sinewatch.apps.bench.args import add_bench_parser
from sinewatch.schemas import __version__
from sinewatch.schemas.errors import ConfigError, SinewatchError

log = logging.getLogger("sinewatch.apps.cli")


def _setup_logging(verbose: int) -> None:
    level = logging.WARNING - 10 * verbose
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def zenoh_log() -> None:
    """Zenoh's own log on stdout: ``RUST_LOG`` when set, else its errors, among them a link
    it closes because a peer took no data for ``wait_before_close`` (docs/cluster.md): the
    one record of blocks lost in flight."""
    import zenoh

    zenoh.init_log_from_env_or("error")


def parse_param(text: str) -> tuple[str, Any]:
    """``k=v`` with v parsed as JSON when it parses (numbers, lists, true), else a string."""
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    key, raw = text.split("=", 1)
    try:
        return key, json.loads(raw)
    except ValueError:
        return key, raw


# ---- commands --------------------------------------------------------------------------------
def cmd_demo(args: argparse.Namespace) -> int:
    from sinewatch.apps.demo import main

    names = args.scenarios.split(",") if args.scenarios else None
    if names:
        _check_scenarios(names)
    if not args.no_record:
        from sinewatch.apps.console import check_output_dir

        check_output_dir(Path(args.record_dir), "--record-dir")
    return main(names, args.duration, Path(args.record_dir), not args.no_record)


def cmd_serve(args: argparse.Namespace) -> int:
    from sinewatch.estimators import check_rules
    from sinewatch.runtime.daemon import serve
    from sinewatch.schemas.config import load_config

    config = load_config(args.config)
    if args.foxglove is not None:  # the flags override [foxglove] port and [metrics] port
        config.foxglove.port = args.foxglove
    if args.metrics is not None:
        config.metrics.port = args.metrics
    if args.c37118 is not None:
        enable_c37118(config, args.c37118)
    check_rules(config.rules)
    _check_recording_dir(config)
    zenoh_log()
    logging.getLogger("sinewatch").setLevel(logging.INFO if args.verbose == 0 else logging.DEBUG)
    from sinewatch.runtime.workers import end_with_parent, supervise, worker_count

    if config.workers.index is not None:  # a worker process of a supervisor
        end_with_parent()
    count = worker_count(config, args.workers)
    if count > 1:
        from sinewatch.runtime.daemon import check_extras

        check_extras(config)  # here, in one line, not in each worker
        return supervise(config, count)
    return serve(config)


def _check_recording_dir(config: Any) -> None:
    if config.recording.enabled:
        from sinewatch.apps.console import check_output_dir

        check_output_dir(Path(config.recording.directory), "recording.directory")


def _check_scenarios(names: list[str]) -> None:
    """Unknown scenario names, with the nearest known ones (the whole list is long)."""
    import difflib

    from sinewatch import scenarios
    from sinewatch.scenarios.power_quality_iec import pq_names

    known = [*scenarios.names(), *pq_names()]
    for name in names:
        if name not in known:
            near = difflib.get_close_matches(name, known, n=3)
            hint = f"did you mean {', '.join(near)}? " if near else ""
            raise ConfigError(
                f"scenario: expected one of {len(known)} names ({hint}`sinewatch bench scenarios` lists them), "
                f"got {name!r}"
            )


def _int_in(lo: int, hi: int, expected: str) -> Callable[[str], int]:
    """An argparse type: an integer from ``lo`` to ``hi``; anything else is one line saying what
    was expected and what came."""

    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            n = lo - 1
        if not lo <= n <= hi:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return n

    return parse


_port = _int_in(0, 65535, "a TCP port 0-65535 (0: any free one)")
# --workers N: 1-256 processes, or 0 for one per core (as [workers] count)
_count = _int_in(0, 256, "a number of processes 1-256, or 0 for one per core")
_frame_count = _int_in(1, 65535, "a number of channels per frame 1-65535")


def enable_c37118(config: Any, port: int) -> None:
    """``serve --c37118 PORT``: the ``[c37118]`` section on, on PORT (its stations come from the config)."""
    from pydantic import ValidationError

    from sinewatch.schemas.errors import ConfigError

    try:
        config.c37118.port = port
        config.c37118.enabled = True
    except ValidationError as exc:
        raise ConfigError(f"--c37118 {port}: {exc.errors()[0]['msg']} (configure [[c37118.stations]])") from None


def cmd_config_show(args: argparse.Namespace) -> int:
    from sinewatch.schemas.config import config_to_json, load_config

    print(config_to_json(load_config(args.config)))
    return 0


def cmd_config_check(args: argparse.Namespace) -> int:
    from sinewatch.estimators import check_rules
    from sinewatch.schemas.config import load_config

    config = load_config(args.config)
    check_rules(config.rules)
    print(f"ok: {len(config.rules)} rule(s), every estimator and parameter valid")
    return 0


def cmd_schemas_export(args: argparse.Namespace) -> int:
    from sinewatch.apps.console import check_output_dir
    from sinewatch.estimators import available
    from sinewatch.schemas.export import export_schemas

    for path in export_schemas(check_output_dir(Path(args.dir), "schemas export"), available()):
        print(path)
    return 0


def cmd_estimators(args: argparse.Namespace) -> int:
    from sinewatch.estimators import available, get

    for name, params in available().items():
        cls = get(name)
        print(f"{name}: {cls.summary}" + (f"  [paper {cls.paper}]" if cls.paper else ""))
        for field, info in params.model_fields.items():
            default = info.get_default(call_default_factory=True)
            print(f"    {field} = {default!r}  {info.description or ''}")
    return 0


def cmd_feed(args: argparse.Namespace) -> int:
    from sinewatch.apps.console import make_console
    from sinewatch.apps.feed import Feed, make_channels
    from sinewatch.clients import BlockPublisher
    from sinewatch.scenarios.demo import DEMO_CHANNELS

    if args.comtrade:
        return _feed_comtrade(args)
    names = args.scenario or DEMO_CHANNELS
    _check_scenarios(names)
    overrides = {"sample_rate_hz": args.rate} if args.rate else {}
    channels = make_channels(names, copies=args.channels, seed=args.seed, prefix=args.prefix, **overrides)
    console = make_console(stderr=True)
    with _connect("feed", args) as session:
        pub = BlockPublisher(session, prefix=args.key_prefix, encoding=args.encoding, dtype=args.dtype or "float32")
        feed = Feed(pub, channels, block_size=args.block, realtime=not args.fast, frame_channels=args.frame_channels)
        _wait_for_subscriber(pub, feed.frames[0][0] if feed.frames else channels[0].channel, bool(feed.frames), args)
        t0 = time.monotonic()
        try:
            sent = feed.run(args.duration)
        except KeyboardInterrupt:
            sent = pub.published
        dt = time.monotonic() - t0
        _settle(session)
        pub.close()
    n_samples = sum(c.blocks for c in channels) * args.block
    what = f"frames of up to {args.frame_channels} channels" if feed.frames else "blocks"
    console.print(
        f"published {sent} {what} ({n_samples} samples) on {len(channels)} channels in {dt:.2f} s "
        f"({n_samples / max(dt, 1e-9):,.0f} samples/s)"
    )
    return 0


def cmd_gateway_sv(args: argparse.Namespace) -> int:
    from sinewatch.apps.gateway import serve

    return serve(args)


def _connect(command: str, args: argparse.Namespace) -> Any:
    """A client session to ``args.connect``, saying on stderr what it waits for while Zenoh
    tries (up to ``args.wait`` seconds)."""
    from sinewatch.apps.console import Waiting
    from sinewatch.clients import connect

    with Waiting(command, f"a Zenoh router or daemon at {', '.join(args.connect)}", args.wait):
        return connect(args.connect, timeout_s=args.wait)


def _wait_for_daemon(command: str, key: str, wait: Any, wait_s: float) -> bool:
    """``wait()`` (a publisher's wait for a subscriber on ``key``), saying on stderr what it
    waits for."""
    from sinewatch.apps.console import Waiting

    with Waiting(command, f"a daemon subscribed to {key}", wait_s):
        return bool(wait())


def _wait_for_subscriber(pub: Any, first: str, frames: bool, args: argparse.Namespace) -> None:
    """``feed`` waits until the daemon subscribes to its first message's key, saying so."""
    waiting = pub.wait_for_frame_subscriber if frames else pub.wait_for_subscriber
    if not _wait_for_daemon("feed", pub.key(first), lambda: waiting(first, args.wait), args.wait):
        raise ConfigError(
            f"expected a subscriber on {pub.key(first)} within {args.wait} s, got none "
            f"(is the daemon running and reachable at {', '.join(args.connect)}?)"
        )


def _settle(session: Any, timeout_s: float = 5.0) -> None:
    """A round trip to the daemons' admin queryables before the session closes: blocks still
    in the session's send queue would be lost with it (``feed --fast`` ends right after its
    last put), and the reply comes over the same link after them."""
    for _ in session.get("sinewatch/admin/*/channels", timeout=timeout_s):
        pass


def _feed_comtrade(args: argparse.Namespace) -> int:
    """``feed --comtrade FILE.cfg``: each analog channel at its recorded rate (float64 samples
    unless --dtype says otherwise: COMTRADE values are scaled integers or floats)."""
    from sinewatch.apps.console import make_console
    from sinewatch.apps.feed import publish_comtrade
    from sinewatch.clients import BlockPublisher
    from sinewatch.core.comtrade_file import read_comtrade

    if args.scenario:
        raise ConfigError("--comtrade: expected instead of --scenario, got both")
    record = read_comtrade(Path(args.comtrade), prefix=args.prefix if args.prefix != "sim" else "comtrade")
    console = make_console(stderr=True)
    with _connect("feed", args) as session:
        pub = BlockPublisher(session, prefix=args.key_prefix, encoding=args.encoding, dtype=args.dtype or "float64")
        as_frames = args.frame_channels > 1
        if as_frames:
            from sinewatch.core.comtrade_file import interleaved_frames

            first = interleaved_frames(record, args.block)[0][0]
        else:
            first = record.channels[0].channel
        _wait_for_subscriber(pub, first, as_frames, args)
        t0 = time.monotonic()
        try:
            sent = publish_comtrade(pub, record, block_size=args.block, realtime=not args.fast, frames=as_frames)
        except KeyboardInterrupt:
            sent = pub.published
        dt = time.monotonic() - t0
        _settle(session)
        pub.close()
    n_samples = sum(len(c.samples) for c in record.channels)
    console.print(
        f"published {sent} {'frames' if as_frames else 'blocks'} ({n_samples} samples) on {len(record.channels)} "
        f"channels of {record.path} "
        f"(COMTRADE {record.rev_year} {record.data_format}, {record.station}) in {dt:.2f} s",
        soft_wrap=True,
    )
    for c in record.channels:
        console.print(f"  {c.channel}: {len(c.samples)} samples at {c.sample_rate_hz:g} Hz ({c.unit or 'no unit'})")
    return 0


def cmd_tail(args: argparse.Namespace) -> int:
    if args.c37118:
        return tail_c37118(args)
    from sinewatch.clients import Fence, JsonSubscription

    shown = 0
    fence = Fence()  # a deposed shard owner's late estimates are not shown
    with _connect("tail", args) as session, JsonSubscription(session, args.keyexpr, fence) as sub:
        limit = f"exits after {args.timeout:g} s without one; " if args.timeout else ""
        print(f"tail: subscribed to {args.keyexpr}; waiting for messages ({limit}Ctrl-C to stop)", file=sys.stderr,
              flush=True)  # fmt: skip
        try:
            for msg in sub.iter(timeout=args.timeout):
                if args.json:
                    msg.pop("_key", None)
                print(json.dumps(msg) if args.json else format_estimate(msg), flush=True)
                shown += 1
                if args.count and shown >= args.count:
                    break
        except KeyboardInterrupt:
            pass
    return 0 if shown or not args.count else 1


def tail_c37118(args: argparse.Namespace) -> int:
    """``tail --c37118 HOST:PORT``: read CFG-2, turn data on, print each frame (one line per PMU)."""
    from sinewatch.apps.console import Waiting
    from sinewatch.clients.c37118 import C37118Reader, parse_host_port

    host, port = parse_host_port(args.c37118)
    shown = 0
    limit = args.timeout or args.wait
    try:
        with ExitStack() as stack:
            with Waiting("tail", f"the C37.118.2 server at {host}:{port} and its configuration", limit):
                pmu = stack.enter_context(C37118Reader(host, port, id_code=args.id_code, timeout_s=limit))
                cfg = pmu.config()
            for p in cfg.pmus:
                print(
                    f"tail: {host}:{port} station {p.station!r} ID {p.id_code}, {cfg.data_rate} frames/s, "
                    f"{p.nominal_frequency_hz} Hz, phasors {', '.join(p.phasor_names)}",
                    file=sys.stderr,
                    flush=True,
                )
            pmu.start()
            try:
                for row in pmu.rows():
                    print(json.dumps(row) if args.json else format_c37118(row), flush=True)
                    shown += 1
                    if args.count and shown >= args.count:
                        break
            finally:
                pmu.stop()
    except (OSError, ValueError) as exc:
        print(f"sinewatch: error: C37.118.2 {args.c37118}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        pass
    return 0 if shown or not args.count else 1


def format_c37118(row: dict[str, Any]) -> str:
    """One line per PMU data block: time, station, frequency, ROCOF, phasors, STAT."""
    if row["polar"]:
        phasors = " ".join(f"{n}={m:.5g}/{a:+.4f}rad" for n, (m, a) in row["phasors"].items())
    else:
        phasors = " ".join(f"{n}={re:.5g}{im:+.5g}j" for n, (re, im) in row["phasors"].items())
    flags = ("" if row["data_error"] == 0 else f" ERROR={row['data_error']:02b}") + (
        "" if row["in_sync"] else " unsync"
    )
    return (
        f"{row['time_ns'] / 1e9:.4f} {row['station']} f={row['frequency_hz']:.4f}Hz "
        f"rocof={row['rocof_hz_per_s']:+.4f}Hz/s {phasors} stat=0x{row['stat']:04X}{flags}"
    )


def cmd_status(args: argparse.Namespace) -> int:
    from sinewatch.apps.console import Waiting

    replies: list[dict[str, Any]] = []
    key = f"{args.admin_prefix.rstrip('/')}/*/channels"
    with _connect("status", args) as session, Waiting("status", f"the daemons' answers on {key}", args.timeout):
        for reply in session.get(key, timeout=args.timeout):
            if reply.ok is not None:
                replies.append(json.loads(reply.ok.payload.to_bytes()))
    replies.sort(key=lambda r: (r["shard_id"], r["role"] != "active", r["daemon_id"]))
    if args.json:
        print(json.dumps(replies, indent=2))
    else:
        print(format_status(replies, show_channels=not args.summary))
    return 0 if replies else 1


def format_status(replies: list[dict[str, Any]], *, show_channels: bool = True) -> str:
    """Who owns what: one line per daemon, then (``show_channels``) one per channel served,
    with the time of its last estimate."""
    if not replies:
        return "no sinewatch daemon answered"
    lines = [f"{'shard':<28} {'term':>10} {'owner':<20} standbys"]
    for shard_id, info in shard_owners(replies).items():
        owner = info["owner"] or "-"
        term = "-" if info["term"] is None else str(info["term"])
        stale = f" (deposed, still answering: {', '.join(info['stale'])})" if info["stale"] else ""
        lines.append(f"{shard_id:<28} {term:>10} {owner:<20} {', '.join(info['standbys']) or '-'}{stale}")
    lines += ["", f"{'daemon':<20} {'shard':<28} {'role':<8} {'term':>10} {'channels':>8} {'takeovers':>9}"]
    for r in replies:
        shard = r["shard_id"] + (f" ({r['shard']})" if r["shard"] else "")
        term = "-" if r.get("term") is None else str(r["term"])
        lines.append(
            f"{r['daemon_id']:<20} {shard:<28} {r['role']:<8} {term:>10} {len(r['channels']):>8} {r['takeovers']:>9}"
        )
    owners = {info["owner"] for info in shard_owners(replies).values()}
    if show_channels:
        lines += ["", f"{'channel':<32} {'owner':<20} {'last estimate (UTC)':<30} {'seq':>10}"]
        for r in replies:
            if r["role"] != "active" or r["daemon_id"] not in owners:
                continue
            for c in r["channels"]:
                lines.append(
                    f"{c['channel']:<32} {r['daemon_id']:<20} {_utc(c['last_estimate_ns']):<30} {c['last_seq']!s:>10}"
                )
    return "\n".join(lines)


def shard_owners(replies: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per shard: its newest term, the owner under it, its standbys, and any daemon that
    still says active under an older term (a deposed owner that has not noticed yet)."""
    shards: dict[str, dict[str, Any]] = {}
    for r in replies:
        info = shards.setdefault(r["shard_id"], {"term": None, "owner": None, "standbys": [], "stale": []})
        for t in (r.get("term"), r.get("newest_term")):
            if t is not None and (info["term"] is None or t > info["term"]):
                info["term"] = t
    for r in replies:
        info = shards[r["shard_id"]]
        if r["role"] != "active":
            info["standbys"].append(r["daemon_id"])
        elif r.get("term") is None or r.get("term") == info["term"]:
            info["owner"] = r["daemon_id"]
        else:
            info["stale"].append(r["daemon_id"])
    return dict(sorted(shards.items()))


def _utc(ns: int | None) -> str:
    if ns is None:
        return "-"
    sec, nsec = divmod(ns, 1_000_000_000)
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(sec)) + f".{nsec:09d}Z"


def cmd_router(args: argparse.Namespace) -> int:
    """A Zenoh router: a session in router mode (the eclipse-zenoh wheel's own), until
    SIGINT/SIGTERM."""
    import signal
    import threading

    from sinewatch.clients.session import DEFAULT_ROUTER_INPUTS, open_session, router_input_qos
    from sinewatch.schemas.config import ZenohSection

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    zenoh_log()
    inputs = [k for k in args.inputs or DEFAULT_ROUTER_INPUTS if k != "none"]
    raw: dict[str, Any] = {"qos/network": router_input_qos(inputs)} if inputs else {}
    raw.update(dict(args.zenoh or []))  # a raw qos/network of the user's replaces the inputs' rule
    section = ZenohSection(
        mode="router",
        listen=args.listen or ["tcp/127.0.0.1:7447"],
        connect=args.connect or [],
        raw=raw,
    )
    with open_session(section) as session:  # its Zenoh id: what a client's log names it by
        print(f"sinewatch router: listening on {', '.join(section.listen)}, zenoh id {session.info.zid()}", flush=True)
        stop.wait()
    return 0


def format_estimate(msg: dict[str, Any]) -> str:
    if "diagnostics" not in msg:  # not an Estimate: power quality on one line, the rest as JSON
        return format_power_quality(msg) or json.dumps({k: v for k, v in msg.items() if k != "_key"})

    def f(values: list[float | None], spec: str) -> str:
        return ",".join("nan" if v is None else format(v, spec) for v in values)

    d = msg["diagnostics"]
    flags = "".join(
        (" converged" if d["converged"] else " -", " GAP" if d["gap"] else "", " RESET" if d["reset"] else "")
    )
    off = "nan" if msg["offset"] is None else f"{msg['offset']:.4f}"
    rocof = msg.get("rocof_hz_per_s")  # Estimate v2; absent in v1 recordings
    rocof_text = "" if rocof is None else f" rocof={f(rocof, '+.4f')}Hz/s"
    std = msg.get("std")
    std_text = "" if not std or std["frequency_hz"][0] is None else f" sd(f)={f(std['frequency_hz'], '.2g')}Hz"
    return (
        f"{msg['timestamp_ns'] / 1e9:.4f} {msg['channel']} #{msg['seq']} {msg['estimator']} "
        f"f={f(msg['frequency_hz'], '.4f')}Hz A={f(msg['amplitude'], '.4f')} "
        f"phi={f(msg['phase_rad'], '.3f')} off={off}{rocof_text}{std_text}{flags}"
    )


def format_power_quality(msg: dict[str, Any]) -> str | None:
    """One line for a HarmonicsReport, ThreePhaseReport or PqAggregate (None for others)."""

    def n(v: float | None, spec: str, scale: float = 1.0) -> str:
        return "nan" if v is None else format(v * scale, spec)

    if "harmonic_rms" in msg:
        h = msg["harmonic_rms"]
        low = " ".join(f"h{k}={n(h[k], '.4f')}" for k in (3, 5, 7) if k < len(h))
        return (
            f"{msg['timestamp_ns'] / 1e9:.4f} {msg['channel']} harmonics f={n(msg['frequency_hz'], '.4f')}Hz "
            f"rms={n(msg['rms'], '.4f')} thd={n(msg['thd'], '.3f', 100)}% {low}"
            + (" GAP" if msg["gap"] else "")
            + ("" if msg["converged"] else " -")
        )
    if "group" in msg and "positive" in msg:
        missing = f" missing={','.join(msg['missing'])}" if msg["missing"] else ""
        return (
            f"{msg['timestamp_ns'] / 1e9:.4f} {msg['group']} three-phase f={n(msg['frequency_hz'], '.4f')}Hz "
            f"V1={n(msg['positive']['magnitude_rms'], '.4f')} u2={n(msg['u2'], '.3f', 100)}% "
            f"u0={n(msg['u0'], '.3f', 100)}%{missing}"
        )
    if "interval" in msg and "source" in msg:
        v = msg["values"]
        pct = {"thd", "u2", "u0"}
        shown = " ".join(
            f"{k}={n(v[k], '.3f', 100)}%" if k in pct else f"{k}={n(v[k], '.4f')}"
            for k in ("frequency_hz", "rms", "thd", "u2")
            if k in v
        )
        return (
            f"{msg['timestamp_ns'] / 1e9:.4f} {msg['source']} {msg['interval']} n={msg['n_windows']}"
            f"{'' if msg['complete'] else ' (incomplete)'} {shown}"
        )
    return None


def cmd_export(args: argparse.Namespace) -> int:
    from sinewatch.apps.export import run_export

    return run_export(args)


def cmd_replay(args: argparse.Namespace) -> int:
    from sinewatch.apps.replay_cli import run_replay

    return run_replay(args)


def cmd_compare(args: argparse.Namespace) -> int:
    from sinewatch.apps.compare import run_compare

    return run_compare(args)


def cmd_plot(args: argparse.Namespace) -> int:
    from sinewatch.apps.plot import run_plot

    return run_plot(args)


def _window_arguments(parser: argparse.ArgumentParser, *, channels: bool = True) -> None:
    """``--start``, ``--end`` (and ``--channels``): the part of a recording a command reads
    (syntax: :mod:`sinewatch.core.window`)."""
    parser.add_argument(
        "--start",
        metavar="TIME",
        help="from this log time: +SECONDS after the recording's start (+2.5s, +2500ms), ISO 8601, or ns since the epoch",
    )
    parser.add_argument("--end", metavar="TIME", help="up to (not including) this log time, as --start")
    if channels:
        parser.add_argument(
            "--channels",
            action="append",
            metavar="GLOB",
            help="channel names to take (repeatable; default all), e.g. 'demo/*'",
        )


# ---- parser ----------------------------------------------------------------------------------
class _Parser(argparse.ArgumentParser):
    """argparse, with a usage mistake told on one line (exit code 2, as argparse's own)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


_Subparsers = argparse._SubParsersAction  # the type of add_subparsers()' result


def _pairs_argument(parser: argparse.ArgumentParser, flag: str, metavar: str, help_text: str) -> None:
    """A repeatable ``NAME=VALUE`` option (:func:`parse_param`), collected into a list."""
    parser.add_argument(flag, action="append", type=parse_param, default=[], metavar=metavar, help=help_text)


def _config_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="TOML or JSON config file (default: $SINEWATCH_CONFIG or built-in defaults)")


def _command(
    sub: _Subparsers[argparse.ArgumentParser], name: str, help: str, fn: Any, *, config: bool = False
) -> argparse.ArgumentParser:
    """Subcommand ``name`` running ``fn``; with ``config``, it takes ``--config``."""
    c = sub.add_parser(name, help=help)
    if config:
        _config_argument(c)
    c.set_defaults(fn=fn)
    return c


def _subcommands(
    sub: _Subparsers[argparse.ArgumentParser], name: str, help: str, dest: str
) -> _Subparsers[argparse.ArgumentParser]:
    """A command ``name`` that only groups subcommands (``dest`` names the chosen one)."""
    return sub.add_parser(name, help=help).add_subparsers(dest=dest, required=True, metavar="SUBCOMMAND")


def build_parser() -> argparse.ArgumentParser:
    from sinewatch.schemas.config import DEFAULT_ENDPOINT  # not the client library: that imports zenoh

    p = _Parser(
        prog="sinewatch",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    p.add_argument("--version", action="version", version=f"sinewatch {__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    p.add_argument("--debug", action="store_true", help="a traceback with every error, not only the one-line message")
    # subcommands' parsers are _Parser too (argparse makes them of the parent's class)
    sub = cast(
        "_Subparsers[argparse.ArgumentParser]", p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    )

    d = _command(sub, "demo", "run daemon + simulated feed on loopback with a live table", cmd_demo)
    d.add_argument("--duration", type=float, default=10.0, help="seconds of signal (default 10)")
    d.add_argument("--scenarios", help="comma-separated scenario names (default: the 8 demo channels)")
    d.add_argument("--record-dir", default="sinewatch-runs", help="where the MCAP file goes")
    d.add_argument("--no-record", action="store_true", help="do not record")

    s = _command(sub, "serve", "run the daemon until SIGINT/SIGTERM", cmd_serve, config=True)
    s.add_argument(
        "--foxglove",
        type=_port,
        metavar="PORT",
        help="serve a live Foxglove WebSocket on PORT ([foxglove] port; needs the foxglove extra)",
    )
    s.add_argument(
        "--metrics",
        type=_port,
        metavar="PORT",
        help="serve Prometheus /metrics and /healthz on PORT ([metrics] port; needs the metrics extra)",
    )
    s.add_argument(
        "--workers",
        type=_count,
        metavar="N",
        help="run the estimators in N worker processes, 0 for one per core ([workers] count; default 1: in this "
        "process)",
    )
    s.add_argument(
        "--c37118",
        type=_port,
        metavar="PORT",
        help="serve IEEE C37.118.2 on PORT (TCP and UDP; the stations come from [c37118] in the config)",
    )

    csub = _subcommands(sub, "config", "configuration", "config_command")
    _command(csub, "show", "print the effective configuration (file + environment)", cmd_config_show, config=True)
    _command(
        csub,
        "check",
        "also check each rule's estimator parameters (imports the estimators)",
        cmd_config_check,
        config=True,
    )

    scsub = _subcommands(sub, "schemas", "JSON Schemas of the wire format and the config", "schemas_command")
    _command(scsub, "export", "write the JSON Schemas to DIR", cmd_schemas_export).add_argument("dir")

    _command(sub, "estimators", "list registered estimators and their parameters", cmd_estimators)

    f = _command(sub, "feed", "publish simulated sample blocks to a daemon", cmd_feed)
    f.add_argument("--connect", action="append", help=f"endpoint (repeatable; default {DEFAULT_ENDPOINT})")
    f.add_argument(
        "--scenario",
        action="append",
        help="scenario name (repeatable; default: the demo channels); see `sinewatch bench scenarios`",
    )
    f.add_argument(
        "--comtrade", metavar="FILE.cfg", help="publish the analog channels of a COMTRADE file (.cfg or .cff)"
    )
    f.add_argument("--channels", type=int, default=1, help="channels per scenario (default 1)")
    f.add_argument(
        "--frame-channels",
        type=_frame_count,
        default=1,
        metavar="N",
        help="send N channels (of one rate) per message as SampleFrames (default 1: one SampleBlock per channel); "
        "with --comtrade, any N > 1 sends each rate segment's analog channels as one frame",
    )
    f.add_argument("--rate", type=float, help="sample rate override, Hz")
    f.add_argument("--block", type=int, default=1000, help="samples per block (default 1000)")
    f.add_argument("--duration", type=float, default=10.0, help="seconds of signal (default 10)")
    f.add_argument("--fast", action="store_true", help="as fast as possible instead of real time")
    f.add_argument("--encoding", choices=["binary", "json"], default="binary")
    f.add_argument(
        "--dtype", choices=["float32", "float64"], help="binary sample type (default float32; COMTRADE float64)"
    )
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--prefix", default="sim", help="channel name prefix (default sim)")
    f.add_argument("--key-prefix", default="sinewatch/in", help="key prefix (default sinewatch/in)")
    f.add_argument(
        "--wait",
        type=float,
        default=60.0,
        help="seconds to wait for the daemon (default 60: a daemon starting its workers opens its endpoint once all serve)",
    )

    _gateway_parser(sub)

    t = _command(sub, "tail", "print estimates (or any sinewatch JSON messages) as they arrive", cmd_tail)
    t.add_argument("keyexpr", nargs="?", default="sinewatch/est/**")
    t.add_argument("--connect", action="append", help=f"endpoint (repeatable; default {DEFAULT_ENDPOINT})")
    t.add_argument("--count", type=int, default=0, help="exit after N messages")
    t.add_argument("--timeout", type=float, default=None, help="exit after this many idle seconds")
    t.add_argument("--json", action="store_true", help="print raw JSON lines")
    t.add_argument("--wait", type=float, default=60.0, help="seconds to keep trying to connect (default 60)")
    t.add_argument("--c37118", metavar="HOST:PORT", help="read a C37.118.2 PMU (or sinewatch serve --c37118) instead")
    t.add_argument("--id-code", type=int, default=1, help="with --c37118: the station's ID code (default 1)")

    r = _command(sub, "replay", "replay recordings through fresh estimators", cmd_replay)
    r.add_argument("paths", nargs="+", type=Path, help="MCAP file(s) of one run, in order")
    r.add_argument("--estimator", help="re-run with this estimator instead of checking the recording")
    _pairs_argument(r, "--param", "KEY=VALUE", "estimator parameter (repeatable; value parsed as JSON when it parses)")
    r.add_argument("--match", default="**", help="with --estimator: input keys it applies to (default all)")
    r.add_argument("--out", type=Path, help="write a new recording")
    _window_arguments(r)
    r.add_argument(
        "--track",
        nargs="?",
        const=True,
        default=False,
        metavar="FILE.parquet",
        help="every sample's estimate and the estimator's internal signals, for the window and channels: "
        "into the --out recording (sinewatch/track/CHANNEL), or into FILE.parquet",
    )
    r.add_argument("--no-progress", action="store_true")

    e = _command(sub, "export", "write a recording's estimates (and samples) as CSV or Parquet tables", cmd_export)
    e.add_argument("path", help="MCAP recording")
    e.add_argument("--format", choices=["csv", "parquet"], default="csv", help="csv (default) or parquet (pyarrow)")
    _window_arguments(e)
    e.add_argument("--out", metavar="DIR", help="output directory (default: the recording's)")
    e.add_argument("--samples", action="store_true", help="also export the input samples")
    e.add_argument("--no-progress", action="store_true")

    cm = _command(sub, "compare", "compare two recordings of the same inputs, channel by channel", cmd_compare)
    cm.add_argument("a", type=Path, help="the first recording (e.g. the original)")
    cm.add_argument("b", type=Path, help="the second recording (e.g. a re-run with another estimator)")
    _window_arguments(cm)
    _pairs_argument(
        cm,
        "--tolerance",
        "PARAM=VALUE",
        "divergence threshold of a parameter (repeatable), e.g. frequency_hz=0.001; "
        "defaults: frequency_hz=0.01 amplitude=0.01 phase_rad=0.01 offset=0.01 rocof_hz_per_s=0.1",
    )
    cm.add_argument("--json", action="store_true", help="the comparison as JSON")

    pl = _command(sub, "plot", "plot one channel of recordings: input, estimates, validity, gaps (PNG)", cmd_plot)
    pl.add_argument("paths", nargs="+", type=Path, help="recordings of the same inputs (each in its own colour)")
    pl.add_argument("--channel", required=True, help="the channel name, e.g. demo/demo-faulty-sensor")
    _window_arguments(pl, channels=False)
    pl.add_argument("--out", type=Path, help="the PNG (default: CHANNEL.png beside the first recording)")
    pl.add_argument("--width", type=float, default=12.0, help="inches (default 12; 100 dpi)")

    st = _command(sub, "status", "ask every daemon which channels it owns (shards, standbys)", cmd_status)
    st.add_argument("--connect", action="append", help=f"endpoint (repeatable; default {DEFAULT_ENDPOINT})")
    st.add_argument("--admin-prefix", default="sinewatch/admin", help="the daemons' keys.admin_prefix")
    st.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the daemons' answers")
    st.add_argument("--wait", type=float, default=5.0, help="seconds to keep trying to connect")
    st.add_argument("--summary", action="store_true", help="one line per daemon, no channel list")
    st.add_argument("--json", action="store_true", help="the daemons' answers as JSON")

    ro = _command(sub, "router", "run a Zenoh router (for several daemons and gateways)", cmd_router)
    ro.add_argument("--listen", action="append", help="endpoint (repeatable; default tcp/127.0.0.1:7447)")
    ro.add_argument("--connect", action="append", help="other routers to connect to (repeatable)")
    ro.add_argument(
        "--inputs",
        action="append",
        metavar="KEYEXPR",
        help="the daemons' input keys (keys.input; repeatable; default sinewatch/in/**): forwarded to "
        "subscribers with CongestionControl.DROP, so a stopped daemon holds back no other (none: as published)",
    )
    ro.add_argument(
        "--zenoh",
        action="append",
        type=parse_param,
        metavar="PATH=JSON",
        help="a raw Zenoh config key (JSON5 path, repeatable), as [zenoh] raw sets it for a daemon, e.g. "
        "transport/link/tx/queue/congestion_control/block/wait_before_close=5000000",
    )

    add_bench_parser(sub)
    return p


def _gateway_parser(sub: _Subparsers[argparse.ArgumentParser]) -> None:
    from sinewatch.schemas.config import DEFAULT_ENDPOINT

    gsub = _subcommands(sub, "gateway", "bring field data in as sample frames", "gateway_command")
    g = _command(gsub, "sv", "IEC 61850-9-2 (9-2LE) sampled values -> SampleFrames on Zenoh", cmd_gateway_sv)
    g.add_argument("--pcap", metavar="FILE", help="read a pcap/pcapng capture (as fast as possible unless --realtime)")
    g.add_argument("--iface", metavar="NAME", help="listen on a network interface (Linux; root or CAP_NET_RAW)")
    g.add_argument("--realtime", action="store_true", help="with --pcap: at the capture's pace")
    g.add_argument("--sv-id", action="append", metavar="SVID", help="only this svID (repeatable; default all)")
    g.add_argument(
        "--app-id", action="append", type=lambda t: int(t, 0), metavar="N", help="only this APPID (repeatable)"
    )
    g.add_argument("--dst-mac", action="append", metavar="MAC", help="only this destination MAC (repeatable)")
    g.add_argument(
        "--channels",
        action="append",
        metavar="SVID=IA,IB,...",
        help="the 8 channel names of a stream (repeatable; default IA,IB,IC,IN,VA,VB,VC,VN), each <svID>/<name>",
    )
    g.add_argument(
        "--rate", type=int, default=4000, help="samples per second of the streams (default 4000; 4800 at 60 Hz)"
    )
    g.add_argument("--samples", type=_count, default=80, help="samples per published frame (default 80: a 50 Hz cycle)")
    g.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (default: the end/never)")
    g.add_argument(
        "--idle", type=float, default=0.0, help="with --iface: stop once the bus has been silent this many seconds"
    )
    g.add_argument("--connect", action="append", help=f"endpoint (repeatable; default {DEFAULT_ENDPOINT})")
    g.add_argument("--key-prefix", default="sinewatch/in", help="key prefix (default sinewatch/in)")
    g.add_argument(
        "--status-prefix",
        default="sinewatch/gateway/sv",
        help="each stream's counts and synchronisation, JSON on PREFIX/<svID> once a second (default sinewatch/gateway/sv)",
    )
    g.add_argument("--wait", type=float, default=60.0, help="seconds to wait for the daemon (default 60)")


def main(argv: list[str] | None = None) -> int:
    """Run a command. A mistake (a missing or wrong file, an unknown estimator, a bad value,
    an unreachable endpoint, an unwritable directory) ends in one line on stderr saying what
    was expected and what came, and exit code 2; ``--debug`` adds the traceback. Anything
    else is a bug and keeps its traceback."""
    args = build_parser().parse_args(argv)
    _setup_logging(args.verbose)
    try:
        if getattr(args, "connect", "absent") is None:
            from sinewatch.clients.session import DEFAULT_CONNECT

            args.connect = list(DEFAULT_CONNECT)
        elif isinstance(getattr(args, "connect", None), list):
            _check_endpoints(args.connect)
        return int(args.fn(args) or 0)
    except (SinewatchError, OSError) as exc:
        # OSError: a file or directory named on the command line (or in the config) that cannot be used
        log.debug("the error's traceback", exc_info=True)
        if args.debug:
            import traceback

            traceback.print_exc()
        print(f"sinewatch: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


def _check_endpoints(endpoints: list[str]) -> None:
    from pydantic import ValidationError

    from sinewatch.schemas.config import ZenohSection

    try:
        ZenohSection(connect=endpoints)
    except ValidationError as exc:
        raise ConfigError(
            "--connect: " + "; ".join(str(e["ctx"].get("error", e["msg"])) for e in exc.errors())
        ) from None


_RUST_SOURCE = re.compile(r"\s+at \S+\.rs:\d+\.?")  # zenoh's messages end with the Rust file that raised


def one_line(exc: BaseException) -> str:
    """The error's message on one line: an indented list after a colon joins with '; '."""
    if isinstance(exc, OSError) and not isinstance(exc, SinewatchError) and exc.filename is not None:
        text = f"{exc.filename}: {(exc.strerror or type(exc).__name__).lower()}"
    else:
        text = _RUST_SOURCE.sub("", str(exc)) or type(exc).__name__
    head, *rest = [line.strip() for line in text.splitlines() if line.strip()] or [type(exc).__name__]
    return f"{head} {'; '.join(rest)}" if rest else head


if __name__ == "__main__":
    raise SystemExit(main())
