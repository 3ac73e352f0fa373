"""Configuration: one model tree, file + environment, unknown keys rejected, safe defaults."""

from __future__ import annotations

import json

import pytest

from sinewatch.apps.cli import main
from sinewatch.clients.session import zenoh_config
from sinewatch.estimators import check_rules
from sinewatch.schemas.config import load_config
from sinewatch.schemas.errors import ConfigError


def test_defaults_are_safe_and_work_out_of_the_box():
    cfg = load_config(env={})
    assert cfg.zenoh.listen == ["tcp/127.0.0.1:7450"] and not cfg.zenoh.multicast_scouting
    assert cfg.rules[0].estimator == "pmu" and cfg.rules[0].params == {"nominal_frequency_hz": "auto"}
    assert cfg.recording.enabled
    zc = json.loads(zenoh_config(cfg.zenoh).get_json("scouting/multicast/enabled"))
    assert zc is False


def test_file_then_environment(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text(
        'daemon_id = "feeder"\n[zenoh]\nmode = "client"\nlisten = []\nconnect = ["tcp/127.0.0.1:7447"]\n'
        '[[rules]]\nmatch = "sinewatch/in/pq/**"\nestimator = "ges-kalman"\nparams = { r = 0.001 }\n'
    )
    env = {
        "SINEWATCH__RECORDING__DIRECTORY": "/data/runs",
        "SINEWATCH__LIMITS__QUEUE_CAPACITY": "128",
        "SINEWATCH__ZENOH__RAW": '{"transport/link/tx/lease": 5000}',
    }
    cfg = load_config(f, env)
    assert cfg.daemon_id == "feeder" and cfg.zenoh.mode == "client"
    assert cfg.rules[0].params == {"r": 0.001}
    assert str(cfg.recording.directory) == "/data/runs" and cfg.limits.queue_capacity == 128
    assert json.loads(zenoh_config(cfg.zenoh).get_json("transport/link/tx/lease")) == 5000


@pytest.mark.parametrize(
    "text, match",
    [
        ("[zenoh]\nmod = 'peer'\n", "zenoh.mod: unknown key"),
        ("[zenoh]\nlisten = ['localhost']\n", "PROTO/ADDRESS"),
        ("on_gap = 'panic'\n", "on_gap"),
    ],
)
def test_bad_config_is_a_clear_error(tmp_path, text, match):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_config(f, {})


@pytest.mark.parametrize(
    "text, match",
    [
        ("[[rules]]\nestimator = 'no-such'\n", r"rules\[0\].*no-such"),
        (
            "[[rules]]\nestimator = 'ges-kalman'\nparams = { qq = 1 }\n",
            r"rules\[0\].*ges-kalman params.qq: unknown key",
        ),
        ("[[rules]]\nestimator = 'ges-kalman'\nparams = { r = -1 }\n", r"params.r"),
    ],
)
def test_bad_estimator_rules_are_clear_errors_from_check_and_serve(tmp_path, text, match, capsys):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    config = load_config(f, {})  # the structure is fine: printing it needs no estimator
    with pytest.raises(ConfigError, match=match):
        check_rules(config.rules)
    assert main(["config", "check", "--config", str(f)]) == 2
    assert "invalid estimator rules" in capsys.readouterr().err
    assert main(["serve", "--config", str(f)]) == 2  # refused before any session is opened


def test_unknown_environment_key_is_rejected():
    with pytest.raises(ConfigError, match="unknown key"):
        load_config(env={"SINEWATCH__ZENOH__MOOD": "peer"})


def test_config_show_prints_the_effective_config(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("SINEWATCH__DAEMON_ID", "from-env")
    assert main(["config", "show"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["daemon_id"] == "from-env" and shown["zenoh"]["listen"] == ["tcp/127.0.0.1:7450"]


def test_deploy_examples_are_valid():
    from pathlib import Path

    examples = sorted((Path(__file__).resolve().parents[1] / "deploy").glob("*.toml"))
    assert len(examples) >= 2
    for path in examples:
        load_config(path, {})
