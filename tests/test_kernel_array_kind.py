"""Every kernel gets one kind of sample array, whatever the payload's sample type.

numba compiles a kernel once per argument type, and an array's type says whether it is
writable, aligned and C-contiguous, and its dtype. A float64 payload decodes to a read-only
view of the payload (unaligned when its header is not a multiple of 8 bytes), a float32 one
to float32 samples: handed on as they are, each kernel would be compiled (and cached, and
warmed up by the daemon) for each kind. The pipeline hands every kernel float64, C-contiguous,
aligned, writable samples (``kernel_samples``); these tests feed both sample types as blocks
and frames and read the signatures numba compiled."""

from __future__ import annotations

import subprocess
import sys

import numba
import numpy as np
import pytest
from conftest import make_config
from numba.core import types

from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.estimators import get
from sinewatch.estimators.base import Estimator, kernel_samples
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.frame import FRAME_BINARY_ENCODING, Frame, encode_frame_binary


def _odd_kinds(signature: tuple[types.Type, ...]) -> list[str]:
    """The float arrays of a signature that are not the kernels' kind."""
    return [
        str(t)
        for t in signature
        if isinstance(t, types.Array)
        and isinstance(t.dtype, types.Float)
        and (t.dtype != types.float64 or not t.mutable or not t.aligned)
    ]


def _sinewatch_kernels() -> dict[str, numba.core.registry.CPUDispatcher]:
    found = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("sinewatch.") and module is not None:
            for attr, value in vars(module).items():
                if isinstance(value, numba.core.registry.CPUDispatcher):
                    found[f"{name}.{attr}"] = value
    return found


@pytest.mark.parametrize("estimator", ["kkl", "pmu", "nls"])  # two with a bank kernel, one without
def test_blocks_and_frames_of_either_sample_type_reach_kernels_as_one_kind(tmp_path, estimator):
    cls: type[Estimator] = get(estimator)
    rate = cls.example_sample_rate_hz
    x = cls.example_signal(1024)
    rule = EstimatorRule(estimator=estimator, params=dict(cls.example_params))
    pipeline = Pipeline(make_config(tmp_path, rules=[rule]), [NullSink()])
    for seq, dtype in enumerate(("float64", "float32")):
        for unit in (None, "A", "kV"):  # header lengths that leave the samples at other alignments
            block = Block(f"b-{unit}", seq, round(seq * 1024 * 1e9 / rate), rate, x, unit)
            pipeline.process(f"sinewatch/in/b-{unit}", encode_block_binary(block, dtype), BLOCK_BINARY_ENCODING, 0)
        frame = Frame(("f/a", "f/b", "f/c"), seq, round(seq * 1024 * 1e9 / rate), rate, np.stack([x, -x, 0.5 * x], 1))
        pipeline.process("sinewatch/in/f", encode_frame_binary(frame, dtype), FRAME_BINARY_ENCODING, 0)
    pipeline.release_held(0)  # the input's end: what the hold (on by default) still holds goes out
    # every block and every frame's channel accepted (pmu reports on a time grid: not one a block)
    assert pipeline.counters.errors == 0 and pipeline.counters.estimates >= (6 if estimator == "pmu" else 12)
    odd = {
        name: kinds
        for name, disp in _sinewatch_kernels().items()
        for sig in disp.signatures
        if (kinds := _odd_kinds(sig))
    }
    assert odd == {}, f"kernels compiled for samples of another kind: {odd}"


def test_kernel_samples_copies_only_what_is_not_of_the_kernels_kind():
    x = np.arange(8, dtype=np.float64)
    assert kernel_samples(x) is x
    view = np.frombuffer(x.tobytes(), dtype=np.float64)  # read-only
    out = kernel_samples(view)
    assert out is not view and out.flags.writeable and np.array_equal(out, x)
    unaligned = np.frombuffer(b"\0" + x.tobytes(), dtype=np.float64, offset=1)
    assert not unaligned.flags.aligned and kernel_samples(unaligned).flags.aligned
    f32 = x.astype(np.float32)
    assert kernel_samples(f32).dtype == np.float64 and np.array_equal(kernel_samples(f32), x)
    strided = np.stack([x, -x], axis=1)[:, 1]
    assert kernel_samples(strided).flags.c_contiguous and np.array_equal(kernel_samples(strided), -x)


# Run in a fresh interpreter: the daemon's warm-up, then a float64 and a float32 block and frame
# through a pipeline; prints the kernels' signature counts after each, the estimates, the errors.
_AFTER_WARM_UP = """
import sys, numba, numpy as np
from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.estimators import get
from sinewatch.runtime.daemon import Daemon
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import SinewatchConfig
from sinewatch.schemas.frame import FRAME_BINARY_ENCODING, Frame, encode_frame_binary

def count():
    mods = [m for name, m in list(sys.modules.items()) if name.startswith("sinewatch.") and m is not None]
    return sum(len(v.signatures) for m in mods for v in vars(m).values() if isinstance(v, numba.core.registry.CPUDispatcher))

config = SinewatchConfig.model_validate_json(sys.stdin.read())
Daemon(config).warm_up()
warm = count()
cls = get("kkl")
rate, x = cls.example_sample_rate_hz, cls.example_signal(1024)
p = Pipeline(config, [NullSink()])
for seq, dtype in enumerate(("float64", "float32")):
    t0 = round(seq * 1024 * 1e9 / rate)
    p.process("sinewatch/in/b", encode_block_binary(Block("b", seq, t0, rate, x), dtype), BLOCK_BINARY_ENCODING, 0)
    f = Frame(("f/a", "f/b"), seq, t0, rate, np.stack([x, -x], 1))
    p.process("sinewatch/in/f", encode_frame_binary(f, dtype), FRAME_BINARY_ENCODING, 0)
p.release_held(0)  # the input's end: what the hold (on by default) still holds goes out
print(warm, count(), p.counters.estimates, p.counters.errors)
"""


def test_the_daemon_s_warm_up_compiles_what_blocks_and_frames_of_either_type_run(tmp_path):
    """After the daemon's warm-up (one kind of samples), float64 and float32 blocks and
    frames compile nothing more. In a fresh interpreter: no test has run a kernel there."""
    config = make_config(tmp_path, rules=[EstimatorRule(estimator="kkl", params=dict(get("kkl").example_params))])
    stdin = config.model_dump_json()
    child = subprocess.run(
        [sys.executable, "-c", _AFTER_WARM_UP], input=stdin, capture_output=True, text=True, check=False
    )
    assert child.returncode == 0, child.stderr
    warm, after, estimates, errors = map(int, child.stdout.split())
    assert (estimates, errors) == (6, 0)
    assert warm > 0 and after == warm, f"{after - warm} kernel signature(s) compiled after the warm-up"
