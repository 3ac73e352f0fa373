"""ges-kalman's bank (``_ges_kalman_bank``) against the single-channel kernel, bit for bit, on
the paths its lanes take apart: T (U3) still propagated in some lanes and zeroed in others, a
lane whose T becomes negligible inside a block, and the noise means' cap (U5a), whose exp the
bank takes only in the lanes whose bound fails (the other lanes' means run as vectors).
tests/test_estimator_banks.py checks every estimator's bank at every size and position; these
are the cases that needs long histories and outliers to reach.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sinewatch.estimators import get
from sinewatch.estimators._ges_kalman_bank import (
    _RM,
    _ROWS,
    _RUO,
    LANES,
    _bank_means_caps,
    _bank_means_lane,
    ges_kalman_bank_kernel,
)
from sinewatch.estimators._ges_kalman_kernels import ROBUST_CAP, TINY, _noise_means, ges_kalman_kernel

CLS = get("ges-kalman")
# samples each lane has seen before the bank: T (U3) is zeroed after ~6,000-6,600 at the example's
# 1 kHz (p0 = 1), so lanes 0-1 start with T live, 2-4 cross its threshold within the blocks below
# (a different sample in each), the others start with T zero
HISTORIES = (0, 1_000, 4_800, 5_200, 5_600, 9_000, 12_000, 20_000, 0, 7_000, 5_400)
BLOCK = 600


def _bytes(*arrays: np.ndarray | float) -> bytes:
    return b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)


def _signal(c: int, n: int) -> np.ndarray:
    """Channel ``c``: the example's tone and noise, with outliers (x1000 the noise) at samples of
    its own, so that the noise means' cap (U5a) binds at different samples in different lanes."""
    x = CLS.example_signal(n, seed=40 + c)
    x[(np.arange(3) * 397 + 61 * c) % n] += 10.0 * (1 + c % 4)
    return x


def _states(history: int, c: int) -> tuple[np.ndarray, np.ndarray]:
    est = CLS.example()
    if history:
        est.update(_signal(c + 100, history))
    return est._state["xP"].copy(), est._state["unc"].copy()


@pytest.mark.parametrize("size", [3, 8, 11])
@pytest.mark.parametrize("last_only", [True, False])
def test_lanes_whose_t_and_cap_differ_match_the_single_kernel(size: int, last_only: bool) -> None:
    consts = CLS.example()._constants[0]
    starts = [_states(HISTORIES[c], c) for c in range(size)]
    y = np.stack([_signal(c, 4 * BLOCK) for c in range(size)], axis=1)
    xP = np.stack([s[0] for s in starts], axis=1)
    unc = np.stack([s[1] for s in starts], axis=1)
    singles = [list(s) for s in starts]
    t_zeroed_inside = 0  # lanes whose T went from live to zero within one bank call
    for b in range(4):
        block = np.ascontiguousarray(y[b * BLOCK : (b + 1) * BLOCK])
        t_before = unc[:16].any(axis=0)
        out, sse, std, xP, unc = ges_kalman_bank_kernel(block, xP, unc, consts, last_only)
        t_zeroed_inside += int(np.sum(t_before & ~unc[:16].any(axis=0)))
        for c in range(size):
            o, s, sd, singles[c][0], singles[c][1] = ges_kalman_kernel(
                np.ascontiguousarray(block[:, c]), singles[c][0], singles[c][1], consts, last_only
            )
            where = f"block {b}, channel {c} of {size}"
            assert _bytes(o, sd) == _bytes(out[c], std[c]), where
            assert _bytes(np.float64(s)) == _bytes(sse[c : c + 1]), where
            assert _bytes(*singles[c]) == _bytes(xP[:, c], unc[:, c]), where
    if size >= 8:
        assert t_zeroed_inside >= 2  # the case is reached: lanes' T zeroed at different samples


def test_the_means_of_eight_lanes_match_the_single_step_where_the_cap_binds_in_some() -> None:
    """The vectorised means step (:func:`_bank_means_lane` for every lane, then
    :func:`_bank_means_caps`) against :func:`_noise_means` lane by lane, over a sequence where the
    cap (U5a) binds in some lanes and not in others at the same sample, and u is 0, subnormal,
    huge or ordinary."""
    rng = np.random.default_rng(7)
    n = 400
    us = (rng.standard_normal((n, LANES)) * 0.1) ** 2
    us[50, [1, 5]] = 1e6  # outliers in two lanes only: their cap binds, the others' does not
    us[51, 2] = 0.0
    us[52, 3] = 5e-310
    us[200:, 6] *= 1e4  # a lane whose noise grows: its cap binds on many samples
    lam = 1.0 - 1.0 / 128.0
    S = np.zeros(_ROWS * LANES)
    single = [(0.0, 0.0, 0.0, 0.0, 0.0)] * LANES  # (w, <u>, <log u>, x_ref, e_ref)
    capped = np.zeros(LANES, dtype=int)
    for k in range(n):
        S[_RUO * LANES : (_RUO + 1) * LANES] = us[k]
        for lane in range(LANES):
            _bank_means_lane(S, lane, lam)
        _bank_means_caps(S)
        for lane in range(LANES):
            w, m_u, m_l, x_ref, e_ref = single[lane]
            uncapped = lam * m_u + (1.0 - lam) * us[k, lane]
            single[lane] = _noise_means(float(us[k, lane]), w, m_u, m_l, lam, x_ref, e_ref)
            capped[lane] += single[lane][1] != uncapped
            row = [S[(_RM + r) * LANES + lane] for r in (0, 1, 2, 3, 4)]
            assert _bytes(np.array(row)) == _bytes(np.array(single[lane])), f"sample {k}, lane {lane}"
    assert capped[1] >= 1 and capped[5] >= 1 and capped[6] > capped[0]  # the cap did bind, unevenly
    assert all(math.isfinite(v) for v in S[_RM * LANES : (_RM + 3) * LANES])
    assert ROBUST_CAP > 1.0 and TINY > 0.0
