"""What an accuracy run works on: which scenarios and estimators it selects, and each
scenario's :class:`Profile` (the bench's view of the scenario library's one description);
also ``sinewatch bench scenarios``, the listing.

A profile is read from the scenario (:attr:`sinewatch.scenarios.Scenario.bench`: declared
by the library's scenarios, derived from the truth for the demo feeds), with its steady
windows and events clipped to the scenario's duration (a ``duration_s`` override may
shorten it).
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import sys
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from sinewatch import estimators as est_registry
from sinewatch import scenarios as sc_registry
from sinewatch.apps.console import make_console, print_table
from sinewatch.scenarios import Event, Scenario
from sinewatch.schemas.errors import ParameterError


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
    events: tuple[Event, ...]
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

    def event_stop(self, ev: Event) -> float:
        """End of the interval that judges the response to ``ev``: the end of the first
        steady window after it, or the next event, or the end of the scenario."""
        later = [w[1] for w in self.steady_windows if w[0] >= ev.time_s]
        nxt = [e.time_s for e in self.events if e.time_s > ev.time_s]
        return min(later[:1] + nxt[:1] + [self.duration_s])

    def settle_by(self, ev: Event) -> float:
        """A response counts only if it has settled when the next steady window starts."""
        later = [w[0] for w in self.steady_windows if w[0] >= ev.time_s]
        return later[0] if later else self.event_stop(ev)


def profile(sc: Scenario) -> Profile:
    """The scenario's bench profile (see the module docstring)."""
    n = sc.n_samples
    dur = n / sc.sample_rate_hz
    info = sc.bench
    windows = tuple((max(0.0, a), min(b, dur)) for a, b in info.steady_windows if a < dur)
    windows = tuple(w for w in windows if w[1] > w[0]) or ((0.5 * dur, dur),)
    lo, hi = info.frequency_range_hz
    return Profile(
        name=sc.name,
        sample_rate_hz=sc.sample_rate_hz,
        n_samples=n,
        n_components=len(info.nominal_frequency_hz),
        n_inputs=sc.n_inputs,
        nominal_frequency_hz=tuple(float(f) for f in info.nominal_frequency_hz),
        frequency_range_hz=(lo, hi),
        steady_windows=windows,
        events=tuple(e for e in info.events if e.time_s < dur),
        tolerance_hz=float(info.tolerance_hz),
        reporting_rate_hz=info.reporting_rate_hz,
        limits=dict(info.limits),
        noise_free=sc.noise_free,
        crlb=info.crlb and sc.is_stationary,
        noise_std=sc.noise_std,
        tags=tuple(sc.tags),
        reference=dict(info.reference),
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


def _matching(kind: str, available: list[str], patterns: Iterable[str], tags: dict[str, set[str]] | None) -> list[str]:
    """Names of ``available`` matching ``patterns`` (names or globs; with ``tags``, also
    tags), each once, in the order the patterns found them."""
    chosen: list[str] = []
    for p in patterns:
        is_tag = p.startswith("tag:") or (p not in available and not any(ch in p for ch in "*?["))
        if tags is not None and is_tag:
            tag = p.removeprefix("tag:")
            hits = [nm for nm in available if tag in tags[nm]]
        else:
            hits = fnmatch.filter(available, p)
        if not hits:
            expected = f"a name, glob or tag matching {available[:3]}..." if tags is not None else f"one of {available}"
            raise ParameterError(f"{kind}: expected {expected}, got {p!r}")
        chosen.extend(h for h in hits if h not in chosen)
    return chosen


def select_scenarios(patterns: Iterable[str] | None, quick: bool = False) -> list[str]:
    """Scenario names from patterns: exact names, shell globs (``c37-50hz-*``), or tags
    (``c37.118``, ``tag:paper``). None: all scenarios (the "quick" tag with ``quick``)."""
    names = sc_registry.names()
    pats = list(patterns or [])
    if not pats:
        if not quick:
            return names
        pats = ["tag:quick"]
    tags = {nm: set(sc_registry.get(nm).tags) for nm in names}
    return _matching("scenarios", names, pats, tags)


#: The bench column of the daemon's default rule (its estimator at its parameters, as a user
#: with no config gets it; :func:`sinewatch.apps.bench.params.bench_estimator`).
DEFAULT_RULE = "default-rule"


def select_estimators(patterns: Iterable[str] | None) -> list[str]:
    """Estimator names from names or globs; None: every registered estimator and
    :data:`DEFAULT_RULE`."""
    avail = [*est_registry.available(), DEFAULT_RULE]
    pats = list(patterns or [])
    return _matching("estimators", avail, pats, None) if pats else avail


def listed_scenarios(patterns: list[str] | None) -> list[dict[str, Any]]:
    """Every scenario ``sinewatch feed --scenario`` accepts that the patterns select (all
    with none): the library's, then the power-quality ones (IEC 61000-4-7/-4-30 signals)."""
    from sinewatch.scenarios.power_quality_iec import get_pq, pq_names

    pq = pq_names()
    pq_tags = {nm: set(get_pq(nm).tags) for nm in pq}
    library = sc_registry.names()
    lib_tags = {nm: set(sc_registry.get(nm).tags) for nm in library}
    names, tags = [*library, *pq], {**lib_tags, **pq_tags}
    chosen = _matching("scenarios", names, list(patterns), tags) if patterns else names
    return [(get_pq(nm) if nm in pq_tags else sc_registry.get(nm)).describe() for nm in chosen]


def run(args: argparse.Namespace) -> int:
    """``sinewatch bench scenarios [NAME|GLOB|TAG ...] [--json]``."""
    try:
        rows = listed_scenarios(args.patterns or None)
    except ParameterError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
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
    print_table(make_console(), table)
    return 0
