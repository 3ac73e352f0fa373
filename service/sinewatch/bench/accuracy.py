"""``sinewatch bench accuracy``: every estimator on every applicable scenario, side by side,
against the Cramer-Rao bound and the C37.118.1 limits; and ``sinewatch bench scenarios``.

The CLI (``sinewatch.cli``) calls four functions: :func:`add_accuracy_arguments`,
:func:`run_accuracy`, :func:`add_scenarios_arguments`, :func:`run_scenarios`. The same run
is available from Python as :func:`run_bench` (the tests use it).

How a run goes
--------------
For each (estimator, scenario) pair: the scenario's :class:`Profile` (nominal frequencies,
steady windows, events, reporting rate, limits; explicit for the library's scenarios,
derived from the truth for any other), the estimator's parameters for it
(:func:`estimator_params`), then seeded Monte Carlo trials (seed, seed + 1, ...; one
trial when the scenario is noise-free, its outcome being deterministic), each one
``update(samples)`` over the whole scenario. Metrics are defined in
:mod:`sinewatch.bench.metrics`; the CRLB comes from :mod:`sinewatch.crlb`.

Per-scenario parameters
-----------------------
:func:`estimator_params` merges, later entries winning:

1. the estimator's ``example_params``;
2. a generic mapping by field name: nominal-frequency fields (``nominal_frequency_hz``,
   ``f0_hz``, ...) get the scenario's nominal frequency (a list field gets one per
   component), required range fields (``f_min_hz``/``f_max_hz``, ``min_frequency_hz``/
   ``max_frequency_hz`` when their default is not None) the scenario's frequency range,
   component-count fields (``n_components``, ``n_sinusoids``, ...) the number of truth
   components, ``omega_unit_rad_s`` 2 pi times the mean nominal frequency;
3. the estimator's own hook, when it has one: ``params_for(sample_rate_hz, hints) ->
   dict`` (classmethod; ``hints`` as built by :func:`scenario_hints`; raising
   ParameterError means "does not apply"), else an adapter from :data:`ADAPTERS`;
4. the scenario's ``suggested_params`` when its ``suggested_estimator`` is this estimator
   (the papers' own tunings).

A pair is "n/a" (with the reason) when the estimator tracks a different number of
components or inputs than the scenario has, or rejects the configuration
(ParameterError).
"""

from __future__ import annotations

import argparse
import fnmatch
import functools
import json
import math
import multiprocessing as mp
import os
import platform
import shlex
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sinewatch import crlb as crlb_mod
from sinewatch import estimators as est_registry
from sinewatch import scenarios as sc_registry
from sinewatch.bench import metrics as M
from sinewatch.console import make_console
from sinewatch.estimators.base import Estimator
from sinewatch.scenarios import Scenario
from sinewatch.schemas.errors import ParameterError, SinewatchError

TWO_PI = 2.0 * math.pi
PARAMS = ("frequency_hz", "amplitude", "phase_rad", "offset")
DEFAULT_TRIALS = 10
QUICK_TRIALS = 3
TRACE_POINTS = 1500
DOCS_BEGIN = "<!-- accuracy-results:begin -->"
DOCS_END = "<!-- accuracy-results:end -->"


# ---- scenario profile ----------------------------------------------------------------------


@dataclass(frozen=True)
class EventSpec:
    time_s: float
    quantity: str  # amplitude | phase_rad | frequency_hz | offset | resume
    size: float = 0.0
    component: int = 0


@dataclass(frozen=True)
class Profile:
    """What the bench needs to know about a scenario."""

    name: str
    sample_rate_hz: float
    n_samples: int
    n_components: int
    n_inputs: int
    nominal_frequency_hz: tuple[float, ...]
    frequency_range_hz: tuple[float, float]
    steady_windows: tuple[tuple[float, float], ...]
    events: tuple[EventSpec, ...]
    tolerance_hz: float
    reporting_rate_hz: float | None
    limits: dict[str, float]
    noise_free: bool
    crlb: bool  # one stationary tone in white Gaussian noise
    noise_std: float
    tags: tuple[str, ...]
    reference: dict[str, Any] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return self.n_samples / self.sample_rate_hz

    @property
    def phasor(self) -> bool:
        return self.reporting_rate_hz is not None


def profile(sc: Scenario) -> Profile:
    """The scenario's bench profile: its ``bench`` metadata (library scenarios) or one
    derived from the truth at t = 0 and the second half as steady window."""
    n = sc.n_samples
    dur = n / sc.sample_rate_hz
    info = getattr(sc, "bench", None)
    if info is not None:
        windows = tuple((max(0.0, a), min(b, dur)) for a, b in info.steady_windows if a < dur)
        windows = tuple(w for w in windows if w[1] > w[0]) or ((0.5 * dur, dur),)
        return Profile(
            name=sc.name,
            sample_rate_hz=sc.sample_rate_hz,
            n_samples=n,
            n_components=len(info.nominal_frequency_hz),
            n_inputs=sc.n_inputs,
            nominal_frequency_hz=tuple(float(f) for f in info.nominal_frequency_hz),
            frequency_range_hz=tuple(info.frequency_range_hz),
            steady_windows=windows,
            events=tuple(EventSpec(e.time_s, e.quantity, e.size, e.component) for e in info.events if e.time_s < dur),
            tolerance_hz=float(info.tolerance_hz),
            reporting_rate_hz=info.reporting_rate_hz,
            limits=dict(info.limits),
            noise_free=bool(getattr(sc, "noise_free", sc.noise_std == 0.0)),
            crlb=bool(getattr(sc, "is_stationary", False)),
            noise_std=sc.noise_std,
            tags=tuple(sc.tags),
            reference=dict(info.reference),
        )
    _, truth = sc.generate(0, n=1)
    f0 = tuple(float(f) for f in truth.frequency_hz[0])
    return Profile(
        name=sc.name,
        sample_rate_hz=sc.sample_rate_hz,
        n_samples=n,
        n_components=len(f0),
        n_inputs=sc.n_inputs,
        nominal_frequency_hz=f0,
        frequency_range_hz=(0.5 * min(f0), min(2.0 * max(f0), 0.45 * sc.sample_rate_hz)),
        steady_windows=((0.5 * dur, dur),),
        events=(),
        tolerance_hz=0.0,
        reporting_rate_hz=None,
        limits={},
        noise_free=sc.noise_std == 0.0,
        crlb=False,
        noise_std=sc.noise_std,
        tags=tuple(sc.tags),
    )


def scenario_hints(sc: Scenario, prof: Profile | None = None) -> dict[str, Any]:
    """The plain-dict description of a scenario handed to an estimator's ``params_for``
    hook: sample_rate_hz, nominal_frequency_hz (tuple, one per component),
    frequency_range_hz, n_components, n_inputs, noise_std, amplitude (tuple, true
    amplitudes at t = 0), offset (true offset at t = 0), reporting_rate_hz (None unless a
    phasor test), tags, scenario (its name)."""
    prof = prof or profile(sc)
    _, truth = sc.generate(0, n=1)
    return {
        "scenario": sc.name,
        "sample_rate_hz": sc.sample_rate_hz,
        "nominal_frequency_hz": prof.nominal_frequency_hz,
        "frequency_range_hz": prof.frequency_range_hz,
        "n_components": prof.n_components,
        "n_inputs": prof.n_inputs,
        "noise_std": prof.noise_std,
        "amplitude": tuple(float(a) for a in truth.amplitude[0]),
        "offset": float(truth.offset[0]),
        "reporting_rate_hz": prof.reporting_rate_hz,
        "tags": prof.tags,
    }


# ---- estimator configuration -----------------------------------------------------------------


class NotApplicable(Exception):
    """This estimator does not apply to this scenario (the message says why)."""


NOMINAL_HZ_FIELDS = (
    "nominal_frequency_hz",
    "nominal_hz",
    "f_nominal_hz",
    "f0_hz",
    "initial_frequency_hz",
    "frequency_hz",
    "center_frequency_hz",
    "centre_frequency_hz",
    "reference_frequency_hz",
    "initial_frequencies_hz",
    "nominal_frequencies_hz",
    "frequencies_hz",
)
RANGE_LO_FIELDS = ("f_min_hz", "min_frequency_hz", "frequency_min_hz")
RANGE_HI_FIELDS = ("f_max_hz", "max_frequency_hz", "frequency_max_hz")
COUNT_FIELDS = ("n_components", "n_sinusoids", "n_tones", "num_components")
TIME_UNIT_FIELDS = ("omega_unit_rad_s",)


def _is_list_field(fld: Any) -> bool:
    return "list" in str(fld.annotation).lower() or "tuple" in str(fld.annotation).lower()


def generic_params(cls: type, hints: dict[str, Any]) -> dict[str, Any]:
    """Step 2 of :func:`estimator_params`: the mapping by field name."""
    fields = cls.Params.model_fields
    nom = tuple(hints["nominal_frequency_hz"])
    k = len(nom)
    fmean = float(np.mean(nom)) if k else 0.0
    lo, hi = hints["frequency_range_hz"]
    out: dict[str, Any] = {}
    for name, fld in fields.items():
        if name in NOMINAL_HZ_FIELDS:
            out[name] = list(nom) if _is_list_field(fld) else (nom[0] if k == 1 else fmean)
        elif name in RANGE_LO_FIELDS and fld.default is not None:
            out[name] = float(lo)
        elif name in RANGE_HI_FIELDS and fld.default is not None:
            out[name] = float(hi)
        elif name in COUNT_FIELDS:
            out[name] = k
        elif name in TIME_UNIT_FIELDS and fmean > 0:
            out[name] = TWO_PI * fmean
    return out


def _ges_kalman_params(fs: float, hints: dict[str, Any]) -> dict[str, Any]:
    """ges-kalman: the paper tunes Q = 1e-6 I for w Ts = 0.2 pi (100 Hz at 1 kHz). The
    states scale as x2 ~ A (w Ts) and x3, x4 ~ (w Ts)^2, so the random walks are scaled by
    (w Ts / 0.2 pi)^2 and ^4 to keep the same relative agility at other rates; R stays the
    paper's 1e-2 unless the noise is larger."""
    f = max(hints["nominal_frequency_hz"][0], 1e-9)
    rel = (TWO_PI * f / fs) / (0.2 * math.pi)
    q = 1e-6
    r = max(1e-2, float(hints.get("noise_std") or 0.0) ** 2)
    return {"q": [q * rel**2, q * rel**2, q * rel**4, q * rel**4], "r": r}


def _adaptive_multisine_params(fs: float, hints: dict[str, Any]) -> dict[str, Any]:
    """adaptive-multisine: one sinusoid per component, every rate relative to the mean
    nominal frequency (as its own example does); its default design otherwise."""
    nom = hints["nominal_frequency_hz"]
    fmean = float(np.mean(nom))
    # its frequency bound (default 4 units) must stay below Nyquist: the projection ball
    # admits up to ~ n^(1/4) omega_max
    nyquist_units = 0.5 * fs / fmean
    return {
        "n_sinusoids": len(nom),
        "omega_unit_rad_s": TWO_PI * fmean,
        "omega_max": min(4.0, 0.8 * nyquist_units / len(nom) ** 0.25),
    }


# Used for an estimator that has no ``params_for`` classmethod of its own.
ADAPTERS: dict[str, Callable[[float, dict[str, Any]], dict[str, Any]]] = {
    "ges-kalman": _ges_kalman_params,
    "adaptive-multisine": _adaptive_multisine_params,
}


def _is_base_hook(hook: Any) -> bool:
    """True for the Estimator base class's own params_for (should base.py ever declare a
    default one): that is "no hook", so the bench adapter still applies."""
    base = getattr(Estimator, "params_for", None)
    return base is not None and getattr(hook, "__func__", hook) is getattr(base, "__func__", base)


def estimator_params(cls: type, sc: Scenario, prof: Profile | None = None) -> tuple[dict[str, Any], str]:
    """Parameters of estimator class ``cls`` for scenario ``sc`` and where they came from
    (see the module docstring). Raises :class:`NotApplicable`."""
    prof = prof or profile(sc)
    hints = scenario_hints(sc, prof)
    params: dict[str, Any] = dict(cls.example_params)
    sources = ["example"]
    generic = generic_params(cls, hints)
    if generic:
        params.update(generic)
        sources.append("generic")
    hook = getattr(cls, "params_for", None)
    if callable(hook) and not _is_base_hook(hook):
        try:
            own = hook(sc.sample_rate_hz, hints)
        except ParameterError as exc:
            raise NotApplicable(str(exc)) from exc
        if own is None:
            raise NotApplicable(f"{cls.name}.params_for declined")
        params.update(own)
        sources.append("params_for")
    elif cls.name in ADAPTERS:
        params.update(ADAPTERS[cls.name](sc.sample_rate_hz, hints))
        sources.append("bench adapter")
    if getattr(sc, "suggested_estimator", None) == cls.name and sc.suggested_params:
        params.update(sc.suggested_params)
        sources.append("scenario")
    return params, "+".join(sources)


# ---- one (estimator, scenario) pair ------------------------------------------------------------


@functools.lru_cache(maxsize=256)
def _crlb_window(name: str) -> dict[str, float] | None:
    """Mean CRLB variance over the steady window (per-sample bound for the n + 1 samples
    seen so far, phase at that sample), for a stationary single-tone scenario."""
    sc = sc_registry.get(name)
    prof = profile(sc)
    if not prof.crlb:
        return None
    fs = sc.sample_rate_hz
    t = np.arange(prof.n_samples) / fs
    mask = M.window_mask(t, prof.steady_windows)
    idx = np.flatnonzero(mask)
    pick = idx[np.linspace(0, idx.size - 1, 12).round().astype(int)]
    _, truth = sc.generate(0)
    acc = dict.fromkeys(PARAMS, 0.0)
    for i in pick:
        n = int(i) + 1
        f, a, ph = truth.frequency_hz[i, 0], truth.amplitude[i, 0], truth.phase_rad[i, 0]
        if n <= 20_000:
            b = crlb_mod.crlb(n, f, a, ph, prof.noise_std, fs)
        else:
            b = crlb_mod.crlb_asymptotic(n, a, prof.noise_std, fs)
        for p in PARAMS:
            acc[p] += getattr(b, p) / len(pick)
    acc["amplitude_true"] = float(truth.amplitude[pick[0], 0])
    return acc


def _na(est: str, scen: str, reason: str, status: str = "n/a", **extra: Any) -> dict[str, Any]:
    return {"estimator": est, "scenario": scen, "status": status, "reason": reason, **extra}


def _finite_or_none(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, list):
        return [_finite_or_none(v) for v in x]
    if isinstance(x, dict):
        return {k: _finite_or_none(v) for k, v in x.items()}
    return x


def evaluate(
    est_name: str, scen_name: str, trials: int = DEFAULT_TRIALS, seed: int = 0, keep_trace: bool = False
) -> dict[str, Any]:
    """Run one estimator on one scenario (Monte Carlo) and return the result record."""
    try:
        return _evaluate(est_name, scen_name, trials, seed, keep_trace)
    except NotApplicable as exc:
        return _na(est_name, scen_name, str(exc))
    except Exception as exc:  # noqa: BLE001 (an estimator bug must not end the whole run)
        tb = traceback.format_exception_only(type(exc), exc)[-1].strip()
        return _na(est_name, scen_name, tb, status="error")


def _evaluate(est_name: str, scen_name: str, trials: int, seed: int, keep_trace: bool) -> dict[str, Any]:
    sc = sc_registry.get(scen_name)
    prof = profile(sc)
    cls = est_registry.get(est_name)
    params, source = estimator_params(cls, sc, prof)
    try:
        est = cls(sc.sample_rate_hz, params)
    except (ParameterError, SinewatchError, ValueError, TypeError) as exc:
        raise NotApplicable(f"{type(exc).__name__}: {exc}") from exc
    if est.n_inputs != prof.n_inputs:
        raise NotApplicable(f"expects {est.n_inputs} input column(s); the scenario has {prof.n_inputs}")
    k = prof.n_components
    if est.n_components != k:
        raise NotApplicable(f"tracks {est.n_components} component(s); the scenario has {k}")

    fs = sc.sample_rate_hz
    n = prof.n_samples
    t = np.arange(n) / fs
    steady = M.window_mask(t, prof.steady_windows)
    first_window_start, first_window_end = prof.steady_windows[0]
    n_trials = 1 if prof.noise_free else max(int(trials), 1)
    mom = {"frequency_hz": M.Moments(k), "amplitude": M.Moments(k), "phase_rad": M.Moments(k), "offset": M.Moments(1)}
    conv_times: list[float] = []
    flag_times: list[float] = []
    ev_times: list[list[float]] = [[] for _ in prof.events]
    ev_tve_times: list[list[float]] = [[] for _ in prof.events]
    ev_err_sum = [None] * len(prof.events)
    ev_err_cnt = [None] * len(prof.events)
    c37 = {"tve": [], "fe": [], "rfe": [], "undefined": 0, "instants": 0}
    rocof_source = None
    trace = None
    elapsed = 0.0
    truth = None
    rep_idx = None
    if prof.phasor:
        rep_idx = M.reporting_indices(n, fs, prof.reporting_rate_hz, steady)

    for trial in range(n_trials):
        y, truth = sc.generate(seed + trial)
        est.reset()
        t0 = time.perf_counter()
        tr = est.update(y)
        elapsed += time.perf_counter() - t0
        perm = list(M.match_components(tr.frequency_hz, truth.frequency_hz, steady))
        ef, ea, ep = tr.frequency_hz[:, perm], tr.amplitude[:, perm], tr.phase_rad[:, perm]
        present = truth.amplitude > 0
        err = {
            "frequency_hz": ef - truth.frequency_hz,
            "amplitude": ea - truth.amplitude,
            "phase_rad": M.wrap(ep - truth.phase_rad),
            "offset": (tr.offset - truth.offset)[:, None],
        }
        valid = {
            "frequency_hz": present,
            "amplitude": np.ones_like(present),
            "phase_rad": present,
            "offset": np.ones((n, 1), dtype=bool),
        }
        for p in PARAMS:
            mom[p].add(err[p][steady], valid[p][steady])
        # convergence: every present component within 1 % (+ tolerance) of its true frequency
        tol = 0.01 * np.abs(truth.frequency_hz) + prof.tolerance_hz
        ok_f = np.where(present, np.abs(err["frequency_hz"]) <= tol, True).all(axis=1)
        conv_times.append(M.settle_time(t, ok_f, 0.0, first_window_end, latest=first_window_start))
        flag_times.append(M.settle_time(t, tr.converged, 0.0, first_window_end, latest=first_window_start))
        # events
        for j, ev in enumerate(prof.events):
            stop = _event_stop(prof, ev)
            if ev.quantity == "resume":
                ok_a = (np.abs(err["amplitude"]) <= 0.1 * np.maximum(truth.amplitude, 1e-12)).all(axis=1)
                ev_times[j].append(M.settle_time(t, ok_f & ok_a, ev.time_s, stop, latest=_settle_by(prof, ev)))
            else:
                col = 0 if ev.quantity == "offset" else ev.component
                e = err[ev.quantity][:, col]
                post = M.window_mask(t, [w for w in prof.steady_windows if w[0] >= ev.time_s][:1])
                fin = e[post][np.isfinite(e[post])]
                rms_post = float(np.sqrt(np.mean(fin**2))) if fin.size else 0.0
                band = max(0.1 * abs(ev.size), 3.0 * rms_post)
                ev_times[j].append(M.settle_time(t, np.abs(e) <= band, ev.time_s, stop, latest=_settle_by(prof, ev)))
                sel = (t >= ev.time_s) & (t < stop)
                es = np.where(np.isfinite(e[sel]), e[sel], 0.0)
                cnt = np.isfinite(e[sel]).astype(float)
                ev_err_sum[j] = es if ev_err_sum[j] is None else ev_err_sum[j] + es
                ev_err_cnt[j] = cnt if ev_err_cnt[j] is None else ev_err_cnt[j] + cnt
            if prof.phasor and "tve_pct" in prof.limits:
                tv = (
                    M.tve(
                        ea[:, ev.component],
                        ep[:, ev.component],
                        truth.amplitude[:, ev.component],
                        truth.phase_rad[:, ev.component],
                    )
                    * 100.0
                )
                above = ~(tv <= prof.limits["tve_pct"])
                ev_tve_times[j].append(M.exceedance_span(t, above, ev.time_s - 1.0 / prof.reporting_rate_hz, stop))
        # C37.118.1 quantities at the reporting instants
        if prof.phasor and rep_idx is not None and rep_idx.size:
            i = rep_idx
            tv = M.tve(ea[i, 0], ep[i, 0], truth.amplitude[i, 0], truth.phase_rad[i, 0]) * 100.0
            fe = np.abs(err["frequency_hz"][i, 0])
            if "rocof_hz_per_s" in tr.extras:
                r = np.asarray(tr.extras["rocof_hz_per_s"])
                r = r[:, perm[0]] if r.ndim == 2 else r
                rocof_source = "extras"
            else:
                m = round(fs / prof.reporting_rate_hz)
                r = M.rocof_from_frequency(ef[:, 0], fs, m)
                rocof_source = f"difference over {m} samples"
            true_r = truth.rocof_hz_per_s[:, 0] if truth.rocof_hz_per_s is not None else np.zeros(n)
            rfe = np.abs(r[i] - true_r[i])
            c37["instants"] += i.size
            c37["undefined"] += int((~np.isfinite(tv) | ~np.isfinite(fe)).sum())
            c37["tve"].append(tv)
            c37["fe"].append(fe)
            c37["rfe"].append(rfe)
        if keep_trace and trace is None:
            trace = _trace(t, ef, truth, ea, ep, prof)

    assert truth is not None
    out_metrics: dict[str, Any] = {}
    for p in PARAMS:
        out_metrics[p] = mom[p].summary()
    out_metrics["defined_pct"] = float(np.nanmin(mom["frequency_hz"].summary()["defined_pct"]))
    out_metrics["convergence_time_s"] = _median(conv_times)
    out_metrics["converged_trials"] = int(np.sum(np.isfinite(conv_times)))
    out_metrics["flag_time_s"] = _median(flag_times)
    bound = _crlb_window(scen_name)
    if bound is not None:
        cr = {}
        for p in PARAMS:
            mse = out_metrics[p]["mse"][0]
            db = math.nan if not mse >= 0 else (10.0 * math.log10(mse / bound[p]) if mse > 0 else -math.inf)
            cr[p] = {"crlb_std": math.sqrt(bound[p]), "over_crlb_db": db}
        mse_w = out_metrics["frequency_hz"]["mse"][0] * (TWO_PI / fs) ** 2
        a = bound["amplitude_true"]
        if mse_w > 0:
            cr["frequency_hz"]["equivalent_window_s"] = (24.0 * prof.noise_std**2 / (a * a * mse_w)) ** (1 / 3) / fs
        out_metrics["crlb"] = cr
    events_out = []
    for j, ev in enumerate(prof.events):
        rec: dict[str, Any] = asdict(ev)
        rec["response_time_s"] = _median(ev_times[j])
        if ev_err_sum[j] is not None and ev.size != 0:
            with np.errstate(invalid="ignore", divide="ignore"):
                mean_err = ev_err_sum[j] / ev_err_cnt[j]
            rec["overshoot_pct"] = M.overshoot_pct(mean_err, ev.size)
        if ev_tve_times[j]:
            vals = np.array(ev_tve_times[j], dtype=float)
            rec["tve_response_time_s"] = math.nan if np.isnan(vals).any() else float(np.max(vals))
        events_out.append(rec)
    if events_out:
        out_metrics["events"] = events_out
    if prof.phasor and c37["tve"]:
        out_metrics["c37"] = _c37_summary(c37, prof, events_out, rocof_source)
    record = {
        "estimator": est_name,
        "scenario": scen_name,
        "status": "ok",
        "params": params,
        "params_source": source,
        "trials": n_trials,
        "n_samples": n,
        "ns_per_sample": elapsed / (n_trials * n) * 1e9,
        "metrics": out_metrics,
    }
    if trace is not None:
        record["_trace"] = trace
    return record


def _event_stop(prof: Profile, ev: EventSpec) -> float:
    """End of the interval that judges the response to ``ev``: the end of the first steady
    window after it, or the next event, or the end of the scenario."""
    later = [w[1] for w in prof.steady_windows if w[0] >= ev.time_s]
    nxt = [e.time_s for e in prof.events if e.time_s > ev.time_s]
    return min(later[:1] + nxt[:1] + [prof.duration_s])


def _settle_by(prof: Profile, ev: EventSpec) -> float:
    """A response counts only if it has settled when the next steady window starts."""
    later = [w[0] for w in prof.steady_windows if w[0] >= ev.time_s]
    return later[0] if later else _event_stop(prof, ev)


def _median(xs: Sequence[float]) -> float:
    """Median with "never" (NaN) counted as infinitely late; NaN if that is the median."""
    a = np.asarray(xs, dtype=float)
    if a.size == 0:
        return math.nan
    med = float(np.median(np.where(np.isnan(a), np.inf, a)))
    return med if math.isfinite(med) else math.nan


def _c37_summary(
    c: dict[str, Any], prof: Profile, events: list[dict[str, Any]], rocof_source: str | None
) -> dict[str, Any]:
    tv = np.concatenate(c["tve"])
    fe = np.concatenate(c["fe"])
    rfe = np.concatenate(c["rfe"])

    def mx(a: np.ndarray) -> float:
        return float(np.max(np.where(np.isfinite(a), a, np.inf))) if a.size else math.nan

    out = {
        "tve_max_pct": mx(tv),
        "tve_mean_pct": float(np.nanmean(tv)) if np.isfinite(tv).any() else math.nan,
        "fe_max_hz": mx(fe),
        "rfe_max_hz_per_s": mx(rfe),
        "rocof_source": rocof_source,
        "reporting_instants": c["instants"],
        "undefined_instants": c["undefined"],
        "limits": dict(prof.limits),
    }
    failed = []
    lim = prof.limits
    for key, val in (
        ("tve_pct", out["tve_max_pct"]),
        ("fe_hz", out["fe_max_hz"]),
        ("rfe_hz_per_s", out["rfe_max_hz_per_s"]),
    ):
        if key in lim and not val <= lim[key]:
            failed.append(key)
    for ev in events:
        if "response_time_s" in lim and not ev.get("tve_response_time_s", math.nan) <= lim["response_time_s"]:
            failed.append("response_time_s")
        if "overshoot_pct" in lim and not ev.get("overshoot_pct", math.nan) <= lim["overshoot_pct"]:
            failed.append("overshoot_pct")
    out["failed"] = sorted(set(failed))
    out["pass"] = not failed
    return out


def _trace(t, ef, truth, ea, ep, prof: Profile) -> dict[str, Any]:
    step = max(1, t.size // TRACE_POINTS)
    sl = slice(None, None, step)
    tr = {
        "t": t[sl].tolist(),
        "frequency_hz": ef[sl].tolist(),
        "true_frequency_hz": truth.frequency_hz[sl].tolist(),
    }
    if prof.phasor:
        tr["tve_pct"] = (M.tve(ea[sl, 0], ep[sl, 0], truth.amplitude[sl, 0], truth.phase_rad[sl, 0]) * 100.0).tolist()
    return tr


# ---- the whole run -----------------------------------------------------------------------------


def select_scenarios(patterns: Iterable[str] | None, quick: bool = False) -> list[str]:
    """Scenario names from patterns: exact names, shell globs (``c37-50hz-*``), or tags
    (``c37.118``, ``tag:paper``). None: all scenarios (the "quick" tag with ``quick``)."""
    names = sc_registry.names()
    pats = list(patterns or [])
    if not pats:
        if not quick:
            return names
        pats = ["tag:quick"]
    chosen: list[str] = []
    tags_of = {}
    for p in pats:
        if p.startswith("tag:") or (p not in names and not any(ch in p for ch in "*?[")):
            tag = p.removeprefix("tag:")
            if not tags_of:
                tags_of = {nm: set(sc_registry.get(nm).tags) for nm in names}
            hits = [nm for nm in names if tag in tags_of[nm]]
        else:
            hits = fnmatch.filter(names, p)
        if not hits:
            raise ParameterError(f"scenarios: expected a name, glob or tag matching {names[:3]}..., got {p!r}")
        chosen.extend(h for h in hits if h not in chosen)
    return chosen


def select_estimators(names: Iterable[str] | None) -> list[str]:
    avail = list(est_registry.available())
    pats = list(names or [])
    if not pats:
        return avail
    chosen: list[str] = []
    for p in pats:
        hits = fnmatch.filter(avail, p)
        if not hits:
            raise ParameterError(f"estimators: expected one of {avail}, got {p!r}")
        chosen.extend(h for h in hits if h not in chosen)
    return chosen


def _cost(scen: str, trials: int) -> float:
    sc = sc_registry.get(scen)
    nf = getattr(sc, "noise_free", sc.noise_std == 0.0)
    return sc.n_samples * (1 if nf else trials)


def run_bench(
    estimators: Sequence[str],
    scenarios: Sequence[str],
    trials: int = DEFAULT_TRIALS,
    seed: int = 0,
    jobs: int = 1,
    keep_trace: bool = False,
    progress: bool = False,
) -> list[dict[str, Any]]:
    """Every estimator on every scenario; records in (scenario, estimator) order."""
    tasks = [(e, s) for s in scenarios for e in estimators]
    order = sorted(tasks, key=lambda es: -_cost(es[1], trials))
    results: dict[tuple[str, str], dict[str, Any]] = {}
    bar = _Progress(len(tasks)) if progress else None
    try:
        if jobs <= 1:
            for e, s in order:
                if bar:
                    bar.describe(f"{e} on {s}")
                results[(e, s)] = evaluate(e, s, trials, seed, keep_trace)
                if bar:
                    bar.advance()
        else:
            with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as pool:
                futs = {pool.submit(evaluate, e, s, trials, seed, keep_trace): (e, s) for e, s in order}
                for fut in as_completed(futs):
                    e, s = futs[fut]
                    try:
                        results[(e, s)] = fut.result()
                    except BrokenProcessPool:
                        continue  # finished in this process below
                    except Exception as exc:  # noqa: BLE001 (reported, the run goes on)
                        results[(e, s)] = _na(e, s, f"worker failed: {exc}", status="error")
                    if bar:
                        bar.describe(f"{e} on {s}")
                        bar.advance()
            for e, s in order:  # whatever a broken pool left undone (e.g. a worker killed)
                if (e, s) not in results:
                    results[(e, s)] = evaluate(e, s, trials, seed, keep_trace)
                    if bar:
                        bar.describe(f"{e} on {s}")
                        bar.advance()
    finally:
        if bar:
            bar.close()
    return [results[t] for t in tasks]


class _Progress:
    def __init__(self, total: int) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self._p = Progress(
            TextColumn("[bold]accuracy"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TextColumn("{task.description}"),
            transient=False,
        )
        self._p.start()
        self._task = self._p.add_task("", total=total)

    def describe(self, text: str) -> None:
        self._p.update(self._task, description=text)

    def advance(self) -> None:
        self._p.advance(self._task)

    def close(self) -> None:
        self._p.stop()


# ---- report ------------------------------------------------------------------------------------


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
        return f"{_fmt(f_rmse, ' Hz')} ({sign}{_fmt(db, ' dB', 3)}; {_fmt(teq, ' s')})"
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
            "CRLB for the samples seen, in dB, 0 dB being the physical limit; and the equivalent "
            "window, the record length an efficient estimator needs for the same RMSE)"
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


def write_json(path: Path, results: list[dict[str, Any]], meta: dict[str, Any]) -> None:
    clean = [{k: v for k, v in r.items() if not k.startswith("_")} for r in results]
    path.write_text(json.dumps(_finite_or_none({"meta": meta, "results": clean}), indent=1, default=str) + "\n")


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
        bound = [math.sqrt(_crlb_window(s)["frequency_hz"]) for s in snr]
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


def update_docs(path: Path, table_md: str) -> None:
    """Replace the text between the results markers of ``path`` (append them if absent)."""
    text = path.read_text() if path.exists() else ""
    block = f"{DOCS_BEGIN}\n{table_md}\n{DOCS_END}"
    if DOCS_BEGIN in text and DOCS_END in text:
        head, rest = text.split(DOCS_BEGIN, 1)
        _, tail = rest.split(DOCS_END, 1)
        text = head + block + tail
    else:
        text = text + ("\n" if text and not text.endswith("\n") else "") + block + "\n"
    path.write_text(text)


# ---- CLI ----------------------------------------------------------------------------------------


def add_accuracy_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--estimators", nargs="+", metavar="NAME", help="estimator names or globs (default: every registered estimator)"
    )
    parser.add_argument(
        "--scenarios",
        nargs="+",
        metavar="NAME",
        help="scenario names, globs (c37-50hz-*) or tags (c37.118, paper, snr, gap, "
        "multitone, phasor; or tag:NAME); default: all (with --quick: tag quick)",
    )
    parser.add_argument(
        "--trials",
        type=int,
        default=None,
        help=f"Monte Carlo trials per noisy scenario (default {DEFAULT_TRIALS}, {QUICK_TRIALS} with --quick)",
    )
    parser.add_argument("--seed", type=int, default=0, help="first seed (trial i uses seed + i)")
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("bench-results/accuracy"),
        help="output directory for accuracy.md, accuracy.json and plots/",
    )
    parser.add_argument("--quick", action="store_true", help="the quick subset and fewer trials")
    parser.add_argument(
        "--jobs",
        type=int,
        default=min(2, os.cpu_count() or 1),
        help="worker processes (default: 2 or the core count if smaller)",
    )
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument(
        "--update-docs",
        type=Path,
        metavar="FILE",
        help="also replace the results block of FILE (e.g. docs/accuracy.md)",
    )


def run_accuracy(args: argparse.Namespace) -> int:
    try:
        scens = select_scenarios(args.scenarios, quick=args.quick)
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
    results = run_bench(
        ests, scens, trials=trials, seed=args.seed, jobs=max(1, args.jobs), keep_trace=want_plots, progress=True
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
    md = render_markdown(results, meta["command"], meta)
    (out / "accuracy.md").write_text("# sinewatch accuracy results\n\n" + md + "\n")
    write_json(out / "accuracy.json", results, meta)
    plots = write_plots(out, results) if want_plots else []
    if getattr(args, "update_docs", None):
        update_docs(args.update_docs, md)
    n_ok = sum(r["status"] == "ok" for r in results)
    n_na = sum(r["status"] == "n/a" for r in results)
    n_err = sum(r["status"] == "error" for r in results)
    msg = f"{n_ok} runs, {n_na} n/a, {n_err} errors in {elapsed:.0f} s; wrote {out / 'accuracy.md'}, {out / 'accuracy.json'}"
    if want_plots:
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


def add_scenarios_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("patterns", nargs="*", metavar="NAME", help="names, globs or tags to list (default: all)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")


def run_scenarios(args: argparse.Namespace) -> int:
    try:
        names = select_scenarios(args.patterns or None)
    except ParameterError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rows = []
    for nm in names:
        sc = sc_registry.get(nm)
        prof = profile(sc)
        rows.append(
            {
                "name": nm,
                "tags": list(sc.tags),
                "sample_rate_hz": sc.sample_rate_hz,
                "duration_s": sc.duration_s,
                "components": prof.n_components,
                "nominal_frequency_hz": list(prof.nominal_frequency_hz),
                "noise_std": sc.noise_std,
                "summary": sc.summary,
            }
        )
    if getattr(args, "json", False):
        print(json.dumps(rows, indent=1))
        return 0
    from rich.table import Table

    table = Table(title=f"{len(rows)} scenarios")
    for col in ("name", "tags", "fs (Hz)", "s", "K", "summary"):
        table.add_column(col, overflow="fold")
    for r in rows:
        table.add_row(
            r["name"],
            ", ".join(r["tags"]),
            f"{r['sample_rate_hz']:g}",
            f"{r['duration_s']:g}",
            str(r["components"]),
            r["summary"],
        )
    make_console().print(table)
    return 0
