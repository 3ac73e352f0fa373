"""What the README and the docs say is so: the versions docs/wire-format.md states are the
code's, the prerequisites the README states are pyproject's, the licence file is the one
pyproject names, figures name the hardware (never "this machine" or an issue number),
``--workers 0`` is accepted as docs/daemon.md documents, and ``bench scenarios`` (which the
README's first ten minutes point to) lists every scenario ``feed --scenario`` takes."""

from __future__ import annotations

import json
import os
import re
import tomllib
from pathlib import Path

import pytest

from sinewatch import scenarios
from sinewatch.apps.cli import build_parser, main
from sinewatch.outputs.recorder import RECORDING_FORMAT_VERSION
from sinewatch.runtime.workers import worker_count
from sinewatch.scenarios.power_quality_iec import pq_names
from sinewatch.schemas.config import SinewatchConfig
from sinewatch.schemas.messages import ESTIMATE_FORMAT_VERSION, FORMAT_VERSION, FRAME_FORMAT_VERSION
from sinewatch.schemas.power_quality import PQ_FORMAT_VERSION

ROOT = Path(__file__).resolve().parents[1]


def _words(path: str) -> str:
    return " ".join((ROOT / path).read_text().split())  # one space between words: line breaks vary


README = _words("README.md")
WIRE_FORMAT = _words("docs/wire-format.md")
DAEMON = _words("docs/daemon.md")
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_the_versions_the_wire_format_page_states_are_the_code_s():
    assert (
        f"Versions in this build: SampleBlock, ErrorReport and Status format version {FORMAT_VERSION}, Estimate "
        f"format version {ESTIMATE_FORMAT_VERSION}, the power-quality messages format version {PQ_FORMAT_VERSION}, "
        f"recordings layout version {RECORDING_FORMAT_VERSION}"
    ) in WIRE_FORMAT
    assert f"`application/json;sinewatch/Estimate@{ESTIMATE_FORMAT_VERSION}`" in WIRE_FORMAT
    assert f"SampleFrame format version {FRAME_FORMAT_VERSION} (a frame that states no time quality" in WIRE_FORMAT
    assert f"`application/x-sinewatch-frame;v={FRAME_FORMAT_VERSION}`" in WIRE_FORMAT
    assert "Wire format (version" not in WIRE_FORMAT


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
    "path",
    [
        "README.md",
        "CHANGELOG.md",
        "deploy/README.md",
        *[str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md")],
    ],
)
def test_figures_name_the_hardware_not_this_machine_or_an_issue(path):
    text = " ".join((ROOT / path).read_text().split())
    for phrase in ("this machine", "this 2-core machine", "the project machine", "the project's 2-core machine"):
        assert phrase not in text, (path, phrase)
    issue = re.search(r".{0,40}\b[Ii]ssues? #?\d+.{0,20}", text)
    assert not issue, (path, issue)


def test_the_readme_is_one_a_newcomer_finishes():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) < 250, len(lines)
    for step in ("**1. Serve.**", "**2. Feed.**", "**3. Tail.**", "**4. Replay.**", "**5. Foxglove.**"):
        assert step in README, step


def test_workers_0_is_one_per_core_as_the_daemon_page_and_the_config_say():
    assert "`sinewatch serve --workers N` (`[workers] count`; default 1, 0 for one per core)" in DAEMON
    args = build_parser().parse_args(["serve", "--workers", "0"])
    assert args.workers == 0
    assert worker_count(SinewatchConfig(), args.workers) == len(os.sched_getaffinity(0))
    with pytest.raises(SystemExit):
        build_parser().parse_args(["serve", "--workers", "-1"])


def test_bench_scenarios_lists_every_scenario_feed_accepts(capsys):
    assert "sinewatch bench scenarios # every scenario feed --scenario takes" in README
    assert main(["bench", "scenarios", "--json"]) == 0
    listed = [row["name"] for row in json.loads(capsys.readouterr().out)]
    accepted = {*scenarios.names(), *pq_names()}  # what `feed --scenario` checks names against
    assert len(listed) == len(set(listed)) and set(listed) == accepted
    assert any(name.startswith("pq-") for name in listed)
    assert main(["bench", "scenarios", "--json", "pq-harmonic-50hz-single"]) == 0
    assert [row["name"] for row in json.loads(capsys.readouterr().out)] == ["pq-harmonic-50hz-single"]
