"""A recording opens in any MCAP tool: every message of every channel, inputs (single blocks
and multi-channel frames) included, is decoded by the standard readers and decoders with the schema the file carries, and no
sinewatch code (Python: ``mcap`` + ``mcap-protobuf-support``, in a subprocess that never
imports sinewatch; Node: ``@mcap/core`` + ``@mcap/support`` + ``protobufjs``). The decoded
samples are the very samples sent; a rejected input's bytes are there as they came; and
the same file replays bit for bit."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sinewatch.core.pipeline import Pipeline
from sinewatch.outputs.recorder import McapRecorder
from sinewatch.runtime.replay import read_recording, replay
from sinewatch.schemas.codec import (
    BLOCK_BINARY_ENCODING,
    BLOCK_JSON_ENCODING,
    Block,
    encode_block_binary,
    encode_block_json,
)
from sinewatch.schemas.config import EstimatorRule, RecordingSection, SinewatchConfig
from sinewatch.schemas.frame import (
    FRAME_BINARY_ENCODING,
    FRAME_JSON_ENCODING,
    Frame,
    encode_frame_binary,
    encode_frame_json,
)

READERS = Path(__file__).parent / "readers"
NODE_CACHE = Path(__file__).parent.parent / ".cache" / "node-mcap-readers"
FS = 10_000.0
T0 = 1_763_900_000_000_000_000


def _sine(i: int, n: int, f: float, rng: np.random.Generator) -> np.ndarray:
    k = np.arange(i * n, (i + 1) * n)
    return 1.5 * np.sin(2 * np.pi * f * k / FS + 0.3) + 0.01 * rng.standard_normal(n)


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
    """A recording through the real pipeline and recorder: 1024-sample float64 and float32
    binary blocks, JSON blocks (one channel under two Zenoh encodings), multi-channel frames
    (binary float64 and float32, JSON under two Zenoh encodings), and inputs the daemon
    rejects (blocks and frames). Returns (path, sent: topic -> [(payload, encoding, block or
    frame, None if rejected)])."""
    d = tmp_path_factory.mktemp("standard-readers")
    config = SinewatchConfig(
        daemon_id="readers",
        rules=[
            EstimatorRule(match="sinewatch/in/a/**", estimator="nls"),
            EstimatorRule(match="sinewatch/in/**", estimator="sogi-fll"),
        ],
        recording=RecordingSection(directory=d, rotate_bytes=None, rotate_seconds=None),
    )
    path = d / "fresh.mcap"
    recorder = McapRecorder(config, path=path)
    pipeline = Pipeline(config, [recorder])
    rng = np.random.default_rng(28)
    sent: dict[str, list[tuple[bytes, str, Block | Frame | None]]] = {}
    t = 0

    def send(topic: str, payload: bytes, encoding: str, block: Block | Frame | None) -> None:
        nonlocal t
        t += 1
        sent.setdefault(topic, []).append((payload, encoding, block))
        pipeline.process(topic, payload, encoding, t)

    for i in range(8):
        t0 = T0 + round(i * 1024 * 1e9 / FS)
        b64 = Block("a/v64", i, t0, FS, _sine(i, 1024, 50.2, rng), "V")
        send("sinewatch/in/a/v64", encode_block_binary(b64, "float64"), BLOCK_BINARY_ENCODING, b64)
        b32 = Block("b/v32", i, t0, FS, _sine(i, 1024, 49.9, rng))
        send("sinewatch/in/b/v32", encode_block_binary(b32, "float32"), "", b32)
        bj = Block("c/json", i, t0, FS, _sine(i, 256, 60.0, rng))
        send("sinewatch/in/c/json", encode_block_json(bj), BLOCK_JSON_ENCODING if i % 2 else "text/plain;x=1", bj)
        if i % 4 == 3:  # rejected: not a block; an unknown dtype code
            send("sinewatch/in/a/v64", b"\x00not a block" + bytes([i]), "application/octet-stream", None)
            bad = bytearray(encode_block_binary(Block("a/v64", 99, 0, FS, np.zeros(8)), "float64"))
            bad[5] = 7
            send("sinewatch/in/a/v64", bytes(bad), BLOCK_BINARY_ENCODING, None)
        f64 = Frame(("f/a", "f/b", "f/c"), i, t0, FS, np.stack([_sine(i, 1024, 50 + c, rng) for c in range(3)], 1))
        send("sinewatch/in/f/mu", encode_frame_binary(f64, "float64"), FRAME_BINARY_ENCODING, f64)
        # every other one states a time quality (format version 2: InputFrame field 17)
        tq = (0x82, 0x84)[i % 4 // 2] if i % 2 else 0
        f32 = Frame(("g/a", "g/b"), i, t0, FS, np.stack([_sine(i, 1024, 49 + c, rng) for c in range(2)], 1), tq)
        send("sinewatch/in/g/mu", encode_frame_binary(f32, "float32"), "", f32)
        tj = T0 + round(i * 256 * 1e9 / FS)
        fj = Frame(("h/a", "h/b"), i, tj, FS, np.stack([_sine(i, 256, 60 - c, rng) for c in range(2)], 1))
        send("sinewatch/in/h/mu", encode_frame_json(fj), FRAME_JSON_ENCODING if i % 2 else "", fj)
        if i % 4 == 1:  # rejected frames: cut short; a non-zero pad byte ("g/x\n" leaves 4)
            send("sinewatch/in/f/mu", encode_frame_binary(f64)[:-5], FRAME_BINARY_ENCODING, None)
            bad = bytearray(encode_frame_binary(Frame(("g/x",), 99, t0, FS, np.ones((8, 1))), "float32"))
            bad[44 + i // 4] = 1
            send("sinewatch/in/g/mu", bytes(bad), "", None)
    pipeline.release_held(t + 1)  # the input's end, as the daemon's drain
    recorder.close()
    assert pipeline.counters.errors == 8 and pipeline.counters.estimates == 24 + 56
    return path, sent


def _check_decoded(out: dict, path: Path, sent: dict) -> None:
    """Every channel's every message decoded (the summary's counts), inputs equal to what
    was sent, estimates as the file holds them."""
    channels, counts = out["channels"], out["counts"]
    assert set(channels) == set(counts) and all(len(channels[c]["messages"]) == n for c, n in counts.items())
    inputs: dict[str, list[tuple[int, dict]]] = {}  # topic -> (log time, message): a channel per Zenoh encoding
    for ch in channels.values():
        if ch["metadata"]["role"] == "input":
            frames = ch["topic"].endswith("/mu")
            assert (ch["message_encoding"], ch["schema_name"], ch["schema_encoding"]) == (
                "protobuf",
                "sinewatch.InputFrame" if frames else "sinewatch.InputBlock",
                "protobuf",
            )
            inputs.setdefault(ch["topic"], []).extend(zip(ch["log_times"], ch["messages"], strict=True))
        else:
            assert (ch["message_encoding"], ch["schema_encoding"]) == ("json", "jsonschema")
    assert set(inputs) == set(sent)
    for topic, timed in inputs.items():
        messages = [m for _, m in sorted(timed, key=lambda tm: tm[0])]  # the order sent (log times rise)
        assert len(messages) == len(sent[topic])
        for msg, (payload, encoding, block) in zip(messages, sent[topic], strict=True):
            assert msg["zenoh_encoding"] == encoding
            if block is None:  # rejected: its bytes as they came
                assert bytes.fromhex(msg["raw"]) == payload
                continue
            if isinstance(block, Frame):
                _check_frame(msg, payload, encoding, block)
                continue
            assert msg["channel"] == block.channel and int(msg["seq"]) == block.seq
            assert int(msg["t0_ns"]) == block.t0_ns and msg["sample_rate_hz"] == block.sample_rate_hz
            sec, nsec = divmod(block.t0_ns, 1_000_000_000)
            assert (int(msg["timestamp"]["sec"]), int(msg["timestamp"]["nsec"])) == (sec, nsec)
            assert msg["n_samples"] == block.n_samples and msg["columns"] == 1
            if topic.endswith("v32"):  # float32 on the wire: those very values
                assert msg["samples"] == [] and np.array_equal(
                    np.float32(msg["samples_f32"]), block.samples.astype(np.float32)
                )
            else:
                assert np.array_equal(np.array(msg["samples"]), block.samples)
    estimates = [m for ch in channels.values() if ch["metadata"]["role"] == "estimate" for m in ch["messages"]]
    truth = [json.loads(m.payload) for k, m in read_recording(path) if k == "message" and m.role == "estimate"]

    def order(m: dict) -> tuple:
        return m["channel"], m["seq"]

    # == on the parsed values (JavaScript writes 1.0 as 1: the same number)
    assert len(estimates) == 80 and sorted(estimates, key=order) == sorted(truth, key=order)


def _check_frame(msg: dict, payload: bytes, encoding: str, frame: Frame) -> None:
    """A decoded InputFrame: the frame's channels, times and samples (n, C) sample-major; a
    binary frame as fields alone, a JSON frame's text kept in ``raw`` as it came."""
    assert msg["channels"] == list(frame.channels) and int(msg["seq"]) == frame.seq
    assert int(msg["t0_ns"]) == frame.t0_ns and msg["sample_rate_hz"] == frame.sample_rate_hz
    sec, nsec = divmod(frame.t0_ns, 1_000_000_000)
    assert (int(msg["timestamp"]["sec"]), int(msg["timestamp"]["nsec"])) == (sec, nsec)
    n, c = frame.samples.shape
    assert msg["n_samples"] == n
    if payload[:1] == b"{":  # JSON: the text as it came, the samples besides
        assert bytes.fromhex(msg["raw"]) == payload and msg["frame_version"] == 0
        assert np.array_equal(np.array(msg["samples"]).reshape(n, c), frame.samples)
    elif encoding == "":  # the float32 frames: those very values, some of version 2 with a time quality
        assert msg["raw"] == "" and msg["frame_version"] == frame.version and msg["samples"] == []
        assert msg["time_quality"] == frame.time_quality
        assert np.array_equal(np.float32(msg["samples_f32"]).reshape(n, c), frame.samples.astype(np.float32))
    else:
        assert msg["raw"] == "" and msg["frame_version"] == 1 and msg["samples_f32"] == []
        assert np.array_equal(np.array(msg["samples"]).reshape(n, c), frame.samples)


def test_python_standard_readers_decode_every_message_without_sinewatch(fresh):
    path, sent = fresh
    script = READERS / "decode_mcap.py"
    assert "sinewatch" not in "".join(line for line in script.read_text().splitlines() if "import" in line)
    # -I: isolated, so neither the worktree nor PYTHONPATH puts sinewatch on the path
    r = subprocess.run(
        [sys.executable, "-I", "-c", "import sys, runpy; sys.modules['sinewatch'] = None; "
         "sys.argv = sys.argv[1:]; runpy.run_path(sys.argv[0], run_name='__main__')", str(script), str(path)],
        capture_output=True, text=True, check=False, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    _check_decoded(json.loads(r.stdout), path, sent)


def test_the_recording_replays_bit_for_bit_rejected_inputs_included(fresh):
    path, sent = fresh
    result = replay([path])
    assert result.ok and result.inputs == sum(map(len, sent.values())) == 28 + 24 + 4
    assert result.matched == result.recorded_estimates == 80
    assert result.recorded_errors == 8 and result.produced_errors == 8
    # what replay feeds the pipeline: the bytes and the Zenoh encodings received
    fed = [
        (m.topic, m.payload, m.zenoh_encoding) for k, m in read_recording(path) if k == "message" and m.role == "input"
    ]
    expected = [(topic, p, e) for topic, items in sent.items() for p, e, _ in items]
    assert sorted(fed) == sorted(expected)


def _npm_install() -> Path:
    """The Node readers in a cache dir (once per package.json): the project's own step, also
    `make node-readers`."""
    manifest = (READERS / "package.json").read_bytes()
    stamp = NODE_CACHE / f".installed-{hashlib.sha256(manifest).hexdigest()[:12]}"
    if not stamp.exists():
        NODE_CACHE.mkdir(parents=True, exist_ok=True)
        (NODE_CACHE / "package.json").write_bytes(manifest)
        r = subprocess.run(
            ["npm", "install", "--no-audit", "--no-fund", "--ignore-scripts"],
            cwd=NODE_CACHE, capture_output=True, text=True, check=False, timeout=600,
        )  # fmt: skip
        if r.returncode != 0:
            pytest.skip(f"npm install of the Node MCAP readers failed (no registry?): {r.stderr.strip()[-300:]}")
        stamp.touch()
    shutil.copy(READERS / "decode_mcap.mjs", NODE_CACHE / "decode_mcap.mjs")  # resolves its imports there
    return NODE_CACHE


@pytest.fixture(scope="module")
def node_readers():
    missing = [tool for tool in ("node", "npm") if shutil.which(tool) is None]
    if missing:
        pytest.skip(f"{' and '.join(missing)} not installed: the Node reader check needs Node.js 18+ and npm")
    return _npm_install()


def test_node_standard_readers_decode_every_message(fresh, node_readers):
    path, sent = fresh
    r = subprocess.run(
        ["node", str(node_readers / "decode_mcap.mjs"), str(path)],
        capture_output=True, text=True, check=False, timeout=120, env={**os.environ, "NODE_NO_WARNINGS": "1"},
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    _check_decoded(json.loads(r.stdout), path, sent)
