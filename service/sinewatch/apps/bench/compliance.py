"""``sinewatch bench pmu``: the IEEE C37.118.1 M-class compliance suite for a grid-reporting
estimator (``pmu``), at 50 and 60 Hz, scored against the standard's limits.

Every test of :mod:`sinewatch.scenarios.c37118` is run through a fresh estimator fed the
whole signal with its absolute start time (a whole second since the epoch, so the grid and
the nominal cosine are aligned with the test's t = 0); the reports are compared with the
exact truth at their own timestamps:

* TVE = |X^ - X| / |X| (%), FE = |f^ - f| (Hz), RFE = |ROCOF^ - ROCOF| (Hz/s), worst over
  the scored reports of every condition of the family;
* steps, by equivalent-time sampling (the step at ``n_offsets`` fractions of the reporting
  interval, the reports of all runs merged on the time since the step): response time =
  last minus first time the error exceeds its threshold; delay time = |time the magnitude
  (or angle) crosses half the step|; overshoot = largest excursion beyond the final (or
  below the initial) value, % of the step;
* latency: the signal fed one sample per update; per report, the time of the sample whose
  arrival produced it, or, held back as the daemon holds it by default (``hold_estimates``),
  the time of the sample at which its presence detector has read its onset latency past the
  report's window, minus the report's timestamp (the transport's block length comes on top
  in a deployment).

The result is one row per (f0, Fs, family, metric): worst value, limit, PASS/FAIL.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from sinewatch.core.channel import cycle_frequency_hz
from sinewatch.estimators import get as get_estimator
from sinewatch.estimators.base import GridReports, concat_tracks
from sinewatch.estimators.pmu import AMBIGUOUS_S, DETECTION_S
from sinewatch.estimators.presence import DEFAULT_HYSTERESIS, SignalPresence
from sinewatch.scenarios.c37118 import (
    FAMILIES,
    LIMIT_NOTES,
    SAMPLE_RATE_HZ,
    STEP_THRESHOLDS,
    TestSignal,
    generate,
    limits,
)
from sinewatch.schemas.config import DEFAULT_ESTIMATOR, DEFAULT_PARAMS, SinewatchConfig

DEFAULT_RULE = "default-rule"  # the daemon's default rule (as sinewatch.apps.bench.scenarios names it)

T0_NS = 1_700_000_000 * 1_000_000_000  # a whole second: grid and nominal cosine aligned


@dataclass
class Row:
    f0: int
    fs_report: int
    family: str
    metric: str
    worst: float
    limit: float | None
    where: str
    sample_rate_hz: float = SAMPLE_RATE_HZ

    @property
    def passed(self) -> bool | None:
        if self.limit is None:
            return None
        return bool(np.isfinite(self.worst) and self.worst <= self.limit)

    @property
    def margin(self) -> float | None:
        """limit / worst (> 1 passes)."""
        if self.limit is None or not np.isfinite(self.worst):
            return None
        return self.limit / self.worst if self.worst > 0 else math.inf


def run_signal(
    test: TestSignal, estimator: str, params: dict[str, Any], block: int | None = None
) -> tuple[np.ndarray, dict[str, np.ndarray], list[float]]:
    """Feed the test through a fresh estimator; return (report times s, reports, emit times).
    ``block`` samples per update (default: the whole signal at once)."""
    cls = get_estimator(estimator)
    est = cls(test.sample_rate_hz, params)
    n = round(test.duration_s * test.sample_rate_hz)
    if params.get("nominal_frequency_hz") == "auto" and block is None:
        # an estimator that finds the nominal frequency from the signal may hold its reports
        # back (a signal at 55 Hz: up to AMBIGUOUS_S); the signal goes on past the test, whose
        # scored reports (t <= duration_s) then all come (latency is measured on its own)
        n += round((AMBIGUOUS_S + 0.5) * test.sample_rate_hz)
    t = np.arange(n) / test.sample_rate_hz
    x = test.signal(t)
    step = n if block is None else block
    parts = []
    emit: list[float] = []
    for i in range(0, n, step):
        t0_ns = T0_NS + round(i * 1e9 / test.sample_rate_hz)
        rep = est.update(x[i : i + step], last_only=True, t0_ns=t0_ns).reports
        if rep is None:
            raise ValueError(f"{estimator}: expected an estimator that reports on a time grid")
        parts.append(rep)
        emit.extend([(i + min(step, n - i) - 1) / test.sample_rate_hz] * rep.n_reports)
    # the last part's rate: one that finds its nominal frequency from the signal knows its rate only then
    reports = GridReports(
        np.concatenate([p.index for p in parts]), parts[-1].reporting_rate_hz, concat_tracks([p.track for p in parts])
    )
    times = reports.times_s(T0_NS)
    tr = reports.track
    rocof = tr.rocof_hz_per_s[:, 0] if tr.rocof_hz_per_s is not None else np.full(times.shape, np.nan)
    # the synchrophasor is referred to the nominal cosine of the nominal frequency the
    # estimator declares (its reporting rate tells a receiver; C37.118.2's FNOM): one that
    # finds it from the signal may take the other suite's (a steady 55 Hz is 50 + 5 and 60 - 5);
    # the truth is then referred to that cosine too (declared_nominal_hz)
    phasor = tr.extras["synchrophasor_magnitude"] * np.exp(1j * tr.extras["synchrophasor_angle_rad"])
    declared = declared_nominal_hz(est, test.f0)
    if declared != test.f0:
        phasor = phasor * np.exp(2j * np.pi * (declared - test.f0) * times)
    fields = {
        "phasor": phasor,
        "frequency_hz": tr.frequency_hz[:, 0],
        "rocof_hz_per_s": rocof,
    }
    return times, fields, emit


def declared_nominal_hz(est: Any, suite_f0: int) -> int:
    """The nominal frequency the estimator's synchrophasors are referred to: its design's
    (``pmu``), found from the signal when configured 'auto'; the suite's for any other."""
    design = getattr(est, "design", None)
    f0 = getattr(design, "f0", None)
    return int(f0) if f0 in (50, 60) else suite_f0


def errors(test: TestSignal, times: np.ndarray, rep: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    x, f, r = test.truth(times)
    return {
        "tve_pct": 100.0 * np.abs(rep["phasor"] - x) / np.abs(x),
        "fe_hz": np.abs(rep["frequency_hz"] - f),
        "rfe_hz_per_s": np.abs(rep["rocof_hz_per_s"] - r),
    }


def _worst(values: np.ndarray) -> float:
    """Worst error; NaN (no estimate) counts as infinitely bad."""
    if values.size == 0:
        return math.nan
    if not np.all(np.isfinite(values)):
        return math.inf
    return float(np.max(values))


def score_steady(
    family: str, f0: int, fs_report: int, tests: list[TestSignal], est: str, params: dict[str, Any]
) -> list[Row]:
    lim = limits(family, f0, fs_report)
    worst: dict[str, tuple[float, str]] = {}
    for test in tests:
        times, rep, _ = run_signal(test, est, params)
        keep = test.scored(times)
        if not keep.any():
            raise RuntimeError(f"{family} {test.label}: no report in the scored window")
        err = errors(test, times[keep], {k: v[keep] for k, v in rep.items()})
        for metric, vals in err.items():
            w = _worst(vals)
            if metric not in worst or not (w <= worst[metric][0]):
                worst[metric] = (w, test.label)
    rows = []
    for metric in ("tve_pct", "fe_hz", "rfe_hz_per_s"):
        value, where = worst[metric]
        rows.append(Row(f0, fs_report, family, metric, value, lim.get(metric), where))
    return rows


def step_response(tests: list[TestSignal], est: str, params: dict[str, Any]) -> dict[str, float]:
    """Equivalent-time-sampled step metrics over the runs of one step direction."""
    rel, tve, fe, rfe, val = [], [], [], [], []
    kind = tests[0].step_kind
    size = tests[0].step_size
    for test in tests:
        times, rep, _ = run_signal(test, est, params)
        keep = times >= test.score_from_s
        times = times[keep]
        rep = {k: v[keep] for k, v in rep.items()}
        err = errors(test, times, rep)
        assert test.step_time_s is not None
        rel.append(times - test.step_time_s)
        tve.append(err["tve_pct"])
        fe.append(err["fe_hz"])
        rfe.append(err["rfe_hz_per_s"])
        x0, _, _ = test.truth(np.array([0.0]))
        if kind == "magnitude":
            val.append(np.abs(rep["phasor"]) / np.abs(x0[0]) - 1.0)  # relative change
        else:
            val.append(np.angle(rep["phasor"] * np.conj(x0[0])))  # radians from the initial angle
    order = np.argsort(np.concatenate(rel), kind="stable")
    t = np.concatenate(rel)[order]
    out: dict[str, float] = {}
    for name, arr, thr in (
        ("response_s", tve, STEP_THRESHOLDS["tve_pct"]),
        ("fe_response_s", fe, STEP_THRESHOLDS["fe_hz"]),
        ("rfe_response_s", rfe, STEP_THRESHOLDS["rfe_hz_per_s"]),
    ):
        e = np.concatenate(arr)[order]
        bad = ~(e <= thr)
        out[name] = float(t[bad][-1] - t[bad][0]) if bad.any() else 0.0
    v = np.concatenate(val)[order] / size  # 0 before, 1 after
    cross = np.nonzero(v >= 0.5)[0]
    if cross.size and cross[0] > 0:
        i = cross[0]
        ta, tb, va, vb = t[i - 1], t[i], v[i - 1], v[i]
        tc = ta + (0.5 - va) * (tb - ta) / (vb - va) if vb != va else tb
        out["delay_s"] = float(abs(tc))
    else:
        out["delay_s"] = math.inf
    over = np.max(v[t > 0] - 1.0) if np.any(t > 0) else 0.0
    under = np.max(-v[t < 0]) if np.any(t < 0) else 0.0
    out["overshoot_pct"] = float(100.0 * max(over, under, 0.0))
    return out


def score_step(
    family: str, f0: int, fs_report: int, tests: list[TestSignal], est: str, params: dict[str, Any]
) -> list[Row]:
    lim = limits(family, f0, fs_report)
    rows = []
    by_sign: dict[str, list[TestSignal]] = {}
    for test in tests:
        by_sign.setdefault(test.label, []).append(test)
    worst: dict[str, tuple[float, str]] = {}
    for label, group in by_sign.items():
        for metric, value in step_response(group, est, params).items():
            if metric not in worst or value > worst[metric][0]:
                worst[metric] = (value, label)
    for metric in ("response_s", "fe_response_s", "rfe_response_s", "delay_s", "overshoot_pct"):
        value, where = worst[metric]
        rows.append(Row(f0, fs_report, family, metric, value, lim[metric], where))
    return rows


def _hold_s(test: TestSignal, est: str, params: dict[str, Any]) -> float:
    """How long after the sample that completes a report the daemon publishes it
    (``hold_estimates``, on by default): the onset latency of the presence detector the
    pipeline runs beside the estimator, as that detector states it once it has read the
    signal; counted from the report's last sample (fed one sample per update, the one that
    completed it), which bounds :meth:`Pipeline._hold`'s wait from above."""
    estimator = get_estimator(est)(test.sample_rate_hz, params)
    presence = SignalPresence(
        test.sample_rate_hz, cycle_frequency_hz(estimator), hysteresis=DEFAULT_HYSTERESIS, fast=True
    )
    n = round(test.duration_s * test.sample_rate_hz)
    presence.update(test.signal(np.arange(n) / test.sample_rate_hz))
    return presence.onset_latency_samples / test.sample_rate_hz


def measure_latency(
    f0: int, fs_report: int, est: str, params: dict[str, Any], settle_s: float, sample_rate_hz: float = SAMPLE_RATE_HZ
) -> Row:
    # at the nominal frequency (the steady-frequency test whose offset is 0)
    tests = list(generate("steady-frequency", f0, fs_report, full=False, settle_s=settle_s))
    test = tests[len(tests) // 2]
    # an estimator that finds the nominal frequency from the signal holds its first reports
    # back until it has (up to AMBIGUOUS_S + DETECTION_S): the latency is that of the reports after
    start_s = AMBIGUOUS_S + DETECTION_S if params.get("nominal_frequency_hz") == "auto" else 0.0
    test = TestSignal(
        **{**asdict(test), "duration_s": start_s + settle_s + 3.0 / fs_report, "sample_rate_hz": sample_rate_hz}
    )
    times, _, emit = run_signal(test, est, params, block=1)
    released = np.array(emit)
    where = "one sample per update" + (f", reports after the first {start_s:g} s" if start_s else "")
    if SinewatchConfig.model_fields["hold_estimates"].default:  # the daemon's default
        released = released + _hold_s(test, est, params)
        where += ", held back as the daemon does (hold_estimates)"
    lat = (released - times)[times >= start_s]
    return Row(f0, fs_report, "latency", "latency_s", _worst(lat), 5.0 / fs_report, where)


def run_suite(
    f0: int,
    fs_report: int,
    *,
    estimator: str = "pmu",
    params: dict[str, Any] | None = None,
    full: bool = False,
    families: tuple[str, ...] = FAMILIES,
    n_offsets: int = 10,
    sample_rate_hz: float = SAMPLE_RATE_HZ,
) -> list[Row]:
    """One (f0, Fs) of the suite; ``sample_rate_hz``: the input's rate (any, whole hertz or not)."""
    params = dict(params or {"nominal_frequency_hz": f0, "reporting_rate_hz": fs_report})
    settle = 12.0 / fs_report + 0.1
    rows: list[Row] = []
    for family in families:
        tests = [
            replace(t, sample_rate_hz=sample_rate_hz)
            for t in generate(family, f0, fs_report, full=full, settle_s=settle, n_offsets=n_offsets)
        ]
        if family.startswith("step"):
            rows.extend(score_step(family, f0, fs_report, tests, estimator, params))
        else:
            rows.extend(score_steady(family, f0, fs_report, tests, estimator, params))
    rows.append(measure_latency(f0, fs_report, estimator, params, settle, sample_rate_hz))
    return rows


def format_rows(rows: list[Row]) -> str:
    lines = [
        "| f0 | Fs | fs (Hz) | test | metric | worst | limit | limit/worst | result | worst at |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        result = {True: "PASS", False: "FAIL", None: "(no limit)"}[r.passed]
        lim = "-" if r.limit is None else f"{r.limit:.4g}"
        margin = "-" if r.margin is None else ("inf" if math.isinf(r.margin) else f"{r.margin:.1f}")
        lines.append(
            f"| {r.f0} | {r.fs_report} | {r.sample_rate_hz:g} | {r.family} | {r.metric} | {r.worst:.3g} | {lim} | {margin} | {result} | "
            f"{r.where} |"
        )
    return "\n".join(lines)


def _suites(estimator: str, rates: str | None) -> list[tuple[int, int, str, dict[str, Any]]]:
    """(f0, Fs, estimator, params) per suite: ``default-rule`` is the daemon's default rule as
    a user with no config gets it (its nominal frequency found from the signal; Fs its own),
    at 50 and 60 Hz."""
    if estimator == DEFAULT_RULE:
        params = dict(DEFAULT_PARAMS)
        fs_report = params.get("reporting_rate_hz")
        pairs = [(f0, int(fs_report or f0)) for f0 in (50, 60)]
        return [(f0, fr, DEFAULT_ESTIMATOR, params) for f0, fr in pairs]
    out = []
    for item in (rates or "50/50,60/60").split(","):
        f0_s, fs_s = item.split("/")
        out.append(
            (int(f0_s), int(fs_s), estimator, {"nominal_frequency_hz": int(f0_s), "reporting_rate_hz": int(fs_s)})
        )
    return out


def run(args: argparse.Namespace) -> int:
    rows: list[Row] = []
    t_start = time.perf_counter()
    for fs_in in [float(v) for v in args.sample_rates.split(",")]:
        for f0, fs_report, estimator, params in _suites(args.estimator, args.rates):
            suite = run_suite(f0, fs_report, estimator=estimator, params=params, full=args.full, sample_rate_hz=fs_in)
            rows.extend(replace(r, sample_rate_hz=fs_in) for r in suite)
    print(format_rows(rows))
    n_fail = sum(1 for r in rows if r.passed is False)
    print(
        f"\n{len(rows)} rows, {n_fail} FAIL ({'full sweep' if args.full else 'representative subset'}, "
        f"{time.perf_counter() - t_start:.1f} s). Limits: {LIMIT_NOTES}"
    )
    if args.json:
        args.json.write_text(json.dumps([{**asdict(r), "passed": r.passed} for r in rows], indent=2))
    return 0 if n_fail == 0 else 1


def markdown_section(estimators: list[str], *, full: bool = False) -> str:
    """The compliance tables of the grid-reporting estimators among ``estimators``, at
    Fs = f0 (50 and 60 Hz), for ``sinewatch bench accuracy --scenarios c37.118``."""
    names = [e for e in estimators if _reports_on_grid(e)]
    if not names:
        return ""
    parts = [
        "## C37.118.1 M-class compliance of the estimators that report on a time grid",
        "",
        "Scored on the reports at their timestamps (`sinewatch bench compliance` runs this alone; "
        f"{'full sweeps' if full else 'representative subset, --full for the sweeps'}). {LIMIT_NOTES}",
        "",
    ]
    for name in names:
        rows: list[Row] = []
        for f0 in (50, 60):
            params = {"nominal_frequency_hz": f0, "reporting_rate_hz": f0}
            rows.extend(run_suite(f0, f0, estimator=name, params=params, full=full))
        parts += [f"### {name}", "", format_rows(rows), ""]
    return "\n".join(parts)


def _reports_on_grid(name: str) -> bool:
    return get_estimator(name).reports_on_grid


def main(argv: list[str] | None = None) -> int:
    from sinewatch.apps.bench.args import add_compliance_arguments

    p = argparse.ArgumentParser(prog="sinewatch bench compliance", description=__doc__)
    add_compliance_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
