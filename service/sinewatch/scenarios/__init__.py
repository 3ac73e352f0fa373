"""Scenario library: named signals with per-sample truth, the one description of each
scenario that ``sinewatch feed``, ``sinewatch demo``, the accuracy bench and the tests read.

``get(name, **overrides)`` builds a scenario; ``names()`` lists them; ``register`` adds a
factory. Every module of this package (other than ``base`` and the private ``_library``)
is imported once and registers its scenarios, so a family of scenarios is one module.

A scenario is a :class:`Composite` of :class:`Component` sinusoids (``_library``) or, for
a signal that is not a sum of sinusoids, a :class:`Scenario` subclass of its own (paper
002's plant, ``grip_demo``). ``Tone`` and ``SumOfTones`` are other names of
:class:`Component` and :class:`Composite`, for code that reads better with them.
"""

from __future__ import annotations

import sinewatch.host_arithmetic  # noqa: F401  # first, before numpy loads (its docstring says why)

# isort: split

import copy
from collections.abc import Callable
from typing import Any

from sinewatch.registry import Registry
from sinewatch.scenarios._library import Component, Composite, snr_noise_std
from sinewatch.scenarios.base import BenchInfo, Event, FaultPlan, Scenario, ScenarioStream, Truth, wrap_phase
from sinewatch.schemas.errors import ParameterError

Tone = Component
SumOfTones = Composite

__all__ = [
    "BenchInfo",
    "Component",
    "Composite",
    "Event",
    "FaultPlan",
    "Scenario",
    "ScenarioStream",
    "SumOfTones",
    "Tone",
    "Truth",
    "declare",
    "get",
    "names",
    "register",
    "snr_noise_std",
    "wrap_phase",
]

_FACTORIES: Registry[Callable[..., Scenario]] = Registry("scenario", __name__, __path__, ParameterError)


def register(name: str) -> Callable[[Callable[..., Scenario]], Callable[..., Scenario]]:
    """Decorator for a factory ``(**overrides) -> Scenario`` registered under ``name``."""

    def deco(factory: Callable[..., Scenario]) -> Callable[..., Scenario]:
        return _FACTORIES.add(name, factory)

    return deco


def declare(
    name: str,
    summary: str,
    components: list[Component],
    bench: BenchInfo | None = None,
    *,
    defaults: dict[str, Any],
    **composite: Any,
) -> None:
    """Register scenario ``name``: a :class:`Composite` of ``components`` (``composite``:
    its other fixed arguments: disturbances, offset, tags, ...) with the sampling, noise and
    suggested estimator of ``defaults`` (``sample_rate_hz``, ``duration_s``,
    ``noise_std``, ``suggested_estimator``, ``suggested_params``), which the overrides
    given to :func:`get` replace."""

    def factory(**overrides: Any) -> Composite:
        return Composite(name, summary, components, bench, **composite, **{**copy.deepcopy(defaults), **overrides})

    factory.__name__ = name.replace("-", "_")
    register(name)(factory)


def names() -> list[str]:
    return _FACTORIES.names()


def get(name: str, **overrides: Any) -> Scenario:
    """Build scenario ``name``; overrides go to its factory (sample_rate_hz, duration_s, ...)."""
    return _FACTORIES.get(name)(**overrides)
