"""``sinewatch.estimators.lanes.aligned_lanes``: the lane-major banks' work arrays start on a cache
line, so that each row of LANES doubles lies in one line (a row across two made a bank ~30 %
slower in some processes and not others)."""

from __future__ import annotations

import numba
import numpy as np

from sinewatch.estimators.lanes import LANES, aligned_lanes


@numba.njit(cache=False)
def _from_compiled_code(size: int) -> tuple[int, int, int]:
    """The address (mod 64) and length of an aligned array made inside a kernel, as the banks make
    theirs, with another allocation before it that moves the allocator's next address."""
    pad = np.empty(size % 7 + 1)
    a = aligned_lanes(size)
    a[:] = 1.0
    pad[:] = 0.0
    return a.ctypes.data % 64, a.shape[0], pad.shape[0]


def test_aligned_lanes_starts_on_a_64_byte_boundary_whatever_the_allocator_gives() -> None:
    # numba's own arrays start on 32-byte boundaries, so about half of these calls would land 32
    # bytes off a line if the helper did not move the start
    sizes = [LANES * r for r in range(1, 40)] + [1, 5, 13]
    for size in sizes:
        a = aligned_lanes(size)
        assert a.ctypes.data % 64 == 0, (size, a.ctypes.data % 64)
        assert a.shape == (size,) and a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable
        assert _from_compiled_code(size)[:2] == (0, size)


def test_aligned_lanes_arrays_are_independent_and_fully_writable() -> None:
    """Each call its own memory: a bank's work array and its samples' rows never overlap."""
    a, b = aligned_lanes(15 * LANES), aligned_lanes(15 * LANES)
    a[:] = np.arange(a.size)
    b[:] = -1.0
    assert np.array_equal(a, np.arange(a.size)) and np.all(b == -1.0)
