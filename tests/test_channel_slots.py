"""A refused block does not take a channel slot: with ``limits.max_channels`` reached only by
blocks that were refused, a legitimate new channel is still served."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import KeepSink as Keep
from conftest import make_config

from sinewatch.core.pipeline import Pipeline
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import LimitsSection


def sine(n: int = 400, columns: int = 1) -> np.ndarray:
    x = np.sin(2 * np.pi * 50.0 * np.arange(n) / 10_000.0)
    return x if columns == 1 else np.column_stack([x] * columns)


@pytest.mark.parametrize(
    "bad",
    [
        pytest.param(lambda name: Block(name, 0, 0, 10_000.0, sine(columns=3)), id="columns"),
        pytest.param(lambda name: Block(name, 0, 0, 10_000.0, np.where(np.arange(400) == 7, np.nan, sine())), id="nan"),
    ],
)
def test_refused_blocks_leave_the_channel_slots_free(tmp_path, bad):
    config = make_config(tmp_path, hold_estimates=False, limits=LimitsSection(max_channels=20))
    keep = Keep()
    pipeline = Pipeline(config, [keep])
    for i in range(40):  # twice the limit, each on a channel of its own
        name = f"hostile/{i}"
        pipeline.process(f"sinewatch/in/{name}", encode_block_binary(bad(name)), BLOCK_BINARY_ENCODING, i)
    assert len(keep.errors) == 40 and all(e["kind"] != "channel_limit" for e in keep.errors), keep.errors[-1]
    assert pipeline.channels == {}
    good = Block("legit/a", 0, 0, 10_000.0, sine())
    pipeline.process("sinewatch/in/legit/a", encode_block_binary(good), BLOCK_BINARY_ENCODING, 99)
    assert [e["channel"] for e in keep.estimates] == ["legit/a"]
    assert list(pipeline.channels) == ["legit/a"]


def test_the_limit_still_holds_for_accepted_channels(tmp_path):
    config = make_config(tmp_path, hold_estimates=False, limits=LimitsSection(max_channels=3))
    keep = Keep()
    pipeline = Pipeline(config, [keep])
    for i in range(4):
        blk = Block(f"ok/{i}", 0, 0, 10_000.0, sine())
        pipeline.process(f"sinewatch/in/ok/{i}", encode_block_binary(blk), BLOCK_BINARY_ENCODING, i)
    assert len(keep.estimates) == 3 and [e["kind"] for e in keep.errors] == ["channel_limit"]
