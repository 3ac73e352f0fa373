"""The accuracy bench's report: the Markdown tables (``accuracy.md``, and the results
block of docs/accuracy.md with ``--update-docs``), the JSON records (``accuracy.json``)
and the PNG plots (matplotlib, when installed).

The tables group scenarios into :data:`FAMILIES` (CRLB, C37.118.1, the papers, gaps,
multi-tone, others), one column per estimator, one cell per (estimator, scenario) record
as :func:`sinewatch.apps.bench.runner.evaluate` returns it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from sinewatch import scenarios as sc_registry
from sinewatch.apps.bench.metrics import PARAMS
from sinewatch.apps.bench.runner import crlb_window
from sinewatch.apps.bench.scenarios import profile

DOCS_BEGIN = "<!-- accuracy-results:begin -->"
DOCS_END = "<!-- accuracy-results:end -->"


def _fmt(x: Any, unit: str = "", digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-" if x is None or math.isnan(x) else ("inf" if x > 0 else "-inf")
    if x == 0:
        return f"0{unit}"
    ax = abs(x)
    if ax >= 1000 or ax < 1e-3:
        return f"{x:.{digits - 1}e}{unit}"
    return f"{x:.{max(digits - math.floor(math.log10(ax)) - 1, 0)}f}{unit}"


def _cell(rec: dict[str, Any] | None, kind: str) -> str:
    if rec is None:
        return ""
    if rec["status"] != "ok":
        return "n/a" if rec["status"] == "n/a" else "error"
    m = rec["metrics"]
    defined = m.get("defined_pct", 100.0)
    if not defined > 0:
        return "no estimate"
    f_rmse = max(m["frequency_hz"]["rmse"])
    note = f"; defined {defined:.0f} %" if defined < 99.5 else ""
    return _cell_body(m, kind, f_rmse) + note


def _cell_body(m: dict[str, Any], kind: str, f_rmse: float) -> str:
    if kind == "crlb":
        cr = m.get("crlb", {}).get("frequency_hz", {})
        db, teq = cr.get("over_crlb_db"), cr.get("equivalent_window_s")
        sign = "+" if db is not None and db >= 0 else ""
        own = m.get("crlb_own_window", {}).get("frequency_hz", {}).get("over_crlb_db")
        more = "" if own is None else f"; own window {'+' if own >= 0 else ''}{_fmt(own, ' dB', 3)}"
        cal = m.get("calibration", {}).get("frequency_hz")
        more += "" if cal is None else f"; cal {_fmt(cal, '', 3)}"
        return f"{_fmt(f_rmse, ' Hz')} ({sign}{_fmt(db, ' dB', 3)}; {_fmt(teq, ' s')}{more})"
    if kind == "c37":
        c = m.get("c37")
        if c is None:
            return _fmt(f_rmse, " Hz")
        mark = "pass" if c["pass"] else "FAIL " + ",".join(k.split("_")[0] for k in c["failed"])
        evs = m.get("events", [])
        if evs:
            ev = evs[0]
            return (
                f"TVE {_fmt(c['tve_max_pct'], '%')}; t_r {_fmt(ev.get('tve_response_time_s'), ' s')}; "
                f"os {_fmt(ev.get('overshoot_pct'), '%')}; {mark}"
            )
        return (
            f"TVE {_fmt(c['tve_max_pct'], '%')}; FE {_fmt(c['fe_max_hz'], ' Hz')}; "
            f"RFE {_fmt(c['rfe_max_hz_per_s'], ' Hz/s')}; {mark}"
        )
    conv = m["convergence_time_s"]
    extra = ""
    evs = [e for e in m.get("events", []) if "response_time_s" in e]
    if evs:
        rts = [e["response_time_s"] for e in evs]
        rt = math.nan if any(not math.isfinite(v) for v in rts) else max(rts)
        extra = f"; resp {_fmt(rt, ' s')}"
    return f"{_fmt(f_rmse, ' Hz')}; conv {_fmt(conv, ' s')}{extra}"


FAMILIES = (
    (
        "Stationary tone against the Cramer-Rao bound",
        (
            "frequency RMSE over the steady window (in brackets: RMSE over the square root of the "
            "CRLB for the samples seen, in dB, 0 dB being the physical limit; the equivalent "
            "window, the record length an efficient estimator needs for the same RMSE; for a "
            "windowed estimator, the dB over the bound of its own window; for one that reports "
            "standard deviations, its calibration: the sd of error / reported sd, 1 when right)"
        ),
        "crlb",
    ),
    (
        "Power quality, modelled on IEEE C37.118.1 (M class, reporting rate = f0)",
        (
            "worst total vector error, frequency error and ROCOF error at the reporting instants, "
            "or for steps the TVE response time and overshoot; pass/FAIL against the limits"
        ),
        "c37",
    ),
    (
        "The papers' own simulations",
        "frequency RMSE (worst component); convergence time; response time after events",
        "paper",
    ),
    ("Data gaps", "frequency RMSE; convergence time; reacquisition time after the gap", "gap"),
    ("Multi-tone signals", "frequency RMSE (worst component); convergence time", "multitone"),
    ("Other scenarios", "frequency RMSE; convergence time", "other"),
)


def _family(rec_tags: set[str], crlb_ok: bool) -> str:
    if crlb_ok and "paper" not in rec_tags:
        return "crlb"
    for key in ("c37", "paper", "gap", "multitone"):
        if key == "c37" and "c37.118" in rec_tags:
            return "c37"
        if key in rec_tags:
            return key
    return "other"


def render_markdown(results: list[dict[str, Any]], command: str, meta: dict[str, Any]) -> str:
    ests = list(dict.fromkeys(r["estimator"] for r in results))
    scens = list(dict.fromkeys(r["scenario"] for r in results))
    by = {(r["estimator"], r["scenario"]): r for r in results}
    profiles = {s: profile(sc_registry.get(s)) for s in scens}
    lines = [
        "Command:",
        "",
        "```",
        command,
        "```",
        "",
        (
            f"{meta['trials']} Monte Carlo trials per noisy scenario (1 for noise-free ones), seeds "
            f"{meta['seed']}..{meta['seed'] + meta['trials'] - 1}; sinewatch {meta.get('version', '?')}, "
            f"{meta.get('date', '')}; {meta.get('elapsed_s', 0):.0f} s on {meta.get('machine', '?')}."
        ),
        (
            'n/a: the estimator does not apply (reasons at the end); "defined N %": the estimator left '
            'the rest of the steady window undefined (NaN); "-": never (a time) or undefined.'
        ),
        "",
    ]
    for title, what, key in FAMILIES:
        rows = [s for s in scens if _family(set(profiles[s].tags), profiles[s].crlb) == key]
        if not rows:
            continue
        lines += [f"### {title}", "", f"Cells: {what}.", ""]
        head = ["scenario"] + ests + (["paper reports"] if key == "paper" else [])
        lines.append("| " + " | ".join(head) + " |")
        lines.append("|" + "---|" * len(head))
        for s in rows:
            cells = [f"`{s}`"] + [_cell(by.get((e, s)), key) for e in ests]
            if key == "paper":
                ref = profiles[s].reference
                cells.append("; ".join(f"{k}: {v}" for k, v in ref.items()) if ref else "")
            lines.append("| " + " | ".join(c.replace("|", "/") for c in cells) + " |")
        lines.append("")
    # CRLB detail: all four parameters for the stationary tones
    crlb_rows = [s for s in scens if profiles[s].crlb]
    if crlb_rows:
        lines += [
            "### All four parameters against the CRLB (dB over the bound: frequency / amplitude / phase / offset)",
            "",
        ]
        lines.append("| scenario | " + " | ".join(ests) + " |")
        lines.append("|" + "---|" * (len(ests) + 1))
        for s in crlb_rows:
            cells = [f"`{s}`"]
            for e in ests:
                r = by.get((e, s))
                if r is None or r["status"] != "ok" or "crlb" not in r["metrics"]:
                    cells.append("n/a" if r is not None and r["status"] == "n/a" else "")
                    continue
                cr = r["metrics"]["crlb"]
                cells.append(" / ".join(_fmt(cr[p]["over_crlb_db"], "", 3) for p in PARAMS))
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    lines += _own_window_and_calibration(results, ests, scens, by, profiles)
    # not applicable / errors
    na = [r for r in results if r["status"] != "ok"]
    if na:
        lines += ["### Not run (n/a) and errors", ""]
        reasons: dict[tuple[str, str, str], list[str]] = {}
        for r in na:
            reasons.setdefault((r["estimator"], r["status"], r["reason"]), []).append(r["scenario"])
        for (e, status, reason), ss in sorted(reasons.items()):
            shown = ", ".join(f"`{s}`" for s in ss[:6]) + (f" and {len(ss) - 6} more" if len(ss) > 6 else "")
            lines.append(f"- **{e}** {status} on {shown}: {reason}")
        lines.append("")
    return "\n".join(lines)


def _own_window_and_calibration(
    results: list[dict[str, Any]],
    ests: list[str],
    scens: list[str],
    by: dict[tuple[str, str], dict[str, Any]],
    profiles: dict[str, Any],
) -> list[str]:
    """Two tables: windowed estimators against their own window's CRLB (stationary tones),
    and the calibration of reported standard deviations (every scenario)."""
    lines: list[str] = []
    for key, title, rows in (
        (
            "crlb_own_window",
            "### Windowed estimators against the CRLB of their own window "
            "(dB over the bound: frequency / amplitude / phase / offset)",
            [s for s in scens if profiles[s].crlb],
        ),
        (
            "calibration",
            "### Calibration of the reported standard deviations: sd of error / reported sd "
            "(frequency / amplitude / phase / offset; 1 when right)",
            scens,
        ),
    ):
        cols = [e for e in ests if any(key in (by.get((e, s)) or {}).get("metrics", {}) for s in rows)]
        if not cols:
            continue
        lines += [title, "", "| scenario | " + " | ".join(cols) + " |", "|" + "---|" * (len(cols) + 1)]
        for s in rows:
            cells = [f"`{s}`"]
            for e in cols:
                m = (by.get((e, s)) or {}).get("metrics", {})
                if key not in m:
                    cells.append("")
                elif key == "calibration":
                    cells.append(" / ".join(_fmt(m[key][p], "", 3) for p in PARAMS))
                else:
                    cells.append(
                        " / ".join(_fmt(m[key][p]["over_crlb_db"], "", 3) for p in PARAMS)
                        + f" (N = {m[key]['window_samples']})"
                    )
            if any(cells[1:]):
                lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def _finite_or_none(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, list):
        return [_finite_or_none(v) for v in x]
    if isinstance(x, dict):
        return {k: _finite_or_none(v) for k, v in x.items()}
    return x


def write_json(
    path: Path, results: list[dict[str, Any]], meta: dict[str, Any], power_quality: list[dict[str, Any]] | None = None
) -> None:
    clean = [{k: v for k, v in r.items() if not k.startswith("_")} for r in results]
    doc: dict[str, Any] = {"meta": meta, "results": clean}
    if power_quality is not None:
        doc["power_quality"] = power_quality
    path.write_text(json.dumps(_finite_or_none(doc), indent=1, default=str) + "\n")


def write_plots(out: Path, results: list[dict[str, Any]]) -> list[Path]:
    """PNG plots (matplotlib, optional): frequency RMSE against SNR with the CRLB, and per
    scenario the frequency error (or TVE) of the first trial of each estimator."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    written: list[Path] = []
    plots = out / "plots"
    plots.mkdir(parents=True, exist_ok=True)
    ests = list(dict.fromkeys(r["estimator"] for r in results))
    # 1. SNR sweep
    snr = sorted({r["scenario"] for r in results if r["scenario"].startswith("tone-snr-")})
    if snr:
        fig, ax = plt.subplots(figsize=(7, 4.5))
        x = [int(s.split("-")[2][:2]) for s in snr]
        bound = [_crlb_std(s) for s in snr]
        ax.semilogy(x, bound, "k--", label="CRLB (samples seen)")
        for e in ests:
            ys = []
            for s in snr:
                r = next((r for r in results if r["estimator"] == e and r["scenario"] == s), None)
                ys.append(max(r["metrics"]["frequency_hz"]["rmse"]) if r and r["status"] == "ok" else np.nan)
            if np.isfinite(ys).any():
                ax.semilogy(x, ys, "o-", label=e)
        ax.set_xlabel("SNR (dB)")
        ax.set_ylabel("frequency RMSE (Hz)")
        ax.set_title("Stationary 50.5 Hz tone at 1 kHz (nominal 50 Hz), steady window 1-2 s")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        p = plots / "snr_sweep.png"
        fig.tight_layout()
        fig.savefig(p, dpi=110)
        plt.close(fig)
        written.append(p)
    # 2. one figure per scenario
    for s in dict.fromkeys(r["scenario"] for r in results):
        recs = [r for r in results if r["scenario"] == s and r["status"] == "ok" and "_trace" in r]
        if not recs:
            continue
        phasor = "tve_pct" in recs[0]["_trace"]
        fig, ax = plt.subplots(figsize=(8, 4))
        for r in recs:
            tr = r["_trace"]
            t = np.asarray(tr["t"])
            if phasor:
                ax.semilogy(t, np.maximum(np.asarray(tr["tve_pct"]), 1e-6), lw=0.8, label=r["estimator"])
            else:
                err = np.asarray(tr["frequency_hz"], dtype=float) - np.asarray(tr["true_frequency_hz"])
                ax.semilogy(t, np.maximum(np.abs(err).max(axis=1), 1e-9), lw=0.8, label=r["estimator"])
        if phasor:
            ax.set_ylabel("TVE (%), floor 1e-6")
            ax.axhline(1.0, color="k", ls=":", lw=0.8)
        else:
            ax.set_ylabel("|frequency error| (Hz), worst component, floor 1e-9")
        ax.set_xlabel("time (s)")
        ax.set_title(f"{s} (first trial)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        p = plots / f"{s}.png"
        fig.tight_layout()
        fig.savefig(p, dpi=100)
        plt.close(fig)
        written.append(p)
    return written


def update_docs(path: Path, table_md: str, begin: str = DOCS_BEGIN, end: str = DOCS_END) -> None:
    """Replace the text between the results markers ``begin`` and ``end`` of ``path``
    (append them if absent)."""
    text = path.read_text() if path.exists() else ""
    block = f"{begin}\n{table_md}\n{end}"
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        text = head + block + tail
    else:
        text = text + ("\n" if text and not text.endswith("\n") else "") + block + "\n"
    path.write_text(text)


def _crlb_std(scenario: str) -> float:
    """The frequency CRLB (standard deviation, Hz) of a stationary-tone scenario."""
    bound = crlb_window(scenario)
    return math.sqrt(bound["frequency_hz"]) if bound is not None else math.nan
