"""``sinewatch.estimators.lanes``: the lane-major banks' row copy and the host's vector width."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from sinewatch.estimators.lanes import LANES, copy_lanes, host_vector_bits

# values whose bits a computed copy could change: -0.0, a NaN with a payload, a subnormal
_ODD = np.array([-0.0, 5e-324, np.inf, -np.inf, 1.0 + 2.0**-52], dtype=np.float64)
_NAN_PAYLOAD = np.frombuffer(np.uint64(0x7FF8_0000_DEAD_BEEF).tobytes(), dtype=np.float64)[0]


def _source(shape: tuple[int, ...]) -> np.ndarray:
    src = np.random.default_rng(3).standard_normal(shape)
    flat = src.reshape(-1)
    flat[13 : 13 + _ODD.size] = _ODD
    flat[19] = _NAN_PAYLOAD
    return src


def test_copy_lanes_moves_one_row_bit_for_bit_and_touches_nothing_else() -> None:
    src = _source((40,))
    dst = np.full(3 * LANES, -7.0)
    copy_lanes(dst, LANES, src, 13)
    assert dst[LANES : 2 * LANES].tobytes() == src[13 : 13 + LANES].tobytes()  # -0.0, the NaN's payload kept
    assert np.all(dst[:LANES] == -7.0) and np.all(dst[2 * LANES :] == -7.0)
    assert src.tobytes() == _source((40,)).tobytes()  # the source unchanged


def test_copy_lanes_reads_a_row_of_a_2d_array_by_its_flat_offset() -> None:
    """As pmu's bank reads its next sample's lanes: row i of the (N, C) samples, columns b..b+7."""
    src = _source((4, 16))
    dst = np.zeros(2 * LANES)
    i, b = 1, 5
    copy_lanes(dst, 0, src, i * src.shape[1] + b)
    assert dst[:LANES].tobytes() == src[i, b : b + LANES].tobytes()
    assert np.all(dst[LANES:] == 0.0)


def test_copy_lanes_within_one_array_between_rows() -> None:
    w = np.arange(4 * LANES, dtype=np.float64)
    copy_lanes(w, 0, w, 2 * LANES)
    assert np.array_equal(w[:LANES], np.arange(2 * LANES, 3 * LANES))
    assert np.array_equal(w[LANES:], np.arange(LANES, 4 * LANES))


@pytest.mark.parametrize(
    ("features", "bits"), [("+avx,+avx2,+avx512f", 512), ("+avx,+avx2,-avx512f", 256), ("+sse2,-avx", 128)]
)
def test_host_vector_bits_follows_numbas_cpu_override(monkeypatch, features: str, bits: int) -> None:
    """NUMBA_CPU_NAME / NUMBA_CPU_FEATURES decide what numba compiles for, so they decide the width."""
    monkeypatch.setattr(numba.config, "CPU_NAME", "generic")
    monkeypatch.setattr(numba.config, "CPU_FEATURES", features)
    assert host_vector_bits() == ("generic", bits)
