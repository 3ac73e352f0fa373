"""Shared fixtures: daemon configs on a free loopback port, recordings in tmp_path."""

from __future__ import annotations

from pathlib import Path

import pytest

from sinewatch.clients.session import free_loopback_port
from sinewatch.scenarios.demo import KALMAN_10K
from sinewatch.schemas.config import (
    EstimatorRule,
    LimitsSection,
    RecordingSection,
    SinewatchConfig,
    ZenohSection,
)


def make_config(tmp_path: Path, **overrides) -> SinewatchConfig:
    port = free_loopback_port()
    kw = dict(
        daemon_id="test",
        zenoh=ZenohSection(listen=[f"tcp/127.0.0.1:{port}"]),
        rules=[EstimatorRule(match="sinewatch/in/**", estimator="ges-kalman", params=KALMAN_10K)],
        recording=RecordingSection(directory=tmp_path / "rec", flush_interval_s=0.2),
        limits=LimitsSection(),
        status_interval_s=0.2,
    )
    kw.update(overrides)
    return SinewatchConfig(**kw)


def endpoint(config: SinewatchConfig) -> str:
    return config.zenoh.listen[0]


@pytest.fixture
def config(tmp_path):
    return make_config(tmp_path)
