"""The parameters of an estimator for a scenario, in the accuracy bench.

:func:`estimator_params` merges, later entries winning:

1. the estimator's ``example_params``;
2. a generic mapping by field name (:func:`generic_params`): nominal-frequency fields
   (``nominal_frequency_hz``, ``f0_hz``, ...) get the scenario's nominal frequency (a list
   field gets one per component), required range fields (``f_min_hz``/``f_max_hz``,
   ``min_frequency_hz``/``max_frequency_hz`` when their default is not None) the
   scenario's frequency range, component-count fields (``n_components``, ``n_sinusoids``,
   ...) the number of truth components;
3. the estimator's own hook, when it has one: ``params_for(sample_rate_hz, hints) ->
   dict`` (classmethod; ``hints`` as built by
   :func:`sinewatch.apps.bench.scenarios.scenario_hints`; raising ParameterError means "does
   not apply"), else an adapter from :data:`ADAPTERS`;
4. the scenario's ``suggested_params`` when its ``suggested_estimator`` is this estimator
   (the papers' own tunings).

:data:`DEFAULT_RULE` (``default-rule``) is one more column: the daemon's default rule
exactly as a user with no config gets it (:data:`sinewatch.schemas.config.DEFAULT_ESTIMATOR`
at :data:`~sinewatch.schemas.config.DEFAULT_PARAMS`, nominal 50 Hz whatever the scenario):
none of the steps above applies to it (:func:`default_rule_estimator`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from sinewatch import estimators as est_registry
from sinewatch.apps.bench.scenarios import Profile, profile, scenario_hints
from sinewatch.estimators.adaptive_multisine import DESIGN, MIN_SAMPLES_PER_PERIOD
from sinewatch.estimators.base import Estimator
from sinewatch.scenarios import Scenario
from sinewatch.schemas.config import DEFAULT_ESTIMATOR, DEFAULT_PARAMS
from sinewatch.schemas.errors import ParameterError

TWO_PI = 2.0 * math.pi


class NotApplicable(Exception):
    """This estimator does not apply to this scenario (the message says why)."""


NOMINAL_HZ_FIELDS = (
    "nominal_frequency_hz",
    "nominal_hz",
    "f_nominal_hz",
    "f0_hz",
    "initial_frequency_hz",
    "frequency_hz",
    "center_frequency_hz",
    "centre_frequency_hz",
    "reference_frequency_hz",
    "initial_frequencies_hz",
    "nominal_frequencies_hz",
    "frequencies_hz",
)
RANGE_LO_FIELDS = ("f_min_hz", "min_frequency_hz", "frequency_min_hz")
RANGE_HI_FIELDS = ("f_max_hz", "max_frequency_hz", "frequency_max_hz")
COUNT_FIELDS = ("n_components", "n_sinusoids", "n_tones", "num_components")
TIME_UNIT_FIELDS: tuple[str, ...] = ()  # none left: adaptive-multisine designs itself from its band


def _is_list_field(fld: Any) -> bool:
    return "list" in str(fld.annotation).lower() or "tuple" in str(fld.annotation).lower()


def generic_params(cls: type[Estimator], hints: dict[str, Any]) -> dict[str, Any]:
    """Step 2 of :func:`estimator_params`: the mapping by field name."""
    fields = cls.Params.model_fields
    nom = tuple(hints["nominal_frequency_hz"])
    k = len(nom)
    fmean = float(np.mean(nom)) if k else 0.0
    lo, hi = hints["frequency_range_hz"]
    out: dict[str, Any] = {}
    for name, fld in fields.items():
        if name in NOMINAL_HZ_FIELDS:
            out[name] = list(nom) if _is_list_field(fld) else (nom[0] if k == 1 else fmean)
        elif name in RANGE_LO_FIELDS and fld.default is not None:
            out[name] = float(lo)
        elif name in RANGE_HI_FIELDS and fld.default is not None:
            out[name] = float(hi)
        elif name in COUNT_FIELDS:
            out[name] = k
        elif name in TIME_UNIT_FIELDS and fmean > 0:
            out[name] = TWO_PI * fmean
    return out


def _ges_kalman_params(fs: float, hints: dict[str, Any]) -> dict[str, Any]:
    """ges-kalman: the paper tunes Q = 1e-6 I for w Ts = 0.2 pi (100 Hz at 1 kHz). The
    states scale as x2 ~ A (w Ts) and x3, x4 ~ (w Ts)^2, so the random walks are scaled by
    (w Ts / 0.2 pi)^2 and ^4 to keep the same relative agility at other rates.

    R is a hundredth of the noise variance, floored at 1e-3 A^2. Not R = sigma^2, the
    textbook choice: the noisy sample also enters the transition matrix (eq. 6), a noisy
    regressor that biases x3 towards 0 the more, the longer the filter's memory; with
    R = sigma^2 the memory at 10 dB SNR is long enough for a -1.9 Hz bias (RMSE 2.1 Hz at
    50.5 Hz, 21 Hz at 0 dB) and a reported sd that describes the spread but not the bias
    (calibration 0.66 at 10 dB, 1.7 at 0 dB). A shorter memory: RMSE 0.72 Hz at 10 dB,
    3.5 Hz at 0 dB, calibration 0.95-1.08 at 0 to 60 dB. The floor keeps the memory at high
    SNR, costing about 3.5 dB of RMSE there against the former floor of 1e-2
    (``sinewatch bench accuracy --estimators ges-kalman --scenarios snr --trials 30``).

    The bias correction (B1-B4 of ``_ges_kalman_kernels``) is off: this tuning's memory is
    short enough at 0 dB that x3_hat's own noise breaks its second-order expansion (frequency
    calibration 1.41 with it, 1.005 without, 12 trials of ``tone-snr-00db``)."""
    f = max(hints["nominal_frequency_hz"][0], 1e-9)
    rel = (TWO_PI * f / fs) / (0.2 * math.pi)
    q = 1e-6
    amplitude = max(hints.get("amplitude") or (1.0,))
    r = max(1e-3 * amplitude**2, float(hints.get("noise_std") or 0.0) ** 2 / 100.0)
    return {"q": [q * rel**2, q * rel**2, q * rel**4, q * rel**4], "r": r, "bias_correction": False}


def _adaptive_multisine_params(fs: float, hints: dict[str, Any]) -> dict[str, Any]:
    """adaptive-multisine: its automatic design, from the number of components and the
    scenario's frequency band only (a band from 0 starts at a twentieth of its top; the top
    is kept where the estimator's discretisation needs it: MIN_SAMPLES_PER_PERIOD samples
    per period, with the band's margin)."""
    if len(hints["nominal_frequency_hz"]) < 2:
        # as before its automatic design: the validity bench (tests/test_validity.py) checks
        # it on its own two-tone example; on one tone its law runs on the observer's free
        # response during an interruption's detection latency (a wild frequency for ~50 ms)
        raise NotApplicable("adaptive-multisine is benchmarked on two or more tones")
    lo, hi = hints["frequency_range_hz"]
    hi = min(float(hi), fs / MIN_SAMPLES_PER_PERIOD / (1.0 + DESIGN["band_margin"]))
    lo = float(lo) if lo > 0 else hi / 20.0
    return {"n_sinusoids": len(hints["nominal_frequency_hz"]), "band_hz": (min(lo, hi / 2.0), hi)}


# Used for an estimator that has no ``params_for`` classmethod of its own.
ADAPTERS: dict[str, Callable[[float, dict[str, Any]], dict[str, Any]]] = {
    "ges-kalman": _ges_kalman_params,
    "adaptive-multisine": _adaptive_multisine_params,
}


def _is_base_hook(hook: Any) -> bool:
    """True for the Estimator base class's own params_for (should base.py ever declare a
    default one): that is "no hook", so the bench adapter still applies."""
    base = getattr(Estimator, "params_for", None)
    return base is not None and getattr(hook, "__func__", hook) is getattr(base, "__func__", base)


def estimator_params(cls: type[Estimator], sc: Scenario, prof: Profile | None = None) -> tuple[dict[str, Any], str]:
    """Parameters of estimator class ``cls`` for scenario ``sc`` and where they came from
    (see the module docstring). Raises :class:`NotApplicable`."""
    prof = prof or profile(sc)
    hints = scenario_hints(sc, prof)
    params: dict[str, Any] = dict(cls.example_params)
    sources = ["example"]
    generic = generic_params(cls, hints)
    if generic:
        params.update(generic)
        sources.append("generic")
    hook = getattr(cls, "params_for", None)
    if callable(hook) and not _is_base_hook(hook):
        try:
            own = hook(sc.sample_rate_hz, hints)
        except ParameterError as exc:
            raise NotApplicable(str(exc)) from exc
        if own is None:
            raise NotApplicable(f"{cls.name}.params_for declined")
        params.update(own)
        sources.append("params_for")
    elif cls.name in ADAPTERS:
        params.update(ADAPTERS[cls.name](sc.sample_rate_hz, hints))
        sources.append("bench adapter")
    if getattr(sc, "suggested_estimator", None) == cls.name and sc.suggested_params:
        params.update(sc.suggested_params)
        sources.append("scenario")
    return params, "+".join(sources)


def default_rule_estimator() -> tuple[type[Estimator], dict[str, Any], str]:
    """Bench column :data:`DEFAULT_RULE`: the default rule's estimator class and parameters,
    untouched by the scenario (what a user with no config gets)."""
    return est_registry.get(DEFAULT_ESTIMATOR), dict(DEFAULT_PARAMS), "default rule"
