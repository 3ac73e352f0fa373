"""The papers' own simulations, as scenarios (tag "paper").

Each keeps the paper's signal, noise and (where given) sampling; what the paper leaves
open is chosen here and said so in the summary. ``bench.reference`` records what the paper
reported, so that docs/accuracy.md can set the measured figure beside it.

* paper 000 ("A globally exponentially stable (GES) discrete-time observer for the
  parameters of a biased sinusoid", Section IV): ``s(t) = sin(2 pi 100 t) + 1``,
  fs = 1 kHz, Gaussian noise std 0.01; and the chirp ``f(t) = t`` Hz (1 Hz/s), same noise.
  Duration not stated: 10 s for the tone, 200 s for the chirp (the paper quotes the error
  at t = 180 s).
* paper 001 ("Differential signal model and sampling techniques for recursive (extended)
  least-squares estimation of frequency, frequency derivatives, phase and amplitude",
  Section 10): w = 1 rad/s, A = 1, noise-free (Fig. 1) and at 10 log10(A^2 / 2 sigma^2)
  = 5.2 dB (Fig. 2, sigma^2 = 0.15); tracking of ``w(t) = w0 [1 + 0.5 sin(0.01 w0 t)]``
  (Fig. 3, noise not stated: none here). The paper gives no sample rate (results are per
  "samples/cycle"): 10 Hz here, 63 samples per cycle.
  Its own setting, in-phase/quadrature components (N, 2) = (y, z) = A (sin, cos)(w t +
  phi), phi = 0.3, served by ``differential-rls`` with ``input = "iq"``: ``paper001-iq-fig1``
  (noise-free, n = 4, intervals cycling 0.6 s, 0.54 s: the I/Q stream at 50 Hz, decimated
  by 30, 27), ``paper001-iq-noisy`` (white noise sigma^2 = 0.15 per component, eq. 11's
  model, 5.2 dB, n = 2, dt = 0.2 s), ``paper001-iq-fig3`` (the Fig. 3 frequency, with the
  derivative model of eqs. 24-25).
* paper 003 (L. Praly, L. Marconi, A. Isidori, "A new observer for an unknown harmonic
  oscillator", Section V): ``2 sin(3 t)`` plus a 10 % harmonic ``0.2 sin(W t)``,
  W = 10, 100, 1000 rad/s; no random noise. Continuous-time in the paper; sampled at
  1 kHz here (the 1000 rad/s component is 159 Hz). Duration not stated: 60 s.
* paper 004 (B. Chen, G. Pin, W. N. Ng, S. Y. Hui, T. Parisini, "An adaptive
  observer-based robust estimator of multi-sinusoidal signals", Section V-A),
  Ts = 3e-4 s: Example 1 ``sin 2t + sin 5t`` noise-free and with uniform noise in
  [-0.25, 0.25]; Example 2 ``4 sin 3t + A2(t) sin 2t + 1 + d(t)``, A2 = 3 until
  t = 120 s then 0; Example 3 ``sin w1(t) t + sin w2(t) t + d(t)`` with w1: 2 -> 3 rad/s
  and w2: 5 -> 4.5 rad/s at t = 70 s (read as frequency steps with continuous phase); the
  experiment (Section V-B) ``4 sin 7t + 2 sin 5t`` at 10 kHz with "additive random noise" of unstated level
  (Gaussian std 0.05 here). Durations not stated: 100 s, 240 s, 140 s, 30 s.
* The nominal frequency handed to the estimators that take one is 10 % below the truth
  for the stationary signals (the papers' own estimators need none).
* paper 002 (observer with a periodic output disturbance) is not here: its plant's input
  matrix and the disturbance waveform are lost from the extraction, and its unknowns are
  plant states, not sinusoid parameters.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sinewatch.estimators.differential_rls import cyclic_intervals
from sinewatch.scenarios import BenchInfo, Component, Event, Scenario, ScenarioStream, Truth, declare, register
from sinewatch.scenarios._library import served_by
from sinewatch.scenarios.base import NoiseOnEveryColumn, wrap_phase

TWO_PI = 2.0 * math.pi


def _hz(rad_per_s: float) -> float:
    return rad_per_s / TWO_PI


# Section IV: fs = 1 kHz, noise std 0.01; ges-kalman with the paper's Q and R
_P000: dict[str, Any] = {"sample_rate_hz": 1000.0, "noise_std": 0.01, "suggested_params": {"q": 1e-6, "r": 1e-2}}


def _paper000(
    name: str, summary: str, component: Component, bench: dict[str, Any], tags: tuple[str, ...], duration_s: float
) -> None:
    """A paper-000 signal: offset 1, 1 kHz, the paper's noise and Kalman tuning; ``bench``
    completes the BenchInfo over the full band 1-499 Hz."""
    declare(
        name,
        summary,
        [component],
        BenchInfo(frequency_range_hz=(1.0, 499.0), **bench),
        offset=1.0,
        tags=("paper", "paper000", *tags),
        defaults={**_P000, "duration_s": duration_s},
    )


_paper000(
    "paper000-tone",
    "paper 000 IV-A: sin(2 pi 100 t) + 1 at 1 kHz, noise std 0.01",
    Component(100.0),
    {
        "nominal_frequency_hz": (90.0,),
        "steady_windows": ((1.0, 10.0),),
        "reference": {
            "convergence_time_s": "< 0.01 (Fig. 1)",
            "frequency_error_hz": "0.2 most of the time (Fig. 2)",
            "offset_error": "< 0.05 most of the time (Fig. 4)",
        },
    },
    ("stationary", "quick"),
    10.0,
)
_paper000(
    "paper000-chirp",
    "paper 000 IV-B: linear chirp f(t) = t Hz (1 Hz/s) + offset 1 at 1 kHz, noise std 0.01",
    Component(0.0, rocof=1.0),
    {
        "nominal_frequency_hz": (100.0,),  # mid-sweep: the estimators that need one
        "steady_windows": ((20.0, 200.0),),
        "tolerance_hz": 1.0,
        "reference": {
            "frequency_error_hz": "about 1 at t = 180 s (Fig. 6)",
            "offset_error": "< 0.01 most of the time (Fig. 8)",
        },
    },
    ("ramp", "tracking"),
    200.0,
)


_W0 = 1.0  # paper 001's w0, rad/s


def _paper001(
    name: str,
    summary: str,
    component: Component,
    steady: tuple[float, float],
    reference: str,
    tags: tuple[str, ...],
    duration_s: float,
    noise_std: float = 0.0,
) -> None:
    """A paper-001 signal around w0 = 1 rad/s, sampled at 10 Hz (assumed), nominal 0.9 w0,
    band 0.2-5 rad/s; ``reference`` is what the paper says of the frequency error."""
    declare(
        name,
        summary,
        [component],
        BenchInfo(
            nominal_frequency_hz=(_hz(0.9 * _W0),),
            frequency_range_hz=(_hz(0.2), _hz(5.0)),
            steady_windows=(steady,),
            reference={"frequency_error": reference},
        ),
        tags=("paper", "paper001", *tags),
        defaults={"sample_rate_hz": 10.0, "duration_s": duration_s, "noise_std": noise_std},
    )


def paper001_baseband(
    k: int, intervals: list[float], w: float = _W0, phase: float = 0.3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Paper 001's own setting (Section 10), complex baseband rather than a sampled real
    signal, hence no scenario: ``k`` sampling intervals cycling through ``intervals``
    (nonuniform cyclic sampling; dt[0] = 0), the sample times and the noise-free in-phase /
    quadrature samples ``c = exp(j (w t + phase))``, for
    :func:`sinewatch.estimators.differential_rls.baseband_estimate`."""
    dt = cyclic_intervals(k, intervals)
    t = np.cumsum(dt)
    return dt, t, np.exp(1j * (w * t + phase))


_paper001(
    "paper001-tone",
    "paper 001 Fig. 1: w = 1 rad/s, A = 1, noise-free, sampled at 10 Hz (rate assumed)",
    Component(_hz(_W0)),
    (50.0, 100.0),
    "within a few percent in a fraction of a period (Fig. 1)",
    ("stationary",),
    100.0,
)
_paper001(
    "paper001-tone-noisy",
    "paper 001 Fig. 2: w = 1 rad/s, A = 1, SNR 5.2 dB (sigma^2 = 0.15), 10 Hz sampling (assumed)",
    Component(_hz(_W0)),
    (50.0, 100.0),
    "close to the optimum in the first 10 samples (Fig. 2)",
    ("stationary", "snr"),
    100.0,
    noise_std=math.sqrt(0.15),
)
_paper001(
    "paper001-fm",
    "paper 001 Fig. 3: w(t) = w0 [1 + 0.5 sin(0.01 w0 t)], w0 = 1 rad/s, noise-free, 10 Hz",
    Component(_hz(_W0), fm_depth=0.5, fm_hz=_hz(0.01 * _W0)),
    (100.0, 1300.0),
    "the estimate follows closely the true frequency (Fig. 3)",
    ("tracking", "modulation"),
    1300.0,
)


class Paper001IQ(Scenario):
    """Paper 001's own measurements (eqs. 1-2) as a two-column stream: column 0 the
    in-phase ``y = A sin(w t + phi)``, column 1 the quadrature ``z = A cos(w t + phi)``,
    relative to an oscillator at 0 Hz (baseband), plus white Gaussian noise of std
    ``noise_std`` on each component. Truth: the component (y = amplitude sin(phase), no offset)."""

    tags = ("paper", "paper001", "iq")

    def __init__(self, name: str, summary: str, component: Component, steady: tuple[float, float],
                 reference: str, **kw: Any) -> None:  # fmt: skip
        super().__init__(**kw)
        self.name = name
        self.summary = summary
        self.component = component
        self._bench = BenchInfo(
            nominal_frequency_hz=(0.0,),
            frequency_range_hz=(_hz(0.2), _hz(2.0)),
            steady_windows=(steady,),
            reference={"frequency_error": reference},
            crlb=False,
        )

    @property
    def n_inputs(self) -> int:
        return 2

    def clean(self, t: np.ndarray) -> tuple[np.ndarray, Truth]:
        f, a, ph, rocof = self.component.evaluate(t)
        iq = np.column_stack([a * np.sin(ph), a * np.cos(ph)])
        return iq, Truth(f[:, None], a[:, None], wrap_phase(ph)[:, None], np.zeros(t.size), rocof[:, None])

    def stream(self, seed: int = 0) -> ScenarioStream:
        return NoiseOnEveryColumn(self, seed)  # noise on both components


#: differential-rls on paper 001's I/Q at 50 Hz, Fig. 1: n = 4, decimation 30, 27 (dt = 0.6 s,
#: 0.54 s: B_N = 1/6 Hz, M = 5, cyclic spacing 0.1), lambda = 0.995, no ELS (noise-free)
PAPER001_IQ_FIG1: dict[str, Any] = {
    "input": "iq",
    "nominal_frequency_hz": 0.0,
    "bandwidth_hz": 1.0 / 6.0,
    "oversampling": 5.0,
    "n_terms": 4,
    "rocof_model": False,
    "forgetting_factor": 0.995,
    "els": False,
    "tracking_range_hz": 0.5,
}
#: white noise (eq. 11): n = 2, dt = 0.2 s (B_N = 0.5 Hz, M = 5, decimation 10), ELS with r1 = 0
PAPER001_IQ_NOISY: dict[str, Any] = {
    "input": "iq",
    "nominal_frequency_hz": 0.0,
    "bandwidth_hz": 0.5,
    "oversampling": 5.0,
    "n_terms": 2,
    "rocof_model": False,
    "forgetting_factor": 0.995,
    "noise_correlation": 0.0,
    "recenter_every": 0,
}
#: Fig. 3: Fig. 1's sampling, lambda = 0.9, the derivative model, re-centring every 10 samples
PAPER001_IQ_FIG3: dict[str, Any] = {
    **PAPER001_IQ_FIG1,
    "rocof_model": True,
    "forgetting_factor": 0.9,
    "recenter_every": 10,
    "convergence_rel_std": 0.01 / 2.0 * 6.0 / math.pi,  # 0.01 rad/s, as the offline run
}


def _paper001_iq(name: str, summary: str, component: Component, steady: tuple[float, float], reference: str,
                 params: dict[str, Any], duration_s: float, noise_std: float = 0.0) -> None:  # fmt: skip
    def factory(**overrides: Any) -> Scenario:
        kw = {**served_by("differential-rls", params, 50.0, duration_s, noise_std), **overrides}
        return Paper001IQ(name, summary, component, steady, reference, **kw)

    factory.__name__ = name.replace("-", "_")
    register(name)(factory)


_paper001_iq(
    "paper001-iq-fig1",
    "paper 001 Fig. 1 in its own setting: I/Q of w = 1 rad/s, A = 1, noise-free, 50 Hz, cyclic 0.6/0.54 s",
    Component(_hz(_W0), phi0=0.3),
    (100.0, 1800.0),
    "within a few percent in a fraction of a period (Fig. 1)",
    {**PAPER001_IQ_FIG1, "recenter_every": 10},
    1800.0,
)
_paper001_iq(
    "paper001-iq-noisy",
    "paper 001 eq. (11)'s noise: I/Q of w = 1 rad/s, A = 1, white noise sigma^2 = 0.15 (5.2 dB), 50 Hz",
    Component(_hz(_W0), phi0=0.3),
    (200.0, 800.0),
    "ELS removes the bias of plain least squares (Section 3)",
    PAPER001_IQ_NOISY,
    800.0,
    math.sqrt(0.15),
)
_paper001_iq(
    "paper001-iq-fig3",
    "paper 001 Fig. 3 in its own setting: I/Q of w(t) = w0 [1 + 0.5 sin(0.01 w0 t)], w0 = 1 rad/s, 50 Hz",
    Component(_hz(_W0), phi0=0.3, fm_depth=0.5, fm_hz=_hz(0.01 * _W0)),
    (200.0, 1900.0),
    "the estimate follows closely the true frequency (Fig. 3)",
    PAPER001_IQ_FIG3,
    1900.0,
)


_P003 = {  # Section V, Figs. 1-6: steady-state mean / std of the estimates
    10.0: {
        "amplitude_mean": 1.9999,
        "amplitude_std": 0.0947,
        "frequency_rad_s_mean": 2.9956,
        "frequency_rad_s_std": 0.1164,
    },
    100.0: {"amplitude_mean": 2.0, "amplitude_std": 0.0108, "frequency_rad_s_mean": 3.0, "frequency_rad_s_std": 0.0142},
    1000.0: {
        "amplitude_mean": 2.0,
        "amplitude_std": 0.0011,
        "frequency_rad_s_mean": 3.0,
        "frequency_rad_s_std": 0.0014,
    },
}


for _w_h in (10.0, 100.0, 1000.0):
    declare(
        f"paper003-harmonic-{int(_w_h)}",
        f"paper 003 V: 2 sin(3t) + 0.2 sin({int(_w_h)} t), no noise, sampled at 1 kHz",
        [Component(_hz(3.0), a0=2.0)],
        BenchInfo(
            nominal_frequency_hz=(_hz(2.7),),
            # sqrt(f_min f_max) = 3 rad/s: with kkl's default lambda factors this gives the
            # paper's lambda = 1, 2, 3, 4 rad/s
            frequency_range_hz=(_hz(1.0), _hz(9.0)),
            steady_windows=((30.0, 60.0),),
            reference=_P003[_w_h],
        ),
        disturbances=[Component(_hz(_w_h), a0=0.2)],
        tags=("paper", "paper003", "harmonic"),
        defaults=served_by("kkl", {"f_min_hz": _hz(1.0), "f_max_hz": _hz(9.0)}, 1000.0, 60.0),
    )


_FS004 = 1.0 / 3e-4  # Ts = 3e-4 s, Section V-A
# adaptive-multisine with its automatic design: n, the band and the offset, nothing else
# (the paper tunes each example by hand; the estimator derives its gains from these).
_BAND004 = (0.5, 10.0)  # rad/s: Examples 1-3 (tones between 2 and 5 rad/s)
_BAND004_EXP = (1.0, 14.0)  # rad/s: the experiment (tones at 5 and 7 rad/s)


def _auto004(bias: bool, band: tuple[float, float]) -> dict[str, Any]:
    return {"n_sinusoids": 2, "bias": bias, "band_hz": (_hz(band[0]), _hz(band[1]))}


_GAINS_EX1 = _auto004(False, _BAND004)
_GAINS_EX2 = _auto004(True, _BAND004)
_GAINS_EXP = _auto004(False, _BAND004_EXP)


def _paper004(
    name: str,
    summary: str,
    components: list[Component],
    bench: dict[str, Any],
    gains: dict[str, Any],
    duration_s: float,
    tags: tuple[str, ...] = (),
    *,
    initial: tuple[float, float] = (3.0, 4.0),
    band: tuple[float, float] = _BAND004,
    fs: float = _FS004,
    noise_std: float = 0.0,
    **composite: Any,
) -> None:
    """An example of Section V served by adaptive-multisine with ``gains``: Ts = 0.3 ms
    unless ``fs`` says, noise-free unless said; the nominal frequencies are the initial
    guesses ``initial`` and the band ``band`` (rad/s); ``bench`` completes the BenchInfo."""
    declare(
        name,
        summary,
        components,
        BenchInfo(
            nominal_frequency_hz=(_hz(initial[0]), _hz(initial[1])),
            frequency_range_hz=(_hz(band[0]), _hz(band[1])),
            **bench,
        ),
        tags=("paper", "paper004", "multitone", *tags),
        defaults=served_by("adaptive-multisine", gains, fs, duration_s, noise_std),
        **composite,
    )


for _suffix, _signal, _fig, _noise in (  # Example 1 with and without its noise
    ("", "sin 2t + sin 5t, noise-free", "all methods converge in a noise-free scenario (Fig. 3)", 0.0),
    (
        "-noisy",
        "sin 2t + sin 5t + uniform noise in [-0.25, 0.25]",
        "better noise immunity than [30], [32] (Fig. 4)",
        0.25,
    ),
):
    _paper004(
        f"paper004-ex1{_suffix}",
        f"paper 004 Example 1: {_signal}, Ts = 0.3 ms",
        [Component(_hz(2.0)), Component(_hz(5.0))],
        {"steady_windows": ((50.0, 100.0),), "reference": {"frequencies": _fig}},  # nominal: the initial guesses
        _GAINS_EX1,
        100.0,
        uniform_noise=_noise,
    )
_paper004(
    "paper004-ex2",
    "paper 004 Example 2: 4 sin 3t + A2 sin 2t + 1, A2 = 3 -> 0 at 120 s, uniform noise +-0.25",
    [Component(_hz(3.0), a0=4.0), Component(_hz(2.0), a0=3.0, t_step=120.0, a_step_factor=0.0)],
    {
        "steady_windows": ((60.0, 120.0), (180.0, 240.0)),
        "events": (Event(120.0, "amplitude", -3.0, component=1),),
        "reference": {"after_120_s": "the vanished component's amplitude estimate fades to 0 (Fig. 9)"},
    },
    _GAINS_EX2,
    240.0,
    ("step",),
    offset=1.0,
    uniform_noise=0.25,
)
_paper004(
    "paper004-ex3",
    "paper 004 Example 3: frequency steps 2 -> 3 and 5 -> 4.5 rad/s at 70 s, uniform noise +-0.25",
    [Component(_hz(2.0), t_step=70.0, f_step_to=_hz(3.0)), Component(_hz(5.0), t_step=70.0, f_step_to=_hz(4.5))],
    {
        "steady_windows": ((35.0, 70.0), (105.0, 140.0)),
        "events": (
            Event(70.0, "frequency_hz", _hz(1.0), component=0),
            Event(70.0, "frequency_hz", _hz(-0.5), component=1),
        ),
        "reference": {"frequencies": "tracks the sudden changes in a noisy environment (Fig. 10)"},
    },
    _GAINS_EX1,
    140.0,
    ("step",),
    uniform_noise=0.25,
)
_paper004(
    "paper004-experiment",
    "paper 004 V-B: 4 sin 7t + 2 sin 5t at 10 kHz, Gaussian noise std 0.05 (level assumed)",
    [Component(_hz(7.0), a0=4.0), Component(_hz(5.0), a0=2.0)],
    {
        "steady_windows": ((70.0, 100.0),),
        "reference": {"frequencies": "gathered with great accuracy (Figs. 13-14)"},
    },
    _GAINS_EXP,
    100.0,
    initial=(6.0, 4.0),
    band=_BAND004_EXP,
    fs=10_000.0,
    noise_std=0.05,
)
