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
from typing import Any

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


@dataclass(frozen=True)
class Event:
    """Something the accuracy bench measures a response to: a step of ``quantity``
    ("amplitude", "phase_rad", "frequency_hz", "offset") of ``size`` on ``component`` at
    ``time_s``, or the end of a data gap (``quantity="resume"``)."""

    time_s: float
    quantity: str
    size: float = 0.0
    component: int = 0


@dataclass(frozen=True)
class BenchInfo:
    """What the accuracy bench needs to judge a scenario (explicit, not guessed).

    ``nominal_frequency_hz`` has one entry per truth component (what an estimator may be
    told in advance); ``frequency_range_hz`` the range it may assume; metrics of the
    steady state (bias, RMSE, C37 quantities) are taken over ``steady_windows``;
    ``tolerance_hz`` is added to the 1 % relative band used for convergence times;
    ``reporting_rate_hz`` (phasor scenarios) sets the reporting instants and the
    differentiation interval for ROCOF; ``limits`` are the pass/fail thresholds
    (keys ``tve_pct``, ``fe_hz``, ``rfe_hz_per_s``, ``response_time_s``, ``overshoot_pct``);
    ``reference`` holds what the source paper reported, for the docs; ``crlb``: the bench
    compares the estimates with the Cramer-Rao bound when the signal allows it (one
    stationary tone in white Gaussian noise, :attr:`Scenario.is_stationary`).
    """

    nominal_frequency_hz: tuple[float, ...]
    frequency_range_hz: tuple[float, float]
    steady_windows: tuple[tuple[float, float], ...]
    events: tuple[Event, ...] = ()
    tolerance_hz: float = 0.0
    reporting_rate_hz: float | None = None
    limits: dict[str, float] = field(default_factory=dict)
    reference: dict[str, Any] = field(default_factory=dict)
    crlb: bool = True


class Scenario(ABC):
    """A named test signal. Subclasses implement :meth:`clean`.

    The one description of a scenario that ``sinewatch feed``, ``sinewatch demo``, the
    accuracy bench and the tests read: the signal and its truth (:meth:`clean`, streamed by
    :meth:`stream`), the transport faults a feed injects (``faults``), the estimator it
    was written for (``suggested_estimator``/``suggested_params``: the demo's rules, the
    bench's tuning for that estimator) and the bench's yardsticks (:attr:`bench`).
    """

    name: str = ""
    summary: str = ""
    tags: tuple[str, ...] = ()
    faults: FaultPlan = FaultPlan()
    _bench: BenchInfo | None = None

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

    @property
    def noise_free(self) -> bool:
        """No random noise: every seed gives the same samples."""
        return self.noise_std == 0.0

    @property
    def is_stationary(self) -> bool:
        """One steady tone (with a constant offset) in white Gaussian noise, nothing else:
        the Cramer-Rao bound applies. Scenarios say so themselves; by default, no."""
        return False

    @property
    def bench(self) -> BenchInfo:
        """The accuracy bench's yardsticks: declared by the scenario, or else derived from
        its truth at t = 0 (nominal frequencies the true ones, range half the lowest to
        twice the highest (at most 0.45 fs), steady window the second half, no events, no
        comparison with the CRLB)."""
        if self._bench is None:
            self._bench = self._derived_bench()
        return self._bench

    def _derived_bench(self) -> BenchInfo:
        _, truth = self.generate(0, n=1)
        f0 = tuple(float(f) for f in truth.frequency_hz[0])
        dur = self.n_samples / self.sample_rate_hz
        return BenchInfo(
            nominal_frequency_hz=f0,
            frequency_range_hz=(0.5 * min(f0), min(2.0 * max(f0), 0.45 * self.sample_rate_hz)),
            steady_windows=((0.5 * dur, dur),),
            crlb=False,
        )

    @abstractmethod
    def clean(self, t: np.ndarray) -> tuple[np.ndarray, Truth]:
        """Noiseless samples at times ``t`` (s) and the truth there."""

    def stream(self, seed: int = 0) -> ScenarioStream:
        return ScenarioStream(self, seed)

    def generate(self, seed: int = 0, n: int | None = None) -> tuple[np.ndarray, Truth]:
        """The whole scenario (or its first ``n`` samples) in one block."""
        return self.stream(seed).read(self.n_samples if n is None else n)

    def describe(self) -> dict[str, Any]:
        """The scenario in one plain dict (``sinewatch bench scenarios --json``)."""
        return {
            "name": self.name,
            "tags": list(self.tags),
            "sample_rate_hz": self.sample_rate_hz,
            "duration_s": self.duration_s,
            "components": len(self.bench.nominal_frequency_hz),
            "nominal_frequency_hz": list(self.bench.nominal_frequency_hz),
            "noise_std": self.noise_std,
            "summary": self.summary,
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
            samples = self._add_noise(samples, sc.noise_std)
        self.position += n
        return samples, truth

    def _add_noise(self, samples: np.ndarray, std: float) -> np.ndarray:
        noise = std * self._rng.standard_normal(samples.shape[0])
        if samples.ndim == 2:  # noise on the measured signal (column 0) only
            samples = samples.copy()
            samples[:, 0] += noise
            return samples
        return samples + noise


class NoiseOnEveryColumn(ScenarioStream):
    """Noise on every column (drawn row by row, so block-wise reads equal one read): both
    components of an I/Q pair, every phase of a three-phase set."""

    def _add_noise(self, samples: np.ndarray, std: float) -> np.ndarray:
        return samples + std * self._rng.standard_normal(samples.shape)
