"""Loading the configuration from a file plus the environment.

Precedence: defaults < file (TOML or JSON, by extension) < environment. Environment
variables are ``SINEWATCH__<SECTION>__<KEY>=value`` (double underscores separate levels,
names are case-insensitive, values are parsed as JSON when they parse, else taken as
strings), e.g. ``SINEWATCH__ZENOH__MODE=client`` or
``SINEWATCH__ZENOH__CONNECT='["tcp/10.0.0.1:7447"]'``. ``SINEWATCH_CONFIG`` names a file
when ``--config`` is not given. Unknown keys are rejected, from either source.
"""

from __future__ import annotations

import json
import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from sinewatch.errors import ConfigError
from sinewatch.schemas.config import SinewatchConfig

ENV_PREFIX = "SINEWATCH__"
ENV_FILE = "SINEWATCH_CONFIG"


def load_config(path: str | Path | None = None, env: Mapping[str, str] | None = None) -> SinewatchConfig:
    env = os.environ if env is None else env
    path = path or env.get(ENV_FILE)
    data: dict[str, Any] = read_config_file(Path(path)) if path else {}
    _merge(data, env_overrides(env))
    try:
        return SinewatchConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"invalid configuration{f' in {path}' if path else ''}:\n{_explain(exc)}") from None


def read_config_file(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"config file {path}: {exc.strerror}") from None
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            data = tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"config file {path}: not valid {path.suffix.lstrip('.') or 'TOML'}: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path}: expected a table at the top, got {type(data).__name__}")
    return data


def env_overrides(env: Mapping[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, raw in env.items():
        if not name.upper().startswith(ENV_PREFIX):
            continue
        path = [p.lower() for p in name[len(ENV_PREFIX) :].split("__")]
        if not all(path):
            raise ConfigError(f"environment variable {name}: empty level in the name")
        try:
            value: Any = json.loads(raw)
        except ValueError:
            value = raw
        node = out
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"environment variable {name}: {part} is not a section")
        node[path[-1]] = value
    return out


def _merge(base: dict[str, Any], over: Mapping[str, Any]) -> None:
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(base.get(k), dict):
            _merge(base[k], v)
        else:
            base[k] = v


def _explain(exc: ValidationError) -> str:
    lines = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "(top)"
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        lines.append(f"  {loc}: {msg}")
    return "\n".join(lines)


def config_to_json(config: SinewatchConfig) -> str:
    return json.dumps(config.model_dump(mode="json"), indent=2)
