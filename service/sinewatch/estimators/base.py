"""The one interface every sinewatch estimator implements.

An estimator is two layers, kept apart on purpose:

* a pure compiled kernel (numba, through the :func:`kernel` decorator below: ``njit`` with
  ``cache=True``) that takes a block of samples and the state arrays and returns the
  outputs and the new state, like ``scipy.signal.sosfilt``'s ``zi``/``zf``; no Python work
  per sample;
* a thin class (subclass of :class:`Estimator`) that validates its parameters with a
  pydantic model (unknown keys rejected), keeps them verbatim, owns the state and exposes
  ``update(samples)``, ``reset()``, ``get_state()`` and ``set_state()``.

The daemon, replay and benchmarks use only this interface: they never know which
algorithm runs.

Output convention: the signal is modelled as ``y = offset + sum_k amplitude_k *
sin(phase_k)``, with ``phase_k`` the instantaneous phase at each sample (radians,
wrapped to (-pi, pi]) and ``frequency_k`` in Hz. Undefined estimates are NaN with
``converged = False``; an estimator never raises per sample.

Kernel state convention (every kernel follows it; :meth:`Estimator._run` makes the call)
---------------------------------------------------------------------------------------
The state is a dict of named numpy arrays (float64, or int64 for counters), built by the
class's ``_initial_state()``; those names are the keys of ``get_state()["state"]``. The
dict's key order is the order in which the kernel takes the arrays and returns them::

    *outputs, *new_state = kernel(block, *state.values(), *constants, last_only)

* ``block``: the samples, float64 and C-contiguous, (N,) or (N, n_inputs), never empty
  (``_kernel_input`` may reshape it, e.g. to (N, 1));
* ``state.values()``: one argument per state array, in key order; read, never written;
* ``constants``: the class's ``_constants`` tuple (arrays and numbers derived once from
  the parameters in ``_setup``); read only;
* ``last_only``: run every sample but write only the last row of the per-sample outputs;
* the kernel returns its outputs first (per-sample columns, extras, the sum of squared
  one-step errors, ...: whatever the class's ``_track`` turns into a :class:`Track`),
  then one freshly allocated array per state array, in the same order, with the same
  shapes and dtypes.

Where one state array packs several quantities, its layout (which slot or slice holds
what) is written once, in the docstring of the class's ``_initial_state``; the kernel
either unpacks it once into named locals at the top and packs them back in the same
order at the end, or names the slots with module-level integer constants (numba folds
them) or a layout function. A short example, an exponentially weighted mean::

    _MEAN, _COUNT = 0, 1  # slots of "avg"

    @kernel
    def ewma_kernel(
        x: np.ndarray, avg: np.ndarray, alpha: float, last_only: bool
    ) -> tuple[np.ndarray, float, np.ndarray]:
        new = avg.copy()
        out = np.empty((1 if last_only else x.shape[0], 5))
        sse = 0.0
        for k in range(x.shape[0]):
            e = x[k] - new[_MEAN]
            sse += e * e
            new[_MEAN] += alpha * e
            new[_COUNT] += 1.0
            ...  # write row k (or row 0 when last_only and k is the last sample)
        return out, sse, new

    class Ewma(Estimator[EwmaParams], kernel=ewma_kernel):
        name = "ewma"

        def _setup(self) -> None:
            self._constants = (0.01,)

        def _initial_state(self) -> dict[str, np.ndarray]:
            '''``avg`` (2,): the running mean, then the number of samples seen.'''
            return {"avg": np.zeros(2)}

        def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
            out, sse = outputs
            return track_from_columns(out, sse, block.shape[0])
"""

from __future__ import annotations

import base64
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar, Generic, Literal, ParamSpec, cast, get_args, get_origin, overload

import numba
import numpy as np
from llvmlite import ir as llvm_ir
from numba.core import cgutils
from numba.extending import intrinsic
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from typing_extensions import TypeVar  # a TypeVar with a default (PEP 696); pydantic requires it

from sinewatch.schemas.errors import InputError, InputTypeError, ParameterError

STATE_FORMAT_VERSION = 1
_F64 = np.dtype(np.float64)  # the dtype of a native float64 array (``_as_block``'s fast path)

_P = ParamSpec("_P")
_R = TypeVar("_R")


@overload
def kernel(fn: Callable[_P, _R], /) -> Callable[_P, _R]: ...
@overload
def kernel(
    *,
    inline: Literal["never", "always"] = "never",
    error_model: Literal["numpy", "python"] = "numpy",
    refcount: bool = True,
) -> Callable[[Callable[_P, _R]], Callable[_P, _R]]: ...
def kernel(
    fn: Callable[_P, _R] | None = None,
    /,
    *,
    inline: Literal["never", "always"] = "never",
    error_model: Literal["numpy", "python"] = "numpy",
    refcount: bool = True,
) -> Callable[_P, _R] | Callable[[Callable[_P, _R]], Callable[_P, _R]]:
    """Compile a kernel or a helper it calls: ``numba.njit(cache=True, nogil=True,
    error_model=...)``, typed as the plain Python function it wraps (numba has no type
    stubs), so that the annotations of a kernel are what callers and mypy see.
    ``@kernel`` or ``@kernel(inline="always", error_model="python")``.

    ``refcount=False`` compiles without numba's reference counting (its ``_nrt`` option), for a
    helper that allocates nothing and only reads or writes the arrays it is given: with it, numba
    takes and releases a reference to every array argument on each call, two atomic operations
    per array (~8 ns each, measured: a helper taking five arrays cost 79 ns a call with them and
    2 ns without, since LLVM then also inlines it). Such a helper must not create arrays (no
    ``np.empty``, no ``.copy()``, no slices kept beyond the call)."""

    def wrap(f: Callable[_P, _R]) -> Callable[_P, _R]:
        # _nrt is numba's own option (numba.core.options), absent from its type stubs
        internal: dict[str, Any] = {"_nrt": refcount}
        compiled = numba.njit(cache=True, nogil=True, error_model=error_model, inline=inline, **internal)(f)
        return cast(Callable[_P, _R], compiled)

    return wrap if fn is None else wrap(fn)


@intrinsic
def _fma_intrinsic(typingctx: Any, a: Any, b: Any, c: Any) -> Any:
    sig = numba.types.float64(numba.types.float64, numba.types.float64, numba.types.float64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        d = llvm_ir.DoubleType()
        fn = cgutils.get_or_insert_function(builder.module, llvm_ir.FunctionType(d, [d, d, d]), "llvm.fma.f64")  # type: ignore[no-untyped-call]
        return builder.call(fn, list(args))  # numba has cast the arguments to the signature's float64

    return sig, codegen


@kernel(inline="always", refcount=False)
def fma(a: float, b: float, c: float) -> float:
    """``a * b + c`` rounded once (IEEE 754 fusedMultiplyAdd), in compiled code only: one
    instruction where the CPU has FMA, a correctly rounded library call where it has not, so the
    same inputs give the same bits on every machine and in every process. Kernels use it on
    their critical paths (a multiply and an add in one step, half the latency); fast-math
    contraction would do the same where the compiler chose to, and what it chose was seen to
    depend on the order in which kernels were compiled and cached."""
    return _fma_intrinsic(a, b, c)  # type: ignore[call-arg]  # numba passes the typing context


def kernel_samples(samples: np.ndarray) -> np.ndarray:
    """``samples`` as every kernel takes them: float64, C-contiguous, aligned and writable; a
    copy (one memcpy, or the float32 -> float64 conversion) only when they are not already.

    numba compiles a kernel once per argument type, and an array's type includes whether it is
    writable, aligned and C-contiguous: a read-only ``np.frombuffer`` view of a payload, or a
    view at an odd offset into it, is another type than the arrays the kernels make themselves,
    and every kernel would be compiled (and cached, and warmed up) once for each. Handing them
    one kind keeps one signature per kernel; the values, hence every output bit, are the same
    (float32 widens to float64 exactly)."""
    f = samples.flags
    if samples.dtype is _F64 and f.c_contiguous and f.writeable and f.aligned:
        return samples
    return np.array(samples, dtype=np.float64, order="C")


def require_below_nyquist(field: str, value: float, sample_rate_hz: float) -> float:
    """The Nyquist frequency 0.5 * sample_rate_hz; ParameterError unless ``value`` (the
    parameter ``field``, Hz) is below it."""
    nyq = 0.5 * sample_rate_hz
    if value >= nyq:
        raise ParameterError(f"{field}: expected < Nyquist = {nyq} Hz, got {value}")
    return nyq


@kernel
def wrap_pi(p: float) -> float:
    """An angle in radians wrapped to (-pi, pi] (exactly pi - ((pi - p) mod 2 pi))."""
    y = math.pi - p
    r = y - 2.0 * math.pi * math.floor(y / (2.0 * math.pi))  # in [0, 2 pi]
    if r >= 2.0 * math.pi:
        r = 0.0
    return math.pi - r


@kernel(inline="always")
def cyclic_next(i: int, n: int) -> int:
    """``i + 1``, back to 0 on reaching ``n`` (a ring-buffer position or a phase counter)."""
    return 0 if i + 1 == n else i + 1


@kernel(inline="always")
def ring_write(b: np.ndarray, xj: float, pos: int, fill: int) -> tuple[int, int]:
    """Write sample ``xj`` at ``pos`` of the ring buffer ``b``; return the next position and
    the fill (counting up to the ring's length). The position wraps by a compare, not a modulo
    (an integer division a sample). Inlined where it is called: the same machine code as the
    lines written out. Mutates ``b``."""
    n = b.shape[0]
    b[pos] = xj
    pos += 1
    if pos == n:
        pos = 0
    if fill < n:
        fill += 1
    return pos, fill


@kernel(inline="always")
def ring_push(
    b: np.ndarray, xj: float, pos: int, fill: int, since: int, hop: int, xw: np.ndarray
) -> tuple[int, int, int, bool]:
    """Write sample ``xj`` into the ring buffer ``b`` (length N) of a sliding window that is
    re-estimated every ``hop`` samples; return the new ``(pos, fill, since, due)``: ``fill``
    counts up to N and ``since`` up to ``hop``; when the window is full and a hop has passed,
    ``due`` is true, ``since`` is 0 and ``xw`` holds the window in chronological order
    (oldest sample, at the write position, first). Mutates ``b`` and ``xw`` (the kernels'
    own working copies)."""
    N = b.shape[0]
    pos, fill = ring_write(b, xj, pos, fill)
    if since < hop:
        since += 1
    due = fill == N and since >= hop
    if due:
        since = 0
        for i in range(N):
            xw[i] = b[pos + i if pos + i < N else pos + i - N]
    return pos, fill, since, due


def state_snapshot(
    format_version: int, role: str, name: str, sample_rate_hz: float, params: BaseModel, state: Mapping[str, np.ndarray]
) -> dict[str, Any]:
    """The JSON-serialisable snapshot of a stateful stage (an estimator, an analyser): its
    format version, ``{role: name}``, sample rate, parameters and state arrays (base64)."""
    return {
        "format_version": format_version,
        role: name,
        "sample_rate_hz": sample_rate_hz,
        "params": params.model_dump(mode="json"),
        "state": {k: encode_array(v) for k, v in state.items()},
    }


class EstimatorParams(BaseModel):
    """Base of every estimator's parameter model: frozen, unknown keys rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True)


#: Field types for parameter models: a finite number > 0, or >= 0, as in
#: ``gain: PositiveFinite = Field(1.0, description="...")``.
PositiveFinite = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegativeFinite = Annotated[float, Field(ge=0, allow_inf_nan=False)]

# The parameter model of an Estimator subclass; a bare ``Estimator`` means any estimator.
ParamsT = TypeVar("ParamsT", bound=EstimatorParams, default=EstimatorParams)


@dataclass(slots=True)
class TrackStd:
    """One standard deviation of each reported parameter, per sample (NaN: cannot say)."""

    frequency_hz: np.ndarray  # (N, K) float64
    amplitude: np.ndarray  # (N, K) float64
    phase_rad: np.ndarray  # (N, K) float64
    offset: np.ndarray  # (N,) float64

    def rows(self, index: slice) -> TrackStd:
        return TrackStd(self.frequency_hz[index], self.amplitude[index], self.phase_rad[index], self.offset[index])


@dataclass(slots=True)
class BankLastRow:
    """A bank's outputs at the last sample of a frame, every channel's in one float64 array
    (C, F), each row in the order an Estimate writes them (frequency, amplitude, phase,
    offset, rocof when present, the four standard deviations when present, then the residual
    RMS): what :mod:`sinewatch.core.estimate_bytes` writes for the whole frame in one compiled
    call (``texts``, made by the first of the frame's Estimates, ``finite`` per channel
    beside them) instead of one call per channel."""

    values: np.ndarray  # (C, F) float64
    texts: list[str] | None = None  # repr of values.ravel(), once made
    finite: list[bool] | None = None  # per channel: every value but the RMS finite


@dataclass(slots=True)
class Track:
    """What one ``update`` returns.

    Per-sample arrays have N rows (N = samples in the block, or 1 when the caller asked
    for ``last_only``) and K columns (K = number of sinusoidal components).
    """

    frequency_hz: np.ndarray  # (N, K) float64
    amplitude: np.ndarray  # (N, K) float64
    phase_rad: np.ndarray  # (N, K) float64
    offset: np.ndarray  # (N,) float64
    converged: np.ndarray  # (N,) bool
    residual_rms: float  # RMS of the one-step prediction error over the block
    # Per-sample diagnostics, (N,) or (N, m). By convention "rocof_hz_per_s" ((N,) or
    # (N, K)) when the estimator tracks the rate of change of frequency.
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    # First-class optional outputs (None: the estimator does not provide them).
    rocof_hz_per_s: np.ndarray | None = None  # (N, K) float64, rate of change of frequency
    std: TrackStd | None = None  # standard deviations of frequency, amplitude, phase, offset
    # Estimators that report on a time grid (``update(..., t0_ns=...)``): the reports this
    # block completed, zero, one or several; None for estimators that do not.
    reports: GridReports | None = None
    # A bank's channel: the bank's last row of every output and this channel's index in it
    # (:func:`sinewatch.estimators.bank.column_tracks`); None otherwise. Same values as the fields.
    bank_row: tuple[BankLastRow, int] | None = None

    @property
    def n_samples(self) -> int:
        return int(self.offset.shape[0])

    @property
    def n_components(self) -> int:
        return int(self.frequency_hz.shape[1])

    def rows(self, index: slice) -> Track:
        """The rows ``index`` (a slice), as a Track (without ``reports``)."""
        return Track(
            frequency_hz=self.frequency_hz[index],
            amplitude=self.amplitude[index],
            phase_rad=self.phase_rad[index],
            offset=self.offset[index],
            converged=self.converged[index],
            residual_rms=self.residual_rms,
            extras={k: v[index] for k, v in self.extras.items()},
            rocof_hz_per_s=None if self.rocof_hz_per_s is None else self.rocof_hz_per_s[index],
            std=None if self.std is None else self.std.rows(index),
        )

    def last(self) -> Track:
        """The final row only, as a one-row Track."""
        return Track(
            frequency_hz=self.frequency_hz[-1:],
            amplitude=self.amplitude[-1:],
            phase_rad=self.phase_rad[-1:],
            offset=self.offset[-1:],
            converged=self.converged[-1:],
            residual_rms=self.residual_rms,
            extras={k: v[-1:] for k, v in self.extras.items()},
            rocof_hz_per_s=None if self.rocof_hz_per_s is None else self.rocof_hz_per_s[-1:],
            std=None if self.std is None else self.std.rows(slice(-1, None)),
            reports=self.reports,  # the block's reports, whatever the rows kept
        )

    def reconstruct(self) -> np.ndarray:
        """The modelled signal offset + sum_k A_k sin(phase_k), per row."""
        y: np.ndarray = self.offset + np.sum(self.amplitude * np.sin(self.phase_rad), axis=1)
        return y


def concat_tracks(tracks: list[Track]) -> Track:
    """Join the tracks of consecutive blocks into one (residual_rms is sample-weighted)."""
    n = np.array([t.n_samples for t in tracks], dtype=np.float64)
    rms = np.array([t.residual_rms for t in tracks], dtype=np.float64)
    total = float(np.sqrt(np.sum(n * rms**2) / max(np.sum(n), 1.0)))
    return Track(
        frequency_hz=np.concatenate([t.frequency_hz for t in tracks]),
        amplitude=np.concatenate([t.amplitude for t in tracks]),
        phase_rad=np.concatenate([t.phase_rad for t in tracks]),
        offset=np.concatenate([t.offset for t in tracks]),
        converged=np.concatenate([t.converged for t in tracks]),
        residual_rms=total,
        extras={k: np.concatenate([t.extras[k] for t in tracks]) for k in tracks[0].extras},
        rocof_hz_per_s=_concat_optional([t.rocof_hz_per_s for t in tracks]),
        reports=_concat_reports([t.reports for t in tracks]),
        std=None
        if tracks[0].std is None
        else TrackStd(
            *(
                np.concatenate([getattr(t.std, f) for t in tracks])
                for f in ("frequency_hz", "amplitude", "phase_rad", "offset")
            )
        ),
    )


@dataclass(slots=True)
class GridReports:
    """Estimates on a reporting grid: report r is at ``index[r] / reporting_rate_hz``
    seconds since the epoch (so the grid is aligned to whole seconds); ``track`` holds
    one row per report, with the values at the report time."""

    index: np.ndarray  # (R,) int64
    reporting_rate_hz: int
    track: Track

    @property
    def n_reports(self) -> int:
        return int(self.index.shape[0])

    def timestamps_ns(self) -> list[int]:
        """Report times in ns since the epoch: k 1e9 / Fs, exact, rounded half up."""
        fs = self.reporting_rate_hz
        return [(int(k) * 2_000_000_000 + fs) // (2 * fs) for k in self.index]

    def times_s(self, origin_ns: int = 0) -> np.ndarray:
        """Report times in seconds after ``origin_ns`` (ns since the epoch)."""
        fs = self.reporting_rate_hz
        return np.array([(int(k) * 1_000_000_000 - origin_ns * fs) / fs * 1e-9 for k in self.index])


def _concat_reports(parts: list[GridReports | None]) -> GridReports | None:
    if parts[0] is None:
        return None
    done = [p for p in parts if p is not None]
    return GridReports(
        np.concatenate([p.index for p in done]), done[0].reporting_rate_hz, concat_tracks([p.track for p in done])
    )


def _concat_optional(parts: list[np.ndarray | None]) -> np.ndarray | None:
    return None if parts[0] is None else np.concatenate(cast(list[np.ndarray], parts))


def encode_array(a: np.ndarray) -> dict[str, Any]:
    """Exact, JSON-safe encoding of an array: dtype, shape and raw little-endian bytes."""
    a = np.ascontiguousarray(a)
    le = a.astype(a.dtype.newbyteorder("<"), copy=False)
    return {
        "dtype": le.dtype.str,
        "shape": list(a.shape),
        "b64": base64.b64encode(le.tobytes()).decode("ascii"),
    }


def decode_array(d: Mapping[str, Any]) -> np.ndarray:
    raw = base64.b64decode(d["b64"])
    out: np.ndarray = np.frombuffer(raw, dtype=np.dtype(d["dtype"])).reshape(d["shape"]).copy()
    return out


class StackedStates:
    """A bank's channels' state arrays kept stacked between frames: each array (*shape, C),
    C-contiguous, channel last, as a compiled bank takes and returns it
    (:func:`sinewatch.estimators.bank.update_bank`), so that a bank whose channels are the
    same frame after frame is not gathered before and scattered after every kernel call (two
    copies a state array and a dict a channel). ``members[c]``'s state is column ``c``; a
    member read or given a state on its own leaves (:attr:`Estimator._state`) and the stack is
    then no longer ``live``: the next frame gathers its bank afresh."""

    __slots__ = ("arrays", "keys", "live", "members")

    def __init__(self, members: tuple[Any, ...], keys: tuple[str, ...], arrays: list[np.ndarray]) -> None:
        self.members = members
        self.keys = keys
        self.arrays = arrays
        self.live = True

    def holds(self, estimators: Sequence[Any]) -> bool:
        """Whether the stack is live and its members are exactly ``estimators``, in order."""
        members = self.members
        return (
            self.live
            and len(members) == len(estimators)
            and all(a is b for a, b in zip(members, estimators, strict=True))
        )

    def column(self, c: int) -> dict[str, np.ndarray]:
        """Channel ``c``'s state as a dict of contiguous arrays of its own (copies)."""
        return {k: np.ascontiguousarray(a[..., c]) for k, a in zip(self.keys, self.arrays, strict=True)}

    def leave(self, c: int) -> dict[str, np.ndarray]:
        """Channel ``c`` taken out: its state (:meth:`column`); the stack is no longer live."""
        self.live = False
        return self.column(c)


class Estimator(ABC, Generic[ParamsT]):
    """Base class of all estimators, declared as
    ``class MyEstimator(Estimator[MyParams], kernel=my_kernel)``: the parameter model
    (``Params``, and the type of ``params``) and the compiled kernel are named once, on
    that line. Subclasses set ``name``, set ``_constants`` in :meth:`_setup` and implement
    :meth:`_initial_state` and :meth:`_track` (module docstring, "Kernel state
    convention"); optionally :meth:`_check_params` (for checks that need the sample rate),
    :meth:`_kernel_input` and ``n_components`` / ``n_inputs``.
    """

    name: ClassVar[str]
    Params: ClassVar[type[EstimatorParams]]
    params: ParamsT
    summary: ClassVar[str] = ""
    paper: ClassVar[str | None] = None  # the paper implemented: authors, title, year
    # True for estimators that report on a time grid (Track.reports, from update(...,
    # t0_ns=...)) rather than once per block
    reports_on_grid: ClassVar[bool] = False
    _kernel: ClassVar[Callable[..., tuple[Any, ...]]]
    _constants: tuple[Any, ...] = ()  # the kernel's read-only arguments after the state

    def __init_subclass__(
        cls, /, kernel: Callable[..., tuple[Any, ...]] | None = None, name: str | None = None, **kwargs: Any
    ) -> None:
        """``class X(Estimator[XParams], kernel=x_kernel, name="x")``: the parameter model, the
        kernel and the registered name in one line; the class docstring is the summary that
        ``sinewatch estimators`` prints."""
        super().__init_subclass__(**kwargs)
        if kernel is not None:
            setattr(cls, "_kernel", staticmethod(kernel))  # noqa: B010 (a ClassVar, set once)
        if name is not None:
            cls.name = name
            cls.summary = " ".join((cls.__doc__ or "").split())
        for base in cls.__dict__.get("__orig_bases__", ()):
            origin = get_origin(base)
            if isinstance(origin, type) and issubclass(origin, Estimator):
                (model,) = get_args(base)
                if isinstance(model, type) and issubclass(model, EstimatorParams):
                    cls.Params = model

    # A working configuration, used by the conformance suite, the kernel benchmark and
    # the docs: the sample rate, parameters, and a test signal (see example_signal).
    example_sample_rate_hz: ClassVar[float] = 1000.0
    example_params: ClassVar[dict[str, Any]] = {}
    example_frequency_hz: ClassVar[float] = 50.0

    # Optional hook for the accuracy bench (sinewatch.apps.bench.accuracy.estimator_params):
    #   @classmethod
    #   def params_for(cls, sample_rate_hz: float, hints: dict) -> dict
    # hints: scenario, sample_rate_hz, nominal_frequency_hz (one per component),
    # frequency_range_hz, n_components, n_inputs, noise_std, amplitude, offset,
    # reporting_rate_hz, tags. Raise ParameterError when the estimator does not apply.

    @classmethod
    def example(cls) -> Estimator[Any]:
        """An instance built from the example configuration."""
        return cls(cls.example_sample_rate_hz, dict(cls.example_params))

    @classmethod
    def example_signal(cls, n: int, seed: int = 0) -> np.ndarray:
        """n samples the example configuration handles: a biased sinusoid at
        ``example_frequency_hz`` plus 1 % white noise (override for multi-input kinds)."""
        rng = np.random.default_rng(seed)
        t = np.arange(n) / cls.example_sample_rate_hz
        return 0.5 + np.sin(2 * np.pi * cls.example_frequency_hz * t + 0.3) + 0.01 * rng.standard_normal(n)

    def __init__(
        self,
        sample_rate_hz: float,
        params: EstimatorParams | Mapping[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        if isinstance(sample_rate_hz, bool) or not isinstance(sample_rate_hz, (int, float)):
            raise InputTypeError(f"sample_rate_hz: expected a number, got {type(sample_rate_hz).__name__}")
        if not np.isfinite(sample_rate_hz) or sample_rate_hz <= 0:
            raise ParameterError(f"sample_rate_hz: expected a finite value > 0, got {sample_rate_hz}")
        self.sample_rate_hz = float(sample_rate_hz)
        self.params = cast(ParamsT, self._validate_params(params, kwargs))
        self._check_params()
        self._setup()
        self._state = self._initial_state()

    # ---- the state, or a bank's column of it ------------------------------------------------
    # Between a bank's frames its channels' states stay stacked, channel last, in one
    # StackedStates (sinewatch.estimators.bank.update_bank): the state of a channel in it is
    # column ``_stack_index`` of the stack's arrays. Reading or replacing ``_state`` takes the
    # channel out of the stack (its column copied into a dict of its own, the stack no longer
    # advanced as a whole), so everything but the bank sees the plain dict of arrays.
    _stack: StackedStates | None = None
    _stack_index: int = 0
    _own_state: dict[str, np.ndarray]

    @property
    def _state(self) -> dict[str, np.ndarray]:
        stack = self._stack
        if stack is not None:
            self._own_state = stack.leave(self._stack_index)
            self._stack = None
        return self._own_state

    @_state.setter
    def _state(self, state: dict[str, np.ndarray]) -> None:
        if self._stack is not None:
            self._stack.live = False
            self._stack = None
        self._own_state = state

    def _state_peek(self) -> dict[str, np.ndarray]:
        """The state, for reading only, without taking the channel out of a bank's stack."""
        stack = self._stack
        return self._own_state if stack is None else stack.column(self._stack_index)

    def _state_checkpoint(self) -> tuple[Any, ...]:
        """Where the state is now (its dict, or its stack and column), without moving it: what
        :meth:`_state_rollback` puts back after a failed update (kernels return new arrays and
        a stack is advanced only when its kernel has returned, so what this names is intact)."""
        return self._stack, self._stack_index, self.__dict__.get("_own_state")

    def _state_rollback(self, checkpoint: tuple[Any, ...]) -> None:
        self._stack, self._stack_index, self._own_state = checkpoint

    # ---- parameters -------------------------------------------------------------------
    @classmethod
    def _validate_params(
        cls, params: EstimatorParams | Mapping[str, Any] | None, kwargs: Mapping[str, Any]
    ) -> EstimatorParams:
        if isinstance(params, cls.Params):
            if kwargs:
                params = params.model_copy(update=dict(kwargs))
                return cls._validate_params(params.model_dump(), {})
            return params
        merged = dict(params or {})
        merged.update(kwargs)
        try:
            return cls.Params.model_validate(merged)
        except ValidationError as exc:
            raise ParameterError(f"{cls.name}: invalid parameters: {_short(exc)}") from exc

    def _check_params(self) -> None:
        """Checks that need the sample rate (Nyquist and the like). Raise ParameterError."""

    def _setup(self) -> None:
        """Compute constants derived from the parameters (gains, discretisations) and set
        ``self._constants``, the kernel's arguments after the state arrays."""

    @property
    def n_components(self) -> int:
        return 1

    @property
    def n_inputs(self) -> int:
        """Columns expected per sample: 1 for the signal, more when known inputs travel along."""
        return 1

    #: The memory of an estimator that does not say (a recursive one without a settling time
    #: of its own): 0.1 s, five cycles at 50 Hz.
    DEFAULT_MEMORY_S: ClassVar[float] = 0.1
    #: How many memories of present signal an estimate needs behind it to be valid (validity
    #: rules version 5): a window holds nothing of the past once it has refilled (1); a
    #: recursive estimator's settling time is counted from a state near the truth, and after a
    #: start, an interruption or a step of the level its state is far off (tens of hertz, or
    #: the old amplitude), so it needs its memory twice (2: kkl, ges-kalman still 1.1-1.5x their
    #: target one memory after an interruption, docs/validity.md).
    REFILL_MEMORIES: ClassVar[int] = 2

    @property
    def memory_samples(self) -> int:
        """How many samples before an estimate's time the estimate depends on: a windowed
        estimator's window, a recursive one's settling time. The pipeline flags an estimate
        valid only once the signal has been present for this long (``diagnostics.valid``,
        :mod:`sinewatch.estimators.presence`). Default: :attr:`DEFAULT_MEMORY_S` seconds."""
        return max(1, math.ceil(self.DEFAULT_MEMORY_S * self.sample_rate_hz))

    def presence_samples(self, samples: np.ndarray) -> np.ndarray:
        """The one-column signal the pipeline's presence detector reads from a block
        (``diagnostics.valid``): column 0, the measurement, unless an estimator says
        otherwise (an in-phase/quadrature pair: its magnitude)."""
        return samples if samples.ndim == 1 else samples[:, 0]

    @property
    def presence_cycle_hz(self) -> float | None:
        """The frequency whose cycle is the presence detector's window, when the estimator
        knows better than its parameters (None: from ``nominal_frequency_hz`` and the like)."""
        return None

    # ---- state --------------------------------------------------------------------------
    @abstractmethod
    def _initial_state(self) -> dict[str, np.ndarray]:
        """Fresh state arrays (float64/int64 numpy arrays), in the kernel's argument order;
        the docstring of an override documents the layout of each array."""

    @abstractmethod
    def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
        """The Track of one kernel call from its outputs (everything it returns before the
        new state arrays) and the block it ran on."""

    def _kernel_input(self, samples: np.ndarray) -> np.ndarray:
        """The block as the kernel takes it (default: as validated)."""
        return samples

    def _run(
        self, samples: np.ndarray, state: dict[str, np.ndarray], last_only: bool
    ) -> tuple[Track, dict[str, np.ndarray]]:
        """Run the kernel over ``samples`` (float64, C-contiguous, (N,) or (N, n_inputs),
        never empty) from ``state`` (which is not modified) and return the track and the
        new state: the one call described in the module docstring."""
        block = self._kernel_input(samples)
        result = self._kernel(block, *state.values(), *self._constants, last_only)
        n_outputs = len(result) - len(state)  # so the zip below pairs every state array
        if n_outputs == len(result) - 1:  # one state array (most kernels): no zip, ~0.3 us less
            (key,) = state
            return self._track(result[:n_outputs], block), {key: result[-1]}
        return self._track(result[:n_outputs], block), dict(zip(state, result[n_outputs:]))  # noqa: B905

    def _run_timed(
        self, samples: np.ndarray, state: dict[str, np.ndarray], last_only: bool, t0_ns: int | None
    ) -> tuple[Track, dict[str, np.ndarray]]:
        """:meth:`_run` for a block whose first sample is at ``t0_ns`` (ns since the epoch,
        None when unknown). Estimators that report on a time grid override this; the
        others ignore the time."""
        return self._run(samples, state, last_only)

    def reset(self) -> None:
        """Return to the state of a freshly constructed estimator."""
        self._state = self._initial_state()

    def get_state(self) -> dict[str, Any]:
        """A JSON-serialisable snapshot that :meth:`set_state` restores exactly."""
        return state_snapshot(
            STATE_FORMAT_VERSION, "estimator", self.name, self.sample_rate_hz, self.params, self._state_peek()
        )

    def set_state(self, snapshot: Mapping[str, Any]) -> None:
        if snapshot.get("format_version") != STATE_FORMAT_VERSION:
            raise ParameterError(
                f"state format_version: expected {STATE_FORMAT_VERSION}, got {snapshot.get('format_version')!r}"
            )
        if snapshot.get("estimator") != self.name:
            raise ParameterError(f"state estimator: expected {self.name!r}, got {snapshot.get('estimator')!r}")
        if float(snapshot.get("sample_rate_hz", -1)) != self.sample_rate_hz:
            raise ParameterError(
                f"state sample_rate_hz: expected {self.sample_rate_hz}, got {snapshot.get('sample_rate_hz')}"
            )
        if self.Params.model_validate(snapshot.get("params", {})) != self.params:
            raise ParameterError("state params differ from this estimator's parameters")
        fresh = self._initial_state()
        arrays = {k: decode_array(v) for k, v in snapshot["state"].items()}
        if set(arrays) != set(fresh):
            raise ParameterError(f"state keys: expected {sorted(fresh)}, got {sorted(arrays)}")
        for k, v in arrays.items():
            if v.shape != fresh[k].shape or v.dtype != fresh[k].dtype:
                raise ParameterError(f"state {k!r}: expected {fresh[k].dtype}{fresh[k].shape}, got {v.dtype}{v.shape}")
        self._state = {k: arrays[k] for k in fresh}  # the kernel's argument order

    @classmethod
    def from_state(cls, snapshot: Mapping[str, Any]) -> Estimator[Any]:
        est = cls(float(snapshot["sample_rate_hz"]), snapshot.get("params", {}))
        est.set_state(snapshot)
        return est

    # ---- the one entry point -------------------------------------------------------------
    def update(self, samples: np.ndarray, *, last_only: bool = False, t0_ns: int | None = None) -> Track:
        """Feed a block of samples; return per-sample estimates (or the last row only).

        The input is never modified. A rejected block raises InputError/InputTypeError
        and leaves the state untouched. ``t0_ns`` (ns since the epoch) is the time of the
        block's first sample: estimators that report on a time grid need it (their
        ``Track.reports``); the others ignore it.
        """
        x = self._as_block(samples)
        track, new_state = self._run_timed(x, self._state, last_only, t0_ns)
        self._state = new_state
        return track

    def _as_block(self, samples: Any) -> np.ndarray:
        # The common case first, in as few Python operations as possible (this runs once per
        # block and per channel): a float64 numpy array of shape (N,) with N > 0 for a
        # one-input estimator, used as is when of the kernels' kind (``kernel_samples``;
        # kernels never write to their input). Everything else takes the general path
        # below, which raises the typed errors.
        if (
            type(samples) is np.ndarray
            and samples.dtype is _F64
            and samples.ndim == 1
            and samples.shape[0]
            and self.n_inputs == 1
        ):
            x = kernel_samples(samples)
            if _all_finite(x):
                return x
            bad = int(np.count_nonzero(~np.isfinite(x)))
            raise InputError(f"samples: expected finite values, got {bad} NaN/Inf", kind="non_finite")
        if not isinstance(samples, np.ndarray):
            if isinstance(samples, (list, tuple)):
                samples = np.asarray(samples)
            else:
                raise InputTypeError(f"samples: expected a numpy array, got {type(samples).__name__}")
        if samples.dtype.kind not in "fiu":
            raise InputTypeError(f"samples: expected a real numeric dtype, got {samples.dtype}")
        want = self.n_inputs
        if want == 1 and samples.ndim == 2 and samples.shape[1] == 1:
            samples = samples[:, 0]
        if want == 1 and samples.ndim != 1:
            raise InputError(f"samples: expected shape (N,), got {samples.shape}", kind="shape_mismatch")
        if want > 1 and (samples.ndim != 2 or samples.shape[1] != want):
            raise InputError(f"samples: expected shape (N, {want}), got {samples.shape}", kind="shape_mismatch")
        if samples.shape[0] == 0:
            raise InputError("samples: expected at least one sample, got 0", kind="empty_block")
        # Kernels never write to their input, so a block already of the kernels' kind is used as is.
        x = kernel_samples(samples)
        if not _all_finite(x.reshape(-1)):
            bad = int(np.count_nonzero(~np.isfinite(x)))
            raise InputError(f"samples: expected finite values, got {bad} NaN/Inf", kind="non_finite")
        return x


def checked_sample_rate(sample_rate_hz: object) -> float:
    """``sample_rate_hz`` as a float, checked as :class:`Estimator` checks it (a number, not a
    bool, finite and > 0), for the analysers that are not estimators but take the same
    argument (``sinewatch.power_quality.harmonics``)."""
    if isinstance(sample_rate_hz, bool) or not isinstance(sample_rate_hz, (int, float)):
        raise InputTypeError(f"sample_rate_hz: expected a number, got {type(sample_rate_hz).__name__}")
    if not np.isfinite(sample_rate_hz) or sample_rate_hz <= 0:
        raise ParameterError(f"sample_rate_hz: expected a finite value > 0, got {sample_rate_hz}")
    return float(sample_rate_hz)


@kernel(error_model="python")
def _all_finite(x: np.ndarray) -> bool:
    # One compiled pass instead of np.isfinite(x).all(): the numpy version costs ~1 us
    # of ufunc overhead per block, which shows at high block rates. v - v is 0 for a finite
    # v and NaN for inf or NaN; counting those over the whole array, without the early exit
    # a test per value needs, is a loop LLVM vectorises (8,192 values, a frame of 8 channels:
    # 4.6 against 7.5 us with the exit, timeit in one process on a 2-core Xeon Sapphire Rapids
    # VM under load 8-17; `sinewatch bench pipeline --frame-channels 8` times the whole path).
    n_bad = 0
    for v in x:
        n_bad += 1 if v - v != 0.0 else 0
    return n_bad == 0


def _short(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "(root)"
        parts.append(f"{loc}: {err['msg']}")
    return "; ".join(parts)


@kernel(inline="always")
def undefined_row(out: np.ndarray, j: int) -> None:
    """Row ``j`` of a one-component kernel's output columns (frequency_hz, amplitude,
    phase_rad, offset, converged) as undefined: NaN estimates, not converged."""
    out[j, 0] = np.nan
    out[j, 1] = np.nan
    out[j, 2] = np.nan
    out[j, 3] = np.nan
    out[j, 4] = 0.0


@kernel(inline="always")
def bank_outputs(nc: int, n: int, last_only: bool, n_extras: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A bank kernel's outputs for ``nc`` channels and a block of ``n`` samples, by the bank's
    calling convention (``sinewatch.estimators.bank``): ``out`` (nc, rows, 5), ``extras`` (nc,
    rows, n_extras) and ``sse`` (nc,), rows = 1 with ``last_only``."""
    rows = 1 if last_only else n
    return np.empty((nc, rows, 5)), np.empty((nc, rows, n_extras)), np.empty(nc)


def empty_outputs(n: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """NaN-filled output arrays (frequency, amplitude, phase, offset) and a False mask."""
    nan2 = np.full((n, k), np.nan)
    return nan2, nan2.copy(), nan2.copy(), np.full(n, np.nan), np.zeros(n, dtype=bool)


def track_from_columns(
    out: np.ndarray, sse: float, n_samples: int, extras: dict[str, np.ndarray] | None = None, **more: Any
) -> Track:
    """Track of a one-component kernel whose output columns are
    (frequency_hz, amplitude, phase_rad, offset, converged as 0/1); ``sse`` is the sum of
    squared one-step prediction errors over the ``n_samples`` of the block; ``more``: the
    other Track fields (rocof_hz_per_s, reports, ...)."""
    n = n_samples
    return Track(
        out[:, 0:1],  # frequency_hz
        out[:, 1:2],  # amplitude
        out[:, 2:3],  # phase_rad
        out[:, 3],  # offset
        out[:, 4].astype(np.bool_),  # converged: != 0 (NaN counts as True either way), one call
        math.sqrt(sse / n) if n else math.nan,  # residual_rms
        extras or {},
        **more,
    )
