"""What the power-quality stage adds to the pipeline's cost per block.

``python -m sinewatch.apps.bench.pq_stage [--blocks N] [--block SAMPLES] [--repeats R]`` runs the
same three-phase blocks (``pq-unbalance-50hz-u2-2pct-harmonics``, 10 kHz, three channels)
through a :class:`~sinewatch.core.pipeline.Pipeline` (sinks that drop everything) configured
three ways, interleaved ``R`` times, best of the repeats:

* ``baseline``: the estimator alone (the rule of ``deploy/power-quality.toml``);
* ``+group``: and the three-phase group;
* ``+harmonics``: and harmonics with aggregates on every channel and the group with its
  own window analysis and aggregates (the whole of ``deploy/power-quality.toml``).

It prints one JSON line per configuration: microseconds per block (decode, estimator,
stage, encoding of every message included) and the ratio to the baseline measured in the
same run.
"""

from __future__ import annotations

import argparse
import json
import time

from sinewatch.apps.feed import make_channels
from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import (
    EstimatorRule,
    HarmonicsRule,
    PowerQualitySection,
    SinewatchConfig,
    ThreePhaseGroup,
)

SCENARIO = "pq-unbalance-50hz-u2-2pct-harmonics"
RULE = EstimatorRule(
    match="sinewatch/in/**", estimator="ipdft", params={"nominal_frequency_hz": 50.0, "window_cycles": 10}
)


def configs(phases: list[str]) -> dict[str, SinewatchConfig]:
    group = ThreePhaseGroup(name="feeder1", phases=phases)
    aggregated = ThreePhaseGroup(name="feeder1", phases=phases, aggregate_nominal_frequency_hz=50)
    harmonics = HarmonicsRule(match="sinewatch/in/**", nominal_frequency_hz=50)
    return {
        "baseline": SinewatchConfig(rules=[RULE]),
        "+group": SinewatchConfig(rules=[RULE], power_quality=PowerQualitySection(groups=[group])),
        "+group-aggregates": SinewatchConfig(rules=[RULE], power_quality=PowerQualitySection(groups=[aggregated])),
        "+harmonics": SinewatchConfig(
            rules=[RULE], power_quality=PowerQualitySection(harmonics=[harmonics], groups=[aggregated])
        ),
    }


def inputs(n_blocks: int, block: int) -> tuple[list[tuple[str, bytes]], list[str]]:
    channels = make_channels([SCENARIO], prefix="bench")
    out = []
    for i in range(n_blocks):
        for c in channels:
            b = Block(c.channel, i, 1_700_000_000_000_000_000 + i * block * 100_000, 10_000.0, c.stream.read(block)[0])
            out.append((f"sinewatch/in/{c.channel}", encode_block_binary(b)))
    return out, [c.channel for c in channels]


def run(n_blocks: int, block: int, repeats: int) -> list[dict[str, object]]:
    data, phases = inputs(n_blocks, block)
    cfgs = configs(phases)
    best = dict.fromkeys(cfgs, float("inf"))
    for _ in range(repeats + 1):  # the first pass warms every kernel up; not counted
        for name, cfg in cfgs.items():
            pipeline = Pipeline(cfg, [NullSink()])
            start = time.perf_counter()
            for key, payload in data:
                pipeline.process(key, payload, BLOCK_BINARY_ENCODING, 0)
            elapsed = time.perf_counter() - start
            if _ > 0:
                best[name] = min(best[name], elapsed)
    base = best["baseline"]
    return [
        {
            "config": name,
            "blocks": len(data),
            "block_samples": block,
            "us_per_block": round(1e6 * t / len(data), 1),
            "ratio_to_baseline": round(t / base, 3),
        }
        for name, t in best.items()
    ]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--blocks", type=int, default=100, help="rounds of three blocks (default 100)")
    p.add_argument("--block", type=int, default=1000, help="samples per block (default 1000: 0.1 s)")
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args()
    for row in run(a.blocks, a.block, a.repeats):
        print(json.dumps(row))


if __name__ == "__main__":
    main()
