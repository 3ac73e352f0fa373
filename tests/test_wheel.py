"""A small install: the wheel holds every module and schema file, and, installed into a fresh
virtual environment, ``sinewatch serve`` / ``feed`` / ``replay`` run from a directory far from
the source tree.

The fresh environment gets the wheel itself (``--no-deps``) and borrows the third-party
packages of the environment running the tests through a path entry after its own
site-packages (a plain path entry: the ``.pth`` hook of the editable install there is not
run, so ``sinewatch`` can only come from the wheel); the test checks that it does.
"""

from __future__ import annotations

import os
import shutil
import signal
import site
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

from sinewatch.clients.session import free_loopback_port

ROOT = Path(__file__).resolve().parents[1]
SOURCE_ROOTS = {  # source root -> its path in the wheel
    ROOT / "service" / "sinewatch": "sinewatch",
    ROOT / "clients" / "sinewatch" / "clients": "sinewatch/clients",
    ROOT / "schemas" / "sinewatch" / "schemas": "sinewatch/schemas",
}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel, built as ``pip wheel`` builds it, from a copy of what the sdist holds (the
    build writes build/ and *.egg-info beside its sources: not in the worktree)."""
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        if (ROOT / name).exists():
            shutil.copy(ROOT / name, src / name)
    for name in ("service", "clients", "schemas"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    out = tmp_path_factory.mktemp("wheel")
    r = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(src), "-w", str(out), "--no-deps", "-q"],
        check=False,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    [whl] = out.glob("sinewatch-*.whl")
    return whl


def source_files() -> set[str]:
    """Every module and data file a run may import or read, by its path in the wheel."""
    files = set()
    for root, inside in SOURCE_ROOTS.items():
        for path in root.rglob("*"):
            if path.suffix in (".py", ".json") and "__pycache__" not in path.parts:
                rel = path.relative_to(root).as_posix()
                if inside == "sinewatch" and rel.split("/")[0] in ("clients", "schemas"):
                    continue
                files.add(f"{inside}/{rel}")
    return files


def test_the_wheel_holds_every_module_and_schema(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    wanted = source_files()
    assert {"sinewatch/schemas/json/Estimate.json", "sinewatch/schemas/json/estimators/ipdft.json"} <= wanted
    assert sorted(wanted - names) == []


@pytest.mark.slow  # about 55 s here: a fresh install compiles every numba kernel it runs
def test_installed_wheel_serves_feeds_and_replays_outside_the_source_tree(wheel, tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    purelib = Path(
        sysconfig.get_path("purelib", vars={"base": str(venv), "platbase": str(venv)})
    )  # the fresh environment's site-packages
    # its own site-packages first (the wheel), then this environment's packages (the dependencies)
    (purelib / "zz-dependencies.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "--python",
            str(venv / "bin" / "python"),
            "install",
            "--no-deps",
            "-q",
            str(wheel),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SINEWATCH_", "PYTHON"))}
    bin_ = venv / "bin"

    where = subprocess.run(
        [
            str(bin_ / "python"),
            "-c",
            "import sinewatch.apps.cli, sinewatch.schemas; print(sinewatch.apps.cli.__file__)",
        ],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    assert Path(where).is_relative_to(purelib), where  # the wheel's copy, not the source tree's

    port = free_loopback_port()
    (work / "sinewatch.toml").write_text(
        f'[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\n\n[recording]\ndirectory = "runs"\n'
    )

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        """``sinewatch ARGS`` from the wheel's environment, in the user's folder."""
        return subprocess.run(
            [str(bin_ / "sinewatch"), *args],
            cwd=work,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )

    serve = subprocess.Popen(
        [str(bin_ / "sinewatch"), "serve", "--config", "sinewatch.toml"],
        cwd=work,
        env=env,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert serve.stderr is not None
        started = next((line for line in serve.stderr if "sinewatch daemon" in line), None)
        assert started is not None  # the line the daemon logs once it is listening
        feed = run(
            "feed", "--connect", f"tcp/127.0.0.1:{port}", "--scenario", "demo-ramp", "--duration", "0.5", "--fast",
            "--wait", "30",
        )  # fmt: skip
        assert feed.returncode == 0, feed.stderr
        assert "published 5 blocks" in feed.stderr
    finally:
        serve.send_signal(signal.SIGINT)
        _, err = serve.communicate(timeout=60)
    assert serve.returncode == 0, err
    assert "drained: 5 inputs, 5 estimates, 0 errors" in err
    [recording] = (work / "runs").glob("*.mcap")
    replay = run("replay", str(recording), "--no-progress")
    assert replay.returncode == 0, replay.stdout + replay.stderr
    assert "OK: all 5 recorded estimates reproduced bit for bit" in replay.stdout
