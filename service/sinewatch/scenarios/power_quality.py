"""Power-quality test signals modelled on IEEE C37.118.1 (tags "c37.118", "phasor",
"power-quality", "50hz"/"60hz").

All at 10 kHz sampling, amplitude 1 (per unit), noise-free as in the standard's test
conditions (the bench then runs one trial: the outcome is deterministic). The reporting
rate Fs equals the nominal frequency (50 or 60 frames/s); metrics are read at the
reporting instants inside the steady windows, after a 1 s settling period the standard
does not have (it tests a PMU already running) but recursive estimators need.

Families, for nominal f0 = 50 and 60 Hz (``c37-50hz-...``, ``c37-60hz-...``):

* ``steady``: f0; ``off-m5/-m2/-p2/-p5``: f0 -5, -2, +2, +5 Hz (signal frequency range,
  M class +-5 Hz);
* ``harmonic-h``: a single harmonic h of 10 % (h = 2, 3, 5, 7, 11, 13, 25, 50; the
  standard sweeps 2..50, the factory takes ``harmonic=h`` for any h);
* ``oob-low/-high``: out-of-band interference, 10 % at f0/2 - 1 Hz and 3 f0/2 + 1 Hz (just
  outside the f0 +- Fs/2 pass band);
* ``ramp-up/-down``: +-1 Hz/s between f0 -+ 5 and f0 +- 5 Hz (held 1 s before and after);
  the window starts 7/Fs after the ramp starts (the M-class exclusion interval);
* ``am-2hz/-5hz``: amplitude modulation ``1 + 0.1 cos(2 pi fm t)``; ``pm-2hz/-5hz``:
  phase modulation ``0.1 cos(2 pi fm t - pi)`` rad (measurement bandwidth test);
* ``step-amp-p10/-m10``: amplitude steps of +-10 %; ``step-phase-p10/-m10``: phase steps
  of +-10 degrees, at t = 1.5 s;
* ``dc-offset``: a constant 10 % DC offset; ``dc-decay``: a decaying DC offset
  ``0.5 exp(-(t - 1.5)/0.05)`` from t = 1.5 s (fault-current like; not in the standard,
  judged against the steady-state limits).

The steady window before a step (or the DC onset) ends ``7 / Fs`` before it, the M-class
TVE response-time allowance: a PMU's centred window answers up to half its length before
an event, which the standard judges as response time (``t_r``), not as steady state.

Limits (``bench.limits``) are the M-class requirements as recalled from C37.118.1-2011
and its 2014 amendment (TVE in %, FE in Hz, RFE in Hz/s, response time in s, overshoot
in % of the step); the bench reports against them, but check the standard before
quoting compliance: this is a model of the test suite, not a certified one.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from sinewatch.scenarios import BenchInfo, Component, Composite, Event, register

SAMPLE_RATE_HZ = 10_000.0
HARMONICS = (2, 3, 5, 7, 11, 13, 25, 50)
T_STEP = 1.5

# M class, reporting rate Fs = f0 (see the module docstring: recalled, not certified).
LIMITS = {
    "steady": {"tve_pct": 1.0, "fe_hz": 0.005, "rfe_hz_per_s": 0.1},
    "harmonic": {"tve_pct": 1.0, "fe_hz": 0.025},
    "oob": {"tve_pct": 1.3, "fe_hz": 0.01},
    "ramp": {"tve_pct": 1.0, "fe_hz": 0.01, "rfe_hz_per_s": 0.2},
    "modulation": {"tve_pct": 3.0, "fe_hz": 0.3, "rfe_hz_per_s": 14.0},
    "step": {"tve_pct": 1.0, "overshoot_pct": 10.0},  # response_time_s = 7 / Fs, set per f0
}


def _c37(
    name: str,
    f0: float,
    summary: str,
    comp: Component,
    kind: str,
    *,
    duration: float = 2.0,
    windows: tuple[tuple[float, float], ...] = ((1.0, 2.0),),
    events: tuple[Event, ...] = (),
    extra_tags: tuple[str, ...] = (),
    disturbances: list[Component] | None = None,
    limits: dict[str, float] | None = None,
    composite_kw: dict[str, Any] | None = None,
    overrides: dict[str, Any] | None = None,
) -> Composite:
    full = f"c37-{int(f0)}hz-{name}"
    kw: dict[str, Any] = {
        "sample_rate_hz": SAMPLE_RATE_HZ,
        "duration_s": duration,
        "noise_std": 0.0,
        "suggested_params": {"q": [1e-10, 1e-10, 1e-14, 1e-14], "r": 1e-4},
    }
    kw.update(overrides or {})
    return Composite(
        full,
        f"{summary} (f0 = {int(f0)} Hz, 10 kHz, C37.118.1-style)",
        [comp],
        BenchInfo(
            nominal_frequency_hz=(f0,),
            frequency_range_hz=(f0 - 10.0, f0 + 10.0),
            steady_windows=windows,
            events=events,
            reporting_rate_hz=f0,
            limits=dict(limits if limits is not None else LIMITS[kind]),
        ),
        disturbances=disturbances,
        tags=("c37.118", "phasor", "power-quality", f"{int(f0)}hz", kind, *extra_tags),
        **(composite_kw or {}),
        **kw,
    )


def _steady(f0: float, df: float, name: str, quick: bool = False) -> Callable[..., Composite]:
    def factory(**kw: Any) -> Composite:
        label = "nominal frequency" if df == 0 else f"off-nominal {df:+g} Hz"
        return _c37(
            name,
            f0,
            label,
            Component(f0 + df, phi0=0.4),
            "steady",
            extra_tags=("quick",) if quick else (),
            overrides=kw,
        )

    return factory


def _harmonic(f0: float, h_default: int) -> Callable[..., Composite]:
    def factory(harmonic: int = h_default, **kw: Any) -> Composite:
        if not 2 <= harmonic <= 50:
            raise ValueError(f"harmonic: expected 2..50, got {harmonic}")
        return _c37(
            f"harmonic-{harmonic}",
            f0,
            f"10 % harmonic {harmonic}",
            Component(f0, phi0=0.4),
            "harmonic",
            disturbances=[Component(harmonic * f0, a0=0.1, phi0=1.0)],
            extra_tags=("quick",) if (harmonic == 3 and f0 == 50.0) else (),
            overrides=kw,
        )

    return factory


def _oob(f0: float, high: bool) -> Callable[..., Composite]:
    fi = 1.5 * f0 + 1.0 if high else 0.5 * f0 - 1.0

    def factory(**kw: Any) -> Composite:
        return _c37(
            "oob-high" if high else "oob-low",
            f0,
            f"10 % interference at {fi:g} Hz",
            Component(f0, phi0=0.4),
            "oob",
            disturbances=[Component(fi, a0=0.1, phi0=0.2)],
            overrides=kw,
        )

    return factory


def _ramp(f0: float, up: bool) -> Callable[..., Composite]:
    sign = 1.0 if up else -1.0
    fs_report = f0

    def factory(**kw: Any) -> Composite:
        return _c37(
            "ramp-up" if up else "ramp-down",
            f0,
            f"frequency ramp {sign:+g} Hz/s over +-5 Hz",
            Component(f0 - sign * 5.0, rocof=sign * 1.0, ramp_start=1.0, ramp_stop=11.0),
            "ramp",
            duration=12.0,
            windows=((1.0 + 7.0 / fs_report, 11.0),),
            extra_tags=("tracking", "quick") if (up and f0 == 50.0) else ("tracking",),
            overrides=kw,
        )

    return factory


def _modulation(f0: float, kind: str, fm: float) -> Callable[..., Composite]:
    def factory(**kw: Any) -> Composite:
        if kind == "am":
            comp = Component(f0, phi0=0.4, am_depth=0.1, am_hz=fm)
            label = f"amplitude modulation 10 % at {fm:g} Hz"
        else:
            comp = Component(f0, phi0=0.4, pm_depth_rad=0.1, pm_hz=fm)
            label = f"phase modulation 0.1 rad at {fm:g} Hz"
        return _c37(
            f"{kind}-{int(fm)}hz",
            f0,
            label,
            comp,
            "modulation",
            duration=3.0,
            windows=((1.0, 3.0),),
            extra_tags=("tracking",),
            overrides=kw,
        )

    return factory


def _step(f0: float, quantity: str, sign: float) -> Callable[..., Composite]:
    def factory(**kw: Any) -> Composite:
        limits = dict(LIMITS["step"], response_time_s=7.0 / f0)
        if quantity == "amplitude":
            comp = Component(f0, phi0=0.4, t_step=T_STEP, a_step_factor=1.0 + 0.1 * sign)
            event = Event(T_STEP, "amplitude", 0.1 * sign)
            label, name = f"amplitude step {10 * sign:+g} %", f"step-amp-{'p' if sign > 0 else 'm'}10"
        else:
            comp = Component(f0, phi0=0.4, t_step=T_STEP, phase_step_rad=math.radians(10.0 * sign))
            event = Event(T_STEP, "phase_rad", math.radians(10.0 * sign))
            label, name = f"phase step {10 * sign:+g} degrees", f"step-phase-{'p' if sign > 0 else 'm'}10"
        return _c37(
            name,
            f0,
            label,
            comp,
            "step",
            duration=3.0,
            windows=((1.0, T_STEP - 7.0 / f0), (T_STEP + 1.0, 3.0)),
            events=(event,),
            limits=limits,
            overrides=kw,
            extra_tags=("quick",) if (f0 == 50.0 and quantity == "phase_rad" and sign > 0) else (),
        )

    return factory


def _dc(f0: float, decay: bool) -> Callable[..., Composite]:
    def factory(**kw: Any) -> Composite:
        if decay:
            return _c37(
                "dc-decay",
                f0,
                "decaying DC offset 0.5 exp(-(t - 1.5)/0.05)",
                Component(f0, phi0=0.4),
                "steady",
                duration=3.0,
                windows=((1.0, T_STEP - 7.0 / f0), (2.0, 3.0)),
                events=(Event(T_STEP, "offset", 0.5),),
                extra_tags=("dc",),
                composite_kw={"offset_decay": 0.5, "offset_tau": 0.05, "offset_decay_start": T_STEP},
                overrides=kw,
            )
        return _c37(
            "dc-offset",
            f0,
            "10 % DC offset",
            Component(f0, phi0=0.4),
            "steady",
            extra_tags=("dc",),
            composite_kw={"offset": 0.1},
            overrides=kw,
        )

    return factory


for _f0 in (50.0, 60.0):
    _n = int(_f0)
    register(f"c37-{_n}hz-steady")(_steady(_f0, 0.0, "steady", quick=True))
    for _df, _lab in ((-5.0, "off-m5"), (-2.0, "off-m2"), (2.0, "off-p2"), (5.0, "off-p5")):
        register(f"c37-{_n}hz-{_lab}")(_steady(_f0, _df, _lab, quick=(_df == 5.0 and _n == 50)))
    for _h in HARMONICS:
        register(f"c37-{_n}hz-harmonic-{_h}")(_harmonic(_f0, _h))
    register(f"c37-{_n}hz-oob-low")(_oob(_f0, False))
    register(f"c37-{_n}hz-oob-high")(_oob(_f0, True))
    register(f"c37-{_n}hz-ramp-up")(_ramp(_f0, True))
    register(f"c37-{_n}hz-ramp-down")(_ramp(_f0, False))
    for _fm in (2.0, 5.0):
        register(f"c37-{_n}hz-am-{int(_fm)}hz")(_modulation(_f0, "am", _fm))
        register(f"c37-{_n}hz-pm-{int(_fm)}hz")(_modulation(_f0, "pm", _fm))
    for _s in (1.0, -1.0):
        register(f"c37-{_n}hz-step-amp-{'p' if _s > 0 else 'm'}10")(_step(_f0, "amplitude", _s))
        register(f"c37-{_n}hz-step-phase-{'p' if _s > 0 else 'm'}10")(_step(_f0, "phase_rad", _s))
    register(f"c37-{_n}hz-dc-offset")(_dc(_f0, False))
    register(f"c37-{_n}hz-dc-decay")(_dc(_f0, True))
