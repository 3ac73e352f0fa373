"""One conformance suite that every registered estimator must pass (after river's checks).

Each estimator is exercised in its example configuration (``Estimator.example()``) on
its example signal. Equality is bitwise (NaN equals NaN), because replay promises
bit-exact reproduction.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from sinewatch.estimators import available, create, get
from sinewatch.estimators.base import Track, concat_tracks
from sinewatch.schemas.errors import InputError, InputTypeError, ParameterError, SinewatchError

NAMES = sorted(available())
N = 2400  # divisible by the block sizes below


def assert_tracks_identical(a: Track, b: Track) -> None:
    for field in ("frequency_hz", "amplitude", "phase_rad", "offset", "converged"):
        x, y = getattr(a, field), getattr(b, field)
        assert x.shape == y.shape, field
        np.testing.assert_array_equal(x, y, err_msg=field)  # NaN == NaN here
    assert set(a.extras) == set(b.extras)
    for k in a.extras:
        np.testing.assert_array_equal(a.extras[k], b.extras[k], err_msg=k)


@pytest.fixture(params=NAMES)
def name(request):
    return request.param


def signal(name: str, n: int = N, seed: int = 0) -> np.ndarray:
    return get(name).example_signal(n, seed)


def test_registry_lists_parameter_models(name):
    cls = get(name)
    assert available()[name] is cls.Params
    assert cls.summary, "each estimator says in one line what it is"
    schema = cls.Params.model_json_schema()
    assert schema["additionalProperties"] is False


def test_output_shapes_and_conventions(name):
    est = get(name).example()
    x = signal(name)
    tr = est.update(x)
    k = est.n_components
    for field in ("frequency_hz", "amplitude", "phase_rad"):
        arr = getattr(tr, field)
        assert arr.shape == (N, k) and arr.dtype == np.float64, field
    assert tr.offset.shape == (N,) and tr.converged.dtype == bool
    for v in tr.extras.values():
        assert v.shape[0] == N
    ph = tr.phase_rad[np.isfinite(tr.phase_rad)]
    assert np.all((ph > -np.pi - 1e-12) & (ph <= np.pi + 1e-12))
    # converged implies every primary output is defined
    c = tr.converged
    assert np.all(np.isfinite(tr.frequency_hz[c])) and np.all(np.isfinite(tr.offset[c]))
    assert np.isfinite(tr.residual_rms)
    assert c[-N // 4 :].any(), "the example configuration converges on its example signal"


def test_input_is_not_mutated(name):
    est = get(name).example()
    x = signal(name)
    x.setflags(write=False)  # a write would raise
    before = x.copy()
    est.update(x)
    np.testing.assert_array_equal(x, before)


def test_last_only_is_the_last_row(name):
    x = signal(name)
    full = get(name).example().update(x)
    last = get(name).example().update(x, last_only=True)
    assert_tracks_identical(full.last(), last)
    assert full.residual_rms == last.residual_rms


def test_seeded_determinism(name):
    a = get(name).example().update(signal(name, seed=7))
    b = get(name).example().update(signal(name, seed=7))
    assert_tracks_identical(a, b)


@pytest.mark.parametrize("block", [1, 7, 100, 800])
def test_block_boundaries_do_not_change_output(name, block):
    x = signal(name)
    whole = get(name).example().update(x)
    est = get(name).example()
    parts = [est.update(x[i : i + block]) for i in range(0, len(x), block)]
    assert_tracks_identical(whole, concat_tracks(parts))


def test_state_round_trips_through_json(name):
    x = signal(name)
    a = get(name).example()
    a.update(x[: N // 2])
    snapshot = json.loads(json.dumps(a.get_state()))
    b = get(name).from_state(snapshot)
    assert_tracks_identical(a.update(x[N // 2 :]), b.update(x[N // 2 :]))


def test_state_with_its_keys_in_another_order_restores_the_same_estimator(name):
    # JSON objects carry no order a reader must keep: set_state puts the arrays back in
    # the kernel's argument order (estimators/base.py, "Kernel state convention").
    x = signal(name)
    a = get(name).example()
    a.update(x[: N // 2])
    snapshot = json.loads(json.dumps(a.get_state()))
    snapshot["state"] = dict(reversed(list(snapshot["state"].items())))
    b = get(name).from_state(snapshot)
    assert list(b.get_state()["state"]) == list(a.get_state()["state"])
    assert_tracks_identical(a.update(x[N // 2 :]), b.update(x[N // 2 :]))


def test_kernel_follows_the_state_convention(name):
    # kernel(block, *state arrays, *constants, last_only) -> (*outputs, *new state arrays):
    # one new array per state array, same order, shapes and dtypes; the inputs untouched.
    est = get(name).example()
    x = signal(name)
    est.update(x[: N // 2])
    state = est._state
    before = {k: v.copy() for k, v in state.items()}
    block = est._kernel_input(est._as_block(x[N // 2 :]))
    result = type(est)._kernel(block, *state.values(), *est._constants, False)
    new = result[len(result) - len(state) :]
    for (key, old), arr in zip(state.items(), new, strict=True):
        assert isinstance(arr, np.ndarray) and arr is not old, key
        assert arr.shape == old.shape and arr.dtype == old.dtype, key
        np.testing.assert_array_equal(old, before[key], err_msg=key)
    assert not np.array_equal(np.concatenate([a.ravel() for a in new]).astype(float),
                              np.concatenate([b.ravel() for b in before.values()]).astype(float)), (
        "1200 samples of signal changed no state"
    )  # fmt: skip


def test_reset_restores_a_fresh_estimator(name):
    x = signal(name)
    est = get(name).example()
    est.update(x)
    est.reset()
    assert_tracks_identical(est.update(x), get(name).example().update(x))


@pytest.mark.parametrize(
    "bad, kind",
    [
        (np.array([0.1, np.nan, 0.3]), "non_finite"),
        (np.array([0.1, np.inf]), "non_finite"),
        (np.array([]), "empty_block"),
    ],
)
def test_bad_block_is_rejected_without_touching_state(name, bad, kind):
    cls = get(name)
    est = cls.example()
    x = signal(name)
    est.update(x[: N // 2])
    if est.n_inputs > 1:
        bad = np.column_stack([bad] * est.n_inputs) if bad.size else np.empty((0, est.n_inputs))
    with pytest.raises(InputError) as info:
        est.update(bad)
    assert info.value.kind == kind
    assert isinstance(info.value, (ValueError, SinewatchError))
    ref = cls.example()
    ref.update(x[: N // 2])
    assert_tracks_identical(est.update(x[N // 2 :]), ref.update(x[N // 2 :]))


# Parameters an estimator must reject with a ParameterError naming the problem: per row the
# kind, the parameters (at 1000 Hz, over the kind's BAD_PARAMETER_BASE) and the words the message
# must hold.
BAD_PARAMETER_BASE = {"differential-rls": {"nominal_frequency_hz": 50.0, "bandwidth_hz": 5.0}}
BAD_PARAMETERS = [
    ("differential-rls", {"forgetting_factor": 0.0}, "forgetting"),
    ("differential-rls", {"forgetting_factor": 1.01}, "forgetting"),
    ("differential-rls", {"phase_forgetting_factor": -0.5}, "forgetting"),
    ("differential-rls", {"oversampling": 0.5}, "oversampling M >= 1"),
    ("differential-rls", {"n_terms": 0}, "n_terms"),
    ("differential-rls", {"n_terms": 7}, "n_terms"),
    ("differential-rls", {"n_terms": 5}, "rocof_model"),
    ("differential-rls", {"nominal_frequency_hz": 495.0}, "Nyquist"),
    ("differential-rls", {"nominal_frequency_hz": 0.0}, "nominal_frequency_hz"),
    ("differential-rls", {"bandwidth_hz": 30.0}, "bandwidth_hz"),
    ("differential-rls", {"bandwidth_hz": 0.0}, "bandwidth_hz"),
    ("differential-rls", {"oversampling": 200.0}, "decimation factor"),
    ("differential-rls", {"n_terms": 6, "rocof_model": False, "oversampling": 40.0}, "distinct sampling intervals"),
    ("differential-rls", {"els_damping": 1.0}, "els_damping"),
    ("differential-rls", {"cycle_spacing": 1.0}, "cycle_spacing"),
    ("differential-rls", {"recenter_every": -1}, "recenter_every"),
    ("differential-rls", {"tracking_range_hz": -1.0}, "tracking_range_hz"),
    ("differential-rls", {"min_amplitude": float("nan")}, "min_amplitude"),
    ("ipdft", {"window_cycles": 4, "window_samples": 80}, "window_cycles or window_samples"),
    ("ipdft", {"window_cycles": 1.5}, "window_cycles"),
    ("ipdft", {"window_samples": 30}, "window_samples: expected >= 2 nominal cycles"),
    ("ipdft", {"hop_samples": 81}, "hop_samples: expected <= window"),
    ("ipdft", {"hop_samples": 0}, "hop_samples"),
    ("ipdft", {"nominal_frequency_hz": 500.0}, "Nyquist"),
    ("ipdft", {"max_frequency_hz": 600.0}, "max_frequency_hz: expected < Nyquist"),
    ("ipdft", {"min_frequency_hz": 60.0, "max_frequency_hz": 55.0}, "min_frequency_hz: expected <"),
    ("ipdft", {"min_frequency_hz": 1.0, "max_frequency_hz": 10.0}, "search band"),
    ("ipdft", {"interpolation": "5-point"}, "interpolation"),
    ("ipdft", {"max_relative_residual": 0}, "max_relative_residual"),
    ("ges-kalman", {"q": [1e-6, 1e-6]}, "q"),
    ("ges-kalman", {"r": 0}, "r"),
    ("ges-kalman", {"x0": [0, 0]}, "x0"),
    ("ges-kalman", {"q": -1.0}, "q"),
    ("nls", {"window_cycles": 4, "window_s": 0.1}, "window"),
    ("nls", {"zero_pad": 3}, "power of 2"),
    ("nls", {"max_frequency_hz": 600.0}, "Nyquist"),
    ("nls", {"window_samples": 10, "n_components": 3}, "samples for 3 tones"),
    ("nls", {"window_samples": 100, "hop_samples": 101}, "hop_samples"),
    ("nls", {"min_frequency_hz": 300.0, "max_frequency_hz": 200.0}, "search band"),
]


@pytest.mark.parametrize("kind, params, match", BAD_PARAMETERS)
def test_bad_parameters_are_clear_errors(kind, params, match):
    with pytest.raises(ParameterError, match=match):
        create(kind, 1000.0, **{**BAD_PARAMETER_BASE.get(kind, {}), **params})


def test_wrong_types_and_shapes_are_typed_errors(name):
    est = get(name).example()
    with pytest.raises(InputTypeError):
        est.update("not samples")
    with pytest.raises(InputError):
        est.update(np.zeros((4, est.n_inputs + 1)))


def test_unknown_parameter_is_rejected(name):
    cls = get(name)
    with pytest.raises(ParameterError, match="no_such_parameter"):
        create(name, cls.example_sample_rate_hz, **cls.example_params, no_such_parameter=1)


def test_zero_input_keeps_state_finite(name):
    est = get(name).example()
    n_in = est.n_inputs
    zeros = np.zeros((20_000, n_in)) if n_in > 1 else np.zeros(20_000)
    tr = est.update(zeros)
    assert not np.any(tr.converged & ~np.isfinite(tr.frequency_hz).all(axis=1))
    for key, value in est.get_state()["state"].items():
        from sinewatch.estimators.base import decode_array

        arr = decode_array(value)
        if arr.dtype.kind == "f":
            assert np.all(np.isfinite(arr)), f"state {key} went non-finite on zero input"
    # and it still works afterwards on a real signal
    tr = est.update(signal(name))
    assert tr.converged[-N // 4 :].any()


def test_params_for_hook_yields_valid_params(name):
    cls = get(name)
    if "params_for" not in cls.__dict__:
        pytest.skip("no params_for hook")
    f0 = cls.example_frequency_hz
    hints = {
        "scenario": "conformance",
        "sample_rate_hz": cls.example_sample_rate_hz,
        "nominal_frequency_hz": (f0,),
        "frequency_range_hz": (0.5 * f0, 2 * f0),
        "n_components": 1,
        "n_inputs": 1,
        "noise_std": 0.01,
        "amplitude": (1.0,),
        "offset": 0.5,
        "reporting_rate_hz": None,
        "tags": (),
    }
    try:
        params = cls.params_for(cls.example_sample_rate_hz, hints)
    except ParameterError:
        pytest.skip("does not apply to a single tone")
    cls(cls.example_sample_rate_hz, {**cls.example_params, **params})
