"""The eight channels of ``sinewatch demo`` (10 kHz): mains-like signals a power-quality
engineer would watch, and one faulty sensor.

Each channel is one :func:`_channel` call below: its name, what it is, its components and
the estimator that serves it; :data:`DEMO_CHANNELS` (the demo's and ``sinewatch feed``'s
default channels) is the list of those names, in that order.
"""

from __future__ import annotations

import math
from typing import Any

from sinewatch.scenarios import Component, FaultPlan, declare

# ges-kalman tuned for 10 kHz: x3 = -4 sin^2(w Ts/2) is ~1e-3 here, so its random walk
# must be far smaller than the paper's 1e-6 (tuned at 1 kHz); R matches the noise.
KALMAN_10K: dict[str, Any] = {"q": [1e-10, 1e-10, 1e-14, 1e-14], "r": 1e-4}

DEMO_CHANNELS: list[str] = []


def _channel(
    name: str,
    summary: str,
    tones: list[Component],
    *,
    offset: float = 0.0,
    noise_std: float = 0.01,
    estimator: str = "ges-kalman",
    params: dict[str, Any] | None = None,
    disturbances: list[Component] | None = None,
    faults: FaultPlan | None = None,
) -> None:
    """Register demo channel ``name`` (10 kHz, 10 s)."""
    declare(
        name,
        summary,
        tones,
        offset=offset,
        tags=("demo",),
        disturbances=disturbances,
        faults=faults,
        defaults={
            "sample_rate_hz": 10_000.0,
            "duration_s": 10.0,
            "noise_std": noise_std,
            "suggested_estimator": estimator,
            "suggested_params": params or KALMAN_10K,
        },
    )
    DEMO_CHANNELS.append(name)


_channel(
    "demo-mains-harmonics",
    "50 Hz with 5 % 3rd and 3 % 5th harmonics",
    [Component(50.0, 1.0)],
    disturbances=[Component(150.0, 0.05, 0.4), Component(250.0, 0.03, 1.1)],
    # The interpolated DFT over whole nominal cycles nulls harmonics, which bias a
    # one-sinusoid model such as ges-kalman (~0.1 Hz here): the right tool for this feed.
    estimator="ipdft",
    params={"nominal_frequency_hz": 50.0},
)
_channel("demo-ramp", "48 Hz ramping at +1 Hz/s", [Component(48.0, 1.0, rocof=1.0)])
_channel("demo-biased", "120 Hz, amplitude 2, offset 0.5", [Component(120.0, 2.0, 0.7)], offset=0.5)
_channel(
    "demo-frequency-step",
    "50 Hz stepping to 51 Hz at t = 5 s",
    [Component(50.0, 1.0, t_step=5.0, f_step_to=51.0)],
)
_channel(
    "demo-amplitude-step",
    "60 Hz, amplitude +10 % at t = 5 s",
    [Component(60.0, 1.0, t_step=5.0, a_step_factor=1.1)],
)
_channel(
    "demo-phase-step",
    "50 Hz, phase +10 degrees at t = 5 s",
    [Component(50.0, 1.0, t_step=5.0, phase_step_rad=math.radians(10.0))],
)
_channel(
    "demo-noisy-60hz",
    "60 Hz at 20 dB SNR",
    [Component(60.0, 1.0)],
    noise_std=math.sqrt(0.5 / 100),  # SNR 20 dB: noise power A^2/2 / 100
    params={"q": [1e-10, 1e-10, 1e-15, 1e-15], "r": 5e-3},
)
_channel(
    "demo-faulty-sensor",
    "50 Hz from a sensor that drops, duplicates and corrupts blocks",
    [Component(50.0, 1.0, 0.2)],
    offset=0.1,
    faults=FaultPlan(drop_every=23, nan_every=31, duplicate_every=37),
)
