"""Shared fixtures: daemon configs on a free loopback port, a running daemon, recordings.

Integration tests run a real daemon in-process (``run_daemon``) with its Zenoh peer on
127.0.0.1 and a client in a thread; waits end when messages arrive (``take``), with
``TIMEOUT`` as a guard for a loaded 2-core machine, never a sleep.
"""

from __future__ import annotations

import sinewatch.host_arithmetic  # first, before numpy loads (its docstring says why)

# isort: split

import asyncio
import contextlib
import functools
import json
import re
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import pytest

from sinewatch.apps.feed import make_channels
from sinewatch.clients import BlockPublisher, connect, subscribe_estimates
from sinewatch.clients.session import free_loopback_port
from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.outputs.recorder import McapRecorder
from sinewatch.runtime.daemon import Daemon
from sinewatch.scenarios.demo import KALMAN_10K
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import (
    EstimatorRule,
    LimitsSection,
    RecordingSection,
    SinewatchConfig,
    ZenohSection,
)

TIMEOUT = 20.0  # a guard for a loaded machine: every wait ends as soon as its message arrives
# How long a client waits for a ``sinewatch serve`` it started to listen: serve imports, opens
# its outputs and loads (or, after a source edit, compiles) its kernels before it listens, tens
# of seconds on a machine whose cores are shared with a dozen busy processes. A wait that ends
# as soon as it connects, so only a daemon that never comes up costs this long.
STARTUP_WAIT_S = 180
R = TypeVar("R")


def make_config(tmp_path: Path, **overrides) -> SinewatchConfig:
    port = free_loopback_port()
    kw = dict(
        daemon_id="test",
        zenoh=ZenohSection(listen=[f"tcp/127.0.0.1:{port}"]),
        rules=[EstimatorRule(match="sinewatch/in/**", estimator="ges-kalman", params=KALMAN_10K)],
        recording=RecordingSection(directory=tmp_path / "rec", flush_interval_s=0.2),
        limits=LimitsSection(),
        status_interval_s=0.2,
    )
    kw.update(overrides)
    return SinewatchConfig(**kw)


def endpoint(config: SinewatchConfig) -> str:
    """Where a client reaches the daemon: its listen endpoint, or the router it connects to."""
    return (config.zenoh.listen or config.zenoh.connect)[0]


@pytest.fixture
def config(tmp_path):
    return make_config(tmp_path)


def run_daemon(
    config: SinewatchConfig, client: Callable[[Daemon, str], R], *, signals: bool = False
) -> tuple[R, Daemon, int]:
    """Start a daemon, run ``client(daemon, endpoint)`` in a thread, stop the daemon (as
    SIGINT would) and return (the client's result, the daemon, its exit code).

    With ``signals=True`` the daemon installs its signal handlers and the client is the one
    that stops it (by raising SIGINT or SIGTERM): setting ``should_exit`` here as well would
    race the handler and turn the client's one SIGINT into a "second" one."""

    async def main() -> tuple[R, Daemon, int]:
        daemon = Daemon(config, install_signal_handlers=signals)
        task = asyncio.create_task(daemon.run())
        await daemon.ready.wait()
        try:
            result = await asyncio.to_thread(client, daemon, endpoint(config))
        except BaseException:
            daemon.should_exit.set()
            await task
            raise
        if not signals:
            daemon.should_exit.set()
        code = await asyncio.wait_for(task, TIMEOUT)
        return result, daemon, code

    return asyncio.run(main())


@contextlib.contextmanager
def publishing(ep: str, channel: str, *subscribe: Callable[[Any], Any]) -> Iterator[tuple[BlockPublisher, list[Any]]]:
    """A client session on ``ep``: the subscriptions ``subscribe`` make (estimates, errors,
    status ...), made first so that nothing the daemon answers is missed, then a publisher
    whose ``channel`` the daemon subscribes to (asserted, ``TIMEOUT`` at most)."""
    with connect([ep]) as s:
        subscriptions = [sub(s) for sub in subscribe]
        pub = BlockPublisher(s)
        assert pub.wait_for_subscriber(channel, TIMEOUT)
        yield pub, subscriptions


def serve_blocks(
    config: SinewatchConfig, channel: str, blocks: list[Block], n_messages: int
) -> tuple[list[Any], Daemon]:
    """Run a daemon on ``config``; a client on real Zenoh publishes ``blocks`` (float64) on
    ``channel`` once the daemon subscribes, and takes ``n_messages`` estimates (20 s each at
    most). Returns the messages and the daemon, after asserting a clean exit and that every
    message came."""

    def client(_daemon: Daemon, ep: str) -> list[Any]:
        with publishing(ep, channel, subscribe_estimates) as (pub, [est]):
            for blk in blocks:
                pub.publish_raw(channel, encode_block_binary(blk, "float64"))
            return [est.get(timeout=20) for _ in range(n_messages)]

    got, daemon, code = run_daemon(config, client)
    assert code == 0 and all(m is not None for m in got)
    return got, daemon


def take(subscription: Any, n: int, timeout: float = TIMEOUT) -> list[dict[str, Any]]:
    """The next ``n`` messages of a JsonSubscription (fewer if one does not come in time)."""
    out: list[dict[str, Any]] = []
    while len(out) < n and (msg := subscription.get(timeout=timeout)) is not None:
        out.append(msg)
    return out


class KeepSink(NullSink):
    """A pipeline sink that keeps every estimate and error message, decoded."""

    estimates: list[dict[str, Any]]
    errors: list[dict[str, Any]]

    def __init__(self) -> None:
        self.estimates, self.errors = [], []

    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self.estimates.append(json.loads(payload))

    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self.errors.append(json.loads(payload))


def clean_estimates(config: SinewatchConfig, key: str, blocks: list[Block]) -> list[dict[str, Any]]:
    """What a fresh pipeline says for exactly these blocks, up to the input's end (the
    estimates still held back for the presence detector released, not valid, as a daemon's idle
    release or drain releases them): the reference that shows a daemon's estimators never saw the
    bad inputs it rejected."""

    keep = KeepSink()
    clean = Pipeline(config, [keep])
    for blk in blocks:
        clean.process(key, encode_block_binary(blk), BLOCK_BINARY_ENCODING, 0)
    clean.release_held(0)
    return keep.estimates


class FakeClock:
    """Recorder clock advanced by the test, so duration-based rotation is deterministic."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def record_run(tmp_path: Path, n_blocks=60, rotate_seconds=None, tamper_at=None, on_gap="coast", flush_every=None):
    """A recording made through the real pipeline and recorder: two channels (biased 120 Hz,
    a 1 Hz/s ramp) in 400-sample blocks, one block missing (a gap); returns (paths, pipeline)."""
    config = make_config(
        tmp_path,
        on_gap=on_gap,
        recording=RecordingSection(directory=tmp_path / "rec", rotate_seconds=rotate_seconds, rotate_bytes=None),
    )
    clock = FakeClock()
    recorder = McapRecorder(config, snapshot=lambda: pipeline.snapshot(), clock=clock)
    if tamper_at is not None:
        original = recorder.on_estimate
        count = {"n": 0}

        def tampered(key, payload, log_time_ns):
            count["n"] += 1
            if count["n"] == tamper_at:
                payload = payload.replace(b'"converged":true', b'"converged":false')
            original(key, payload, log_time_ns)

        recorder.on_estimate = tampered
    pipeline = Pipeline(config, [recorder])
    streams = make_channels(["demo-biased", "demo-ramp"], prefix="rr")
    t = 1_000
    for i in range(n_blocks):
        for ch in streams:
            if ch.channel == "rr/demo-ramp" and i == 30:
                continue  # a gap
            x, _ = ch.stream.read(400)
            blk = Block(ch.channel, i, i * 40_000_000, 10_000.0, x)
            t += 1
            pipeline.process(f"sinewatch/in/{ch.channel}", encode_block_binary(blk), BLOCK_BINARY_ENCODING, t)
        clock.now += 0.04
        if flush_every and i % flush_every == 0:
            recorder.flush()  # what the daemon's flush timer does
    recorder.close()
    return recorder.paths, pipeline


def sinewatch(*args: str) -> list[str]:
    """The command line that runs ``sinewatch ARGS`` with this interpreter."""
    return [sys.executable, "-m", "sinewatch", *args]


def serve_feed_tail(
    serve_args: list[str], tail_args: list[str], feed_args: list[str], serve_env: dict[str, str] | None = None
) -> tuple[str, list[dict[str, Any]], str]:
    """``sinewatch serve``, ``tail --json`` and ``feed`` as separate processes, as a user runs
    them: tail is subscribed before feed (``--fast --wait 60`` after ``feed_args``) publishes; serve is stopped by SIGINT once tail has its
    messages. Returns feed's stderr, tail's messages and serve's stderr, after asserting that
    all three exited 0."""
    serve = subprocess.Popen(sinewatch("serve", *serve_args), stderr=subprocess.PIPE, text=True, env=serve_env)
    try:
        tail = subprocess.Popen(
            sinewatch("tail", *tail_args), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        assert tail.stderr is not None
        # "tail: waiting for a Zenoh router ..." first, then "tail: subscribed to ..." once it is
        said: list[str] = []
        for line in iter(tail.stderr.readline, ""):
            said.append(line)
            if line.startswith("tail: subscribed to"):
                break
        else:  # what tail said is why (a failure that only said `any(...)` was False was seen at load 30)
            raise AssertionError(f"tail ended (exit {tail.wait()}) before subscribing; it said: {''.join(said)!r}")
        feed = subprocess.run(
            sinewatch("feed", *feed_args, "--fast", "--wait", str(STARTUP_WAIT_S)),
            capture_output=True,
            text=True,
            timeout=STARTUP_WAIT_S + 60,
            check=False,
        )
        assert feed.returncode == 0, feed.stderr
        out, _ = tail.communicate(timeout=STARTUP_WAIT_S + 60)
    finally:
        serve.send_signal(signal.SIGINT)
        # a serve still starting (imports, kernels) stops once it runs Python again: on a loaded
        # machine that can be longer than a minute, and a timeout here would hide the failure above
        _, err = serve.communicate(timeout=STARTUP_WAIT_S)
    assert serve.returncode == 0, err
    return feed.stderr, [json.loads(line) for line in out.splitlines()], err


def replay_recording(directory: Path) -> str:
    """``sinewatch replay`` of the one MCAP file in ``directory``; its stdout, after asserting
    that it exited 0."""
    [mcap] = list(directory.glob("*.mcap"))
    r = subprocess.run(
        sinewatch("replay", str(mcap), "--no-progress"), capture_output=True, text=True, timeout=120, check=False
    )
    assert r.returncode == 0, r.stdout + r.stderr
    return r.stdout


def serve_config_feed_tail(
    tmp_path: Path, config: SinewatchConfig, n_messages: int, feed_args: list[str]
) -> tuple[str, list[dict[str, Any]], str]:
    """``serve_feed_tail`` with ``config`` (written as JSON) served, ``tail --json`` taking
    ``n_messages`` and ``feed`` publishing ``feed_args``; both clients connect to it."""
    ep = endpoint(config)
    cfg_file = tmp_path / "serve.json"
    cfg_file.write_text(json.dumps(config.model_dump(mode="json")))
    return serve_feed_tail(
        ["--config", str(cfg_file)],
        ["--connect", ep, "--count", str(n_messages), "--json", "--timeout", "60", "--wait", str(STARTUP_WAIT_S)],
        ["--connect", ep, *feed_args],
    )


def serve_comtrade(tmp_path: Path, cfg: Path, *feed_args: str, name: str = "daemon") -> tuple[str, list[dict]]:
    """A COMTRADE record fed (``feed --comtrade cfg``, then ``feed_args``) to a daemon whose
    one rule runs ipdft (50 Hz, 10 cycles) on it; feed's stderr and 12 estimates from tail."""
    port = free_loopback_port()
    config = tmp_path / f"{name}.toml"
    config.write_text(
        # idle_release_s: the record's last estimates go out when its feed ends; mid-record, a block
        # that reaches the daemon over 0.5 s (the default) after its channel's previous one, as on a
        # loaded machine, released the held estimate early, not valid, and two runs differed
        "idle_release_s = 2.0\n"
        f'[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\n\n[recording]\nenabled = false\n\n'
        '[[rules]]\nmatch = "sinewatch/in/comtrade/**"\nestimator = "ipdft"\n'
        "params = { nominal_frequency_hz = 50.0, window_cycles = 10 }\n"
    )
    ep = f"tcp/127.0.0.1:{port}"
    feed_err, estimates, _ = serve_feed_tail(
        ["--config", str(config)],
        ["--connect", ep, "--json", "--count", "12"],
        ["--connect", ep, "--comtrade", str(cfg), *feed_args],
    )
    return feed_err, estimates


def cli_without(module: str, argv: list[str]) -> subprocess.CompletedProcess[str]:
    """``sinewatch ARGV`` in a fresh interpreter in which ``module`` cannot be imported, as if
    the optional package were not installed."""
    code = f"import sys; sys.modules[{module!r}] = None\nfrom sinewatch.apps.cli import main\nsys.exit(main({argv!r}))"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)


# --- Running on two workers (``make test``: pytest-xdist, ``-n 2 --dist loadgroup``) ----------

# Tests that start etcd and several daemon processes, and whose faults are timed against
# leases (the chaos test runs its own CPU burner): one worker runs them one after another,
# so that two of them never compete for the same cores at once.
SERIAL_CLUSTER = ("tests/test_cluster_", "tests/test_election.py", "tests/test_access_control.py")
# The longest tests and groups (tens of seconds each on a quiet 2-core machine, longest
# first): dispatched first, in this order, so that no worker is left with a long one while
# the other has finished. (``pytest --durations=25`` lists the longest of a run.)
LONG_FIRST = (
    *SERIAL_CLUSTER,
    "tests/test_demo.py",
    "tests/test_workers.py",
    "tests/test_default_rule.py",
    "tests/test_compare_track.py",
    "tests/test_fuzz.py",
    "tests/test_pq_service.py",
    "tests/test_container.py",
    "tests/test_frames.py",
    "tests/test_differential_rls_served.py",
    "tests/test_cli_processes.py",
    "tests/test_adaptive_multisine_auto.py",
    "tests/test_recording_compatibility.py",
)
_SHARED_FIXTURE = re.compile(r"""@pytest\.fixture\(.*scope=["'](module|class|package)["']""")


@functools.cache
def _shares_fixtures(root: Path, path: str) -> bool:
    """Whether a test module has module- or class-scoped fixtures (a recording, a wheel, an
    npm install): its tests stay on one worker, so those are built once and never by two
    workers in the same directory at once."""
    try:
        return _SHARED_FIXTURE.search((root / path).read_text(encoding="utf-8")) is not None
    except OSError:
        return False


def xdist_scope(root: Path, nodeid: str) -> str:
    """The unit of work one worker runs from start to end: the cluster tests together, a
    module with shared fixtures whole, any other test alone."""
    path = nodeid.split("::", 1)[0]
    if path.startswith(SERIAL_CLUSTER):
        return "cluster"
    return path if _shares_fixtures(root, path) else nodeid


@pytest.hookimpl(tryfirst=True, optionalhook=True)  # before xdist's own choice; xdist may be absent
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``--dist loadgroup`` with the groups of ``xdist_scope``. (xdist 3.8 marks a group by
    renaming the test's node id, which pytest 9.2's node ids no longer allow.)"""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class Groups(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return xdist_scope(config.rootpath, nodeid)

    return Groups(config, log)


# Benches that measure what the machine sustains (tests/test_bench_e2e.py): `make test` runs
# them alone, after the two workers, so that no other test shares their cores. The file's
# in-process tests (the probe's parsing, the feeder's stamps) run with the others.
ALONE = (
    "tests/test_bench_e2e.py::test_sweep_",
    "tests/test_bench_e2e.py::test_fanout_",
    "tests/test_bench_e2e.py::test_frame_channels_",
)


def pytest_itemcollected(item: pytest.Item) -> None:
    if item.nodeid.startswith(ALONE):
        item.add_marker(pytest.mark.alone)


def _dispatch_rank(nodeid: str) -> int:
    """Where a test's module stands in ``LONG_FIRST`` (any other test after all of them)."""
    return next((i for i, prefix in enumerate(LONG_FIRST) if nodeid.startswith(prefix)), len(LONG_FIRST))


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    items.sort(key=lambda item: _dispatch_rank(item.nodeid))  # stable: collection order within a rank


def pytest_sessionstart(session: pytest.Session) -> None:
    """A run on xdist workers (``-n``) starts with the kernels compiled, as ``make test`` does
    (``tests/compile_kernels.py``, before the workers start), unless that script has completed
    since the sources last changed. Otherwise the first test to call a kernel compiles it, for
    tens of seconds of CPU, which on a loaded machine outlasts pytest-timeout's 300 s; and the
    timeout's exception, raised in whichever frame runs then, can land inside numba's
    object-cache callback, where it is swallowed and numba fails to save the kernel ("no
    compiled object yet"): the estimator stage rejects the block and the test fails on that
    instead. Runs without ``-n`` (one file, one test) compile on demand as before."""
    config = session.config
    if hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", None):
        return
    if config.option.collectonly:
        return
    script = Path(__file__).parent / "compile_kernels.py"
    sys.path.insert(0, str(script.parent))
    try:
        import compile_kernels
    finally:
        sys.path.remove(str(script.parent))
    if not compile_kernels.is_warm():
        subprocess.run([sys.executable, str(script)], check=True)
