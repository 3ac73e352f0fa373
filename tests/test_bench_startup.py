"""`sinewatch bench startup` and what it guards: building the CLI parser imports no bench
module beyond its arguments (no numba, scipy, estimator or scenario module)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

from sinewatch.apps.bench import startup
from sinewatch.apps.bench.args import add_startup_arguments

HEAVY = (
    "numba",
    "scipy",
    "matplotlib",
    "mcap",
    "zenoh",
    "sinewatch.estimators",
    "sinewatch.scenarios",
    "sinewatch.crlb",
)


def test_building_the_cli_parser_imports_no_bench_and_no_maths():
    code = "import sys; from sinewatch.apps.cli import build_parser; build_parser(); print('\\n'.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert "sinewatch.apps.bench.args" in out  # the check sees the parser's imports
    bench = [m for m in out if m.startswith("sinewatch.apps.bench.")]
    assert bench == ["sinewatch.apps.bench.args"]
    assert [m for m in out if m.split(".")[0] in HEAVY or m.startswith(HEAVY)] == []


def test_every_bench_command_parses_and_resolves_to_its_module():
    from sinewatch.apps.cli import build_parser

    parser = build_parser()
    for argv, module in (
        (["bench", "kernels", "--block", "64"], "kernels"),
        (["bench", "e2e", "--channels", "2"], "e2e"),
        (["bench", "accuracy", "--quick"], "accuracy"),
        (["bench", "scenarios", "gap"], "scenarios"),
        (["bench", "startup", "--runs", "2"], "startup"),
    ):
        args = parser.parse_args(argv)
        assert args.bench_command == module and args.fn.__name__ == f"run_{module}"


def test_startup_bench_measures_each_command_against_the_baseline(tmp_path, capsys):
    p = argparse.ArgumentParser()
    add_startup_arguments(p)
    out = tmp_path / "startup.json"
    assert startup.run(p.parse_args(["--runs", "2", "--json", str(out)])) == 0
    data = json.loads(out.read_text())
    assert data["runs"] == 2
    rows = {r["command"]: r for r in data["results"]}
    assert list(rows) == [startup.BASELINE, "sinewatch --help", "sinewatch config show"]
    base = rows[startup.BASELINE]
    assert base["ratio"] == 1.0 and base["added_ms"] == 0.0
    for r in rows.values():
        assert len(r["runs_s"]) == 2 and r["fastest_s"] == min(r["runs_s"]) > 0
        assert r["median_s"] == pytest.approx(sum(r["runs_s"]) / 2)  # the median of two runs
        assert r["ratio"] == pytest.approx(r["median_s"] / base["median_s"])
        assert r["added_ms"] == pytest.approx((r["median_s"] - base["median_s"]) * 1e3)
    assert rows["sinewatch config show"]["argv"][-2:] == ["config", "show"]
    text = capsys.readouterr().out
    assert "sinewatch config show" in text and "< 300 ms" in text


def test_startup_bench_reports_a_failing_command(tmp_path):
    from sinewatch.schemas.errors import SinewatchError

    missing = tmp_path / "missing.toml"
    with pytest.raises(SinewatchError, match="expected exit code 0"):
        startup.measure(startup.commands(str(missing)), runs=1)
