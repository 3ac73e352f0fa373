"""``python -m sinewatch.apps.bench.validity``: every estimator through interruptions and deep sags
from a third-party power-quality disturbance generator; what ``diagnostics.valid`` and
``converged`` say during and after each event, and how soon each estimator recovers.

The disturbances come from pypqd (R. A. Montoya Gutierrez; the integral model of Igual,
Medrano, Arcega, Mantescu, "Integral mathematical model of power quality disturbances",
ICHQP 2018; ``pip install pypqd``, in the ``test`` extra), with fixed start, end and depth so
that nothing is drawn at random: 50 Hz at 10 kHz, the event from 1.0235 s to 1.3235 s, seeded white
noise at 57 dB SNR, 25 ms blocks through the real pipeline (the event starts 1.5 ms before a
block ends, where an estimate's window holds the onset before the presence detector can have
read it), each estimator at the accuracy
bench's parameters for ``c37-50hz-steady`` (``default-rule``: the daemon's default rule as is).
pypqd's time base is ``linspace(0, D, N)``, a step of D / (N - 1) rather than 1 / fs: at the
declared rate its fundamental is ``f N / (N - 1)``, the truth used here.

``tests/test_validity.py`` asserts on the same runs; docs/validity.md has the table.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from typing import Any

import numpy as np

from sinewatch import estimators as est_registry
from sinewatch.apps.bench.params import default_rule_estimator, estimator_params
from sinewatch.apps.bench.scenarios import DEFAULT_RULE
from sinewatch.core.continuity import VALIDITY_RULES_VERSION
from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.scenarios import get as get_scenario
from sinewatch.schemas.codec import Block, encode_block_binary
from sinewatch.schemas.config import EstimatorRule, SinewatchConfig

FS = 10_000
DURATION_S = 3.0
BLOCK = 250  # 25 ms
# the event starts 1.5 ms before a block ends (the estimate at that block's end is the first
# whose window holds it, and the presence detector has not read it yet) and lasts 0.3 s
T_ON = 1.0235
T_OFF = T_ON + 0.3
RESTART_S = 1.0  # the gateway's restart: at a block boundary (its blocks resume there)
T00 = 1_700_000_000_000_000_000
EVENTS = (
    "interruption",
    "interruption-0.08pu",
    "deep-sag-0.05pu",
    "sag-0.5pu",
    "interruption-0.05pu",
    "interruption-0.097pu",
    "interruption-0.099pu",
    "gateway-restart",
)
ABSENCES = EVENTS[:3]  # below 0.1 pu: the signal is absent
NEAR_THRESHOLD = EVENTS[4:7]  # 0.05, 0.097, 0.099 pu: interruptions too (IEEE 1159: below 0.1 pu)
#: what ``make bench-validity`` shows: every event, one row per estimator and event
TABLE_EVENTS = EVENTS
RESTART_SILENCE_NS = 45 * 1_000_000_000  # the gateway is away 45 s, then counts from 0 again
RESTART_PHASE_RAD = 2.0  # and its signal resumes at another phase
SINGLE_TONE_SCENARIO = "c37-50hz-steady"
NO_SD_TARGET_HZ = 0.05  # a valid estimate's frequency error, where no sd is reported


def disturbance(kind: str) -> tuple[np.ndarray, float]:
    """pypqd's signal for event ``kind`` plus seeded noise, and the true frequency (Hz)."""
    import pypqd.synthetic as pqd  # type: ignore[import-untyped]  # the test extra, imported only when run

    common: dict[str, Any] = dict(fundamental_freq=50, phase_angle=(0.3,), signal_duration=DURATION_S, sampling_freq=FS)
    interval = ("fixed", (T_ON, T_OFF))
    if kind == "interruption":  # to zero
        [s] = pqd.interruption(interruption_magnitude=(1.0,), interruption_interval=interval, **common)
    elif kind == "interruption-0.08pu":  # IEEE 1159: below 0.1 pu
        [s] = pqd.interruption(interruption_magnitude=(0.92,), interruption_interval=interval, **common)
    elif kind == "deep-sag-0.05pu":
        [s] = pqd.sag(sag_magnitude=(0.95,), sag_interval=interval, **common)
    elif kind == "sag-0.5pu":
        [s] = pqd.sag(sag_magnitude=(0.5,), sag_interval=interval, **common)
    elif kind.startswith("interruption-0.0"):  # to 0.05, 0.097, 0.099 pu: below 0.1, an interruption
        depth = float(kind.removeprefix("interruption-").removesuffix("pu"))
        [s] = pqd.interruption(interruption_magnitude=(1.0 - depth,), interruption_interval=interval, **common)
    elif kind == "gateway-restart":  # no disturbance in the signal: the blocks carry it (run)
        [s] = pqd.sag(sag_magnitude=(0.0,), sag_interval=interval, **common)
    else:
        raise ValueError(f"event: expected one of {EVENTS}, got {kind!r}")
    x = np.asarray(s["Values"], dtype=np.float64)
    x = x + np.random.default_rng(7).normal(0.0, 1e-3, x.size)
    n = x.size
    return x, 50.0 * n / (n - 1)


class _Keep(NullSink):
    def __init__(self) -> None:
        self.estimates: list[dict[str, Any]] = []
        self.errors: list[dict[str, Any]] = []
        self.now_ns = 0  # the data time of the input being processed: its last sample

    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
        e = json.loads(payload)
        e["published_ns"] = self.now_ns
        self.estimates.append(e)

    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self.errors.append(json.loads(payload))


@dataclass
class Run:
    """One estimator through one event: per estimate (time s, frequency Hz, valid, converged,
    the frequency's reported sd in Hz or NaN where none is reported); ``wait_s``: per
    estimate, the data time from its timestamp to the last sample of the input that
    published it (held back: the block that confirmed it)."""

    estimator: str
    event: str
    truth_hz: float
    memory_s: float
    rows: list[tuple[float, float, bool, bool, float]]
    wait_s: list[float]
    refill_s: float  # the signal an estimate needs behind it to be valid: memory_s, twice for a recursive one (rules 5)

    def error(self, f: float) -> float:
        return abs(f - self.truth_hz)

    def between(self, a: float, b: float) -> list[tuple[float, float, bool, bool, float]]:
        return [r for r in self.rows if a <= r[0] < b]

    @staticmethod
    def target(row: tuple[float, float, bool, bool, float]) -> float:
        """What a valid estimate's frequency error must stay within: 3 reported sd, or
        ``NO_SD_TARGET_HZ`` where the estimator reports none."""
        sd = row[4]
        return 3.0 * sd if math.isfinite(sd) and sd > 0 else NO_SD_TARGET_HZ

    def worst_ratio(self, rows: list[tuple[float, float, bool, bool, float]]) -> float:
        """The largest frequency error over its target among ``rows`` flagged valid."""
        return max((self.error(r[1]) / self.target(r) for r in rows if r[2]), default=math.nan)

    def summary(self) -> dict[str, Any]:
        during = self.between(T_ON + 0.03 + BLOCK / FS, T_OFF)  # from 1.5 cycles (detection) and a block in
        after = self.between(T_OFF, math.inf)
        first_valid = next((r[0] for r in after if r[2]), math.nan)
        unsettled = [r[0] for r in after if not (r[3] and self.error(r[1]) < 0.05)]
        return {
            "estimator": self.estimator,
            "event": self.event,
            "memory_s": self.memory_s,
            "valid_during": sum(r[2] for r in during),
            "converged_during": sum(r[3] for r in during),
            "worst_unflagged_during_hz": max((self.error(r[1]) for r in during), default=math.nan),
            "worst_valid_hz": max((self.error(r[1]) for r in self.rows if r[2]), default=math.nan),
            "worst_converged_hz": max((self.error(r[1]) for r in self.rows if r[3]), default=math.nan),
            "valid_again_s": first_valid - T_OFF,
            "settled_s": (max(unsettled) if unsettled else T_OFF) - T_OFF,
        }


def applicable() -> list[str]:
    """The estimators this run covers: every registered one that tracks one tone, and the
    default rule (adaptive-multisine tracks two or more: ``tests/test_validity.py`` checks it
    on its own example)."""
    names = []
    sc = get_scenario(SINGLE_TONE_SCENARIO)
    for name in est_registry.available():
        cls = est_registry.get(name)
        try:
            params, _ = estimator_params(cls, sc)
            if cls(float(FS), params).n_components == 1:
                names.append(name)
        except Exception:  # noqa: BLE001 (does not apply to one tone at 10 kHz: not in this run)
            continue
    return [*names, DEFAULT_RULE]


def run(name: str, event: str, rules_version: int = VALIDITY_RULES_VERSION) -> Run:
    """``name`` (a registered estimator or ``default-rule``) through ``event``, under the
    pipeline's validity rules ``rules_version``, each with its default: 5 holds estimates back
    and calls a step of the level an edge and a recursive estimator valid after two memories,
    4 held them back by the presence detector's quarter-cycle test (``hold_estimates`` on), 3
    published them as soon as made (its ``hold_estimates`` was off by default), 2 had no
    hysteresis either."""
    if name == DEFAULT_RULE:
        cls, params, _ = default_rule_estimator()
    else:
        cls = est_registry.get(name)
        params, _ = estimator_params(cls, get_scenario(SINGLE_TONE_SCENARIO))
    x, truth = disturbance(event)
    cfg = SinewatchConfig(
        rules=[EstimatorRule(match="sinewatch/in/**", estimator=cls.name, params=params)],
        hold_estimates=rules_version >= 4,  # each version's default: held back from version 4 on
    )
    sink = _Keep()
    pipeline = Pipeline(cfg, [sink], validity_version=rules_version)
    restart_at = round(RESTART_S * FS) if event == "gateway-restart" else None
    for seq, i in enumerate(range(0, x.size, BLOCK)):
        t0 = T00 + round(i * 1e9 / FS)
        xb = x[i : i + BLOCK]
        if restart_at is not None and i >= restart_at:
            # after a 45 s silence the gateway counts from 0, its signal at another phase
            seq, t0 = seq - restart_at // BLOCK, t0 + RESTART_SILENCE_NS
            xb = _shifted_phase(x, i, BLOCK)
        block = Block("d", seq, t0, float(FS), xb)
        _idle(pipeline, sink, t0)
        sink.now_ns = t0 + round((xb.size - 1) * 1e9 / FS)
        pipeline.process("sinewatch/in/d", encode_block_binary(block), "", t0)
    if sink.errors:
        raise RuntimeError(f"{name} on {event}: {sink.errors[0]['message']}")
    rows = []
    wait = []
    for e in sink.estimates:
        wait.append((e["published_ns"] - e["timestamp_ns"]) / 1e9)
        f = e["frequency_hz"][0]
        diag = e["diagnostics"]
        t_ns = e["timestamp_ns"] - T00
        if restart_at is not None and t_ns >= RESTART_SILENCE_NS:
            t_ns -= RESTART_SILENCE_NS  # on the signal's own time axis
        sd = (e.get("std") or {}).get("frequency_hz") or [None]
        rows.append(
            (
                t_ns / 1e9,
                math.inf if f is None else f,
                diag["valid"],
                diag["converged"],
                math.nan if sd[0] is None else float(sd[0]),
            )
        )
    ch = pipeline.channels["d"]
    return Run(name, event, truth, ch.estimator.memory_samples / FS, rows, wait, ch.valid_memory_samples / FS)


def _idle(pipeline: Pipeline, sink: _Keep, t0_ns: int) -> None:
    """What the daemon's idle release does in a silence before the block at ``t0_ns`` (log
    time is data time here): the held estimates go out ``idle_release_s`` after the last block."""
    idle_ns = round(pipeline.config.idle_release_s * 1e9)
    last = max((ch.last_log_ns for ch in pipeline.channels.values()), default=t0_ns)
    if t0_ns - last >= idle_ns:
        sink.now_ns = last + (BLOCK - 1) * round(1e9 / FS) + idle_ns
        pipeline.release_idle(last + idle_ns)


def _shifted_phase(x: np.ndarray, i: int, n: int) -> np.ndarray:
    """``x[i:i+n]`` turned by RESTART_PHASE_RAD (its analytic signal rotated): the same tone
    resumed at another phase, as a sensor that was off for a while sees it."""
    from scipy.signal import hilbert

    z = hilbert(x)[i : i + n]
    out: np.ndarray = np.real(z * np.exp(1j * RESTART_PHASE_RAD))
    return out


def _fmt(v: float, unit: str = "") -> str:
    if math.isnan(v):
        return "-"
    if math.isinf(v):
        return "undefined"
    return f"{v:.3g}{unit}"


def table(events: tuple[str, ...] = ABSENCES) -> str:
    """Markdown: per estimator, the worst over ``events``."""
    lines = [
        "| estimator | memory | valid / converged estimates during the event | worst error during it, unflagged | "
        "worst error of a valid estimate | of a converged one | valid again after | converged within 0.05 Hz after |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name in applicable():
        s = [run(name, ev).summary() for ev in events]
        lines.append(
            f"| `{name}` | {s[0]['memory_s'] * 1e3:.1f} ms | {max(x['valid_during'] for x in s)} / "
            f"{max(x['converged_during'] for x in s)} | {_fmt(max(x['worst_unflagged_during_hz'] for x in s), ' Hz')} | "
            f"{_fmt(max(x['worst_valid_hz'] for x in s), ' Hz')} | {_fmt(max(x['worst_converged_hz'] for x in s), ' Hz')} | "
            f"+{max(x['valid_again_s'] for x in s) * 1e3:.0f} ms | +{max(x['settled_s'] for x in s) * 1e3:.0f} ms |"
        )
    return "\n".join(lines)


def _event_row(r: Run, ev: str) -> list[str]:
    """One event's cells: valid estimates during, the worst error of a valid one during and
    after, that error over its target, valid again after, the worst wait to publication."""
    t_on, t_end = (RESTART_S, RESTART_S) if ev == "gateway-restart" else (T_ON, T_OFF)
    during = [x for x in r.between(t_on, t_end) if x[2]]
    # the restart's signal is turned by a Hilbert transform, whose last ~50 ms are not a tone
    after = r.between(t_end, DURATION_S - 0.05 if ev == "gateway-restart" else math.inf)
    valid_after = [x for x in after if x[2]]
    back = next((x[0] for x in after if x[2]), math.nan) - t_end
    return [
        str(len(during)),
        _fmt(max((r.error(x[1]) for x in during), default=math.nan), " Hz"),
        _fmt(max((r.error(x[1]) for x in valid_after), default=math.nan), " Hz"),
        _fmt(r.worst_ratio(during + valid_after)),
        "-" if math.isnan(back) else f"+{back * 1e3:.0f} ms",
        f"{np.median(r.wait_s) * 1e3:.0f} / {max(r.wait_s) * 1e3:.0f} ms",
    ]


def event_table(events: tuple[str, ...] = TABLE_EVENTS, versions: tuple[int, ...] = (4, VALIDITY_RULES_VERSION)) -> str:
    """Markdown: one row per estimator and event: the worst frequency error of an estimate
    flagged valid during the event and after it, that error over its target (3 reported sd,
    or 0.05 Hz where none is reported; the worst ratio, so <= 1 is within target), how soon
    after the event's end an estimate is valid again (a restart: after the blocks resume),
    and the longest an estimate waited to be published (data time from its timestamp to the
    last sample of the input that published it). "During" starts at the event's first
    sample: an estimate whose window holds the onset is counted there. Each cell gives every
    rules version of ``versions`` in turn ("a -> b"), each with its defaults."""
    lines = [
        "| estimator | event | valid estimates during | worst error of a valid one during | "
        "worst error of a valid one after | worst error / target | valid again after | published after its time, median / worst |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name in applicable():
        for ev in events:
            cells = [_event_row(run(name, ev, v), ev) for v in versions]
            joined = [" -> ".join(c) for c in zip(*cells, strict=True)]
            lines.append(f"| `{name}` | {ev} | " + " | ".join(joined) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m sinewatch.apps.bench.validity", description=__doc__.split("\n\n")[0])
    p.add_argument("--events", nargs="+", choices=EVENTS, default=list(TABLE_EVENTS))
    p.add_argument("--summary", action="store_true", help="the worst over the events per estimator (the older table)")
    p.add_argument(
        "--rules-versions",
        type=int,
        nargs="+",
        choices=(2, 3, 4, VALIDITY_RULES_VERSION),
        default=[4, VALIDITY_RULES_VERSION],
        help="the pipeline's validity rules compared, each with its defaults (4: held back, no edges, one "
        "memory; 3: estimates published as soon as made; 2: without the hysteresis either; default: 4 and 5)",
    )
    args = p.parse_args(argv)
    print(table(tuple(args.events)) if args.summary else event_table(tuple(args.events), tuple(args.rules_versions)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
