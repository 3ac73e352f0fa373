"""The deployment files do what they say: mutual TLS, access control, a hardened unit.

A real Zenoh router process runs ``deploy/zenoh-router-tls.json5`` (TLS only, mutual TLS,
access control by certificate Common Name) with certificates made by
``deploy/tls/make-certs.sh``; the daemon connects as ``sinewatch-daemon`` with the TLS keys of
``deploy/secure.toml``; a gateway and a reader connect with their own certificates.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import signal
import subprocess
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import TIMEOUT, make_config, run_daemon, take

from sinewatch.clients import BlockPublisher, JsonSubscription
from sinewatch.clients.session import free_loopback_port, open_session
from sinewatch.schemas.config import ZenohSection
from sinewatch.schemas.errors import ConfigError

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"

ROUTER = """
import json, sys, threading, zenoh
conf = zenoh.Config.from_file(sys.argv[1])
certs = sys.argv[3]
conf.insert_json5("listen/endpoints", json.dumps(["tls/127.0.0.1:" + sys.argv[2]]))
conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(certs + "/ca.pem"))
conf.insert_json5("transport/link/tls/listen_certificate", json.dumps(certs + "/router.pem"))
conf.insert_json5("transport/link/tls/listen_private_key", json.dumps(certs + "/router-key.pem"))
session = zenoh.open(conf)
print("ready", flush=True)
threading.Event().wait()
"""


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is needed to make the test certificates")
    out = tmp_path_factory.mktemp("tls")
    subprocess.run(["bash", str(DEPLOY / "tls" / "make-certs.sh"), str(out)], check=True, capture_output=True)
    return out


@contextlib.contextmanager
def secure_router(certs: Path, port: int) -> Iterator[None]:
    proc = subprocess.Popen(
        [sys.executable, "-c", ROUTER, str(DEPLOY / "zenoh-router-tls.json5"), str(port), str(certs)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        yield
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()


def tls_section(certs: Path, role: str, endpoint: str) -> ZenohSection:
    """The daemon's zenoh section from deploy/secure.toml, pointed at the test's files."""
    raw = tomllib.loads((DEPLOY / "secure.toml").read_text())["zenoh"]["raw"]
    raw = {k: v.replace("/etc/sinewatch/tls", str(certs)) if isinstance(v, str) else v for k, v in raw.items()}
    raw["transport/link/tls/connect_certificate"] = str(certs / f"{role}.pem")
    raw["transport/link/tls/connect_private_key"] = str(certs / f"{role}-key.pem")
    raw["connect/timeout_ms"] = int(TIMEOUT * 1000)
    return ZenohSection(mode="client", listen=[], connect=[endpoint], raw=raw)


def test_mutual_tls_and_access_control_on_a_live_daemon(tmp_path, certs):
    port = free_loopback_port()
    endpoint = f"tls/127.0.0.1:{port}"
    config = make_config(tmp_path, zenoh=tls_section(certs, "sinewatch-daemon", endpoint))
    x = np.sin(2 * np.pi * 50.0 * np.arange(500) / 10_000.0)

    def client(_daemon, _ep):
        gateway = open_session(tls_section(certs, "gateway", endpoint))
        reader = open_session(tls_section(certs, "reader", endpoint))
        with gateway, reader, JsonSubscription(reader, "sinewatch/est/**") as seen:
            with JsonSubscription(gateway, "sinewatch/est/**") as gateway_reads:
                pub = BlockPublisher(gateway)
                assert pub.wait_for_subscriber("sec/a", TIMEOUT)
                pub.publish("sec/a", x, 10_000.0)
                first = take(seen, 1)
                # An authorised gateway forging an estimate: the router drops it.
                gateway.put("sinewatch/est/sec/a", b'{"forged": true}')
                # A reader trying to feed the daemon: dropped too.
                reader.put("sinewatch/in/sec/b", b"{}")
                pub.publish("sec/a", x, 10_000.0)
                # Had the forgery passed, it would arrive before this (it left first and
                # takes one hop, the real estimate three): absence is shown by arrival.
                second = take(seen, 1)
                gateway_got = []
                while (msg := gateway_reads.get(timeout=0.0)) is not None:
                    gateway_got.append(msg)
                return first + second, gateway_got

    with secure_router(certs, port):
        (estimates, gateway_got), daemon, code = run_daemon(config, client)
    assert code == 0
    assert [e["seq"] for e in estimates] == [0, 1]  # only the daemon's, in order; no forgery
    assert all("forged" not in e for e in estimates)
    # gateways do not read estimates: the gateway saw only its own forgery (Zenoh delivers a
    # session's puts to its own subscribers locally), never one of the daemon's
    assert all(m.get("forged") for m in gateway_got)
    assert set(daemon.pipeline.channels) == {"sec/a"}  # the reader's put never reached it


def test_a_plain_tcp_connection_to_the_tls_router_is_refused(certs):
    port = free_loopback_port()
    with secure_router(certs, port):
        with pytest.raises(ConfigError, match="could not open the Zenoh session"):
            open_session(
                ZenohSection(
                    mode="client", listen=[], connect=[f"tcp/127.0.0.1:{port}"], raw={"connect/timeout_ms": 2000}
                )
            )
        with pytest.raises(ConfigError, match="could not open the Zenoh session"):
            # TLS, but without a client certificate: mutual TLS refuses it
            open_session(
                ZenohSection(
                    mode="client",
                    listen=[],
                    connect=[f"tls/127.0.0.1:{port}"],
                    raw={"transport/link/tls/root_ca_certificate": str(certs / "ca.pem"), "connect/timeout_ms": 2000},
                )
            )


def test_the_systemd_unit_is_hardened():
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed")
    out = subprocess.run(
        ["systemd-analyze", "security", "--offline=true", str(DEPLOY / "sinewatch.service")],
        capture_output=True,
        text=True,
        check=False,
    ).stdout
    exposure = float(out.rsplit("Overall exposure level for sinewatch.service:", 1)[1].split()[0])
    assert exposure < 3.0, out[-2000:]


def test_the_secure_daemon_config_loads():
    from sinewatch.schemas.config import load_config

    cfg = load_config(DEPLOY / "secure.toml", {})
    assert cfg.zenoh.connect[0].startswith("tls/") and cfg.zenoh.raw["transport/link/tls/enable_mtls"] is True
    assert json.loads(json.dumps(cfg.model_dump(mode="json")))["zenoh"]["mode"] == "client"
