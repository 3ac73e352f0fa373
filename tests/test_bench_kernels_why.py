"""``sinewatch bench kernels --bank N`` says why a bank stays below twice the streaming FFT with
figures of the same run: a compiled bank's kernel is timed alone beside ``update_bank``, so the
reason shows whether the arithmetic or the Python around the call bounds it (no timing asserted:
the figures printed are the figures in the JSON)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from sinewatch.apps.bench import kernels
from sinewatch.estimators import get
from sinewatch.estimators.bank import bank_of


def test_a_compiled_bank_is_timed_alone_and_its_why_quotes_those_figures(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    names = ["ges-kalman", "pmu"]  # a lane-major kernel; a bank that runs the frame itself
    out_json = tmp_path / "k.json"
    args = argparse.Namespace(estimators=",".join(names), block=[256], seconds=0.02, bank=3, json=out_json)
    assert kernels.run(args) == 0
    printed = " ".join(capsys.readouterr().out.split())  # the console wraps long lines
    results = json.loads(out_json.read_text())
    ges = results["estimators"]["ges-kalman"]["256"]
    assert ges["bank3_kernel"] > 0 and ges["bank3_kernel_vs_fft"] > 0
    assert "bank3_kernel" not in results["estimators"]["pmu"]["256"]  # no kernel to time alone
    assert bank_of(get("pmu")).run is not None  # ... because pmu's bank runs its frames itself
    for name in names:
        r = {k.removeprefix("bank3_"): v for k, v in results["estimators"][name]["256"].items()}
        if r["bank_vs_fft"] >= kernels.BANK_TARGET:
            assert name not in results.get("why", {})
            continue
        why = results["why"][name]
        assert why == kernels.bank_why(name, r)
        assert " ".join(why.split()) in printed
        if name == "ges-kalman":
            k_ns, b_ns = 1e9 / r["kernel"], 1e9 / r["bank"]
            assert f"the kernel alone {k_ns:.1f} ns a channel-sample ({r['kernel_vs_fft']:.2f}x" in why
            assert f"update_bank {b_ns:.1f} (the Python around the call {b_ns - k_ns:.1f})" in why
        else:
            assert "the kernel alone" not in why
