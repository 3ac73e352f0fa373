"""The configuration: one pydantic model tree, unknown keys rejected everywhere.

Defaults work out of the box and are safe: a Zenoh peer listening on loopback only,
multicast scouting off, every channel estimated with ``ges-kalman``, recording on.
Loaded from a TOML or JSON file plus ``SINEWATCH__SECTION__KEY`` environment variables by
:func:`sinewatch.config.load_config`; printed back by ``sinewatch config show``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7450"


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class ZenohSection(_Section):
    mode: Literal["peer", "client", "router"] = Field("peer", description="Zenoh session mode")
    listen: list[str] = Field(
        default_factory=lambda: [DEFAULT_ENDPOINT],
        description="Endpoints to listen on (loopback by default; [] for none)",
    )
    connect: list[str] = Field(default_factory=list, description="Endpoints to connect to (routers or peers)")
    multicast_scouting: bool = Field(False, description="Zenoh multicast scouting (off unless asked for)")
    shared_memory: bool | None = Field(None, description="Zenoh shared memory transport (None: Zenoh's default)")
    raw: dict[str, Any] = Field(
        default_factory=dict,
        description="Passthrough of raw Zenoh config keys (JSON5 paths), e.g. {'transport/link/tx/lease': 5000}",
    )

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        for ep in v:
            if "/" not in ep:
                raise ValueError(f"endpoint: expected PROTO/ADDRESS such as {DEFAULT_ENDPOINT}, got {ep!r}")
        return v


class KeysSection(_Section):
    """The key layout. Inputs, estimates, errors and status live under their own prefixes."""

    input: str = Field("sinewatch/in/**", description="Key expression subscribed for SampleBlocks")
    estimates_prefix: str = Field("sinewatch/est", description="Estimates go to PREFIX/<channel>")
    errors_prefix: str = Field("sinewatch/err", description="ErrorReports go to PREFIX/<channel or _unknown>")
    status_key: str = Field("sinewatch/status", description="Status messages go to KEY/<daemon_id>")


class EstimatorRule(_Section):
    """Channels whose input key matches ``match`` get ``estimator`` with ``params``."""

    match: str = Field("sinewatch/in/**", description="Key expression matched against the input key")
    estimator: str = Field("ges-kalman", description="Registered estimator name (sinewatch estimators)")
    params: dict[str, Any] = Field(default_factory=dict, description="Estimator parameters")

    @model_validator(mode="after")
    def _known_estimator(self) -> EstimatorRule:
        from sinewatch.estimators import get  # late import: estimators import numba

        cls = get(self.estimator)
        extra = set(self.params) - set(cls.Params.model_fields)
        if extra:
            raise ValueError(
                f"params for {self.estimator}: unknown keys {sorted(extra)}; "
                f"expected some of {sorted(cls.Params.model_fields)}"
            )
        cls.Params.model_validate(self.params)
        return self


class RecordingSection(_Section):
    enabled: bool = True
    directory: Path = Field(Path("sinewatch-runs"), description="Where MCAP files are written")
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    chunk_size_bytes: int = Field(1 << 20, ge=1024)
    rotate_bytes: int | None = Field(1 << 30, ge=1 << 16, description="Start a new file past this size")
    rotate_seconds: float | None = Field(3600.0, gt=0, description="Start a new file after this long")
    flush_interval_s: float = Field(1.0, gt=0, description="Close the open chunk this often: a crash loses at most this much")
    inputs: bool = True
    estimates: bool = True
    errors: bool = True
    status: bool = True


class LimitsSection(_Section):
    max_payload_bytes: int = Field(16 << 20, ge=64)
    max_block_samples: int = Field(1_000_000, ge=1)
    max_channels: int = Field(10_000, ge=1)
    queue_capacity: int = Field(8192, ge=1, description="Input blocks waiting for the estimators")
    queue_policy: Literal["block", "drop"] = Field(
        "block", description="block: back-pressure to Zenoh (no loss); drop: drop and count the newest"
    )
    intake_batch: int = Field(256, ge=1, description="Blocks handed to the event loop at once")


class SinewatchConfig(_Section):
    daemon_id: str = Field("sinewatch", pattern=r"^[A-Za-z0-9_.\-]+$")
    zenoh: ZenohSection = Field(default_factory=ZenohSection)
    keys: KeysSection = Field(default_factory=KeysSection)
    rules: list[EstimatorRule] = Field(
        default_factory=lambda: [EstimatorRule()],
        description="First matching rule wins; a channel no rule matches is rejected (no_rule)",
    )
    on_gap: Literal["coast", "reset"] = Field(
        "coast",
        description="After a sequence gap: coast (keep the state, flag the gap) or reset the estimator",
    )
    recording: RecordingSection = Field(default_factory=RecordingSection)
    limits: LimitsSection = Field(default_factory=LimitsSection)
    status_interval_s: float = Field(1.0, gt=0)
    sink_retry_s: float = Field(
        1.0, gt=0, description="After an output fails (disk full, session closed), retry it this often; estimation goes on"
    )
