"""Estimator registry.

``create(name, sample_rate_hz, **params)`` builds an estimator by name;
``available()`` lists the names with their parameter models. Every module in this
package (other than ``base``) is imported once and registers its class with
:func:`register`, so adding an estimator means adding one module.
"""

from __future__ import annotations

import sinewatch.host_arithmetic  # noqa: F401  # first, before numpy loads (its docstring says why)

# isort: split

from typing import Any, TypeVar

from pydantic import ValidationError

from sinewatch.estimators.base import Estimator, EstimatorParams, Track
from sinewatch.registry import Registry
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.errors import ConfigError, UnknownEstimatorError

__all__ = ["Estimator", "EstimatorParams", "Track", "available", "check_rules", "create", "get", "register"]

_E = TypeVar("_E", bound=type[Estimator[Any]])
_REGISTRY: Registry[type[Estimator[Any]]] = Registry("estimator", __name__, __path__, UnknownEstimatorError)


def register(cls: _E) -> _E:
    """Class decorator: make an estimator available by its ``name``."""
    _REGISTRY.add(cls.name, cls)
    return cls


def available() -> dict[str, type[EstimatorParams]]:
    """Registered estimator names, sorted, with their parameter models."""
    return {name: _REGISTRY.get(name).Params for name in _REGISTRY.names()}


def get(name: str) -> type[Estimator[Any]]:
    return _REGISTRY.get(name)


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
