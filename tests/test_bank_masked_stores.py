"""The lane loops of kkl's, kkl-biased's and pmu's banks compile without masked moves on a host
without AVX-512 (docs/benchmarks.md, "Aligned work arrays, and what the AVX2 assembly says").

Where a lane's step is taken or not, a bank computes both sides and chooses. Written as a Python
conditional (a branch in numba's IR), or as a select of a row's own old value, LLVM vectorises
the choice as masked stores and loads (``vmaskmovpd``), microcode on AMD's cores: 26 a sample
made kkl-biased's bank kernel ~25 % slower. ``lanes.select`` and ``lanes.frozen`` keep them
blends; this reads the compiled assembly, so that a choice written back as a conditional shows.
Slow: the kernels are compiled afresh (numba shows no assembly for cached code), ~1 min of CPU.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from sinewatch.estimators.lanes import HOST_VECTOR_BITS

# (estimator, module, compiled function whose assembly holds the bank's sample loop)
BANK_LOOPS = (
    ("kkl", "sinewatch.estimators.kkl_kernels", "_kkl_bank"),
    ("kkl-biased", "sinewatch.estimators.kkl_biased_kernels", "_kkl_biased_bank"),
    ("pmu", "sinewatch.estimators._pmu_bank", "_lanes"),
)

_COUNT = """
import importlib, json, sys
import numpy as np
import sinewatch
from sinewatch.estimators import get
from sinewatch.estimators.bank import update_bank
counts = {}
for name, module, function in json.loads(sys.argv[1]):
    cls = get(name)
    ests = [cls.example() for _ in range(8)]
    update_bank(ests, np.stack([cls.example_signal(512, seed=c) for c in range(8)], axis=1), last_only=True)
    asm = "".join(getattr(importlib.import_module(module), function).inspect_asm().values())
    counts[name] = {"vmaskmovpd": asm.count("vmaskmovpd"), "vmulpd": asm.count("vmulpd")}
print(json.dumps(counts))
"""


@pytest.mark.slow
@pytest.mark.skipif(HOST_VECTOR_BITS != 256, reason="AVX2 without AVX-512: masked stores are vmaskmovpd there")
def test_bank_lane_loops_have_no_masked_moves(tmp_path) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}  # an empty cache: compiled here, assembly shown
    run = subprocess.run(
        [sys.executable, "-c", _COUNT, json.dumps(BANK_LOOPS)], env=env, capture_output=True, text=True, check=False
    )
    assert run.returncode == 0, f"expected the compile to succeed, got exit {run.returncode}: {run.stderr[-2000:]}"
    counts = json.loads(run.stdout.strip().splitlines()[-1])
    for name, _, function in BANK_LOOPS:
        assert counts[name]["vmulpd"] > 0, f"{name}: expected {function}'s assembly, got none"
        assert counts[name]["vmaskmovpd"] == 0, f"{name}: expected no vmaskmovpd in {function}, got {counts[name]}"
