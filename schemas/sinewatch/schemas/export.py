"""Export the JSON Schemas of the wire format, the config and every estimator's parameters.

The estimators' parameter models are handed in by the caller (``sinewatch schemas export``
passes :func:`sinewatch.estimators.available`), so this layer imports no estimator.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from sinewatch.schemas.config import SinewatchConfig
from sinewatch.schemas.messages import MESSAGE_MODELS
from sinewatch.schemas.power_quality import PQ_MESSAGE_MODELS


def all_schemas(estimator_params: Mapping[str, type[BaseModel]]) -> dict[str, dict[str, Any]]:
    models = {**MESSAGE_MODELS, **PQ_MESSAGE_MODELS}
    out = {f"{name}.json": model.model_json_schema() for name, model in models.items()}
    out["Config.json"] = SinewatchConfig.model_json_schema()
    for name, params in estimator_params.items():
        out[f"estimators/{name}.json"] = params.model_json_schema()
    return out


def export_schemas(directory: Path, estimator_params: Mapping[str, type[BaseModel]]) -> list[Path]:
    written = []
    for rel, schema in all_schemas(estimator_params).items():
        path = directory / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(schema, indent=2, sort_keys=True) + "\n", encoding="utf-8")
        written.append(path)
    return written
