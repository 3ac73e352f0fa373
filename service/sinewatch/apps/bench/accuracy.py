"""``sinewatch bench accuracy``: every estimator on every applicable scenario, side by side,
against the Cramer-Rao bound and the C37.118.1 limits.

The run, module by module:

* :mod:`sinewatch.apps.bench.scenarios`: which scenarios and estimators it selects (names,
  globs, tags) and each scenario's profile (nominal frequencies, steady windows, events,
  reporting rate, limits), read from the scenario library;
* :mod:`sinewatch.apps.bench.params`: the estimator's parameters for each scenario;
* :mod:`sinewatch.apps.bench.runner`: the seeded Monte Carlo trials (in worker processes);
* :mod:`sinewatch.apps.bench.metrics`: the definitions of every figure;
* :mod:`sinewatch.apps.bench.report`: the Markdown tables, the JSON records and the plots;
* :mod:`sinewatch.apps.bench.pq_accuracy`: the power-quality families (``--scenarios pq``),
  scored against IEC 61000-4-7 class I and IEC 61000-4-30 class A, pqopen-lib beside.

The arguments are defined in :mod:`sinewatch.apps.bench.args`; :func:`run` is the command. The
same run is available from Python as :func:`sinewatch.apps.bench.runner.run_bench` (the tests
use it).
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import sys
import time
from pathlib import Path

from sinewatch.apps.bench.args import DEFAULT_TRIALS, QUICK_TRIALS
from sinewatch.apps.bench.pq_accuracy import DOCS_BEGIN as PQ_DOCS_BEGIN
from sinewatch.apps.bench.pq_accuracy import DOCS_END as PQ_DOCS_END
from sinewatch.apps.bench.pq_accuracy import pqopen_available, run_pq, split_patterns
from sinewatch.apps.bench.pq_accuracy import render_markdown as render_pq_markdown
from sinewatch.apps.bench.report import render_markdown, update_docs, write_json, write_plots
from sinewatch.apps.bench.runner import run_bench
from sinewatch.apps.bench.scenarios import DEFAULT_RULE, select_estimators, select_scenarios
from sinewatch.schemas.errors import ParameterError


def run(args: argparse.Namespace) -> int:
    """``sinewatch bench accuracy [...]``: run, write accuracy.md, accuracy.json, plots."""
    try:
        regular, pq = split_patterns(args.scenarios)
        scens = select_scenarios(regular, quick=args.quick) if regular is None or regular else []
        ests = select_estimators(args.estimators)
    except ParameterError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    trials = args.trials if args.trials is not None else (QUICK_TRIALS if args.quick else DEFAULT_TRIALS)
    if trials < 1:
        print(f"error: --trials: expected >= 1, got {trials}", file=sys.stderr)
        return 2
    want_plots = not getattr(args, "no_plots", False)
    t0 = time.perf_counter()
    results = (
        run_bench(
            ests, scens, trials=trials, seed=args.seed, jobs=max(1, args.jobs), keep_trace=want_plots, progress=True
        )
        if scens
        else []
    )
    elapsed = time.perf_counter() - t0
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "command": _command_line(args),
        "trials": trials,
        "seed": args.seed,
        "estimators": ests,
        "scenarios": scens,
        "elapsed_s": elapsed,
        "version": _version(),
        "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {max(1, args.jobs)} jobs",
    }
    md = render_markdown(results, meta["command"], meta) if scens else ""
    if any(p in ("c37.118", "tag:c37.118") for p in (args.scenarios or [])):
        from sinewatch.apps.bench.compliance import markdown_section  # the grid estimators' full C37 suite

        section = markdown_section([e for e in ests if e != DEFAULT_RULE])
        md += "\n\n" + section if section else ""
    pq_md, pq_records, pq_over = "", None, 0
    if pq:
        t1 = time.perf_counter()
        installed = pqopen_available()
        pq_records = run_pq(pq, with_pqopen=installed)
        pq_s = time.perf_counter() - t1
        meta["pq_scenarios"], meta["pq_elapsed_s"] = pq, pq_s
        pq_over = sum(v["ratio"] > 1.0 for r in pq_records for v in r["sinewatch"].values())
        pq_md = (
            f"Command:\n\n```\n{meta['command']}\n```\n\n"
            f"{len(pq)} power-quality scenarios, deterministic (noise-free); sinewatch {meta['version']}, "
            f"{meta['date']}; {pq_s:.0f} s on {platform.machine()}, {os.cpu_count()} cores, one process.\n\n"
            + render_pq_markdown(pq_records, installed)
        )
    full = "\n\n".join(part for part in (md, pq_md) if part)
    (out / "accuracy.md").write_text("# sinewatch accuracy results\n\n" + full + "\n")
    write_json(out / "accuracy.json", results, meta, power_quality=pq_records)
    plots = write_plots(out, results) if want_plots and results else []
    if getattr(args, "update_docs", None):
        if scens:
            update_docs(args.update_docs, md)
        if pq:
            update_docs(args.update_docs, pq_md, PQ_DOCS_BEGIN, PQ_DOCS_END)
    n_ok = sum(r["status"] == "ok" for r in results)
    n_na = sum(r["status"] == "n/a" for r in results)
    n_err = sum(r["status"] == "error" for r in results)
    msg = f"{n_ok} runs, {n_na} n/a, {n_err} errors in {elapsed:.0f} s"
    if pq:
        msg += f"; {len(pq)} power-quality scenarios, {pq_over} sinewatch rows over their IEC limit"
    msg += f"; wrote {out / 'accuracy.md'}, {out / 'accuracy.json'}"
    if want_plots and results:
        msg += f", {len(plots)} plots" if plots else " (no plots: matplotlib is not installed)"
    print(msg)
    return 1 if n_err else 0


def _command_line(args: argparse.Namespace) -> str:
    parts = ["sinewatch", "bench", "accuracy"]
    if args.estimators:
        parts += ["--estimators", *args.estimators]
    if args.scenarios:
        parts += ["--scenarios", *args.scenarios]
    if args.trials is not None:
        parts += ["--trials", str(args.trials)]
    if args.seed:
        parts += ["--seed", str(args.seed)]
    if args.quick:
        parts.append("--quick")
    if getattr(args, "update_docs", None):
        parts += ["--update-docs", str(args.update_docs)]
    return " ".join(shlex.quote(p) for p in parts)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("sinewatch")
    except PackageNotFoundError:
        return "?"
