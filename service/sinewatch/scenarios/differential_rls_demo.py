"""Scenarios for ``differential-rls`` (paper 001): a 50 Hz feed with a frequency ramp,
whose truth carries the rate of change of frequency (ROCOF) that the estimator reports in
``extras["rocof_hz_per_s"]``.

* ``rocof-demo``: 50 Hz, amplitude 1, phase 0.2 rad, ramping at +1 Hz/s from t = 0 (50 ->
  55 Hz over the default 5 s), Gaussian noise std 0.01, sampled at 10 kHz. The suggested
  parameters let the reference oscillator follow the ramp up to 10 Hz from nominal.
"""

from __future__ import annotations

from typing import Any

from sinewatch.scenarios import Component, Composite, register

ROCOF_DEMO_PARAMS: dict[str, Any] = {
    "nominal_frequency_hz": 50.0,
    "bandwidth_hz": 5.0,
    "tracking_range_hz": 10.0,
    "rocof_model": True,
}


@register("rocof-demo")
def rocof_demo(**overrides: Any) -> Composite:
    kw: dict[str, Any] = {
        "sample_rate_hz": 10_000.0,
        "duration_s": 5.0,
        "noise_std": 0.01,
        "suggested_estimator": "differential-rls",
        "suggested_params": dict(ROCOF_DEMO_PARAMS),
    }
    rocof = float(overrides.pop("rocof_hz_per_s", 1.0))
    f0 = float(overrides.pop("f0_hz", 50.0))
    kw.update(overrides)
    return Composite(
        "rocof-demo",
        f"{f0:g} Hz ramping at {rocof:g} Hz/s, noise std {kw['noise_std']:g} (differential-rls, paper 001)",
        [Component(f0=f0, a0=1.0, phi0=0.2, rocof=rocof)],
        offset=0.0,
        tags=("demo", "ramp", "rocof", "paper001"),
        **kw,
    )
