"""Estimator registry.

``create(name, sample_rate_hz, **params)`` builds an estimator by name;
``available()`` lists the names with their parameter models. Every module in this
package (other than ``base``) is imported once and registers its class with
:func:`register`, so adding an estimator means adding one module.
"""

from __future__ import annotations

import importlib
import pkgutil
from typing import Any, TypeVar

from pydantic import ValidationError

from sinewatch.estimators.base import Estimator, EstimatorParams, Track
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.errors import ConfigError, UnknownEstimatorError

__all__ = ["Estimator", "EstimatorParams", "Track", "available", "check_rules", "create", "get", "register"]

_REGISTRY: dict[str, type[Estimator[Any]]] = {}
_LOADED = False


_E = TypeVar("_E", bound=type[Estimator[Any]])


def register(cls: _E) -> _E:
    """Class decorator: make an estimator available by its ``name``."""
    name = cls.name
    if name in _REGISTRY and _REGISTRY[name] is not cls:
        raise ValueError(f"estimator name {name!r} registered twice")
    _REGISTRY[name] = cls
    return cls


def _load_all() -> None:
    global _LOADED
    if _LOADED:
        return
    for mod in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if mod.name != "base" and not mod.name.startswith("_"):
            importlib.import_module(f"{__name__}.{mod.name}")
    _LOADED = True


def available() -> dict[str, type[EstimatorParams]]:
    """Registered estimator names, sorted, with their parameter models."""
    _load_all()
    return {name: _REGISTRY[name].Params for name in sorted(_REGISTRY)}


def get(name: str) -> type[Estimator[Any]]:
    _load_all()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise UnknownEstimatorError(f"estimator: expected one of {sorted(_REGISTRY)}, got {name!r}") from None


def create(name: str, sample_rate_hz: float, **params: Any) -> Estimator[Any]:
    """Build the estimator registered as ``name`` for a channel sampled at ``sample_rate_hz``."""
    return get(name)(sample_rate_hz, params)


def check_rules(rules: list[EstimatorRule]) -> None:
    """Check every rule's estimator name and parameters against the estimator's own model;
    raise ConfigError naming the rule and what was expected."""
    problems = []
    for i, rule in enumerate(rules):
        try:
            get(rule.estimator).Params.model_validate(rule.params)
        except UnknownEstimatorError as exc:
            problems.append(f"  rules[{i}] ({rule.match}): {exc}")
        except ValidationError as exc:
            for err in exc.errors():
                where = ".".join(str(p) for p in err["loc"]) or "(params)"
                what = "unknown key" if err["type"] == "extra_forbidden" else err["msg"]
                problems.append(f"  rules[{i}] ({rule.match}) {rule.estimator} params.{where}: {what}")
    if problems:
        raise ConfigError("invalid estimator rules:\n" + "\n".join(problems))
