"""Reporting at a block's row n - L without a row argument in any kernel: two ``last_only`` calls
split after the row give that row, and leave the state, bit for bit as one call does.

The pipeline (validity rules version 6) reports each block's estimate at the sample the presence
detector has read its onset latency L past, in the same block, so that the hold releases it at
once (docs/benchmarks.md, "The hold and a 5 ms p99"). That rests on every estimator's output not
depending on where its blocks are split; checked here for that split, every registered
estimator, alone (:func:`update_reporting_at`) and in banks whose channels report at different
rows (:func:`update_bank_reporting_at`: one bank call a distinct row).
"""

from __future__ import annotations

import numpy as np
import pytest
from test_estimator_banks import assert_states_bitwise

from sinewatch.estimators import available, get
from sinewatch.estimators.bank import update_bank_reporting_at, update_reporting_at
from sinewatch.estimators.base import Estimator, Track
from sinewatch.schemas.errors import InputError

NAMES = sorted(available())
N = 1024  # a usual frame's block
HISTORY = 700  # samples each channel has seen before the block (a converging state, not a fresh one)
# L: the detector's quadrature test armed at 50 Hz and 10 kHz (Q + m - 1), its level test (4 H), none
LATENCIES = (61, 400, 0)
ROW_FIELDS = ("frequency_hz", "amplitude", "phase_rad", "offset", "converged")


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def assert_row_of(full: Track, row: int, got: Track, where: str) -> None:
    """``got`` (a one-row Track) is row ``row`` of ``full`` (the whole block's), bit for bit."""
    for f in ROW_FIELDS:
        assert _same_bits(getattr(full, f)[row : row + 1], getattr(got, f)), f"{where}: {f}"
    assert set(full.extras) == set(got.extras), where
    for k, v in full.extras.items():
        assert _same_bits(v[row : row + 1], got.extras[k]), f"{where}: extras[{k}]"
    assert (full.rocof_hz_per_s is None) == (got.rocof_hz_per_s is None), where
    if full.rocof_hz_per_s is not None:
        assert _same_bits(full.rocof_hz_per_s[row : row + 1], got.rocof_hz_per_s), f"{where}: rocof"
    assert (full.std is None) == (got.std is None), where
    if full.std is not None and got.std is not None:
        for f in ("frequency_hz", "amplitude", "phase_rad", "offset"):
            assert _same_bits(getattr(full.std, f)[row : row + 1], getattr(got.std, f)), f"{where}: std.{f}"


def _pair(name: str, seed: int) -> tuple[np.ndarray, Estimator, Estimator, Estimator]:
    """A block and three estimators with the same history of ``seed``'s signal."""
    cls = get(name)
    x = cls.example_signal(HISTORY + N, seed=seed)
    ests = (cls.example(), cls.example(), cls.example())
    for est in ests:
        est.update(np.ascontiguousarray(x[:HISTORY]), last_only=True)
    return np.ascontiguousarray(x[HISTORY:]), *ests


@pytest.mark.parametrize("name", NAMES)
def test_two_calls_split_after_row_n_minus_l_are_one_call(name: str) -> None:
    for latency in LATENCIES:
        block, one, split, _ = _pair(name, seed=3)
        row = N - 1 - latency
        full = one.update(block, last_only=False)
        got = update_reporting_at(split, block, row)
        where = f"{name}, L = {latency}"
        assert_row_of(full, row, got, where)
        assert_states_bitwise(one, split, where)


@pytest.mark.parametrize("name", NAMES)
def test_a_bank_reporting_at_each_channels_own_row_is_each_channel_alone(name: str) -> None:
    """Five channels, own signals and histories, at three distinct rows in no order (three bank
    calls and the rest): each channel's row and state are its single path's, at every position."""
    latencies = (400, 61, 61, 0, 400)
    pairs = [_pair(name, seed=20 + c) for c in range(len(latencies))]
    x = np.stack([p[0] for p in pairs], axis=1)
    rows = [N - 1 - lat for lat in latencies]
    fulls = [single.update(p[0], last_only=False) for p, single in zip(pairs, [p[1] for p in pairs], strict=True)]
    banked = [p[2] for p in pairs]
    got = update_bank_reporting_at(banked, x, rows, finite=True)
    for c, (full, row) in enumerate(zip(fulls, rows, strict=True)):
        where = f"{name} bank position {c}, row {row}"
        assert_row_of(full, row, got[c], where)
        assert_states_bitwise(pairs[c][1], banked[c], where)
        # the residual RMS: of the channel's samples up to its row, as its single split says
        alone = update_reporting_at(pairs[c][3], pairs[c][0], row)
        assert np.float64(alone.residual_rms).tobytes() == np.float64(got[c].residual_rms).tobytes(), where


@pytest.mark.parametrize("name", ["sogi-fll", "ges-kalman"])
def test_a_bank_at_one_row_is_two_calls_and_each_channel_alone(name: str) -> None:
    pairs = [_pair(name, seed=40 + c) for c in range(8)]
    x = np.stack([p[0] for p in pairs], axis=1)
    fulls = [p[1].update(p[0], last_only=False) for p in pairs]
    got = update_bank_reporting_at([p[2] for p in pairs], x, [N - 62] * 8, finite=True)
    for c, full in enumerate(fulls):
        assert_row_of(full, N - 62, got[c], f"{name} position {c}")
        assert_states_bitwise(pairs[c][1], pairs[c][2], f"{name} position {c}")


def test_a_non_finite_sample_after_the_row_changes_no_state() -> None:
    block, _, est, _ = _pair("sogi-fll", seed=5)
    before = {k: v.copy() for k, v in est._state.items()}
    bad = block.copy()
    bad[N - 10] = np.nan  # after the row: the first call alone would have accepted its part
    with pytest.raises(InputError) as info:
        update_reporting_at(est, bad, N - 62)
    assert info.value.kind == "non_finite"
    assert all(_same_bits(est._state[k], v) for k, v in before.items())
    banked = [_pair("sogi-fll", seed=6 + c)[2] for c in range(3)]
    states = [{k: v.copy() for k, v in e._state.items()} for e in banked]
    x = np.stack([bad] * 3, axis=1)
    with pytest.raises(InputError, match=r"columns \[0, 1, 2\]"):
        update_bank_reporting_at(banked, x, [N - 62, N - 401, N - 62])
    for e, s in zip(banked, states, strict=True):
        assert all(_same_bits(e._state[k], v) for k, v in s.items())


def test_a_row_outside_the_block_is_a_typed_error() -> None:
    block, _, est, _ = _pair("sogi-fll", seed=7)
    with pytest.raises(InputError, match=r"expected 0 <= row < 1024, got 1024"):
        update_reporting_at(est, block, N)
    with pytest.raises(InputError, match=r"expected 2 rows in \[0, 1024\), got \[-1, 3\]"):
        update_bank_reporting_at([est, get("sogi-fll").example()], np.stack([block, block], axis=1), [-1, 3])


@pytest.mark.parametrize("kept_stacked", [False, True])
def test_a_fault_after_the_first_call_leaves_every_state_as_it_was(monkeypatch, kept_stacked: bool) -> None:
    """A kernel fault in the call after the row (the first call has advanced the bank's stack):
    the call raises and every channel's state, stacked or not, is what it was before."""
    from sinewatch.estimators import bank as bank_module

    pairs = [_pair("sogi-fll", seed=60 + c) for c in range(3)]
    x = np.stack([p[0] for p in pairs], axis=1)
    banked = [p[2] for p in pairs]
    if kept_stacked:  # a bank kept stacked from a previous frame: the first call advances its arrays
        bank_module.update_bank(banked, x[:10], last_only=True)
        for p in pairs:
            p[1].update(np.ascontiguousarray(p[0][:10]), last_only=True)
    real, calls = bank_module.update_bank, []

    def second_call_faults(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise ZeroDivisionError("injected kernel fault")
        return real(*args, **kwargs)

    monkeypatch.setattr(bank_module, "update_bank", second_call_faults)
    with pytest.raises(ZeroDivisionError):
        update_bank_reporting_at(banked, x, [N - 62] * 3, finite=True)
    monkeypatch.setattr(bank_module, "update_bank", real)
    for p in pairs:  # each continues exactly as its single twin, which never saw the faulty call
        assert_states_bitwise(p[1], p[2], "after the fault")
    single = pairs[0][3]
    if kept_stacked:
        single.update(np.ascontiguousarray(pairs[0][0][:10]), last_only=True)
    before = {k: v.copy() for k, v in single._state.items()}
    monkeypatch.setattr(single, "update", _fault_on_second(single.update))
    with pytest.raises(ZeroDivisionError):
        update_reporting_at(single, pairs[0][0], N - 62)
    assert all(_same_bits(single._state[k], v) for k, v in before.items())


def _fault_on_second(update):
    calls = []

    def wrapped(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise ZeroDivisionError("injected kernel fault")
        return update(*args, **kwargs)

    return wrapped
