"""What the README says is so: the versions it states are the code's, the prerequisites are
pyproject's, the licence file is the one pyproject names, figures name the hardware (never
"this machine" or an issue number), ``--workers 0`` is accepted as documented, and ``bench
scenarios`` lists every scenario ``feed --scenario`` takes."""

from __future__ import annotations

import json
import os
import re
import tomllib
from pathlib import Path

import pytest

from sinewatch import scenarios
from sinewatch.cli import build_parser, main
from sinewatch.recorder import RECORDING_FORMAT_VERSION
from sinewatch.scenarios.power_quality_iec import pq_names
from sinewatch.schemas.config import SinewatchConfig
from sinewatch.schemas.messages import ESTIMATE_FORMAT_VERSION, FORMAT_VERSION, FRAME_FORMAT_VERSION
from sinewatch.schemas.power_quality import PQ_FORMAT_VERSION
from sinewatch.workers import worker_count

ROOT = Path(__file__).resolve().parents[1]
README = " ".join((ROOT / "README.md").read_text().split())  # one space between words: line breaks vary
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_the_versions_the_readme_states_are_the_code_s():
    assert (
        f"Versions in this build: SampleBlock, ErrorReport and Status format version {FORMAT_VERSION}, Estimate "
        f"format version {ESTIMATE_FORMAT_VERSION}, the power-quality messages format version {PQ_FORMAT_VERSION}, "
        f"recordings layout version {RECORDING_FORMAT_VERSION}"
    ) in README
    assert f"`application/json;sinewatch/Estimate@{ESTIMATE_FORMAT_VERSION}`" in README
    assert f"SampleFrame format version {FRAME_FORMAT_VERSION} (a frame that states no time quality" in README
    assert f"`application/x-sinewatch-frame;v={FRAME_FORMAT_VERSION}`" in README
    assert "Wire format (version" not in README


def test_the_prerequisites_are_pyproject_s():
    assert PYPROJECT["project"]["requires-python"] == ">=3.11"
    assert "Prerequisites: Python 3.11 or later (`python3`), `pip` (with `venv`) and `make`" in README


def test_the_licence_file_is_the_apache_2_0_text_pyproject_names():
    assert PYPROJECT["project"]["license"] == "Apache-2.0" and PYPROJECT["project"]["license-files"] == ["LICENSE"]
    text = (ROOT / "LICENSE").read_text()
    assert text.split()[:5] == ["Apache", "License", "Version", "2.0,", "January"]
    for section in range(1, 10):  # the nine sections of the terms, and their end
        assert re.search(rf"^\s+{section}\. [A-Z]", text, re.M), section
    assert "END OF TERMS AND CONDITIONS" in text and "APPENDIX: How to apply the Apache License" in text
    assert "COPY pyproject.toml README.md LICENSE ./" in (ROOT / "deploy" / "Dockerfile").read_text()


@pytest.mark.parametrize(
    "path", ["README.md", "deploy/README.md", *[f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md")]]
)
def test_figures_name_the_hardware_not_this_machine_or_an_issue(path):
    text = " ".join((ROOT / path).read_text().split())
    for phrase in ("this machine", "this 2-core machine", "the project machine", "the project's 2-core machine"):
        assert phrase not in text, (path, phrase)
    assert not re.search(r"\b[Ii]ssue \d+", text), (path, re.search(r".{40}\b[Ii]ssue \d+.{20}", text))


def test_workers_0_is_one_per_core_as_the_readme_and_the_config_say():
    assert "`sinewatch serve --workers N` (`[workers] count`; default 1, 0 for one per core)" in README
    args = build_parser().parse_args(["serve", "--workers", "0"])
    assert args.workers == 0
    assert worker_count(SinewatchConfig(), args.workers) == len(os.sched_getaffinity(0))
    with pytest.raises(SystemExit):
        build_parser().parse_args(["serve", "--workers", "-1"])


def test_bench_scenarios_lists_every_scenario_feed_accepts(capsys):
    assert main(["bench", "scenarios", "--json"]) == 0
    listed = [row["name"] for row in json.loads(capsys.readouterr().out)]
    accepted = {*scenarios.names(), *pq_names()}  # what `feed --scenario` checks names against
    assert len(listed) == len(set(listed)) and set(listed) == accepted
    assert any(name.startswith("pq-") for name in listed)
    assert main(["bench", "scenarios", "--json", "pq-harmonic-50hz-single"]) == 0
    assert [row["name"] for row in json.loads(capsys.readouterr().out)] == ["pq-harmonic-50hz-single"]
