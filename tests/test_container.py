"""The container: ``deploy/Dockerfile`` builds and its ``sinewatch --help`` runs (when a
Docker daemon is reachable; skipped otherwise), and the configuration the image carries,
``deploy/container.toml``, serves estimates behind a Zenoh router as ``deploy/compose.yaml``
wires it (here a router process on loopback stands in for the ``router`` service).
"""

from __future__ import annotations

import itertools
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import replay_recording, serve_feed_tail

from sinewatch.clients.session import free_loopback_port
from sinewatch.schemas.config import DEFAULT_ESTIMATOR, load_config

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"

ROUTER = """
import json, sys, threading, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", json.dumps("router"))
conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:" + sys.argv[1]]))
conf.insert_json5("scouting/multicast/enabled", "false")
session = zenoh.open(conf)
print("ready", flush=True)
threading.Event().wait()
"""


def container_engine() -> tuple[str | None, str]:
    """(the first of docker and podman whose engine answers ``info``, or None; why none does)."""
    reasons = []
    for engine in ("docker", "podman"):
        if shutil.which(engine) is None:
            reasons.append(f"{engine} is not installed")
            continue
        info = subprocess.run([engine, "info"], capture_output=True, text=True, check=False, timeout=60)
        if info.returncode == 0:
            return engine, ""
        reasons.append(f"`{engine} info` fails ({(info.stderr.strip().splitlines() or ['no engine'])[-1][:120]})")
    return None, "no container engine runs here: " + "; ".join(reasons)


ENGINE, NO_ENGINE = container_engine()


def test_the_image_config_is_a_client_of_the_compose_router():
    config = load_config(DEPLOY / "container.toml", env={})
    assert (config.zenoh.mode, config.zenoh.listen, config.zenoh.connect) == ("client", [], ["tcp/router:7447"])
    assert str(config.recording.directory) == "/data/runs"
    compose = (DEPLOY / "compose.yaml").read_text()
    assert re.search(r"^  router:\n    .*\n    image: eclipse/zenoh:\d+\.\d+\.\d+\n", compose, re.M)  # pinned
    assert "dockerfile: deploy/Dockerfile" in compose and "stop_signal: SIGINT" in compose
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    assert re.search(r"^FROM python:\$\{PYTHON_VERSION\}-slim$", dockerfile, re.M)
    assert re.search(r"^USER sinewatch$", dockerfile, re.M)  # not root
    assert "COPY deploy/container.toml /etc/sinewatch/sinewatch.toml" in dockerfile
    # the extras compose serves: metrics and the Foxglove live view, on the ports it publishes
    assert re.search(r'pip install .*"\$\{wheel\}\[metrics,foxglove,cluster\]"', dockerfile)
    assert (config.metrics.port, config.metrics.host, config.foxglove.port, config.foxglove.host) == (
        9464,
        "0.0.0.0",
        8765,
        "0.0.0.0",
    )
    assert '"127.0.0.1:9464:9464"' in compose and '"127.0.0.1:8765:8765"' in compose


def test_the_container_config_serves_behind_a_router(tmp_path):
    port = free_loopback_port()
    router = subprocess.Popen([sys.executable, "-c", ROUTER, str(port)], stdout=subprocess.PIPE, text=True)
    try:
        assert router.stdout is not None and router.stdout.readline().strip() == "ready"
        endpoint = f"tcp/127.0.0.1:{port}"
        env = dict(
            os.environ,
            SINEWATCH_CONFIG=str(DEPLOY / "container.toml"),
            SINEWATCH__ZENOH__CONNECT=json.dumps([endpoint]),  # the router service's address, here
            SINEWATCH__RECORDING__DIRECTORY=str(tmp_path / "runs"),
            # the image's metrics and live view, on ports of the OS's choosing and loopback here
            SINEWATCH__METRICS__PORT="0",
            SINEWATCH__METRICS__HOST="127.0.0.1",
            SINEWATCH__FOXGLOVE__PORT="0",
            SINEWATCH__FOXGLOVE__HOST="127.0.0.1",
        )
        _, estimates, _ = serve_feed_tail(
            [],
            ["--connect", endpoint, "--json", "--count", "5"],
            ["--connect", endpoint, "--scenario", "demo-ramp", "--duration", "0.5"],
            serve_env=env,
        )
    finally:
        router.kill()
        router.wait(timeout=30)
    # the default rule reports on its own grid (several a block, each at the instant it describes)
    assert len(estimates) == 5 and {e["estimator"] for e in estimates} == {DEFAULT_ESTIMATOR}
    seqs, times = [e["seq"] for e in estimates], [e["timestamp_ns"] for e in estimates]
    assert seqs == sorted(seqs) and all(b > a for a, b in itertools.pairwise(times))
    assert re.search(r"OK: all \d+ recorded estimates reproduced bit for bit", replay_recording(tmp_path / "runs"))


@pytest.mark.skipif(ENGINE is None, reason=NO_ENGINE)
def test_the_image_builds_and_its_cli_runs():
    tag = "sinewatch:test"
    docker = str(ENGINE)
    build = subprocess.run(
        [docker, "build", "-f", str(DEPLOY / "Dockerfile"), "-t", tag, str(ROOT)],
        capture_output=True,
        text=True,
        timeout=1800,
        check=False,
    )
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    run = subprocess.run([docker, "run", "--rm", tag, "--help"], capture_output=True, text=True, check=False)
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("usage: sinewatch")
    user = subprocess.run(
        [docker, "run", "--rm", "--entrypoint", "id", tag, "-u"], capture_output=True, text=True, check=False
    )
    assert user.stdout.strip() == "10001"  # not root
    config = subprocess.run(
        [docker, "run", "--rm", tag, "config", "check"], check=False, capture_output=True, text=True
    )
    assert config.returncode == 0 and config.stdout.startswith("ok: 2 rule(s)"), config.stderr
    extras = subprocess.run(
        [docker, "run", "--rm", "--entrypoint", "python", tag, "-c",
         "import foxglove, prometheus_client; print(foxglove.__name__, prometheus_client.__name__)"],
        check=False, capture_output=True, text=True,
    )  # fmt: skip
    assert extras.stdout.strip() == "foxglove prometheus_client", extras.stderr
