"""``sinewatch bench pmu-reference``: a real PMU's C37.118.2 stream as the reference for a
sinewatch channel measuring the same signal.

Reads ``--frames`` data frames from the PMU (``--c37118 HOST:PORT``, ``--id-code``; the phasor
``--phasor``, default its first) and, over Zenoh, the Estimates of ``--channel``; pairs them by
time stamp (so the channel must report on the same grid: the ``pmu`` estimator at the PMU's
reporting rate) and reports, against the PMU, the total vector error
``TVE = |X - Xr| / |Xr|`` (C37.118.1-2011 eq. (2)), the frequency error ``FE = |f - fr|`` and
the ROCOF error ``RFE = |df/dt - (df/dt)r|`` (eq. (6)-(7)): max, 95th percentile and mean.
Frames whose STAT reports a data error are left out (and counted). A PMU reports one FREQ
and DFREQ per station (sinewatch's: its first channel's), so FE and RFE mean something only
when ``--channel`` measures the signal the PMU takes its frequency from. sinewatch's synchrophasor
is the Estimate's (see :func:`sinewatch.outputs.c37118_server.synchrophasor`).
"""

from __future__ import annotations

import argparse
import cmath
import json
import math
from collections.abc import Callable
from typing import Any

import numpy as np
from rich.table import Table

from sinewatch.apps.console import make_console
from sinewatch.clients import connect, subscribe_estimates
from sinewatch.clients.c37118 import C37118Reader, parse_host_port
from sinewatch.outputs.c37118_server import synchrophasor


def reference_phasor(row: dict[str, Any], name: str) -> complex:
    a, b = row["phasors"][name]
    return cmath.rect(a, b) if row["polar"] else complex(a, b)


def score(rows: list[dict[str, Any]], estimates: list[dict[str, Any]], phasor: str, nominal_hz: int) -> dict[str, Any]:
    """TVE (%), FE (Hz) and RFE (Hz/s) of ``estimates`` against the PMU's ``rows`` (from
    :func:`sinewatch.clients.c37118.data_rows`), paired by time stamp."""
    by_time = {e["timestamp_ns"]: e for e in estimates}
    tve, fe, rfe = [], [], []
    flagged = unmatched = 0
    for row in rows:
        if row["data_error"] != 0:
            flagged += 1
            continue
        est = by_time.get(row["time_ns"])
        ph = None if est is None else synchrophasor(est, nominal_hz)
        if est is None or ph is None:
            unmatched += 1
            continue
        xr = reference_phasor(row, phasor)
        x = cmath.rect(*ph)
        tve.append(100 * abs(x - xr) / abs(xr))
        f = est["frequency_hz"][0]
        if f is not None:
            fe.append(abs(f - row["frequency_hz"]))
        r = (est.get("rocof_hz_per_s") or [None])[0]
        if r is not None and math.isfinite(row["rocof_hz_per_s"]):
            rfe.append(abs(r - row["rocof_hz_per_s"]))

    def stats(v: list[float]) -> dict[str, float | None]:
        if not v:
            return {"max": None, "p95": None, "mean": None}
        a = np.asarray(v)
        return {"max": float(a.max()), "p95": float(np.percentile(a, 95)), "mean": float(a.mean())}

    return {
        "frames": len(rows),
        "pairs": len(tve),
        "flagged": flagged,
        "unmatched": unmatched,
        "tve_pct": stats(tve),
        "fe_hz": stats(fe),
        "rfe_hz_per_s": stats(rfe),
    }


def read_reference(
    reader: C37118Reader,
    phasor: str | None,
    frames: int,
    *,
    confirm: bool = False,
    on_start: Callable[[], None] | None = None,
) -> tuple[list[dict[str, Any]], str, int]:
    """The configuration, "data on", then ``frames`` data frames of the reader's station (rows
    of :func:`sinewatch.clients.c37118.data_rows`); with the phasor's name and the nominal
    frequency. ``confirm`` and ``on_start`` as a test uses them: wait until data is on (see
    :meth:`C37118Reader.start`), then call ``on_start``."""
    cfg = reader.config()
    pmu = cfg.pmus[0]
    name = phasor or pmu.phasor_names[0]
    if name not in pmu.phasor_names:
        raise ValueError(f"--phasor: expected one of {pmu.phasor_names}, got {name!r}")
    reader.start(confirm=confirm)
    if on_start is not None:
        on_start()
    rows = [r for r in reader.rows(count=frames) if r["id_code"] == pmu.id_code]
    reader.stop()
    return rows, name, pmu.nominal_frequency_hz


def collect_estimates(estimates: Any, until_ns: int, timeout_s: float) -> list[dict[str, Any]]:
    """Estimates from a subscription up to the first at or after ``until_ns`` (or a timeout)."""
    got: list[dict[str, Any]] = []
    while (msg := estimates.get(timeout=timeout_s)) is not None:
        got.append(msg)
        if msg["timestamp_ns"] >= until_ns:
            break
    return got


def compare_live(
    reader: C37118Reader, estimates: Any, phasor: str | None, frames: int, timeout_s: float
) -> tuple[dict[str, Any], str]:
    """Read ``frames`` data frames, then the estimates up to the last frame's time; return the
    score and the phasor compared."""
    rows, name, nominal = read_reference(reader, phasor, frames)
    got = collect_estimates(estimates, max(r["time_ns"] for r in rows), timeout_s)
    return score(rows, got, name, nominal), name


def run(args: argparse.Namespace) -> int:
    console = make_console()
    host, port = parse_host_port(args.c37118)
    with (
        connect(args.connect, timeout_s=args.timeout) as session,
        subscribe_estimates(session, f"sinewatch/est/{args.channel}") as estimates,
        C37118Reader(host, port, id_code=args.id_code, timeout_s=args.timeout) as reader,
    ):
        result, name = compare_live(reader, estimates, args.phasor, args.frames, args.timeout)
    table = Table(title=f"{args.channel} against PMU {args.c37118} ID {args.id_code} phasor {name}")
    for col in ("", "max", "p95", "mean"):
        table.add_column(col, justify="right")
    for label, key in (("TVE, %", "tve_pct"), ("FE, Hz", "fe_hz"), ("RFE, Hz/s", "rfe_hz_per_s")):
        table.add_row(label, *("-" if v is None else f"{v:.4g}" for v in result[key].values()))
    console.print(table)
    console.print(
        f"{result['pairs']} pairs of {result['frames']} frames ({result['flagged']} flagged by the PMU, "
        f"{result['unmatched']} without an estimate at their time)"
    )
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))
    return 0 if result["pairs"] else 1
