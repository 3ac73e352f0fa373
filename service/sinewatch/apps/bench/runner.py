"""The accuracy bench's seeded Monte Carlo: one (estimator, scenario) pair
(:func:`evaluate`) and the whole run (:func:`run_bench`, in worker processes).

For each pair: the scenario's profile (:mod:`sinewatch.apps.bench.scenarios`), the estimator's
parameters for it (:mod:`sinewatch.apps.bench.params`), then trials with seeds seed, seed + 1,
... (one trial when the scenario is noise-free, its outcome being deterministic), each one
``update(samples)`` over the whole scenario; the errors against the truth accumulate into
the metrics of :mod:`sinewatch.apps.bench.metrics`; the CRLB comes from :mod:`sinewatch.crlb`.
A pair is "n/a" (with the reason) when the estimator tracks a different number of
components or inputs than the scenario has, or rejects the configuration.
"""

from __future__ import annotations

import functools
import math
import multiprocessing as mp
import time
import traceback
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict
from typing import Any

import numpy as np

from sinewatch import crlb as crlb_mod
from sinewatch import estimators as est_registry
from sinewatch import scenarios as sc_registry
from sinewatch.apps.bench import metrics as M
from sinewatch.apps.bench.args import DEFAULT_TRIALS
from sinewatch.apps.bench.params import NotApplicable, default_rule_estimator, estimator_params
from sinewatch.apps.bench.scenarios import DEFAULT_RULE, Profile, profile
from sinewatch.estimators.base import Track
from sinewatch.scenarios import Truth
from sinewatch.schemas.errors import ParameterError, SinewatchError

TWO_PI = 2.0 * math.pi
PARAMS = M.PARAMS
TRACE_POINTS = 1500


@functools.lru_cache(maxsize=256)
def crlb_window(name: str) -> dict[str, float] | None:
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


@functools.lru_cache(maxsize=256)
def crlb_own_window(name: str, window_samples: int, hop_samples: int) -> dict[str, float] | None:
    """Like :func:`crlb_window`, but the bound of an estimator's own window: N =
    ``window_samples`` samples, the phase taken m = 0 .. hop - 1 samples past the window's
    last one (an estimate held between hops), averaged over m. What a windowed estimator
    can at best reach, however long the record."""
    sc = sc_registry.get(name)
    prof = profile(sc)
    if not prof.crlb or window_samples < 4:
        return None
    fs = sc.sample_rate_hz
    t = np.arange(prof.n_samples) / fs
    idx = np.flatnonzero(M.window_mask(t, prof.steady_windows))
    pick = idx[np.linspace(0, idx.size - 1, 12).round().astype(int)]
    _, truth = sc.generate(0)
    lags = np.unique(np.linspace(0, max(hop_samples - 1, 0), 8).round().astype(int))
    acc = dict.fromkeys(PARAMS, 0.0)
    n_terms = len(pick) * len(lags)
    for i in pick:
        f, a, ph = truth.frequency_hz[i, 0], truth.amplitude[i, 0], truth.phase_rad[i, 0]
        for m in lags:
            b = crlb_mod.crlb(window_samples, f, a, ph, prof.noise_std, fs, reference=window_samples - 1 + int(m))
            for p in PARAMS:
                acc[p] += getattr(b, p) / n_terms
    acc["amplitude_true"] = float(truth.amplitude[pick[0], 0])
    return acc


def _na(est: str, scen: str, reason: str, status: str = "n/a") -> dict[str, Any]:
    return {"estimator": est, "scenario": scen, "status": status, "reason": reason}


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
    if est_name == DEFAULT_RULE:
        cls, params, source = default_rule_estimator()
    else:
        cls = est_registry.get(est_name)
        params, source = estimator_params(cls, sc, prof)
    try:
        est = cls(sc.sample_rate_hz, params)
    except (ParameterError, SinewatchError, ValueError, TypeError) as exc:
        raise NotApplicable(f"{type(exc).__name__}: {exc}") from exc
    if est.n_inputs != prof.n_inputs:
        raise NotApplicable(f"expects {est.n_inputs} input column(s); the scenario has {prof.n_inputs}")
    if est.n_components != prof.n_components:
        raise NotApplicable(f"tracks {est.n_components} component(s); the scenario has {prof.n_components}")

    n_trials = 1 if prof.noise_free else max(int(trials), 1)
    acc = _Trials(prof)
    trace = None
    elapsed = 0.0
    # an estimator that reports on a time grid gives the report for time t one latency
    # after t: it is fed the scenario's continuation (1 s more) so that every reporting
    # instant of the scenario has its report, and scored on the first n rows
    on_grid = est.reports_on_grid
    for trial in range(n_trials):
        y, truth = sc.generate(seed + trial)
        if on_grid:
            y = sc.generate(seed + trial, n=prof.n_samples + round(sc.sample_rate_hz))[0]
        est.reset()
        t0 = time.perf_counter()
        tr = est.update(y, t0_ns=0) if on_grid else est.update(y)  # grid reports at k / Fs from the start
        elapsed += time.perf_counter() - t0
        if on_grid and tr.reports is not None:
            tr = reports_on_rows(tr, sc.sample_rate_hz).rows(slice(0, prof.n_samples))
        ef, ea, ep = acc.add(tr, truth)
        if keep_trace and trace is None:
            trace = _trace(acc.t, ef, truth, ea, ep, prof)

    record = {
        "estimator": est_name,
        "scenario": scen_name,
        "status": "ok",
        "params": params,
        "params_source": source,
        "trials": n_trials,
        "n_samples": prof.n_samples,
        "ns_per_sample": elapsed / (n_trials * prof.n_samples) * 1e9,
        "metrics": acc.metrics(crlb_window(scen_name), _own_window_bound(est, scen_name)),
    }
    if trace is not None:
        record["_trace"] = trace
    return record


def reports_on_rows(tr: Track, sample_rate_hz: float) -> Track:
    """The per-sample track of an estimator that reports on a time grid, rebuilt from its
    reports by their timestamps (not by when they were computed, one latency later).
    Between reports k and k+1 every quantity is interpolated linearly, the phase as
    ``phase_k + 2 pi fbar dt + d (dt / Dt)`` with ``fbar`` the mean of the two frequencies
    and ``d`` what that leaves of the next report's phase (wrapped): exact for a steady
    tone, and a step's change spread over one interval rather than extrapolated at a
    transient frequency. After the last report: held, the phase advanced at its
    frequency; before the first: NaN, not converged. The reporting instants of the C37
    scoring then read the reports themselves."""
    assert tr.reports is not None
    grid = tr.reports
    g = grid.track
    n = tr.n_samples
    t = np.arange(n) / sample_rate_hz
    tk = grid.times_s()
    n_rep = tk.size
    if n_rep == 0:
        nan2 = np.full((n, 1), np.nan)
        return Track(nan2, nan2.copy(), nan2.copy(), np.full(n, np.nan), np.zeros(n, dtype=bool), tr.residual_rms)
    k = np.searchsorted(tk, t + 0.5 / sample_rate_hz, side="right") - 1  # report at or before (to half a sample)
    have = k >= 0
    k0 = np.clip(k, 0, n_rep - 1)
    k1 = np.minimum(k0 + 1, n_rep - 1)
    span = np.where(k1 > k0, tk[k1] - tk[k0], 1.0)
    dt = t - tk[k0]
    alpha = np.where(k1 > k0, np.clip(dt / span, 0.0, 1.0), 0.0)[:, None]

    def lerp(a: np.ndarray) -> np.ndarray:
        a2 = a if a.ndim == 2 else a[:, None]
        out: np.ndarray = a2[k0] + alpha * (a2[k1] - a2[k0])
        out[~have] = np.nan
        return out if a.ndim == 2 else out[:, 0]

    f0, f1 = g.frequency_hz[k0], g.frequency_hz[k1]
    fbar = np.where(k1[:, None] > k0[:, None], 0.5 * (f0 + f1), f0)
    d = M.wrap(g.phase_rad[k1] - g.phase_rad[k0] - 2.0 * np.pi * fbar * span[:, None])
    phase = M.wrap(g.phase_rad[k0] + 2.0 * np.pi * fbar * dt[:, None] + d * alpha)
    phase[~have] = np.nan
    return Track(
        frequency_hz=lerp(g.frequency_hz),
        amplitude=lerp(g.amplitude),
        phase_rad=phase,
        offset=lerp(g.offset),
        converged=np.where(have, g.converged[k0], False),
        residual_rms=tr.residual_rms,
        rocof_hz_per_s=None if g.rocof_hz_per_s is None else lerp(g.rocof_hz_per_s),
    )


def _own_window_bound(est: Any, scen_name: str) -> dict[str, float] | None:
    """The own-window bound of an estimator with a fixed window (``window_samples`` and
    ``hop_samples`` attributes, as nls and ipdft have), else None."""
    n, hop = getattr(est, "window_samples", None), getattr(est, "hop_samples", 1)
    if not isinstance(n, int) or not isinstance(hop, int):
        return None
    bound = crlb_own_window(scen_name, n, hop)
    return None if bound is None else {**bound, "window_samples": float(n)}


class _Trials:
    """The errors of an estimator's tracks against the truth, accumulated over trials."""

    def __init__(self, prof: Profile) -> None:
        self.prof = prof
        fs, n, k = prof.sample_rate_hz, prof.n_samples, prof.n_components
        self.t = np.arange(n) / fs
        self.steady = M.window_mask(self.t, prof.steady_windows)
        self.moments = {p: M.Moments(1 if p == "offset" else k) for p in PARAMS}
        # error / reported sd, for estimators that report one (Track.std)
        self.normalised = {p: M.Moments(1 if p == "offset" else k) for p in PARAMS}
        self.has_std = False
        self.conv_times: list[float] = []
        self.flag_times: list[float] = []
        n_ev = len(prof.events)
        self.ev_times: list[list[float]] = [[] for _ in range(n_ev)]
        self.ev_tve_times: list[list[float]] = [[] for _ in range(n_ev)]
        self.ev_err_sum: list[np.ndarray | None] = [None] * n_ev
        self.ev_err_cnt: list[np.ndarray | None] = [None] * n_ev
        self.c37 = M.C37Accumulator()
        self.rep_idx = None
        if prof.reporting_rate_hz is not None:
            self.rep_idx = M.reporting_indices(n, fs, prof.reporting_rate_hz, self.steady)

    def add(self, tr: Track, truth: Truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One trial; returns the estimates' (frequency, amplitude, phase) columns in the
        truth's component order."""
        prof, t, steady = self.prof, self.t, self.steady
        first_window_start, first_window_end = prof.steady_windows[0]
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
            "offset": np.ones((prof.n_samples, 1), dtype=bool),
        }
        for p in PARAMS:
            self.moments[p].add(err[p][steady], valid[p][steady])
        if tr.std is not None:
            self.has_std = True
            sd = {
                "frequency_hz": tr.std.frequency_hz[:, perm],
                "amplitude": tr.std.amplitude[:, perm],
                "phase_rad": tr.std.phase_rad[:, perm],
                "offset": tr.std.offset[:, None],
            }
            for p in PARAMS:
                with np.errstate(invalid="ignore", divide="ignore"):
                    z = err[p][steady] / sd[p][steady]
                self.normalised[p].add(z, valid[p][steady])
        # convergence: every present component within 1 % (+ tolerance) of its true frequency
        tol = 0.01 * np.abs(truth.frequency_hz) + prof.tolerance_hz
        ok_f = np.asarray(np.where(present, np.abs(err["frequency_hz"]) <= tol, True).all(axis=1))
        self.conv_times.append(M.settle_time(t, ok_f, 0.0, first_window_end, latest=first_window_start))
        self.flag_times.append(M.settle_time(t, tr.converged, 0.0, first_window_end, latest=first_window_start))
        for j, ev in enumerate(prof.events):
            self._add_event(j, ev, err, ok_f, ea, ep, truth)
        if prof.reporting_rate_hz is not None and self.rep_idx is not None and self.rep_idx.size:
            # C37.118.1 quantities at the reporting instants, of the first component
            if tr.rocof_hz_per_s is not None:  # the estimator's own ROCOF, (N, K)
                r = np.asarray(tr.rocof_hz_per_s)[:, perm[0]]
                source = "track"
            elif "rocof_hz_per_s" in tr.extras:
                r = np.asarray(tr.extras["rocof_hz_per_s"])
                r = r[:, perm[0]] if r.ndim == 2 else r
                source = "extras"
            else:
                m = round(prof.sample_rate_hz / prof.reporting_rate_hz)
                r = M.rocof_from_frequency(ef[:, 0], prof.sample_rate_hz, m)
                source = f"difference over {m} samples"
            true_r = truth.rocof_hz_per_s[:, 0] if truth.rocof_hz_per_s is not None else np.zeros(prof.n_samples)
            amp, phase = truth.amplitude[:, 0], truth.phase_rad[:, 0]
            self.c37.add(self.rep_idx, ea[:, 0], ep[:, 0], amp, phase, err["frequency_hz"][:, 0], r, true_r, source)
        return ef, ea, ep

    def _add_event(
        self,
        j: int,
        ev: sc_registry.Event,
        err: dict[str, np.ndarray],
        ok_f: np.ndarray,
        ea: np.ndarray,
        ep: np.ndarray,
        truth: Truth,
    ) -> None:
        prof, t = self.prof, self.t
        stop = prof.event_stop(ev)
        if ev.quantity == "resume":
            ok_a = (np.abs(err["amplitude"]) <= 0.1 * np.maximum(truth.amplitude, 1e-12)).all(axis=1)
            self.ev_times[j].append(M.settle_time(t, ok_f & ok_a, ev.time_s, stop, latest=prof.settle_by(ev)))
        else:
            col = 0 if ev.quantity == "offset" else ev.component
            e = err[ev.quantity][:, col]
            post = M.window_mask(t, [w for w in prof.steady_windows if w[0] >= ev.time_s][:1])
            fin = e[post][np.isfinite(e[post])]
            rms_post = float(np.sqrt(np.mean(fin**2))) if fin.size else 0.0
            band = max(0.1 * abs(ev.size), 3.0 * rms_post)
            self.ev_times[j].append(M.settle_time(t, np.abs(e) <= band, ev.time_s, stop, latest=prof.settle_by(ev)))
            sel = (t >= ev.time_s) & (t < stop)
            es = np.where(np.isfinite(e[sel]), e[sel], 0.0)
            cnt = np.isfinite(e[sel]).astype(float)
            s0, c0 = self.ev_err_sum[j], self.ev_err_cnt[j]
            self.ev_err_sum[j] = es if s0 is None else s0 + es
            self.ev_err_cnt[j] = cnt if c0 is None else c0 + cnt
        if prof.reporting_rate_hz is not None and "tve_pct" in prof.limits:
            c = ev.component
            tv = M.tve(ea[:, c], ep[:, c], truth.amplitude[:, c], truth.phase_rad[:, c]) * 100.0
            above = ~(tv <= prof.limits["tve_pct"])
            start = ev.time_s - 1.0 / prof.reporting_rate_hz
            self.ev_tve_times[j].append(M.exceedance_span(t, above, start, stop))

    def metrics(self, bound: dict[str, float] | None, own_bound: dict[str, float] | None = None) -> dict[str, Any]:
        """The metrics record (see :mod:`sinewatch.apps.bench.metrics`); ``bound``: the CRLB
        over the steady window, for a stationary tone; ``own_bound``: that of the
        estimator's own window (:func:`crlb_own_window`)."""
        prof = self.prof
        out: dict[str, Any] = {p: self.moments[p].summary() for p in PARAMS}
        if own_bound is not None:
            out["crlb_own_window"] = M.against_crlb(out, own_bound, prof.sample_rate_hz, prof.noise_std)
            out["crlb_own_window"]["window_samples"] = int(own_bound["window_samples"])
        if self.has_std:  # sd of error / reported sd per parameter (worst component)
            cal: dict[str, float] = {}
            for p in PARAMS:
                sm = self.normalised[p].summary()
                sds = [math.sqrt(max(m2 - b * b, 0.0)) for m2, b in zip(sm["mse"], sm["bias"], strict=True)]
                finite = [v for v in sds if math.isfinite(v)]
                cal[p] = max(finite, key=lambda v: abs(math.log(v)) if v > 0 else math.inf) if finite else math.nan
            out["calibration"] = cal
        out["defined_pct"] = float(np.nanmin(self.moments["frequency_hz"].summary()["defined_pct"]))
        out["convergence_time_s"] = M.median_never_late(self.conv_times)
        out["converged_trials"] = int(np.sum(np.isfinite(self.conv_times)))
        out["flag_time_s"] = M.median_never_late(self.flag_times)
        if bound is not None:
            out["crlb"] = M.against_crlb(out, bound, prof.sample_rate_hz, prof.noise_std)
        events_out = []
        for j, ev in enumerate(prof.events):
            rec: dict[str, Any] = asdict(ev)
            rec["response_time_s"] = M.median_never_late(self.ev_times[j])
            s, c = self.ev_err_sum[j], self.ev_err_cnt[j]
            if s is not None and c is not None and ev.size != 0:
                with np.errstate(invalid="ignore", divide="ignore"):
                    mean_err = s / c
                rec["overshoot_pct"] = M.overshoot_pct(mean_err, ev.size)
            if self.ev_tve_times[j]:
                vals = np.array(self.ev_tve_times[j], dtype=float)
                rec["tve_response_time_s"] = math.nan if np.isnan(vals).any() else float(np.max(vals))
            events_out.append(rec)
        if events_out:
            out["events"] = events_out
        if prof.reporting_rate_hz is not None and self.c37.tve:
            out["c37"] = self.c37.summary(prof.limits, events_out)
        return out


def _trace(
    t: np.ndarray, ef: np.ndarray, truth: Truth, ea: np.ndarray, ep: np.ndarray, prof: Profile
) -> dict[str, Any]:
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


def _cost(scen: str, trials: int) -> float:
    sc = sc_registry.get(scen)
    return sc.n_samples * (1 if sc.noise_free else trials)


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

    def done(e: str, s: str, record: dict[str, Any]) -> None:
        results[(e, s)] = record
        if bar:
            bar.advance(f"{e} on {s}")

    try:
        if jobs > 1:
            with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as pool:
                futs = {pool.submit(evaluate, e, s, trials, seed, keep_trace): (e, s) for e, s in order}
                for fut in as_completed(futs):
                    e, s = futs[fut]
                    try:
                        done(e, s, fut.result())
                    except BrokenProcessPool:
                        continue  # finished in this process below
                    except Exception as exc:  # noqa: BLE001 (reported, the run goes on)
                        done(e, s, _na(e, s, f"worker failed: {exc}", status="error"))
        for e, s in order:  # one job, or whatever a broken pool left undone (e.g. a worker killed)
            if (e, s) not in results:
                if bar:
                    bar.describe(f"{e} on {s}")
                done(e, s, evaluate(e, s, trials, seed, keep_trace))
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

    def advance(self, text: str) -> None:
        self._p.update(self._task, description=text, advance=1)

    def close(self) -> None:
        self._p.stop()
