"""Scenario core: a signal with its per-sample truth, generated block by block.

A :class:`Scenario` describes a noiseless signal analytically (``clean(t)``) and adds
seeded white Gaussian noise when streamed. Reading a stream in blocks of any size gives
the same samples as reading it at once (numpy's Generator draws normals sequentially),
so feeds, tests and benchmarks agree.

Truth uses the estimator output convention: ``y = offset + sum_k amplitude_k *
sin(phase_k)``, frequency in Hz, instantaneous phase in radians wrapped to (-pi, pi].
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np


def wrap_phase(phase: np.ndarray) -> np.ndarray:
    """Wrap radians to (-pi, pi]."""
    return np.pi - np.mod(np.pi - phase, 2.0 * np.pi)


@dataclass(frozen=True)
class Truth:
    frequency_hz: np.ndarray  # (N, K)
    amplitude: np.ndarray  # (N, K)
    phase_rad: np.ndarray  # (N, K), wrapped
    offset: np.ndarray  # (N,)
    rocof_hz_per_s: np.ndarray | None = None  # (N, K), when the scenario defines it

    @property
    def n_samples(self) -> int:
        return int(self.offset.shape[0])

    def last(self) -> Truth:
        return Truth(
            self.frequency_hz[-1:],
            self.amplitude[-1:],
            self.phase_rad[-1:],
            self.offset[-1:],
            None if self.rocof_hz_per_s is None else self.rocof_hz_per_s[-1:],
        )


@dataclass(frozen=True)
class FaultPlan:
    """Transport faults the feed injects, by block index (1-based counts): skip a block
    (a sequence gap), send a block with a NaN in it, send a block twice."""

    drop_every: int | None = None
    nan_every: int | None = None
    duplicate_every: int | None = None

    def action(self, block_index: int) -> str | None:
        i = block_index + 1
        for name, every in (("drop", self.drop_every), ("nan", self.nan_every), ("duplicate", self.duplicate_every)):
            if every and i % every == 0:
                return name
        return None


class Scenario(ABC):
    """A named test signal. Subclasses implement :meth:`clean`."""

    name: ClassVar[str] = ""
    summary: ClassVar[str] = ""
    tags: ClassVar[tuple[str, ...]] = ()
    faults: FaultPlan = FaultPlan()

    def __init__(
        self,
        sample_rate_hz: float = 10_000.0,
        duration_s: float = 10.0,
        noise_std: float = 0.0,
        suggested_estimator: str = "ges-kalman",
        suggested_params: dict[str, Any] | None = None,
    ) -> None:
        self.sample_rate_hz = float(sample_rate_hz)
        self.duration_s = float(duration_s)
        self.noise_std = float(noise_std)
        self.suggested_estimator = suggested_estimator
        self.suggested_params = dict(suggested_params or {})

    @property
    def n_samples(self) -> int:
        return round(self.duration_s * self.sample_rate_hz)

    @property
    def n_inputs(self) -> int:
        """Columns per sample: 1, or more when known inputs travel with the signal."""
        return 1

    @abstractmethod
    def clean(self, t: np.ndarray) -> tuple[np.ndarray, Truth]:
        """Noiseless samples at times ``t`` (s) and the truth there."""

    def stream(self, seed: int = 0) -> ScenarioStream:
        return ScenarioStream(self, seed)

    def generate(self, seed: int = 0, n: int | None = None) -> tuple[np.ndarray, Truth]:
        """The whole scenario (or its first ``n`` samples) in one block."""
        return self.stream(seed).read(self.n_samples if n is None else n)

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "summary": self.summary,
            "tags": list(self.tags),
            "sample_rate_hz": self.sample_rate_hz,
            "duration_s": self.duration_s,
            "noise_std": self.noise_std,
        }


class ScenarioStream:
    """Sequential reader of a scenario: ``read(n)`` returns the next n samples and truth."""

    def __init__(self, scenario: Scenario, seed: int) -> None:
        self.scenario = scenario
        self.position = 0
        self._rng = np.random.default_rng(seed)

    def read(self, n: int) -> tuple[np.ndarray, Truth]:
        sc = self.scenario
        t = (self.position + np.arange(n, dtype=np.float64)) / sc.sample_rate_hz
        samples, truth = sc.clean(t)
        if sc.noise_std > 0:
            noise = sc.noise_std * self._rng.standard_normal(n)
            if samples.ndim == 2:  # noise on the measured signal (column 0) only
                samples = samples.copy()
                samples[:, 0] += noise
            else:
                samples = samples + noise
        self.position += n
        return samples, truth


@dataclass(frozen=True)
class Tone:
    """One sinusoidal component, described analytically.

    Frequency: ``f0 + rocof * t``, then ``f_step_to`` from ``t_step`` on (the phase stays
    continuous). Amplitude ``a0``, multiplied by ``a_step_factor`` from ``t_step``. Phase
    ``phi0`` plus ``phase_step_rad`` from ``t_step``. ``t_step = inf`` disables steps.
    """

    f0: float
    a0: float = 1.0
    phi0: float = 0.0
    rocof: float = 0.0
    t_step: float = float("inf")
    f_step_to: float | None = None
    a_step_factor: float = 1.0
    phase_step_rad: float = 0.0

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Instantaneous (frequency Hz, amplitude, unwrapped phase rad, rocof Hz/s) at t."""
        after = t >= self.t_step
        freq = self.f0 + self.rocof * t
        cycles = self.f0 * t + 0.5 * self.rocof * t * t
        rocof = np.full_like(t, self.rocof)
        if self.f_step_to is not None and np.isfinite(self.t_step):
            ts = self.t_step
            cycles_at_step = self.f0 * ts + 0.5 * self.rocof * ts * ts
            freq = np.where(after, self.f_step_to, freq)
            cycles = np.where(after, cycles_at_step + self.f_step_to * (t - ts), cycles)
            rocof = np.where(after, 0.0, rocof)
        amp = np.where(after, self.a0 * self.a_step_factor, self.a0)
        phase = 2.0 * np.pi * cycles + self.phi0 + np.where(after, self.phase_step_rad, 0.0)
        return freq, amp, phase, rocof


class SumOfTones(Scenario):
    """offset + sum of :class:`Tone` components + disturbances + noise; the generic scenario.

    ``tones`` are the components an estimator should report (they make up the truth);
    ``disturbances`` (harmonics, ripple, interference) are added to the signal but are
    not part of the truth, so a one-component estimator is scored on the fundamental.
    """

    def __init__(
        self,
        name: str,
        summary: str,
        tones: list[Tone],
        offset: float = 0.0,
        tags: tuple[str, ...] = (),
        disturbances: list[Tone] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        self.name = name  # instance attribute shadows the ClassVar on purpose
        self.summary = summary
        self.tags = tags
        self.tones = list(tones)
        self.disturbances = list(disturbances or [])
        self.offset = float(offset)

    def clean(self, t: np.ndarray) -> tuple[np.ndarray, Truth]:
        cols = [tone.evaluate(t) for tone in self.tones]
        freq = np.stack([c[0] for c in cols], axis=1)
        amp = np.stack([c[1] for c in cols], axis=1)
        phase = np.stack([c[2] for c in cols], axis=1)
        rocof = np.stack([c[3] for c in cols], axis=1)
        y = self.offset + np.sum(amp * np.sin(phase), axis=1)
        for d in self.disturbances:
            _, d_amp, d_phase, _ = d.evaluate(t)
            y = y + d_amp * np.sin(d_phase)
        truth = Truth(freq, amp, wrap_phase(phase), np.full(t.shape, self.offset), rocof)
        return y, truth

    def describe(self) -> dict[str, Any]:
        d = super().describe()
        d["tones"] = [tone.__dict__ for tone in self.tones]
        d["disturbances"] = [tone.__dict__ for tone in self.disturbances]
        d["offset"] = self.offset
        return d


@dataclass
class ScenarioSpec:
    """A registry entry: a factory that builds the scenario with optional overrides."""

    name: str
    factory: Any
    summary: str = ""
    tags: tuple[str, ...] = field(default_factory=tuple)
