"""The cluster deployment files configure what they say: two shards and a standby for the
first, every daemon a Zenoh client of the router, the router the wheel's own.

Each daemon's environment (compose) or start script (Kubernetes, run here with the pod's
hostname) goes through the real config loader, as `sinewatch serve` would take it.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import yaml

from sinewatch.schemas.config import load_config

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"
EXPECTED = {("1/2", "active"), ("2/2", "active"), ("1/2", "standby")}


def test_compose_runs_a_router_two_shards_and_a_standby():
    compose = yaml.safe_load((DEPLOY / "cluster" / "compose.yaml").read_text())
    services = compose["services"]
    assert services["router"]["command"][0] == "router"  # the image's entrypoint is `sinewatch`
    daemons = {name: s for name, s in services.items() if s.get("command") == ["serve"]}
    configs = {name: load_config(env={k: str(v) for k, v in s["environment"].items()}) for name, s in daemons.items()}
    assert {(c.cluster.shard, c.cluster.role) for c in configs.values()} == EXPECTED
    assert len({c.daemon_id for c in configs.values()}) == 3
    for c in configs.values():
        assert c.zenoh.mode == "client" and c.zenoh.connect == ["tcp/router:7447"] and c.zenoh.listen == []
        assert c.cluster.etcd == "etcd:2379"  # the shards' elections, beside the router
        assert (c.limits.queue_policy, c.limits.queue_capacity) == ("drop", 65536)  # never stops reading its link
    etcd = services["etcd"]
    assert "--data-dir=/etcd-data" in etcd["command"] and etcd["volumes"] == ["etcd-data:/etcd-data"]
    assert all("etcd" in s["depends_on"] for s in daemons.values())


def test_kubernetes_statefulset_maps_pod_ordinals_to_shards_and_a_standby():
    docs = {
        d["kind"] + "/" + d["metadata"]["name"]: d
        for d in yaml.safe_load_all((DEPLOY / "k8s" / "sinewatch-cluster.yaml").read_text())
    }
    router = docs["Deployment/zenoh-router"]["spec"]["template"]["spec"]["containers"][0]
    assert router["command"][:2] == ["sinewatch", "router"]
    assert docs["Service/zenoh-router"]["spec"]["ports"][0]["port"] == 7447
    assert docs["Service/etcd"]["spec"]["ports"][0]["port"] == 2379
    etcd = docs["StatefulSet/etcd"]["spec"]
    assert etcd["replicas"] == 1 and etcd["volumeClaimTemplates"][0]["metadata"]["name"] == "etcd-data"
    sts = docs["StatefulSet/sinewatch"]["spec"]
    container = sts["template"]["spec"]["containers"][0]
    script = container["command"][2].replace("exec sinewatch serve", "env")  # print what serve would read
    base = {e["name"]: e["value"] for e in container["env"]}
    seen = set()
    for ordinal in range(sts["replicas"]):
        env = {"PATH": os.environ["PATH"], "HOSTNAME": f"sinewatch-{ordinal}", **base}
        out = subprocess.run(["sh", "-c", script], env=env, capture_output=True, text=True, check=True).stdout
        pod_env = dict(line.split("=", 1) for line in out.splitlines() if line.startswith("SINEWATCH"))
        config = load_config(env=pod_env)
        assert config.daemon_id == f"sinewatch-{ordinal}" and config.zenoh.connect == ["tcp/zenoh-router:7447"]
        assert config.cluster.etcd == "etcd:2379" and config.limits.queue_policy == "drop"
        assert config.limits.queue_capacity == 65536
        seen.add((config.cluster.shard, config.cluster.role))
    assert seen == EXPECTED
