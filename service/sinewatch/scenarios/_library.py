"""The signal every registered scenario but one is made of (not a scenario module itself:
the registry skips modules whose name starts with ``_``).

:class:`Component` is one sinusoid described analytically, with everything the demo,
power-quality and paper scenarios need: linear frequency ramps over a time window,
sinusoidal frequency modulation (paper 001), C37.118.1-style amplitude and phase
modulation, and steps of amplitude, phase and frequency. :class:`Composite` sums
components that are estimated (they make the truth) and disturbances that are not
(harmonics, interference), plus a possibly time-varying offset, data gaps and noise
(Gaussian or uniform), and carries the metadata the accuracy bench needs
(:class:`~sinewatch.scenarios.base.BenchInfo`: nominal frequencies, steady-state
windows, events, reporting rate, the limits to judge against; derived from the truth when
a scenario does not declare them, as the demo feeds do).

Truth convention (scenarios/base.py): ``y = offset + sum_k amplitude_k sin(phase_k)``.
While a component's amplitude is zero (a dropout, a component that vanishes) its truth
keeps the frequency and phase of the underlying oscillator; the bench ignores frequency
and phase errors there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sinewatch.scenarios.base import BenchInfo, FaultPlan, Scenario, ScenarioStream, Truth, wrap_phase

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class Component:
    """One sinusoid ``a(t) sin(phase(t))``; all times in seconds, frequencies in Hz.

    * frequency ``f0``, ramped at ``rocof`` Hz/s between ``ramp_start`` and ``ramp_stop``
      (held before and after);
    * sinusoidal frequency modulation ``f0 * fm_depth * sin(2 pi fm_hz t)`` (paper 001's
      ``w(t) = w0 [1 + 0.5 sin(0.01 w0 t)]``);
    * phase modulation ``pm_depth_rad * cos(2 pi pm_hz t - pi)`` and amplitude modulation
      ``a0 * (1 + am_depth * cos(2 pi am_hz t))`` (C37.118.1 measurement-bandwidth test);
    * at ``t_step``: frequency jumps to ``f_step_to`` (phase continuous), amplitude is
      multiplied by ``a_step_factor``, phase gains ``phase_step_rad``.
    """

    f0: float
    a0: float = 1.0
    phi0: float = 0.0
    rocof: float = 0.0
    ramp_start: float = 0.0
    ramp_stop: float = math.inf
    fm_depth: float = 0.0
    fm_hz: float = 0.0
    pm_depth_rad: float = 0.0
    pm_hz: float = 0.0
    am_depth: float = 0.0
    am_hz: float = 0.0
    t_step: float = math.inf
    f_step_to: float | None = None
    a_step_factor: float = 1.0
    phase_step_rad: float = 0.0

    def __post_init__(self) -> None:
        if self.f_step_to is not None and (self.fm_depth or self.pm_depth_rad or self.rocof):
            raise ValueError("Component: a frequency step cannot be combined with a ramp or modulation")

    @property
    def is_stationary(self) -> bool:
        return (
            self.rocof == 0.0
            and self.fm_depth == 0.0
            and self.pm_depth_rad == 0.0
            and self.am_depth == 0.0
            and not math.isfinite(self.t_step)
        )

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(frequency Hz, amplitude, unwrapped phase rad, rocof Hz/s) at times t."""
        t1, t2 = self.ramp_start, self.ramp_stop
        u = np.clip(t - t1, 0.0, t2 - t1)  # time spent ramping so far
        freq = self.f0 + self.rocof * u
        # integral of rocof * clip(s - t1, 0, t2 - t1) ds from 0 to t
        cycles = self.f0 * t + self.rocof * (0.5 * u * u + u * np.maximum(t - t2, 0.0))
        rocof = np.where((t >= t1) & (t < t2), self.rocof, 0.0)
        if self.fm_depth:
            wm = TWO_PI * self.fm_hz
            freq = freq + self.f0 * self.fm_depth * np.sin(wm * t)
            cycles = cycles + self.f0 * self.fm_depth * (1.0 - np.cos(wm * t)) / wm
            rocof = rocof + self.f0 * self.fm_depth * wm * np.cos(wm * t)
        extra_phase = np.zeros_like(t)
        if self.pm_depth_rad:
            wp = TWO_PI * self.pm_hz
            arg = wp * t - math.pi
            extra_phase = self.pm_depth_rad * np.cos(arg)
            freq = freq - self.pm_depth_rad * self.pm_hz * np.sin(arg)
            rocof = rocof - self.pm_depth_rad * self.pm_hz * wp * np.cos(arg)
        after = t >= self.t_step
        if self.f_step_to is not None and math.isfinite(self.t_step):
            ts = self.t_step
            freq = np.where(after, self.f_step_to, freq)
            cycles = np.where(after, self.f0 * ts + self.f_step_to * (t - ts), cycles)
            rocof = np.where(after, 0.0, rocof)
        amp = self.a0 * np.where(after, self.a_step_factor, 1.0)
        if self.am_depth:
            amp = amp * (1.0 + self.am_depth * np.cos(TWO_PI * self.am_hz * t))
        phase = TWO_PI * cycles + self.phi0 + extra_phase + np.where(after, self.phase_step_rad, 0.0)
        return freq, amp, phase, rocof


class Composite(Scenario):
    """Estimated components + disturbances + offset + gaps + noise (see module docstring).

    ``offset``: constant; ``offset_step_to`` from ``offset_t_step`` on; plus
    ``offset_decay * exp(-(t - offset_decay_start) / offset_tau)`` from
    ``offset_decay_start`` on. ``dropout=(t0, t1)``: the signal and offset are zero there
    (noise continues). ``skip=(t0, seconds)``: the stream loses ``seconds`` of signal at
    ``t0`` (samples after it are those of time ``t + seconds``). ``uniform_noise``: the
    half-width of additive uniform noise (paper 004's bounded disturbance) instead of
    Gaussian ``noise_std``. ``faults``: the transport faults a feed injects.
    """

    def __init__(
        self,
        name: str,
        summary: str,
        components: list[Component],
        bench: BenchInfo | None = None,
        *,
        disturbances: list[Component] | None = None,
        offset: float = 0.0,
        offset_step_to: float | None = None,
        offset_t_step: float = math.inf,
        offset_decay: float = 0.0,
        offset_tau: float = 1.0,
        offset_decay_start: float = 0.0,
        dropout: tuple[float, float] | None = None,
        skip: tuple[float, float] | None = None,
        uniform_noise: float = 0.0,
        tags: tuple[str, ...] = (),
        faults: FaultPlan | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        if faults is not None:
            self.faults = faults
        self.name = name
        self.summary = summary
        self.tags = tuple(tags)
        self.components = list(components)
        self.disturbances = list(disturbances or [])
        self._bench = bench
        self.offset = float(offset)
        self.offset_step_to = offset_step_to
        self.offset_t_step = float(offset_t_step)
        self.offset_decay = float(offset_decay)
        self.offset_tau = float(offset_tau)
        self.offset_decay_start = float(offset_decay_start)
        self.dropout = dropout
        self.skip = skip
        self.uniform_noise = float(uniform_noise)
        if bench is not None and len(bench.nominal_frequency_hz) != len(self.components):
            raise ValueError(
                f"{name}: expected one nominal frequency per component ({len(self.components)}), "
                f"got {len(bench.nominal_frequency_hz)}"
            )

    # ---- properties the bench reads -------------------------------------------------------
    @property
    def n_components(self) -> int:
        return len(self.components)

    @property
    def noise_free(self) -> bool:
        return self.noise_std == 0.0 and self.uniform_noise == 0.0

    @property
    def is_stationary(self) -> bool:
        """One steady biased tone in white Gaussian noise: the CRLB applies."""
        return (
            len(self.components) == 1
            and self.components[0].is_stationary
            and not self.disturbances
            and self.offset_step_to is None
            and self.offset_decay == 0.0
            and self.dropout is None
            and self.skip is None
            and self.uniform_noise == 0.0
            and self.noise_std > 0.0
        )

    # ---- signal -----------------------------------------------------------------------------
    def _time(self, t: np.ndarray) -> np.ndarray:
        if self.skip is None:
            return t
        t0, lost = self.skip
        return np.where(t >= t0, t + lost, t)

    def _offset(self, t: np.ndarray) -> np.ndarray:
        b = np.full(t.shape, self.offset)
        if self.offset_step_to is not None:
            b = np.where(t >= self.offset_t_step, self.offset_step_to, b)
        if self.offset_decay:
            dt = t - self.offset_decay_start
            b = b + np.where(dt >= 0.0, self.offset_decay * np.exp(-np.maximum(dt, 0.0) / self.offset_tau), 0.0)
        return b

    def clean(self, t: np.ndarray) -> tuple[np.ndarray, Truth]:
        ta = self._time(t)
        cols = [c.evaluate(ta) for c in self.components]
        freq = np.stack([c[0] for c in cols], axis=1)
        amp = np.stack([c[1] for c in cols], axis=1)
        phase = np.stack([c[2] for c in cols], axis=1)
        rocof = np.stack([c[3] for c in cols], axis=1)
        offset = self._offset(ta)
        y = offset + np.sum(amp * np.sin(phase), axis=1)
        for d in self.disturbances:
            _, da, dp, _ = d.evaluate(ta)
            y = y + da * np.sin(dp)
        if self.dropout is not None:
            off = (t >= self.dropout[0]) & (t < self.dropout[1])
            y = np.where(off, 0.0, y)
            amp = np.where(off[:, None], 0.0, amp)
            offset = np.where(off, 0.0, offset)
        return y, Truth(freq, amp, wrap_phase(phase), offset, rocof)

    def stream(self, seed: int = 0) -> ScenarioStream:
        return _CompositeStream(self, seed)


class _CompositeStream(ScenarioStream):
    """Adds uniform noise when the scenario asks for it (drawn sequentially from a
    generator of its own, so block-wise reads equal one read)."""

    def __init__(self, scenario: Composite, seed: int) -> None:
        super().__init__(scenario, seed)
        self._urng = np.random.default_rng([seed, 0x55])

    def read(self, n: int) -> tuple[np.ndarray, Truth]:
        samples, truth = super().read(n)
        h = self.scenario.uniform_noise  # type: ignore[attr-defined]
        if h > 0:
            samples = samples + self._urng.uniform(-h, h, n)
        return samples, truth


def snr_noise_std(amplitude: float, snr_db: float) -> float:
    """Noise standard deviation giving SNR = A^2 / (2 sigma^2) = snr_db."""
    return amplitude / math.sqrt(2.0 * 10.0 ** (snr_db / 10.0))
