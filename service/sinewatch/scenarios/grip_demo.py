"""Scenarios for ``grip-mixing`` (paper 002: H. F. Grip, "Observer design in the presence of
periodic output disturbances by mixing of past and present output data").

* ``grip-demo``: mains lines at 50, 150 and 250 Hz (amplitudes 1, 0.2, 0.1) + offset 0.3 + a
  periodic disturbance of period T = 0.05 s (a 1200 rpm machine: 20, 40, 60, 100 and 140 Hz)
  + white noise std 0.01, at 10 kHz (T = 500 samples). No line sits on a harmonic of 20 Hz,
  so Theorem 1 holds. Suggested estimator: ``grip-mixing``, preset ``harmonics``. Truth: the
  three lines; the disturbance is zero-mean, so the offset is 0.3.
* ``grip-section-v``: the paper's Section V simulation, rebuilt (see the estimator's module
  docstring): x1' = x2, x2' = -x1 + u, y = x1 + d, u = 2 + 3 sin(0.3 t), d of period 4.5 s.
  The extraction lost the figures, the initial state, the disturbance waveform and the noise
  level; chosen here: x(0) = (1, -1), d(t) = 0.3 + 1.2 tri(t / T) + 0.4 sin(4 pi t / T + 1)
  (tri: unit triangle wave), fs = 100 Hz, 40 s, and for the noisy runs "band-limited white
  noise" as Simulink makes it: Gaussian values of std ``bandlimited_noise_std`` held for
  ``noise_hold_s`` = 0.1 s. Samples are (N, 2): column 0 = y, column 1 = u. Truth: the
  plant's one oscillatory mode (eigenvalues +-j, 1 / (2 pi) Hz) with amplitude
  hypot(x1, x2) and phase atan2(x1, x2) (x1 = amplitude sin(phase)); offset = the mean of d
  over a period, 0.3. ``truth_states(t)`` gives x(t) and d(t) for the tests.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sinewatch.scenarios import BenchInfo, Component, Composite, Scenario, ScenarioStream, Truth, register, wrap_phase

GRIP_DEMO_PERIOD_S = 0.05
GRIP_DEMO_PARAMS = {"preset": "harmonics", "frequencies_hz": [50.0, 150.0, 250.0], "period_s": 0.05}

SECTION_V_PLANT = {
    "preset": "plant",
    "A": [[0.0, 1.0], [-1.0, 0.0]],
    "B": [[0.0], [1.0]],
    "C": [[1.0, 0.0]],
    "poles": [-1.0, -2.0],
    "frequencies_hz": None,  # explicit: a merge over harmonics-preset parameters must drop them
}


@register("grip-demo")
def grip_demo(**kw: Any) -> Composite:
    kw = dict(kw)
    fs = float(kw.get("sample_rate_hz", 10_000.0))
    params = dict(GRIP_DEMO_PARAMS)
    delay = GRIP_DEMO_PERIOD_S * fs
    if abs(delay - round(delay)) > 1e-9 * delay:
        params["fractional_delay"] = True  # T is not a whole number of samples at this rate
    base: dict[str, Any] = {
        "sample_rate_hz": 10_000.0,
        "duration_s": 10.0,
        "noise_std": 0.01,
        "suggested_estimator": "grip-mixing",
        "suggested_params": params,
    }
    base.update(kw)
    return Composite(
        "grip-demo",
        "50/150/250 Hz lines + offset 0.3 + a 20 Hz-periodic disturbance (T = 0.05 s), noise 0.01",
        [Component(50.0, 1.0, 0.3), Component(150.0, 0.2, -1.0), Component(250.0, 0.1, 2.0)],
        BenchInfo(
            nominal_frequency_hz=(50.0, 150.0, 250.0),
            frequency_range_hz=(45.0, 255.0),
            steady_windows=((1.0, float(base["duration_s"])),),
            reference={"paper": "002 (no figure for this signal: a sinewatch use of the design)"},
        ),
        disturbances=[
            Component(20.0, 0.4, 0.0),
            Component(40.0, 0.3, 0.5),
            Component(60.0, 0.25, 1.0),
            Component(100.0, 0.15, 2.0),
            Component(140.0, 0.1, -1.0),
        ],
        offset=0.3,
        tags=("demo", "paper002", "disturbance"),
        **base,
    )


class GripSectionV(Scenario):
    """Paper 002, Section V (see module docstring); samples are (N, 2) = (y, u)."""

    name = "grip-section-v"
    summary = "paper 002 V: x1'' = -x1 + u, u = 2 + 3 sin(0.3 t), y = x1 + d, d of period 4.5 s"
    tags = ("paper", "paper002", "inputs")

    def __init__(
        self,
        disturbance_period_s: float = 4.5,
        x0: tuple[float, float] = (1.0, -1.0),
        bandlimited_noise_std: float = 0.0,
        noise_hold_s: float = 0.1,
        **kw: Any,
    ) -> None:
        base: dict[str, Any] = {
            "sample_rate_hz": 100.0,
            "duration_s": 40.0,
            "noise_std": 0.0,
            "suggested_estimator": "grip-mixing",
            "suggested_params": {**SECTION_V_PLANT, "period_s": float(disturbance_period_s)},
        }
        base.update(kw)
        super().__init__(**base)
        self.period = float(disturbance_period_s)
        self.x0 = (float(x0[0]), float(x0[1]))
        self.bandlimited_noise_std = float(bandlimited_noise_std)
        self.noise_hold_s = float(noise_hold_s)

    @property
    def n_inputs(self) -> int:
        return 2

    @property
    def noise_free(self) -> bool:
        return super().noise_free and self.bandlimited_noise_std == 0.0

    def truth_states(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x(t) (N, 2), u(t) and d(t), in closed form."""
        # x1'' + x1 = 2 + 3 sin(0.3 t): particular 2 + 3/0.91 sin(0.3 t), plus a cos t + b sin t
        a = self.x0[0] - 2.0
        b = self.x0[1] - 0.9 / 0.91
        x1 = 2.0 + 3.0 / 0.91 * np.sin(0.3 * t) + a * np.cos(t) + b * np.sin(t)
        x2 = 0.9 / 0.91 * np.cos(0.3 * t) - a * np.sin(t) + b * np.cos(t)
        u = 2.0 + 3.0 * np.sin(0.3 * t)
        s = np.mod(t / self.period, 1.0)
        tri = 4.0 * np.abs(s - 0.5) - 1.0  # continuous, zero-mean, period T
        d = 0.3 + 1.2 * tri + 0.4 * np.sin(4.0 * np.pi * s + 1.0)
        return np.column_stack([x1, x2]), u, d

    def clean(self, t: np.ndarray) -> tuple[np.ndarray, Truth]:
        x, u, d = self.truth_states(t)
        y = x[:, 0] + d
        ones = np.ones((t.size, 1))
        truth = Truth(
            frequency_hz=ones / (2.0 * math.pi),
            amplitude=np.hypot(x[:, 0], x[:, 1])[:, None],
            phase_rad=wrap_phase(np.arctan2(x[:, 0], x[:, 1]))[:, None],
            offset=np.full(t.size, 0.3),
        )
        return np.column_stack([y, u]), truth

    def stream(self, seed: int = 0) -> ScenarioStream:
        return _HeldNoiseStream(self, seed)


class _HeldNoiseStream(ScenarioStream):
    """Adds Gaussian values held for ``noise_hold_s`` to column 0, drawn one per hold
    interval in order, so block-wise reads equal one read."""

    def __init__(self, scenario: GripSectionV, seed: int) -> None:
        super().__init__(scenario, seed)
        self._nrng = np.random.default_rng([seed, 0x002])
        self._hold = max(1, round(scenario.noise_hold_s * scenario.sample_rate_hz))
        self._last_index = -1
        self._last_value = 0.0

    def read(self, n: int) -> tuple[np.ndarray, Truth]:
        start = self.position
        samples, truth = super().read(n)
        sc = self.scenario
        if sc.bandlimited_noise_std > 0 and n > 0:  # type: ignore[attr-defined]
            idx = (start + np.arange(n)) // self._hold
            fresh = int(idx[-1] - self._last_index)
            values = np.concatenate([[self._last_value], self._nrng.standard_normal(fresh)])
            noise = sc.bandlimited_noise_std * values[idx - self._last_index]  # type: ignore[attr-defined]
            self._last_index = int(idx[-1])
            self._last_value = float(values[-1])
            samples = samples.copy()
            samples[:, 0] += noise
        return samples, truth


@register("grip-section-v")
def grip_section_v(**kw: Any) -> GripSectionV:
    return GripSectionV(**kw)
