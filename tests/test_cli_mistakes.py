"""Every CLI mistake ends in one line on stderr saying what was expected and what came, and
exit code 2: real command lines, run as the user runs them (a process each).

Before this table existed, the missing or non-MCAP file, the unknown estimator or parameter
in ``replay``, the malformed endpoint, the unwritable output directory and the unknown
scenario each ended in a traceback (or, for the estimator, in exit code 0 and no estimate).
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from conftest import sinewatch

from sinewatch.clients.session import free_loopback_port

DATA = Path(__file__).parent / "data"
RECORDING = DATA / "recorded-before-layering.mcap"


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("mistakes")
    (d / "notes.txt").write_text("hello\n")  # a file where a directory or an MCAP file is expected
    (d / "empty.mcap").write_bytes(b"")
    (d / "bad-rules.toml").write_text(
        '[[rules]]\nmatch = "sinewatch/in/a/**"\nestimator = "nope"\n\n'
        '[[rules]]\nmatch = "sinewatch/in/**"\nestimator = "kkl"\nparams = { f_min_hz = "abc" }\n'
    )
    (d / "bad-endpoint.toml").write_text('[zenoh]\nlisten = ["nonsense"]\n')
    (d / "bad-recording-dir.toml").write_text(
        f'[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{free_loopback_port()}"]\n\n'
        f'[recording]\ndirectory = "{d / "notes.txt" / "runs"}"\n'
    )
    (d / "not-toml.toml").write_text("this is not toml\n")
    (d / "bad.cfg").write_text("not, a comtrade\nconfiguration\n")
    return d


# (command line with {d} for the fixture directory and {rec} for a real recording, words the line must hold)
MISTAKES = [
    ("replay {d}/missing.mcap", ["missing.mcap", "expected an MCAP recording", "no such file"]),
    ("replay {d}/notes.txt", ["notes.txt", "expected an MCAP recording", "b'hello"]),
    ("replay {d}/empty.mcap", ["expected an MCAP recording", "an empty file"]),
    ("replay {rec} --estimator nope", ["expected one of", "'kkl'", "got 'nope'"]),
    ("replay {rec} --estimator kkl --param nope=1", ["kkl params.nope: unknown key"]),
    ("replay {rec} --estimator kkl --param f_min_hz=-5", ["f_min_hz", "greater than 0"]),
    ("replay {rec} --estimator kkl --param f_min_hz", ["expected KEY=VALUE, got 'f_min_hz'"]),
    ("replay {rec} --param f_min_hz=5", ["--param: expected with --estimator"]),
    ("replay {rec} --out {d}/notes.txt/x.mcap", ["--out", "expected a writable directory", "a file in the way"]),
    ("export {d}/missing.mcap", ["missing.mcap", "expected an MCAP recording", "no such file"]),
    ("export {d}/notes.txt", ["expected an MCAP recording"]),
    ("export {rec} --format xlsx", ["invalid choice: 'xlsx'"]),
    ("export {rec} --out {d}/notes.txt/out", ["--out", "expected a writable directory", "a file in the way"]),
    ("export {rec} --channels nope*", ["--channels", "fx/kkl", "got 'nope*'"]),
    ("serve --config {d}/missing.toml", ["missing.toml", "No such file"]),
    ("serve --config {d}/not-toml.toml", ["not valid toml"]),
    ("serve --config {d}/bad-rules.toml", ["rules[0]", "got 'nope'", "; rules[1]", "f_min_hz"]),
    ("serve --config {d}/bad-endpoint.toml", ["zenoh.listen", "expected PROTO/ADDRESS", "got 'nonsense'"]),
    ("serve --config {d}/bad-recording-dir.toml", ["recording.directory", "expected a writable directory"]),
    ("config check --config {d}/bad-rules.toml", ["rules[0]", "; rules[1]"]),
    ("tail --connect nonsense --wait 1", ["--connect", "expected PROTO/ADDRESS", "got 'nonsense'"]),
    ("tail --connect tcp/127.0.0.1:{port} --wait 1", ["could not open the Zenoh session", "Unable to connect"]),
    ("feed --connect tcp/127.0.0.1:{port} --wait 1", ["could not open the Zenoh session", "Unable to connect"]),
    ("feed --scenario demo-rmp --wait 1", ["expected one of", "did you mean demo-ramp", "got 'demo-rmp'"]),
    ("feed --comtrade {d}/missing.cfg --wait 1", ["missing.cfg", "expected a COMTRADE file", "no such file"]),
    ("feed --comtrade {d}/notes.txt --wait 1", ["expected a COMTRADE .cfg or .cff file, got a .txt file"]),
    ("feed --comtrade {d}/bad.cfg --wait 1", ["bad.cfg", "expected a COMTRADE record"]),
    ("replay {d}/bad.cfg", ["bad.cfg", "expected a COMTRADE record"]),
    ("feed --encoding xml", ["invalid choice: 'xml'"]),
    ("feed --duration soon", ["invalid float value: 'soon'"]),
    ("schemas export {d}/notes.txt/schemas", ["schemas export", "expected a writable directory"]),
    ("demo --record-dir {d}/notes.txt/runs", ["--record-dir", "expected a writable directory"]),
    ("estimators --bogus", ["unrecognized arguments: --bogus"]),
    ("frobnicate", ["invalid choice: 'frobnicate'"]),
]


@pytest.mark.parametrize(
    ("line", "words"), MISTAKES, ids=[m[0].split(" {")[0] + f"-{i}" for i, m in enumerate(MISTAKES)]
)
def test_a_mistake_is_one_line_and_exit_code_2(files, line, words):
    args = [
        a.format(d=files, rec=RECORDING, port=free_loopback_port()) for a in line.split(" ")
    ]  # no argument here holds a space
    r = subprocess.run(sinewatch(*args), check=False, capture_output=True, text=True, timeout=120)
    # a command that waits for a daemon says so first (tests/test_no_silent_waits.py); the error is one line
    lines = [line for line in r.stderr.splitlines() if not re.match(r"\w+: (still )?waiting for ", line)]
    assert r.returncode == 2, r.stderr
    assert len(lines) == 1, r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""
    for word in words:
        assert word in lines[0], lines[0]


def test_debug_adds_the_traceback_to_the_one_line(files):
    r = subprocess.run(
        sinewatch("--debug", "replay", str(files / "missing.mcap")),
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2
    assert r.stderr.startswith("Traceback (most recent call last):")
    assert "ReplayError" in r.stderr
    assert r.stderr.splitlines()[-1].startswith("sinewatch: error: ")
