"""The eight channels of ``sinewatch demo`` (10 kHz): mains-like signals a power-quality
engineer would watch, and one faulty sensor."""

from __future__ import annotations

import math

from sinewatch.scenarios import register
from sinewatch.scenarios.base import FaultPlan, SumOfTones, Tone

# ges-kalman tuned for 10 kHz: x3 = -4 sin^2(w Ts/2) is ~1e-3 here, so its random walk
# must be far smaller than the paper's 1e-6 (tuned at 1 kHz); R matches the noise.
KALMAN_10K = {"q": [1e-10, 1e-10, 1e-14, 1e-14], "r": 1e-4}
DEMO_CHANNELS = [
    "demo-mains-harmonics",
    "demo-ramp",
    "demo-biased",
    "demo-frequency-step",
    "demo-amplitude-step",
    "demo-phase-step",
    "demo-noisy-60hz",
    "demo-faulty-sensor",
]


def _demo(
    name: str,
    summary: str,
    tones: list[Tone],
    offset: float = 0.0,
    noise_std: float = 0.01,
    params: dict | None = None,
    disturbances: list[Tone] | None = None,
    **overrides,
) -> SumOfTones:
    kw = dict(
        sample_rate_hz=10_000.0,
        duration_s=10.0,
        noise_std=noise_std,
        suggested_estimator="ges-kalman",
        suggested_params=params or KALMAN_10K,
    )
    kw.update(overrides)  # may name another estimator
    return SumOfTones(name, summary, tones, offset=offset, tags=("demo",), disturbances=disturbances, **kw)


@register("demo-mains-harmonics")
def mains_harmonics(**kw):
    # The interpolated DFT over whole nominal cycles nulls harmonics, which bias a
    # one-sinusoid model such as ges-kalman (~0.1 Hz here): the right tool for this feed.
    kw.setdefault("suggested_estimator", "ipdft")
    kw.setdefault("suggested_params", {"nominal_frequency_hz": 50.0})
    return _demo(
        "demo-mains-harmonics",
        "50 Hz with 5 % 3rd and 3 % 5th harmonics",
        [Tone(50.0, 1.0)],
        disturbances=[Tone(150.0, 0.05, 0.4), Tone(250.0, 0.03, 1.1)],
        **kw,
    )


@register("demo-ramp")
def ramp(**kw):
    return _demo("demo-ramp", "48 Hz ramping at +1 Hz/s", [Tone(48.0, 1.0, rocof=1.0)], **kw)


@register("demo-biased")
def biased(**kw):
    return _demo("demo-biased", "120 Hz, amplitude 2, offset 0.5", [Tone(120.0, 2.0, 0.7)], offset=0.5, **kw)


@register("demo-frequency-step")
def frequency_step(**kw):
    return _demo(
        "demo-frequency-step", "50 Hz stepping to 51 Hz at t = 5 s", [Tone(50.0, 1.0, t_step=5.0, f_step_to=51.0)], **kw
    )


@register("demo-amplitude-step")
def amplitude_step(**kw):
    return _demo(
        "demo-amplitude-step",
        "60 Hz, amplitude +10 % at t = 5 s",
        [Tone(60.0, 1.0, t_step=5.0, a_step_factor=1.1)],
        **kw,
    )


@register("demo-phase-step")
def phase_step(**kw):
    return _demo(
        "demo-phase-step",
        "50 Hz, phase +10 degrees at t = 5 s",
        [Tone(50.0, 1.0, t_step=5.0, phase_step_rad=math.radians(10.0))],
        **kw,
    )


@register("demo-noisy-60hz")
def noisy_60hz(**kw):
    # SNR 20 dB: noise power A^2/2 / 100
    return _demo(
        "demo-noisy-60hz",
        "60 Hz at 20 dB SNR",
        [Tone(60.0, 1.0)],
        noise_std=math.sqrt(0.5 / 100),
        params={"q": [1e-10, 1e-10, 1e-15, 1e-15], "r": 5e-3},
        **kw,
    )


@register("demo-faulty-sensor")
def faulty_sensor(**kw):
    sc = _demo(
        "demo-faulty-sensor",
        "50 Hz from a sensor that drops, duplicates and corrupts blocks",
        [Tone(50.0, 1.0, 0.2)],
        offset=0.1,
        **kw,
    )
    sc.faults = FaultPlan(drop_every=23, nan_every=31, duplicate_every=37)
    return sc
