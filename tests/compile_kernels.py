"""Compile (or load from numba's cache) the kernels the test suite runs, once, before it runs.

A fresh clone has no numba cache: every ``cache=True`` kernel is compiled on its first call,
inside whichever test (or daemon subprocess) calls it first, and two processes that call the
same kernel before either has written the cache both compile it. ``make test`` runs this script
beside ``make lint`` so that the suite starts with a warm cache, on two processes (one task per
estimator): the lint is much shorter, and one process would leave a core idle meanwhile.
Nothing here is asserted: a kernel this script does not reach is compiled on demand as before,
and a kernel that fails to compile fails here and in its tests alike.

Reached: every registered estimator through a real :class:`Pipeline` (a block, whole
blocks and the last sample only, and a two-channel frame: its bank and the presence detectors'
bank; one sample type is enough, the pipeline hands every kernel the same kind of array,
:func:`sinewatch.estimators.base.kernel_samples`), with its example parameters, the default rule and every
scenario's suggested parameters at the scenario's sample rate; the automatic adaptive
multisine for one, two and three sinusoids and its explicit design; the power-quality
stage's harmonic analyser; and the recordings in ``tests/data`` replayed.
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numba
import numpy as np

from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.estimators import available, get
from sinewatch.power_quality.stage import warm_up
from sinewatch.scenarios import get as get_scenario
from sinewatch.scenarios import names as scenario_names
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import EstimatorRule, RecordingSection, SinewatchConfig
from sinewatch.schemas.frame import FRAME_BINARY_ENCODING, Frame, encode_frame_binary


def _through_pipeline(rule: EstimatorRule, rate: float, x: np.ndarray, directory: Path) -> None:
    config = SinewatchConfig(
        daemon_id="compile-kernels", rules=[rule], recording=RecordingSection(directory=directory, enabled=False)
    )
    pipeline = Pipeline(config, [NullSink()])
    blk = Block("warm", 0, 0, rate, x)
    pipeline.process("sinewatch/in/warm", encode_block_binary(blk, "float64"), BLOCK_BINARY_ENCODING, 0)


def _through_frames(rule: EstimatorRule, rate: float, x: np.ndarray, directory: Path) -> None:
    """Two channels in one frame: the estimator's bank kernel and the presence detectors' bank."""
    config = SinewatchConfig(
        daemon_id="compile-kernels", rules=[rule], recording=RecordingSection(directory=directory, enabled=False)
    )
    pipeline = Pipeline(config, [NullSink()])
    columns = np.ascontiguousarray(np.stack([x, 0.5 * x], axis=1))
    frame = Frame(("warm/a", "warm/b"), 0, 0, rate, columns)
    pipeline.process("sinewatch/in/warm", encode_frame_binary(frame, "float64"), FRAME_BINARY_ENCODING, 0)


def _estimator(name: str, params: dict[str, Any] | None = None) -> None:
    cls = get(name)
    est = cls(cls.example_sample_rate_hz, dict(cls.example_params if params is None else params))
    x = cls.example_signal(256)
    est.update(x)
    est.update(x, last_only=True)


def _one(name: str) -> str:
    """Compile one estimator's kernels (alone, then through a pipeline), in a pool worker."""
    with tempfile.TemporaryDirectory() as tmp:
        cls = get(name)
        _estimator(name)
        x = cls.example_signal(1000)
        if x.ndim == 1:
            rule = EstimatorRule(estimator=name, params=dict(cls.example_params))
            _through_pipeline(rule, cls.example_sample_rate_hz, x, Path(tmp))
            _through_frames(rule, cls.example_sample_rate_hz, x, Path(tmp))
        if name == "pmu":  # the default rule
            _through_pipeline(EstimatorRule(), 10_000.0, get("pmu").example_signal(2000), Path(tmp))
        for rate, params, x in _scenario_settings(name):  # params that can choose other kernels
            _through_pipeline(EstimatorRule(estimator=name, params=params), rate, x, Path(tmp))
        if name == "adaptive-multisine":
            for n in (1, 3):
                _estimator(name, {"n_sinusoids": n, "band_hz": (5.0, 25.0)})
            _estimator(name, {"n_sinusoids": 2})  # no band: the explicit design
    return name


def _scenario_settings(name: str) -> list[tuple[float, dict[str, Any], np.ndarray]]:
    """Each distinct ``suggested_params`` the scenario library gives ``name`` (the tests and
    ``sinewatch feed`` serve scenarios with them; differential-rls's ``input = "iq"`` runs
    another kernel on two columns), with 2000 samples of the scenario at its sample rate."""
    seen: dict[str, tuple[float, dict[str, Any], np.ndarray]] = {}
    for scenario_name in scenario_names():
        sc = get_scenario(scenario_name)
        key = json.dumps(sc.suggested_params, sort_keys=True)
        if sc.suggested_estimator == name and key not in seen:
            seen[key] = (sc.sample_rate_hz, dict(sc.suggested_params), sc.generate(n=2000)[0])
    return list(seen.values())


def _power_quality() -> str:
    warm_up()
    return "power-quality"


def _recordings() -> str:
    """Replay the recordings the tests replay (``tests/data``): an older build's files run
    their estimators with the params of that time (``defaults_before``), which can be another
    signature of a kernel (adaptive-multisine's, in the one recorded before the layering)."""
    from sinewatch.runtime.replay import replay

    for path in sorted((Path(__file__).parent / "data").glob("*.mcap")):
        replay([path])
    return "recordings"


SOURCES = Path(__file__).resolve().parents[1] / "service" / "sinewatch"


def stamp_path() -> Path:
    """Where a completed run leaves its key: numba's cache directory when one is set, else the
    ``__pycache__`` beside the sources, where numba keeps its cache by default."""
    root = Path(numba.config.CACHE_DIR) if numba.config.CACHE_DIR else SOURCES / "__pycache__"
    return root / "compile_kernels.stamp"


def sources_key() -> str:
    """What the cache this script fills depends on: numba's version and every source file's
    bytes (numba drops a file's cache entries when that file changes), and the recordings it
    replays. Reading them takes milliseconds."""
    h = hashlib.sha256(f"{numba.__version__} {sys.version}".encode())
    data = Path(__file__).parent / "data"
    for path in sorted([*SOURCES.rglob("*.py"), *data.glob("*.mcap"), Path(__file__)]):
        h.update(str(path.relative_to(SOURCES.parents[1])).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def is_warm() -> bool:
    """Whether this script has completed since the sources last changed."""
    try:
        return stamp_path().read_text(encoding="ascii").strip() == sources_key()
    except OSError:
        return False


# The estimators' tasks by their compile CPU on a cold cache, longest first (this script prints
# each task's; `.ci/run` on a fresh clone, 2-core AMD EPYC VM (AVX2), numba 0.68.1): the pool starts
# each task as a process frees, so the longest ones first leave the shortest to fill the end
# (adaptive-multisine 56.5 s, ges-kalman 33.3, differential-rls 23.5, nls ~23 (27.2 while its
# order-0 fit compiled twice), kkl-biased 19.8, grip-mixing 16.0, pmu 15.3, kkl 13.8, ipdft 13.0,
# sogi-fll 8.7; the recordings' replay, 8.6, and the power-quality stage, 0.5, go last).
# An estimator not listed goes after these.
LONGEST_FIRST = (
    "adaptive-multisine", "ges-kalman", "differential-rls", "nls", "kkl-biased", "grip-mixing", "pmu", "kkl",
    "ipdft", "sogi-fll",
)  # fmt: skip


def _longest_first(name: str) -> int:
    return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)


def _timed(task: Callable[..., str], *args: str) -> tuple[str, float, float]:
    """Run ``task`` in a pool worker; its name, wall and CPU seconds (that worker's user +
    system time: what the task compiled, less what an earlier task on the worker had)."""
    wall, cpu = time.monotonic(), time.process_time()
    name = task(*args)
    return name, time.monotonic() - wall, time.process_time() - cpu


def main() -> int:
    """One task per estimator (and the power-quality stage), on two processes: numba compiles
    on one core, and ``make test`` runs this beside the much shorter lint, so a single process
    would leave a core idle for most of the compilation. Each task's wall and CPU seconds are
    printed as it completes (on a warm cache, the loading alone)."""
    t0 = time.monotonic()
    key = sources_key()  # the sources compiled: a file edited meanwhile leaves the stamp stale
    names = sorted(available(), key=_longest_first)
    with ProcessPoolExecutor(max_workers=2) as pool:
        tasks = [*(pool.submit(_timed, _one, n) for n in names), pool.submit(_timed, _recordings)]
        for task in as_completed([*tasks, pool.submit(_timed, _power_quality)]):
            name, wall, cpu = task.result()  # a kernel that fails to compile fails here
            print(f"compile_kernels: {name:<20} {wall:6.1f} s wall {cpu:6.1f} s CPU", file=sys.stderr)
    stamp = stamp_path()
    stamp.parent.mkdir(parents=True, exist_ok=True)
    stamp.write_text(key + "\n", encoding="ascii")
    print(f"compile_kernels: {time.monotonic() - t0:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
