"""Power-quality scenario families with exact truth for IEC 61000-4-7 (harmonics, class I)
and IEC 61000-4-30 (unbalance, class A): three-phase unbalance and harmonic content,
at nominal and off-nominal fundamental.

These scenarios are **not** in the global scenario registry (``scenarios.names()``): a
three-phase scenario has one column per phase, which the single-channel accuracy bench
would read as known inputs. They have their own registry here (:func:`pq_names`,
:func:`get_pq`) until the bench scores power-quality reports.

Every scenario carries ``pq_truth`` (:class:`PqTruth`): the fundamental frequency, the
RMS of every harmonic order 0..50 of each phase, THD (orders 2..40), and the sequence phasors (complex
RMS, sine convention at t = 0), u2 and u0. The signals are stationary, so the truth holds
at every window. The limits (:data:`LIMITS`) are those of IEC 61000-4-7 class I and
IEC 61000-4-30 class A as recalled here: check the standards before quoting compliance.

Families (``f0`` = 50 or 60 Hz; ``df`` in percent of nominal: m5 = -5 %, p5 = +5 %):

* ``pq-unbalance-{50,60}hz-u2-{0.5,1,2,5}pct[-m5|-p5]``: V1 = 1 per unit (RMS), a negative
  sequence of u2 and a zero sequence of u2 / 2, no harmonics;
* ``pq-unbalance-{50,60}hz-u2-2pct-harmonics[-m5|-p5]``: the same at u2 = 2 % with the 5th
  (5 %), 7th (3 %), 11th (2 %) and 3rd (1 %) harmonics in every phase;
* ``pq-harmonics-{50,60}hz-all[-m5|-p5]``: one phase, every harmonic 2..50 at a level drawn
  (seeded) uniformly in 1-10 % of the fundamental, random phases;
* ``pq-harmonics-{50,60}hz-low[-m5|-p5]``: every harmonic 2..50 at 0.1-0.9 % (the range
  where the limit is 0.05 % of nominal);
* ``pq-harmonic-{50,60}hz-single`` (factory arguments ``harmonic`` 2..50, ``level``,
  ``df_pct``): one harmonic alone;
* ``pq-interharmonics-{50,60}hz-{1,3,5}pct[-m5|-p5]``: one phase, the 3rd, 5th, 7th and
  11th harmonics and three interharmonics at the level (2.5 f, 13 + 2/N f, 49.5 f);
* ``pq-unbalance-{50,60}hz-u2-2pct-interharmonic-5pct[-m5|-p5]``: u2 = 2 % with a 5 %
  interharmonic at 2.5 f in every phase;
* ``pq-interharmonic-{50,60}hz-single`` (factory arguments ``ratio``, ``level``, ``phase``,
  ``df_pct``): one interharmonic alone.

Interharmonics lie on the bins of the N-cycle window (their frequency a multiple of f/N,
following the fundamental), so that their groups have an exact truth
(:func:`grouped_truth`); one between bins spreads over its neighbours in any
IEC 61000-4-7 instrument, and its groups are then a property of the method, not of the
signal.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sinewatch.power_quality.limits import LIMITS, class_i_limit
from sinewatch.power_quality.sequence import phases_from_sequence, symmetrical_components
from sinewatch.scenarios.base import NoiseOnEveryColumn, Scenario, ScenarioStream, Truth, wrap_phase
from sinewatch.schemas.errors import ParameterError

MAX_ORDER = 50
SAMPLE_RATE_HZ = 10_000.0


@dataclass(frozen=True)
class PqTruth:
    frequency_hz: float
    nominal_frequency_hz: float
    harmonic_rms: np.ndarray  # (P, 51): RMS of order 0..50 per phase
    thd: np.ndarray  # (P,) over orders 2..40 (IEC 61000-4-7)
    sequence_rms: tuple[complex, complex, complex] | None  # (V0, V1, V2), complex RMS
    u2: float | None
    u0: float | None
    groups: dict[str, np.ndarray] = field(default_factory=dict)  # see :func:`grouped_truth`


def n_cycles(nominal_frequency_hz: float) -> int:
    """N of the IEC 61000-4-7 window: 10 cycles at 50 Hz, 12 at 60 Hz."""
    return 10 if nominal_frequency_hz == 50.0 else 12


def grouped_truth(
    harmonic_rms: np.ndarray, interharmonics: tuple[tuple[float, float, float], ...], n: int
) -> dict[str, np.ndarray]:
    """The exact IEC 61000-4-7 groupings of a stationary signal whose components all lie on
    the N-cycle window's bins (harmonic h at bin hN, an interharmonic of ratio r at bin rN),
    per phase (P, 51), written from the standard's definitions component by component:

    * harmonic subgroup of order m: the components within one bin of mN;
    * harmonic group of order m: those within N/2 bins of mN, half the power of one
      exactly N/2 away;
    * interharmonic group n: those strictly between bins nN and (n+1)N;
    * interharmonic centred subgroup n: those strictly between nN + 1 and (n+1)N - 1;

    and THD, THDG, THDS over orders 2..40 (P,). Every interharmonic is in every phase
    at its level."""
    p = harmonic_rms.shape[0]
    comps = [(h * n, harmonic_rms[:, h] ** 2) for h in range(1, MAX_ORDER + 1)]
    comps += [(round(r * n), np.full(p, c * c)) for r, c, _ in interharmonics]
    out = {k: np.zeros((p, MAX_ORDER + 1)) for k in ("subgroup", "group", "ig", "isg")}
    for b, power in comps:
        for m in range(1, MAX_ORDER + 1):
            d = abs(b - m * n)
            if d <= 1:
                out["subgroup"][:, m] += power
            if 2 * d < n:
                out["group"][:, m] += power
            elif 2 * d == n:
                out["group"][:, m] += 0.5 * power
        if b % n:
            k = b // n
            out["ig"][:, k] += power
            if 1 < b - k * n < n - 1:
                out["isg"][:, k] += power
    res = {f"{k}_rms": np.sqrt(v) for k, v in out.items()}
    for name, key in (("thdg", "group_rms"), ("thds", "subgroup_rms")):
        g = res[key]
        res[name] = np.sqrt(np.sum(g[:, 2:41] ** 2, axis=1)) / g[:, 1]
    return res


class PqScenario(Scenario):
    """Stationary P-phase signal: phase p is ``sum_h sqrt(2) C_{p,h} sin(2 pi h f t + phi_{p,h})``.

    ``harmonic_rms`` and ``harmonic_phase`` are (P, 51) arrays (order 0 is a DC value,
    its phase ignored). ``sample(t)`` is (n,) for one phase, (n, P) otherwise; the noise
    (``noise_std``) is added to every phase, seeded.
    """

    def __init__(
        self,
        name: str,
        summary: str,
        frequency_hz: float,
        nominal_frequency_hz: float,
        harmonic_rms: np.ndarray,
        harmonic_phase: np.ndarray,
        tags: tuple[str, ...] = (),
        interharmonics: tuple[tuple[float, float, float], ...] = (),
        **kwargs: Any,
    ) -> None:
        kwargs.setdefault("sample_rate_hz", SAMPLE_RATE_HZ)
        kwargs.setdefault("duration_s", 2.0)
        super().__init__(**kwargs)
        self.name = name  # the instance attribute shadows the ClassVar on purpose
        self.summary = summary
        self.tags = tags
        self.frequency_hz = float(frequency_hz)
        self.nominal_frequency_hz = float(nominal_frequency_hz)
        self.harmonic_rms = np.atleast_2d(np.asarray(harmonic_rms, dtype=np.float64))
        self.harmonic_phase = np.atleast_2d(np.asarray(harmonic_phase, dtype=np.float64))
        if self.harmonic_rms.shape != self.harmonic_phase.shape or self.harmonic_rms.shape[1] != MAX_ORDER + 1:
            raise ParameterError(f"harmonics: expected two (P, {MAX_ORDER + 1}) arrays, got {self.harmonic_rms.shape}")
        n = n_cycles(self.nominal_frequency_hz)
        for ratio, _, _ in interharmonics:
            if not (1.0 < ratio < MAX_ORDER + 1) or abs(ratio * n - round(ratio * n)) > 1e-9 or ratio == round(ratio):
                raise ParameterError(
                    f"interharmonic: expected a frequency ratio k / {n} between 1 and {MAX_ORDER + 1}, not whole "
                    f"(on the {n}-cycle window's bins, where its groups are exact), got {ratio}"
                )
        self.interharmonics = tuple((float(r), float(c), float(ph)) for r, c, ph in interharmonics)

    @property
    def n_phases(self) -> int:
        return int(self.harmonic_rms.shape[0])

    def interharmonic_phase(self, phase: int, phase_rad: float) -> float:
        """An interharmonic's phase in phase ``phase`` of the scenario (three phases: the
        given phase shifted by -2 pi p / 3, a positive-sequence set)."""
        return phase_rad - 2.0 * np.pi * phase / 3.0 if self.n_phases == 3 else phase_rad

    @property
    def pq_truth(self) -> PqTruth:
        c = self.harmonic_rms
        thd = np.sqrt(np.sum(c[:, 2:41] ** 2, axis=1)) / c[:, 1]
        seq: tuple[complex, complex, complex] | None = None
        u2 = u0 = None
        if self.n_phases == 3:
            z = c[:, 1] * np.exp(1j * self.harmonic_phase[:, 1])
            sc = symmetrical_components(z[0], z[1], z[2])
            seq = (complex(sc.zero), complex(sc.positive), complex(sc.negative))
            u2, u0 = float(sc.u2), float(sc.u0)
        groups = grouped_truth(c, self.interharmonics, n_cycles(self.nominal_frequency_hz))
        return PqTruth(self.frequency_hz, self.nominal_frequency_hz, c.copy(), thd, seq, u2, u0, groups)

    def clean(self, t: np.ndarray) -> tuple[np.ndarray, Truth]:
        h = np.arange(MAX_ORDER + 1)
        y = np.empty((t.shape[0], self.n_phases))
        for p in range(self.n_phases):
            c = self.harmonic_rms[p]
            dc = c[0]
            orders = h[1:][c[1:] != 0.0]
            arg = 2.0 * np.pi * self.frequency_hz * np.outer(t, orders) + self.harmonic_phase[p, orders]
            y[:, p] = dc + math.sqrt(2.0) * np.sin(arg) @ c[orders]
            for ratio, rms, ph in self.interharmonics:
                w = 2.0 * np.pi * ratio * self.frequency_hz
                y[:, p] += math.sqrt(2.0) * rms * np.sin(w * t + self.interharmonic_phase(p, ph))
        phase_a = 2.0 * np.pi * self.frequency_hz * t + self.harmonic_phase[0, 1]
        n = t.shape[0]
        truth = Truth(
            np.full((n, 1), self.frequency_hz),
            np.full((n, 1), math.sqrt(2.0) * self.harmonic_rms[0, 1]),
            wrap_phase(phase_a)[:, None],
            np.full(n, self.harmonic_rms[0, 0]),
            np.zeros((n, 1)),
        )
        return (y[:, 0] if self.n_phases == 1 else y), truth

    def stream(self, seed: int = 0) -> ScenarioStream:
        return NoiseOnEveryColumn(self, seed)  # noise on every phase

    def describe(self) -> dict[str, Any]:
        d = super().describe()
        d.update(frequency_hz=self.frequency_hz, nominal_frequency_hz=self.nominal_frequency_hz, n_phases=self.n_phases)
        if self.interharmonics:
            d["interharmonics"] = [{"ratio": r, "rms": c, "phase_rad": ph} for r, c, ph in self.interharmonics]
        return d


def _balanced_harmonics(
    v_phasors: tuple[complex, complex, complex], harmonics: dict[int, float] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Three phases with fundamental phasors ``v_phasors`` (complex RMS) and each harmonic h
    at ``level`` x |V_p| with phase ``h x angle(V_p) + 0.3 h`` (a distorted set rotating with
    the fundamental: h = 3k zero, 3k+1 positive, 3k+2 negative sequence)."""
    rms = np.zeros((3, MAX_ORDER + 1))
    ph = np.zeros((3, MAX_ORDER + 1))
    for p, z in enumerate(v_phasors):
        rms[p, 1] = abs(z)
        ph[p, 1] = float(np.angle(z))
        for h, level in (harmonics or {}).items():
            rms[p, h] = level * abs(z)
            ph[p, h] = float(wrap_phase(np.array(h * np.angle(z) + 0.3 * h)))
    return rms, ph


def unbalance(
    f0: float = 50.0,
    u2: float = 0.02,
    df_pct: float = 0.0,
    harmonics: dict[int, float] | None = None,
    interharmonic: float = 0.0,
    **kw: Any,
) -> PqScenario:
    """V1 = 1 (RMS, angle 0.2 rad), V2 = u2 at angle 1.1 rad, V0 = u2/2 at angle -0.7 rad;
    ``interharmonic`` > 0: an interharmonic at 2.5 f of that level in every phase."""
    v1 = complex(np.exp(0.2j))
    v2 = u2 * complex(np.exp(1.1j))
    v0 = 0.5 * u2 * complex(np.exp(-0.7j))
    va, vb, vc = phases_from_sequence(v0, v1, v2)
    rms, ph = _balanced_harmonics((complex(va), complex(vb), complex(vc)), harmonics)
    label = f"u2 {100 * u2:g} %" + (" with harmonics" if harmonics else "") + (f", f {df_pct:+g} %" if df_pct else "")
    if interharmonic:
        label += f", interharmonic 2.5 f at {100 * interharmonic:g} %"
        kw["interharmonics"] = ((2.5, interharmonic, 0.9),)
    return PqScenario(
        kw.pop("name", f"pq-unbalance-{int(f0)}hz"),
        f"three-phase unbalance {label} (IEC 61000-4-30 class A)",
        f0 * (1.0 + df_pct / 100.0),
        f0,
        rms,
        ph,
        tags=("power-quality", "iec61000-4-30", "unbalance", "three-phase", f"{int(f0)}hz"),
        **kw,
    )


def harmonics_family(
    f0: float = 50.0, low: float = 0.01, high: float = 0.10, df_pct: float = 0.0, seed: int = 15, **kw: Any
) -> PqScenario:
    """One phase: fundamental 1 (RMS), every harmonic 2..50 at a seeded level in
    [low, high] x fundamental, seeded phases, a DC of 0 ."""
    rng = np.random.default_rng(seed)
    rms = np.zeros((1, MAX_ORDER + 1))
    rms[0, 1] = 1.0
    rms[0, 2:] = rng.uniform(low, high, MAX_ORDER - 1)
    ph = rng.uniform(-np.pi, np.pi, (1, MAX_ORDER + 1))
    return _one_phase(
        f"pq-harmonics-{int(f0)}hz", f"harmonics 2..50 at {100 * low:g}-{100 * high:g} %", f0, df_pct, rms, ph, kw
    )


def single_harmonic(
    f0: float = 50.0, harmonic: int = 5, level: float = 0.1, df_pct: float = 0.0, **kw: Any
) -> PqScenario:
    if not 2 <= harmonic <= MAX_ORDER:
        raise ParameterError(f"harmonic: expected 2..{MAX_ORDER}, got {harmonic}")
    rms = np.zeros((1, MAX_ORDER + 1))
    ph = np.zeros((1, MAX_ORDER + 1))
    rms[0, 1], ph[0, 1] = 1.0, 0.4
    rms[0, harmonic], ph[0, harmonic] = level, 1.0
    return _one_phase(
        f"pq-harmonic-{int(f0)}hz-single", f"harmonic {harmonic} at {100 * level:g} %", f0, df_pct, rms, ph, kw
    )


def interharmonic_positions(f0: float) -> tuple[float, ...]:
    """Where :func:`interharmonics_family` puts its interharmonics (ratios to the
    fundamental, on the window's bins): the middle of interharmonic group 2 (2.5 f), the
    first bin of centred subgroup 13 (13 + 2/N), the middle of group 49 (49.5 f)."""
    return (2.5, 13.0 + 2.0 / n_cycles(f0), 49.5)


def interharmonics_family(f0: float = 50.0, level: float = 0.05, df_pct: float = 0.0, **kw: Any) -> PqScenario:
    """One phase: fundamental 1 (RMS), the 5th (5 %), 7th (3 %), 11th (2 %) and 3rd (1 %)
    harmonics, and interharmonics at :func:`interharmonic_positions` each at ``level``."""
    rms = np.zeros((1, MAX_ORDER + 1))
    ph = np.zeros((1, MAX_ORDER + 1))
    rms[0, 1], ph[0, 1] = 1.0, 0.4
    for h, lv in _MIXED.items():
        rms[0, h], ph[0, h] = lv, 0.3 * h
    kw.setdefault("interharmonics", tuple((r, level, 0.7 + i) for i, r in enumerate(interharmonic_positions(f0))))
    return _one_phase(
        f"pq-interharmonics-{int(f0)}hz",
        f"interharmonics at {100 * level:g} % (2.5, 13 + 2/N, 49.5) with harmonics",
        f0, df_pct, rms, ph, kw,
    )  # fmt: skip


def single_interharmonic(
    f0: float = 50.0, ratio: float = 2.5, level: float = 0.05, phase: float = 0.7, df_pct: float = 0.0, **kw: Any
) -> PqScenario:
    """One phase: fundamental 1 (RMS) and one interharmonic at ``ratio`` x f (on the
    window's bins: a multiple of 1/N) of RMS ``level``."""
    rms = np.zeros((1, MAX_ORDER + 1))
    ph = np.zeros((1, MAX_ORDER + 1))
    rms[0, 1], ph[0, 1] = 1.0, 0.4
    kw["interharmonics"] = ((ratio, level, phase),)
    return _one_phase(
        f"pq-interharmonic-{int(f0)}hz-single",
        f"interharmonic {ratio:g} f at {100 * level:g} %",
        f0,
        df_pct,
        rms,
        ph,
        kw,
    )


def _one_phase(
    name: str, what: str, f0: float, df_pct: float, rms: np.ndarray, ph: np.ndarray, kw: dict[str, Any]
) -> PqScenario:
    """The one-phase harmonic scenario with RMS ``rms`` and phases ``ph`` per order, at
    ``df_pct`` % off the nominal ``f0``; ``name`` unless ``kw`` names it, ``what`` for the
    summary."""
    return PqScenario(
        kw.pop("name", name),
        what + (f", f {df_pct:+g} %" if df_pct else ""),
        f0 * (1.0 + df_pct / 100.0),
        f0,
        rms,
        ph,
        tags=("power-quality", "iec61000-4-7", "harmonics", f"{int(f0)}hz"),
        **kw,
    )


_PQ: dict[str, Callable[..., PqScenario]] = {}
_OFF = {"": 0.0, "-m5": -5.0, "-p5": 5.0}
_MIXED = {5: 0.05, 7: 0.03, 11: 0.02, 3: 0.01}


def _add(name: str, factory: Callable[..., PqScenario], **fixed: Any) -> None:
    def build(**kw: Any) -> PqScenario:
        return factory(**{**fixed, **kw, "name": name})

    _PQ[name] = build


for _f0 in (50.0, 60.0):
    _n = int(_f0)
    for _suffix, _df in _OFF.items():
        for _u2 in (0.005, 0.01, 0.02, 0.05):
            _add(f"pq-unbalance-{_n}hz-u2-{100 * _u2:g}pct{_suffix}", unbalance, f0=_f0, u2=_u2, df_pct=_df)
        _add(
            f"pq-unbalance-{_n}hz-u2-2pct-harmonics{_suffix}", unbalance, f0=_f0, u2=0.02, df_pct=_df, harmonics=_MIXED
        )
        _add(f"pq-harmonics-{_n}hz-all{_suffix}", harmonics_family, f0=_f0, df_pct=_df)
        _add(f"pq-harmonics-{_n}hz-low{_suffix}", harmonics_family, f0=_f0, df_pct=_df, low=0.001, high=0.009)
        for _lvl in (0.01, 0.03, 0.05):
            _add(
                f"pq-interharmonics-{_n}hz-{100 * _lvl:g}pct{_suffix}",
                interharmonics_family,
                f0=_f0,
                df_pct=_df,
                level=_lvl,
            )
        _add(
            f"pq-unbalance-{_n}hz-u2-2pct-interharmonic-5pct{_suffix}",
            unbalance, f0=_f0, u2=0.02, df_pct=_df, interharmonic=0.05,
        )  # fmt: skip
    _add(f"pq-harmonic-{_n}hz-single", single_harmonic, f0=_f0)
    _add(f"pq-interharmonic-{_n}hz-single", single_interharmonic, f0=_f0)


def pq_names() -> list[str]:
    return sorted(_PQ)


def get_pq(name: str, **overrides: Any) -> PqScenario:
    try:
        factory = _PQ[name]
    except KeyError:
        raise ParameterError(f"power-quality scenario: expected one of {pq_names()[:4]}..., got {name!r}") from None
    return factory(**overrides)


__all__ = ["LIMITS", "PqScenario", "PqTruth", "class_i_limit", "get_pq", "pq_names"]


def main() -> None:
    """``python -m sinewatch.scenarios.power_quality_iec``: sinewatch's harmonic analyser and
    pqopen-lib (when installed) on these scenarios, worst error as a fraction of the IEC
    limit, one JSON line per scenario."""
    import json

    from sinewatch.power_quality.speed import compare_accuracy

    for row in compare_accuracy([get_pq(n) for n in COMPARED]):
        print(json.dumps({k: (round(v, 6) if isinstance(v, float) else v) for k, v in row.items()}))


COMPARED = [
    "pq-harmonics-50hz-all", "pq-harmonics-50hz-all-m5", "pq-harmonics-50hz-all-p5",
    "pq-harmonics-60hz-all", "pq-harmonics-60hz-all-m5", "pq-harmonics-60hz-all-p5",
    "pq-harmonics-50hz-low-p5", "pq-harmonics-60hz-low-m5",
    "pq-unbalance-50hz-u2-2pct-harmonics-m5", "pq-unbalance-60hz-u2-5pct-p5",
]  # fmt: skip


if __name__ == "__main__":
    main()
