"""MCAP recording and replay: rotation with snapshots, crash recovery, mismatch reports."""

from __future__ import annotations

import json

import numpy as np
from conftest import record_run
from mcap.reader import make_reader

from sinewatch.apps.cli import main
from sinewatch.runtime.replay import read_recording, replay
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING


def test_rotation_writes_self_contained_files(tmp_path):
    paths, pipeline = record_run(tmp_path, n_blocks=60, rotate_seconds=1.0)
    assert len(paths) == 3  # 60 blocks x 0.04 s, a new file every second
    for p in paths:
        with open(p, "rb") as f:
            reader = make_reader(f)
            meta = {m.name: m.metadata for m in reader.iter_metadata()}
            assert "sinewatch" in meta and json.loads(meta["sinewatch"]["config"])["daemon_id"] == "test"
    # a later file replays on its own from its snapshot, bit for bit
    second = replay([paths[1]])
    assert second.ok and second.matched == second.recorded_estimates > 0
    # and the whole run replays in order
    whole = replay(paths)
    assert whole.ok and whole.matched == pipeline.counters.estimates


def test_unfinished_file_replays_its_complete_chunks(tmp_path):
    [path], _ = record_run(tmp_path, n_blocks=200, flush_every=10)
    data = path.read_bytes()
    cut = tmp_path / "crashed.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])  # as if the writer had been killed
    r = replay([cut])
    assert r.incomplete_files == [cut]
    assert r.ok and 0 < r.matched < 400


def test_replay_reports_a_changed_estimate_and_exits_non_zero(tmp_path, capsys):
    [path], _ = record_run(tmp_path, n_blocks=40, tamper_at=57)
    r = replay([path])
    assert not r.ok and len(r.mismatches) == 1
    assert "diagnostics.converged: recorded False != replayed True" in r.mismatches[0].describe()
    assert main(["replay", str(path), "--no-progress"]) == 1
    assert "MISMATCH" in capsys.readouterr().out


def test_replay_with_another_estimator_writes_a_new_recording(tmp_path, capsys):
    [path], _ = record_run(tmp_path, n_blocks=40)
    out = tmp_path / "alt.mcap"
    estimator = ["--estimator", "ges-kalman", "--param", "r=0.5", "--param", "q=[1e-10,1e-10,1e-14,1e-14]"]
    assert main(["replay", str(path), "--no-progress", *estimator, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "recorded vs re-run" in text and str(out) in text
    again = replay([out])  # the new file is itself a faithful recording
    assert again.ok and again.recorded_estimates == 79
    rec = json.loads(
        make_reader(open(out, "rb")).get_summary()
        and next(m for m in make_reader(open(out, "rb")).iter_metadata()).metadata["config"]
    )
    assert rec["rules"][0]["params"]["r"] == 0.5


def test_gap_policy_reset_is_recorded_and_replayed(tmp_path):
    [path], _pipeline = record_run(tmp_path, n_blocks=40, on_gap="reset")
    estimates = []
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            if channel.metadata["role"] == "estimate":
                estimates.append(json.loads(message.data))
    reset = [e for e in estimates if e["diagnostics"]["reset"]]
    assert [(e["channel"], e["seq"], e["diagnostics"]["gap_blocks"]) for e in reset] == [("rr/demo-ramp", 31, 1)]
    assert replay([path]).ok


def test_replay_of_a_non_sinewatch_file_is_a_clear_error(tmp_path, capsys):
    from mcap.writer import Writer

    p = tmp_path / "other.mcap"
    with open(p, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        cid = w.register_channel("/x", "json", sid)
        w.add_message(cid, 1, b"{}", 1)
        w.finish()
    assert main(["replay", str(p), "--no-progress"]) == 2
    assert "expected a file written by sinewatch" in capsys.readouterr().err


def test_recorded_inputs_give_back_the_received_bytes(tmp_path):
    [path], _ = record_run(tmp_path, n_blocks=3)
    inputs = [m for kind, m in read_recording(path) if kind == "message" and m.role == "input"]
    assert inputs[0].zenoh_encoding == BLOCK_BINARY_ENCODING and inputs[0].payload[:4] == b"SWSB"
    blk = np.frombuffer(inputs[0].payload, "<f8", offset=40 + len("rr/demo-biased"))
    assert blk.shape == (400,)
