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

import copy
import importlib
import pkgutil
from collections.abc import Callable
from typing import Any

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

_FACTORIES: dict[str, Callable[..., Scenario]] = {}
_LOADED = False


def register(name: str) -> Callable[[Callable[..., Scenario]], Callable[..., Scenario]]:
    """Decorator for a factory ``(**overrides) -> Scenario`` registered under ``name``."""

    def deco(factory: Callable[..., Scenario]) -> Callable[..., Scenario]:
        if name in _FACTORIES and _FACTORIES[name] is not factory:
            raise ValueError(f"scenario name {name!r} registered twice")
        _FACTORIES[name] = factory
        return factory

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


def _load_all() -> None:
    global _LOADED
    if _LOADED:
        return
    for mod in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if mod.name != "base" and not mod.name.startswith("_"):
            importlib.import_module(f"{__name__}.{mod.name}")
    _LOADED = True


def names() -> list[str]:
    _load_all()
    return sorted(_FACTORIES)


def get(name: str, **overrides: Any) -> Scenario:
    """Build scenario ``name``; overrides go to its factory (sample_rate_hz, duration_s, ...)."""
    _load_all()
    try:
        factory = _FACTORIES[name]
    except KeyError:
        raise ParameterError(f"scenario: expected one of {sorted(_FACTORIES)}, got {name!r}") from None
    return factory(**overrides)
