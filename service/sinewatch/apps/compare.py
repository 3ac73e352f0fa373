"""``sinewatch compare A.mcap B.mcap``: two recordings of the same inputs side by side.

Typically the original and a re-run (``replay --estimator X --out B.mcap``), or two
settings of one estimator. Estimates are paired by channel and ``timestamp_ns`` (the
time they are at: the block's last sample, or the report's grid time); for each channel
and parameter (``frequency_hz[k]``, ``amplitude[k]``, ``phase_rad[k]``, ``offset``,
``rocof_hz_per_s[k]``) the difference ``B - A`` (phases wrapped to (-pi, pi]) gives

* ``rms`` and ``worst`` (largest absolute difference, and where): over the pairs where
  both are defined (JSON null is undefined);
* ``first_divergence``: the first pair, in time, whose difference exceeds the
  parameter's tolerance, or where one is defined and the other is not;
* per recording, how many estimates it has in the window and how many were
  ``diagnostics.valid`` and ``converged``; the estimates only one of them has.

Where is said as the estimate's ``seq``, ``timestamp_ns`` and its log time after the
start of recording A (``+S s``: what ``--start`` takes, to replay or plot around it).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from sinewatch.core.window import ChannelFilter, Window, WindowError
from sinewatch.runtime.replay import check_recording, read_window
from sinewatch.schemas.errors import ConfigError

PARAMETERS = ("frequency_hz", "amplitude", "phase_rad", "offset", "rocof_hz_per_s")
DEFAULT_TOLERANCES = {"frequency_hz": 0.01, "amplitude": 0.01, "phase_rad": 0.01, "offset": 0.01, "rocof_hz_per_s": 0.1}


@dataclass
class _Estimate:
    seq: int
    log_time_ns: int
    estimator: str
    values: dict[str, list[float | None]]  # parameter -> per component (offset: one)
    valid: bool | None
    converged: bool


@dataclass
class Where:
    seq: int
    timestamp_ns: int
    at_s: float  # log time after recording A's start

    def text(self) -> str:
        return f"+{self.at_s:.3f} s (seq {self.seq})"


@dataclass
class ParameterDiff:
    parameter: str  # e.g. "frequency_hz[0]", "offset"
    tolerance: float
    compared: int = 0  # pairs where both are defined
    one_defined: int = 0  # pairs where only one is
    rms: float | None = None
    worst: float | None = None  # the largest |B - A|
    worst_at: Where | None = None
    first_divergence: Where | None = None
    reported_by: str = "both"  # "A", "B": the other recording's estimator never gives it (not a divergence)
    _sum_sq: float = field(default=0.0, repr=False)
    _first_beyond: Where | None = field(default=None, repr=False)
    _first_one_sided: Where | None = field(default=None, repr=False)
    _defined: list[int] = field(default_factory=lambda: [0, 0], repr=False)  # in A, in B


@dataclass
class RecordingCounts:
    estimator: str = ""
    estimates: int = 0
    valid: int = 0
    converged: int = 0
    only_here: int = 0  # estimates the other recording has no pair for


@dataclass
class ChannelComparison:
    channel: str
    paired: int
    a: RecordingCounts
    b: RecordingCounts
    parameters: list[ParameterDiff]

    @property
    def identical(self) -> bool:
        return (
            self.a.only_here == 0
            and self.b.only_here == 0
            and all(p.one_defined == 0 and not p.worst for p in self.parameters if p.reported_by == "both")
        )


@dataclass
class Comparison:
    a: Path
    b: Path
    window: str
    channels: list[ChannelComparison]

    def to_json(self) -> dict[str, Any]:
        def clean(d: Any) -> Any:
            if isinstance(d, dict):
                return {k: clean(v) for k, v in d.items() if not k.startswith("_")}
            if isinstance(d, list):
                return [clean(v) for v in d]
            if isinstance(d, Path):
                return str(d)
            return d

        out: dict[str, Any] = clean(asdict(self))
        for ch, c in zip(out["channels"], self.channels, strict=True):
            ch["identical"] = c.identical
        return out


def read_estimates(
    path: Path, window: Window, channels: ChannelFilter
) -> tuple[dict[str, dict[int, _Estimate]], int | None]:
    """The estimates of ``path`` in the window on the selected channels, by channel and
    ``timestamp_ns``; and the recording's first log time."""
    check_recording(path)
    out: dict[str, dict[int, _Estimate]] = {}
    for kind, item in read_window(path, window):
        if kind != "message" or item.role != "estimate":
            continue
        msg = json.loads(item.payload)
        if not channels.matches(msg["channel"]):
            continue
        d = msg["diagnostics"]
        values = {p: list(msg.get(p) or []) for p in PARAMETERS if p != "offset"}
        values["offset"] = [msg.get("offset")]
        out.setdefault(msg["channel"], {})[int(msg["timestamp_ns"])] = _Estimate(
            int(msg["seq"]), item.log_time_ns, msg["estimator"], values, d.get("valid"), bool(d["converged"])
        )
    return out, window.origin_ns


def _counts(estimates: dict[int, _Estimate], other: dict[int, _Estimate]) -> RecordingCounts:
    first = next(iter(estimates.values()), None)
    return RecordingCounts(
        estimator=first.estimator if first is not None else "",
        estimates=len(estimates),
        valid=sum(1 for e in estimates.values() if e.valid),
        converged=sum(1 for e in estimates.values() if e.converged),
        only_here=sum(1 for t in estimates if t not in other),
    )


def _difference(parameter: str, a: float, b: float) -> float:
    d = b - a
    return math.remainder(d, 2 * math.pi) if parameter == "phase_rad" else d


def compare_channel(
    channel: str, a: dict[int, _Estimate], b: dict[int, _Estimate], tolerances: dict[str, float], origin_ns: int
) -> ChannelComparison:
    """One channel's comparison (module docstring)."""
    times = sorted(set(a) & set(b))
    diffs: dict[str, ParameterDiff] = {}
    for t in times:
        ea, eb = a[t], b[t]
        where = Where(ea.seq, t, (ea.log_time_ns - origin_ns) / 1e9)
        for p in PARAMETERS:
            va, vb = ea.values[p], eb.values[p]
            for k in range(max(len(va), len(vb))):
                name = p if p == "offset" else f"{p}[{k}]"
                d = diffs.get(name)
                if d is None:
                    d = diffs[name] = ParameterDiff(name, tolerances[p])
                x = va[k] if k < len(va) else None
                y = vb[k] if k < len(vb) else None
                d._defined[0] += x is not None
                d._defined[1] += y is not None
                if x is None and y is None:
                    continue
                if x is None or y is None:
                    d.one_defined += 1
                    d._first_one_sided = d._first_one_sided or where
                    continue
                delta = abs(_difference(p, x, y))
                d.compared += 1
                d._sum_sq += delta * delta
                if d.worst is None or delta > d.worst:
                    d.worst, d.worst_at = delta, where
                if delta > d.tolerance and d._first_beyond is None:
                    d._first_beyond = where
    for d in diffs.values():
        d.rms = math.sqrt(d._sum_sq / d.compared) if d.compared else None
        if not d._defined[0] or not d._defined[1]:  # one estimator does not report it at all
            d.reported_by = "B" if d._defined[1] else "A" if d._defined[0] else "neither"
            d.first_divergence = d._first_beyond
        else:
            firsts = [w for w in (d._first_beyond, d._first_one_sided) if w is not None]
            d.first_divergence = min(firsts, key=lambda w: w.timestamp_ns) if firsts else None
    return ChannelComparison(channel, len(times), _counts(a, b), _counts(b, a), list(diffs.values()))


def compare(
    a: Path,
    b: Path,
    *,
    window: Window | None = None,
    channels: ChannelFilter | None = None,
    tolerances: dict[str, float] | None = None,
) -> Comparison:
    """Compare the estimates of recordings ``a`` and ``b`` (module docstring); a relative
    window is resolved against A's start, for both."""
    tol = dict(DEFAULT_TOLERANCES)
    for name, value in (tolerances or {}).items():
        if name not in tol:
            raise ConfigError(f"--tolerance: expected one of {', '.join(PARAMETERS)}, got {name!r}")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
            raise ConfigError(f"--tolerance {name}: expected a number >= 0, got {value!r}")
        tol[name] = float(value)
    window = window or Window()
    channels = channels or ChannelFilter()
    est_a, origin = read_estimates(a, Window(window.start, window.end), channels)
    window_b = Window(window.start, window.end)
    if origin is not None:  # relative times are A's: B may start later (a re-run of some channels)
        window_b.anchor(origin)
    est_b, _ = read_estimates(b, window_b, channels)
    if not est_a and not est_b:
        raise WindowError(
            f"{a}, {b}: expected estimates in the window ({window.describe()}) on the channels "
            f"selected ({channels.describe()}), got none"
        )
    names = sorted(set(est_a) | set(est_b))
    result = [compare_channel(n, est_a.get(n, {}), est_b.get(n, {}), tol, origin or 0) for n in names]
    described = Window(window.start, window.end)
    described.anchor(origin or 0)
    return Comparison(a, b, described.describe(), result)


# ---- the command -----------------------------------------------------------------------------
def _g(v: float | None) -> str:
    return "-" if v is None else f"{v:.3g}"


def _pct(k: int, n: int) -> str:
    return f"{100.0 * k / n:.1f} %" if n else "-"


def format_comparison(c: Comparison) -> list[str]:
    """The comparison as text: a header per channel, a line per parameter."""
    lines = [f"A: {c.a}", f"B: {c.b}", f"window: {c.window}; B - A, phases wrapped"]
    for ch in c.channels:
        lines.append("")
        lines.append(
            f"{ch.channel}: {ch.paired} paired estimates"
            + (f" ({ch.a.only_here} only in A, {ch.b.only_here} only in B)" if ch.a.only_here or ch.b.only_here else "")
            + (" - identical" if ch.identical else "")
        )
        for tag, n in (("A", ch.a), ("B", ch.b)):
            lines.append(
                f"  {tag} {n.estimator or '-'}: {n.estimates} estimates, valid {_pct(n.valid, n.estimates)}, "
                f"converged {_pct(n.converged, n.estimates)}"
            )
        lines.append(f"  {'parameter':<18} {'n':>6} {'RMS':>10} {'worst':>10} {'at':>22} {'first > tol':>30}")
        for p in ch.parameters:
            first = "-" if p.first_divergence is None else p.first_divergence.text()
            worst_at = "-" if p.worst_at is None else p.worst_at.text()
            undefined = (
                f" (only {p.reported_by} reports it)"
                if p.reported_by != "both"
                else f" ({p.one_defined} defined in one only)"
                if p.one_defined
                else ""
            )
            lines.append(
                f"  {p.parameter:<18} {p.compared:>6} {_g(p.rms):>10} {_g(p.worst):>10} {worst_at:>22} "
                f"{first + f' [tol {p.tolerance:g}]':>30}{undefined}"
            )
    return lines


def run_compare(args: Any) -> int:
    """``sinewatch compare A B [--start --end --channels --tolerance --json]``: exit 0."""
    result = compare(
        Path(args.a),
        Path(args.b),
        window=Window.parse(args.start, args.end),
        channels=ChannelFilter.of(args.channels),
        tolerances=dict(args.tolerance),
    )
    if args.json:
        print(json.dumps(result.to_json(), indent=2))
    else:
        print("\n".join(format_comparison(result)))
    return 0


__all__ = ["Comparison", "compare", "format_comparison", "run_compare"]
