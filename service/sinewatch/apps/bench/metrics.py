"""Accuracy metrics of an estimator's track against a scenario's truth (pure numpy).

Definitions (the accuracy bench and docs/accuracy.md use exactly these):

* error of a parameter: estimate - truth per sample; the phase error is wrapped to
  (-pi, pi]. Frequency and phase errors are ignored where the true amplitude is 0.
* bias / RMSE: mean / root mean square of the error over the steady-state windows, pooled
  over Monte Carlo trials (undefined estimates left out and counted in ``defined_pct``).
* convergence time: the first time from which every component's frequency error stays
  within ``1 % of the true frequency + tolerance_hz`` (and is defined) up to the end of
  the first steady window; "never" (NaN, shown "-") when that time is after the window's
  start. The median over trials counts "never" as infinitely late.
* response time after a step of size s: the time from the step until the stepped
  quantity's error stays within ``max(0.1 |s|, 3 x its RMSE in the following steady
  window)``, "never" unless settled by the start of that window; overshoot: the largest excursion of the trial-averaged error beyond the new
  value, in % of |s|. For a data gap ("resume"), the reacquisition time uses the
  convergence criterion from the end of the gap.
* C37.118.1 quantities, at the reporting instants k / Fs inside the steady windows:
  total vector error ``TVE = |Ah e^{j phih} - A e^{j phi}| / A`` (the synchrophasor is
  A/sqrt(2) e^{j phi} in any common reference, which cancels), frequency error
  ``FE = |fh - f|`` and ROCOF error ``RFE = |rh - r|``; ``rh`` is the estimator's own
  ``rocof_hz_per_s`` (the track's field, or else its extra of that name) when it publishes
  one, else the difference of its frequency track over one reporting interval. The C37 response time is the time between the TVE first leaving
  and last re-entering its limit around a step.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

TWO_PI = 2.0 * math.pi
PARAMS = ("frequency_hz", "amplitude", "phase_rad", "offset")


def wrap(x: np.ndarray) -> np.ndarray:
    """Radians to (-pi, pi]."""
    out: np.ndarray = np.pi - np.mod(np.pi - x, TWO_PI)
    return out


def window_mask(t: np.ndarray, windows: list[tuple[float, float]] | tuple[tuple[float, float], ...]) -> np.ndarray:
    """Samples with t inside any [t0, t1)."""
    m = np.zeros(t.shape, dtype=bool)
    for t0, t1 in windows:
        m |= (t >= t0) & (t < t1)
    return m


def match_components(est_f: np.ndarray, true_f: np.ndarray, mask: np.ndarray) -> tuple[int, ...]:
    """The assignment of estimate columns to truth columns (``perm[k]`` is the estimate
    column of truth component k) minimising the summed median |frequency error| over
    ``mask``; identity for one component."""
    k = true_f.shape[1]
    if k == 1 or not mask.any():
        return tuple(range(k))
    ef, tf = est_f[mask], true_f[mask]
    cost = np.empty((k, k))
    for i in range(k):
        for j in range(k):
            d = np.abs(ef[:, j] - tf[:, i])
            d = d[np.isfinite(d)]
            cost[i, j] = np.median(d) if d.size else np.inf
    best, best_cost = tuple(range(k)), math.inf
    for perm in itertools.permutations(range(k)):
        c = sum(cost[i, perm[i]] for i in range(k))
        if c < best_cost:
            best, best_cost = perm, c
    return best


def settle_time(t: np.ndarray, ok: np.ndarray, start: float, stop: float, latest: float = math.inf) -> float:
    """Time from ``start`` until ``ok`` holds for every sample in [that time, stop);
    NaN when that time is after ``latest`` (or ``ok`` fails at the last sample)."""
    sel = (t >= start) & (t < stop)
    idx = np.flatnonzero(sel)
    if idx.size == 0:
        return math.nan
    seg = ok[idx]
    if not seg[-1]:
        return math.nan
    bad = np.flatnonzero(~seg)
    first_good = 0 if bad.size == 0 else bad[-1] + 1
    when = float(t[idx[first_good]])
    return when - start if when <= latest else math.nan


def tve(est_amp: np.ndarray, est_phase: np.ndarray, true_amp: np.ndarray, true_phase: np.ndarray) -> np.ndarray:
    """Total vector error (fraction, not %) of the phasor (amplitude, phase)."""
    dx = est_amp * np.cos(est_phase) - true_amp * np.cos(true_phase)
    dy = est_amp * np.sin(est_phase) - true_amp * np.sin(true_phase)
    with np.errstate(divide="ignore", invalid="ignore"):
        out: np.ndarray = np.hypot(dx, dy) / true_amp
    return out


def rocof_from_frequency(f: np.ndarray, sample_rate_hz: float, interval_samples: int) -> np.ndarray:
    """Backward difference of a frequency track over ``interval_samples`` (Hz/s); NaN for
    the first interval."""
    m = max(int(interval_samples), 1)
    r = np.full(f.shape, np.nan)
    r[m:] = (f[m:] - f[:-m]) * (sample_rate_hz / m)
    return r


def reporting_indices(n: int, sample_rate_hz: float, reporting_rate_hz: float, mask: np.ndarray) -> np.ndarray:
    """Sample indices nearest the reporting instants k / Fs that fall inside ``mask``."""
    k = np.arange(math.floor((n - 1) / sample_rate_hz * reporting_rate_hz) + 1)
    idx = np.unique(np.clip(np.rint(k * sample_rate_hz / reporting_rate_hz).astype(np.int64), 0, n - 1))
    out: np.ndarray = idx[mask[idx]]
    return out


def exceedance_span(t: np.ndarray, above: np.ndarray, start: float, stop: float) -> float:
    """Time between the first and the end of the last sample where ``above`` holds in
    [start, stop) (0 when it never holds; NaN when it still holds at ``stop``)."""
    sel = np.flatnonzero((t >= start) & (t < stop))
    if sel.size == 0:
        return math.nan
    hit = np.flatnonzero(above[sel])
    if hit.size == 0:
        return 0.0
    if hit[-1] == sel.size - 1:
        return math.nan
    dt = t[1] - t[0] if t.size > 1 else 0.0
    return float(t[sel[hit[-1]]] + dt - t[sel[hit[0]]])


def overshoot_pct(mean_err: np.ndarray, size: float) -> float:
    """Largest excursion of the (trial-averaged) error after a step of ``size`` beyond the
    new value, in the direction of the step, in % of |size| (0 if it never passes it)."""
    fin = mean_err[np.isfinite(mean_err)]
    if fin.size == 0 or size == 0:
        return math.nan
    return max(0.0, float(np.max(math.copysign(1.0, size) * fin))) / abs(size) * 100.0


class Moments:
    """Running bias/RMSE/max over pooled samples (per component column)."""

    def __init__(self, k: int) -> None:
        self.n = np.zeros(k)
        self.total = np.zeros(k)
        self.s1 = np.zeros(k)
        self.s2 = np.zeros(k)
        self.mx = np.zeros(k)

    def add(self, err: np.ndarray, valid: np.ndarray) -> None:
        """``err`` (M, K) errors, ``valid`` (M, K) where the truth defines the error."""
        fin = np.isfinite(err) & valid
        e = np.where(fin, err, 0.0)
        self.total += valid.sum(axis=0)
        self.n += fin.sum(axis=0)
        self.s1 += e.sum(axis=0)
        self.s2 += (e * e).sum(axis=0)
        if e.size:
            self.mx = np.maximum(self.mx, np.abs(e).max(axis=0))

    def summary(self) -> dict[str, list[float]]:
        with np.errstate(invalid="ignore", divide="ignore"):
            bias = self.s1 / self.n
            mse = self.s2 / self.n
            defined = 100.0 * self.n / self.total
        return {
            "bias": bias.tolist(),
            "rmse": np.sqrt(mse).tolist(),
            "max_abs": np.where(self.n > 0, self.mx, np.nan).tolist(),
            "mse": mse.tolist(),
            "defined_pct": defined.tolist(),
        }


def median_never_late(xs: Sequence[float]) -> float:
    """Median of times with "never" (NaN) counted as infinitely late; NaN if that is the
    median."""
    a = np.asarray(xs, dtype=float)
    if a.size == 0:
        return math.nan
    med = float(np.median(np.where(np.isnan(a), np.inf, a)))
    return med if math.isfinite(med) else math.nan


def against_crlb(m: dict[str, Any], bound: dict[str, float], sample_rate_hz: float, noise_std: float) -> dict[str, Any]:
    """Each parameter's pooled MSE (``m[p]["mse"][0]``) against its CRLB variance
    (``bound[p]``): the bound's standard deviation and the excess in dB; for the frequency
    also the equivalent window, the record length over which an efficient estimator
    reaches the same MSE: ``var(w) = 24 sigma^2 / (A^2 N^3)`` (w in rad/sample) solved for
    N, in seconds."""
    cr: dict[str, Any] = {}
    for p in PARAMS:
        mse = m[p]["mse"][0]
        db = math.nan if not mse >= 0 else (10.0 * math.log10(mse / bound[p]) if mse > 0 else -math.inf)
        cr[p] = {"crlb_std": math.sqrt(bound[p]), "over_crlb_db": db}
    fs = sample_rate_hz
    mse_w = m["frequency_hz"]["mse"][0] * (TWO_PI / fs) ** 2
    a = bound["amplitude_true"]
    if mse_w > 0:
        cr["frequency_hz"]["equivalent_window_s"] = (24.0 * noise_std**2 / (a * a * mse_w)) ** (1 / 3) / fs
    return cr


class C37Accumulator:
    """TVE, FE and RFE at the reporting instants, pooled over trials, and their summary
    against the C37.118.1 limits."""

    def __init__(self) -> None:
        self.tve: list[np.ndarray] = []
        self.fe: list[np.ndarray] = []
        self.rfe: list[np.ndarray] = []
        self.instants = 0
        self.undefined = 0
        self.rocof_source: str | None = None

    def add(
        self,
        i: np.ndarray,
        amp: np.ndarray,
        phase: np.ndarray,
        true_amp: np.ndarray,
        true_phase: np.ndarray,
        freq_err: np.ndarray,
        rocof: np.ndarray,
        true_rocof: np.ndarray,
        rocof_source: str,
    ) -> None:
        """One trial: per-sample tracks of one component, read at sample indices ``i``."""
        tv = tve(amp[i], phase[i], true_amp[i], true_phase[i]) * 100.0
        fe = np.abs(freq_err[i])
        rfe = np.abs(rocof[i] - true_rocof[i])
        self.instants += i.size
        self.undefined += int((~np.isfinite(tv) | ~np.isfinite(fe)).sum())
        self.tve.append(tv)
        self.fe.append(fe)
        self.rfe.append(rfe)
        self.rocof_source = rocof_source

    def summary(self, limits: dict[str, float], events: list[dict[str, Any]]) -> dict[str, Any]:
        """Worst and mean TVE, worst FE and RFE, and pass/fail against ``limits`` (the step
        ``events`` bring their TVE response time and overshoot)."""
        tv = np.concatenate(self.tve)
        fe = np.concatenate(self.fe)
        rfe = np.concatenate(self.rfe)

        def mx(a: np.ndarray) -> float:
            return float(np.max(np.where(np.isfinite(a), a, np.inf))) if a.size else math.nan

        out: dict[str, Any] = {
            "tve_max_pct": mx(tv),
            "tve_mean_pct": float(np.nanmean(tv)) if np.isfinite(tv).any() else math.nan,
            "fe_max_hz": mx(fe),
            "rfe_max_hz_per_s": mx(rfe),
            "rocof_source": self.rocof_source,
            "reporting_instants": self.instants,
            "undefined_instants": self.undefined,
            "limits": dict(limits),
        }
        failed = []
        for key, val in (
            ("tve_pct", out["tve_max_pct"]),
            ("fe_hz", out["fe_max_hz"]),
            ("rfe_hz_per_s", out["rfe_max_hz_per_s"]),
        ):
            if key in limits and not val <= limits[key]:
                failed.append(key)
        for ev in events:
            if "response_time_s" in limits and not ev.get("tve_response_time_s", math.nan) <= limits["response_time_s"]:
                failed.append("response_time_s")
            if "overshoot_pct" in limits and not ev.get("overshoot_pct", math.nan) <= limits["overshoot_pct"]:
                failed.append("overshoot_pct")
        out["failed"] = sorted(set(failed))
        out["pass"] = not failed
        return out
