"""Export the JSON Schemas of the wire format, the config and every estimator's parameters."""

from __future__ import annotations

import json
from pathlib import Path

from sinewatch.schemas.config import SinewatchConfig
from sinewatch.schemas.messages import MESSAGE_MODELS


def all_schemas() -> dict[str, dict]:
    from sinewatch.estimators import available

    out = {f"{name}.json": model.model_json_schema() for name, model in MESSAGE_MODELS.items()}
    out["Config.json"] = SinewatchConfig.model_json_schema()
    for name, params in available().items():
        out[f"estimators/{name}.json"] = params.model_json_schema()
    return out


def export_schemas(directory: Path) -> list[Path]:
    written = []
    for rel, schema in all_schemas().items():
        path = directory / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(schema, indent=2, sort_keys=True) + "\n", encoding="utf-8")
        written.append(path)
    return written
