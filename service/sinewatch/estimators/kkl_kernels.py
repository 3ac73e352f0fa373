"""Compiled kernels of ``kkl`` and ``kkl-biased`` (the maths: :mod:`sinewatch.estimators.kkl`).

The single-channel kernel :func:`kkl_kernel` and the pieces it shares with the ``kkl-biased``
kernel (inlined: the same arithmetic in both), and :func:`kkl_bank_kernel`, the bank of
:mod:`sinewatch.estimators.bank`: the same observer for 8 channels at once, each operation of
a sample written once in a helper that both the single kernel and the bank call, so that
every channel's bits are the single kernel's whatever the bank's size and the channel's
position in it. The bank's work-array rows and its plumbing (``bank_*``: loading, the filter
step, the sines, converged, the rows) serve ``kkl-biased``'s bank too
(:mod:`sinewatch.estimators.kkl_biased_kernels`).
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
from llvmlite import ir as llvm_ir
from numba.core import cgutils
from numba.extending import intrinsic

from sinewatch.estimators import detmath
from sinewatch.estimators.base import kernel, undefined_row
from sinewatch.estimators.lanes import aligned_lanes, copy_lanes, frozen, select

ABS_FLOOR = 1e-150  # |xi| at or below this is "zero"
FLUSH = 1e-250  # xi entries below this are set to 0 (no denormals in long silences)
JUMP_RATIO = 9.0  # prediction error: short-term mean square above 9x its long-term level
JUMP_FLOOR = 4e-4  # ... and above (2 % of the RMS of y)^2: a jump, not converged

#: values kept per sample for its row (:func:`record_sample`)
RECORD_SIZE = 12


@intrinsic
def _sqrt_intrinsic(typingctx: Any, a: Any) -> Any:
    sig = numba.types.float64(numba.types.float64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        d = llvm_ir.DoubleType()
        fn = cgutils.get_or_insert_function(builder.module, llvm_ir.FunctionType(d, [d]), "llvm.sqrt.f64")  # type: ignore[no-untyped-call]
        return builder.call(fn, list(args))

    return sig, codegen


@kernel(inline="always", refcount=False)
def sqrt(a: float) -> float:
    """The square root, correctly rounded (IEEE 754) like the C library's, as the instruction
    itself: ``math.sqrt`` compiles to the C library's call (kept for its errno on a negative
    argument), which the compiler does not vectorise across a bank's lanes. The same bits for
    every argument >= 0, the only ones whose root is used here."""
    return _sqrt_intrinsic(a)  # type: ignore[call-arg]  # numba passes the typing context


# ---- kernel pieces shared with kkl-biased (inlined: the same arithmetic in both) -----------


@kernel(inline="always")
def observer_constants(
    consts: np.ndarray,
) -> tuple[float, float, float, float, float, float, float, float, float, float, float, float, float]:
    """The 13 constants of :func:`observer_consts`, unpacked: Ts, omega_ref, l,
    silence_ratio, env_decay, n_settle, max_fit_residual^2, max_prediction_error^2,
    avg_gain, the omega Ts bounds of the converged range, the jump detector's gains."""
    return (
        consts[0], consts[1], consts[2], consts[3], consts[4], consts[5], consts[6] * consts[6],
        consts[7] * consts[7], consts[8], consts[9], consts[10], consts[11], consts[12],
    )  # fmt: skip


@kernel(inline="always")
def observer_head(
    state: np.ndarray, m: int, n: int, last_only: bool
) -> tuple[np.ndarray, float, float, float, float, float, float, np.ndarray, np.ndarray, np.ndarray]:
    """The state entries both kernels start with (a copy of xi_1..xi_m, then y_prev,
    have_prev, y_pred, pred_valid, n_good, env) and the ``out`` and ``extras`` arrays of a
    block of ``n`` samples, and the ``rec`` array of :func:`record_sample` (per-sample values
    for the rows, none when only the last row is wanted)."""
    rows = 1 if last_only else n
    return (
        state[:m].copy(), float(state[m]), state[m + 1], state[m + 2], state[m + 3], state[m + 4], state[m + 5],
        np.empty((rows, 5)), np.empty((rows, 3)), np.empty((0 if last_only else n, RECORD_SIZE)),
    )  # fmt: skip


@kernel(inline="always")
def prediction_error(
    yk: float, y_pred: float, pred_valid: float, sse: float, e2_avg: float, avg_gain: float
) -> tuple[float, float, float]:
    """The squared one-step prediction error of sample ``yk`` (against 0 while there is no
    prediction), the block's sum of squares and the running mean square, updated."""
    e = select(pred_valid != 0.0, yk - y_pred, yk)
    e2 = e * e
    return e2, sse + e2, e2_avg + avg_gain * (e2 - e2_avg)


@kernel(inline="always")
def undefined_sample() -> tuple[bool, bool, float, float, float, float, float, float]:
    """defined, good, det, A sin(theta), A cos(theta), omega Ts, and the squared fit residual
    and its reference |F^2 xi|^2, for a sample where the estimate is undefined (until the
    inverse map says otherwise)."""
    return False, False, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0


@kernel(inline="always")
def consistent(
    mu: float, rr: float, ff: float, max_fit2: float, e2_avg: float, max_pred2: float, level: float,
    jump: bool, wts: float, wts_lo: float, wts_hi: float,
) -> bool:  # fmt: skip
    """ "Good" (module docstring, converged): mu = 0, the relative fit residual and the
    running prediction error (against ``level``, the running mean square or variance of y)
    within bounds, no jump, and omega Ts inside the converged range."""
    # (& not `and`: no branch, see lanes.select; every operand is a plain comparison)
    return (
        (mu == 0.0)
        & (rr <= max_fit2 * ff)
        & (e2_avg <= max_pred2 * level)
        & (not jump)
        & (wts_lo <= wts)
        & (wts <= wts_hi)
    )


@kernel(inline="always")
def record_sample(
    rec: np.ndarray, k: int, last_only: bool, good: bool, n_good: float, n_settle: float, defined: bool,
    wts: float, a_sin: float, a_cos: float, offset: float, det: float, rr: float, ff: float, e2_avg: float,
    level: float,
) -> float:  # fmt: skip
    """Count ``good`` samples (converged after n_settle in a row) and, unless only the last
    is wanted, keep sample ``k``'s values in row k of ``rec`` for :func:`write_samples`:
    the rows are written after the per-sample loop, because their calls (atan2 and the
    like) in the loop, even on a branch taken once, slowed every sample. Returns the new
    count."""
    n_good = count_good(good, n_good, n_settle)
    if not last_only:  # (last_only: the loop's final values are the row)
        record_row(rec, k, good, n_good, defined, wts, a_sin, a_cos, offset, det, rr, ff, e2_avg, level)
    return n_good


@kernel(inline="always")
def count_good(good: bool, n_good: float, n_settle: float) -> float:
    """The run of good samples, counted up to n_settle (converged once it is reached)."""
    up = n_good + 1.0
    return select(good, select(n_settle < up, n_settle, up), 0.0)  # min(up, n_settle), as Python's min


@kernel(inline="always")
def record_row(
    rec: np.ndarray, k: int, good: bool, n_good: float, defined: bool, wts: float, a_sin: float, a_cos: float,
    offset: float, det: float, rr: float, ff: float, e2_avg: float, level: float,
) -> None:  # fmt: skip
    """Row k of ``rec``: what :func:`write_sample` needs of sample k."""
    rec[k, 0] = 1.0 if good else 0.0
    rec[k, 1] = n_good
    rec[k, 2] = 1.0 if defined else 0.0
    rec[k, 3] = wts
    rec[k, 4] = a_sin
    rec[k, 5] = a_cos
    rec[k, 6] = offset
    rec[k, 7] = det
    rec[k, 8] = rr
    rec[k, 9] = ff
    rec[k, 10] = e2_avg
    rec[k, 11] = level


@kernel(inline="always")
def write_rows(
    out: np.ndarray, ext: np.ndarray, rec: np.ndarray, last_only: bool, good: bool, n_good: float,
    n_settle: float, defined: bool, wts: float, Ts: float, a_sin: float, a_cos: float, offset: float, det: float,
    ell: float, rr: float, ff: float, e2_avg: float, level: float,
) -> None:  # fmt: skip
    """After a block's loop: the last sample's row from the loop's final values, or every
    sample's row from ``rec``."""
    if last_only:
        write_sample(out, ext, 0, good, n_good, n_settle, defined, wts, Ts, a_sin, a_cos, offset, det, ell, rr, ff,
                     e2_avg, level)  # fmt: skip
    else:
        write_samples(out, ext, rec, n_settle, Ts, ell)


@kernel(inline="always")
def write_samples(
    out: np.ndarray, ext: np.ndarray, rec: np.ndarray, n_settle: float, Ts: float, ell: float
) -> None:  # fmt: skip
    """The rows of the samples kept in ``rec`` by :func:`record_sample`."""
    for k in range(rec.shape[0]):
        write_sample(out, ext, k, rec[k, 0] != 0.0, rec[k, 1], n_settle, rec[k, 2] != 0.0, rec[k, 3], Ts,
                     rec[k, 4], rec[k, 5], rec[k, 6], rec[k, 7], ell, rec[k, 8], rec[k, 9], rec[k, 10],
                     rec[k, 11])  # fmt: skip


@kernel(inline="always")
def write_sample(
    out: np.ndarray, ext: np.ndarray, j: int, good: bool, n_good: float, n_settle: float, defined: bool,
    wts: float, Ts: float, a_sin: float, a_cos: float, offset: float, det: float, ell: float, rr: float,
    ff: float, e2_avg: float, level: float,
) -> None:  # fmt: skip
    """Row ``j`` of a sample counted by :func:`record_sample`: frequency from omega Ts, the
    margin 2 det / l, the relative fit residual, and the prediction error relative to
    ``level``."""
    ext[j, 2] = math.sqrt(e2_avg / level) if level > 0.0 else np.nan
    write_row(out, ext, j, defined, wts / (2.0 * math.pi * Ts), a_sin, a_cos, offset,
              good and n_good >= n_settle, 2.0 * det / ell, math.sqrt(rr / ff))  # fmt: skip


@kernel(inline="always")
def packed_state(xi: np.ndarray, tail: np.ndarray) -> np.ndarray:
    """The new state array: xi, then the kernel's scalars ``tail``."""
    m = xi.shape[0]
    new_state = np.empty(m + tail.shape[0])
    new_state[:m] = xi
    new_state[m:] = tail
    return new_state


@kernel(inline="always")
def filter_step(xi: np.ndarray, fa: np.ndarray, fb0: np.ndarray, fb1: np.ndarray, y_prev: float, yk: float) -> None:
    """(12) over one sample, exact for y linear between samples (in place); entries below
    FLUSH become 0 (no denormals in a long silence)."""
    for i in range(xi.shape[0]):
        xi[i] = filter_one(fa[i], fb0[i], fb1[i], xi[i], y_prev, yk)


@kernel(inline="always")
def next_sample(
    y: np.ndarray, k: int, xi: np.ndarray, fa: np.ndarray, fb0: np.ndarray, fb1: np.ndarray, have_prev: float,
    y_prev: float,
) -> float:  # fmt: skip
    """Sample k of ``y``, after the filters (12) have advanced to it (from the previous
    sample, if there was one)."""
    yk = float(y[k])
    if have_prev != 0.0:
        filter_step(xi, fa, fb0, fb1, y_prev, yk)
    return yk


@kernel(inline="always")
def filter_one(a: float, b0: float, b1: float, x: float, y_prev: float, yk: float) -> float:
    """One filter of (12) over one sample; below FLUSH, 0."""
    v = a * x + b0 * y_prev + b1 * yk
    return select(abs(v) > FLUSH, v, 0.0)


@kernel(inline="always")
def filter_sums(
    lam: float, v: float, s2: float, p0: float, p1: float, p2: float, p3: float, q2: float
) -> tuple[float, float, float, float, float, float]:
    """The sums over the filters of :func:`kkl_kernel`, advanced by filter (lam, xi = v):
    |xi|^2, sum xi, sum lam xi, sum lam^2 xi, sum lam^3 xi, sum lam^2 xi^2."""
    l2v = lam * lam * v
    return s2 + v * v, p0 + v, p1 + lam * v, p2 + l2v, p3 + lam * l2v, q2 + l2v * v


@kernel(inline="always")
def jump_detector(
    e2: float, e2_fast: float, e2_slow: float, fast_gain: float, slow_gain: float, level: float
) -> tuple[bool, float, float]:
    """The squared prediction error's short-term mean against its long-term level, before
    and after this sample: (jump, new e2_fast, new e2_slow)."""
    jump = e2_fast > JUMP_RATIO * e2_slow + JUMP_FLOOR * level
    e2_fast += fast_gain * (e2 - e2_fast)
    e2_slow += slow_gain * (e2 - e2_slow)
    return jump | (e2_fast > JUMP_RATIO * e2_slow + JUMP_FLOOR * level), e2_fast, e2_slow


@kernel(inline="always")
def half_step(wts: float) -> tuple[float, float, float]:
    """sin and cos of omega Ts / 2, and 1 / sinc^2(omega Ts / 2), the first-order hold's
    amplitude correction."""
    half = 0.5 * wts
    return half_step_of(half, detmath.sin(half))


@kernel(inline="always")
def half_step_of(half: float, sh: float) -> tuple[float, float, float]:
    """:func:`half_step` given ``sh = sin(half)`` (:func:`sinewatch.estimators.detmath.sin`, the
    same function in the single kernel and in a bank's vectorised lanes)."""
    c2 = 1.0 - sh * sh
    ch = sqrt(select(0.0 > c2, 0.0, c2))  # max(c2, 0.0), as Python's max
    q = half / sh
    return sh, ch, select(half > 1e-8, q * q, 1.0)


@kernel(inline="always")
def write_row(
    out: np.ndarray,
    ext: np.ndarray,
    j: int,
    defined: bool,
    frequency_hz: float,
    a_sin: float,
    a_cos: float,
    offset: float,
    converged: bool,
    margin: float,
    fit: float,
) -> None:
    """Row ``j`` of the outputs and of the first two extras (module docstring, outputs)."""
    if defined:
        phase = math.atan2(a_sin, a_cos)  # x1 = A sin(theta), x2 = -A omega cos(theta)
        out[j, 0] = frequency_hz
        out[j, 1] = math.sqrt(a_sin * a_sin + a_cos * a_cos)
        out[j, 2] = phase if phase > -math.pi else math.pi
        out[j, 4] = 1.0 if converged else 0.0
        ext[j, 0] = margin
        ext[j, 1] = fit
    else:
        undefined_row(out, j)
        ext[j, 0] = np.nan
        ext[j, 1] = np.nan
    out[j, 3] = offset


@kernel(inline="always")
def inverse_map(
    s_ll: float, s_l: float, s_11: float, p0: float, p1: float, p2: float, p3: float, q2: float, s: float, ell: float
) -> tuple[float, float, float, bool, float, float, float]:
    """gamma (8)-(9) on the unit vector xi/|xi| from the sums of :func:`filter_sums` (s = |xi|):
    ``(1/s, det(L^T L), mu, solved, z0, z1, z2)`` with z = (x1 / |xi~|, x2 / (omega_ref |xi~|),
    x3 / omega_ref^2), xi~ = omega_ref xi; ``solved``: Phi invertible and x3 > 0 (z is
    meaningless otherwise). Straight-line (no branch), so that a bank runs it as one vector."""
    inv = 1.0 / s
    # L^T L = [[s_ll, s_l, b02], [s_l, s_11, b12], [b02, b12, 1]] and
    # r = L^T F^2 xi, for the unit vector xi/|xi| (8)
    b02 = -p1 * inv
    b12 = -p0 * inv
    r0 = p3 * inv
    r1 = p2 * inv
    r2 = -q2 * inv * inv
    # |M xi|^2 = det(L^T L) (Gram determinant; equals the printed M for m = 4)
    det = s_ll * (s_11 - b12 * b12) - s_l * (s_l - b12 * b02) + b02 * (s_l * b12 - s_11 * b02)
    mu = ell - 2.0 * det
    mu = select(0.0 > mu, 0.0, mu)  # (9) with |xi| = 1: max(mu, 0), as Python's max
    # Phi = L^T L + mu I, solved with its adjugate (8)
    a = s_ll + mu
    d = s_11 + mu
    f = 1.0 + mu
    k00 = d * f - b12 * b12
    k01 = b02 * b12 - s_l * f
    k02 = s_l * b12 - d * b02
    k11 = a * f - b02 * b02
    k12 = s_l * b02 - a * b12
    k22 = a * d - s_l * s_l
    det_phi = a * k00 + s_l * k01 + b02 * k02
    idet = 1.0 / det_phi
    z0 = (k00 * r0 + k01 * r1 + k02 * r2) * idet
    z1 = (k01 * r0 + k11 * r1 + k12 * r2) * idet
    z2 = (k02 * r0 + k12 * r1 + k22 * r2) * idet
    return inv, det, mu, (det_phi > 1e-300) & (z2 > 0.0), z0, z1, z2


@kernel(inline="always")
def read_out(
    w_ref: float, s: float, z0: float, z1: float, sq: float, sh: float, ch: float, g: float
) -> tuple[float, float, float]:
    """A sin(theta) = x1, A cos(theta) = -x2 / omega (corrected by g = 1/sinc^2 of the
    first-order hold) and the prediction of y(k+1), A sin(theta + w Ts)."""
    a_sin = w_ref * s * z0 * g
    a_cos = -w_ref * s * z1 * g / sq
    return a_sin, a_cos, a_sin * (1.0 - 2.0 * sh * sh) + a_cos * (2.0 * sh * ch)


@kernel(inline="always")
def fit_residual(lam: float, xn: float, z0: float, z1: float, z2: float) -> tuple[float, float]:
    """Filter (lam, xn = xi/|xi|)'s residual of (13) at z, and its term of F^2 xi/|xi|."""
    t = lam * lam * xn
    return lam * z0 + z1 - xn * z2 - t, t


# ---- kernel -------------------------------------------------------------------------------


@kernel
def kkl_kernel(
    y: np.ndarray,
    state: np.ndarray,
    lam: np.ndarray,
    fa: np.ndarray,
    fb0: np.ndarray,
    fb1: np.ndarray,
    consts: np.ndarray,
    last_only: bool,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Run the observer over block ``y`` from ``state``; return ``(out, extras, sse, new_state)``.

    ``lam`` holds lambda~_i = lambda_i / omega_ref; ``fa, fb0, fb1`` the exact first-order
    hold coefficients of (12) (physical units). ``state`` is the ``xi_state`` array
    (layout: :meth:`Kkl._initial_state`). ``consts`` packs Ts, omega_ref, l (in units of omega_ref^2), silence_ratio, env_decay,
    n_settle, max_fit_residual, max_prediction_error, avg_gain, the omega Ts bounds of the
    converged range, and the gains of the jump detector's fast and slow means. ``out``
    columns: frequency_hz, amplitude, phase_rad, offset, converged; ``extras`` columns:
    manifold_margin, fit_residual, prediction_error. Pure: the inputs are not modified.
    """
    Ts, w_ref, ell, silence_ratio, env_decay, n_settle, max_fit2, max_pred2, avg_gain, wts_lo, wts_hi, fast_gain, slow_gain = (
        observer_constants(consts)
    )  # fmt: skip
    m, n = lam.shape[0], y.shape[0]
    xi, y_prev, have_prev, y_pred, pred_valid, n_good, env, out, ext, rec = observer_head(state, m, n, last_only)
    e2_avg, y2_avg = state[m + 6], state[m + 7]
    e2_fast, e2_slow = state[m + 8], state[m + 9]
    # constant entries of L^T L (L = (lambda 1 -xi), eq. 8)
    s_ll = 0.0
    s_l = 0.0
    for i in range(m):
        s_ll += lam[i] * lam[i]
        s_l += lam[i]
    s_11 = float(m)
    sse = 0.0
    defined, good, det, a_sin, a_cos, wts, rr, ff = undefined_sample()  # (n >= 1: set by the loop)
    offset = np.nan
    for k in range(n):
        yk = next_sample(y, k, xi, fa, fb0, fb1, have_prev, y_prev)  # (12)
        have_prev = 1.0
        y_prev = yk
        # one-step prediction error and its running mean square, against that of y
        e2, sse, e2_avg = prediction_error(yk, y_pred, pred_valid, sse, e2_avg, avg_gain)
        jump, e2_fast, e2_slow = jump_detector(e2, e2_fast, e2_slow, fast_gain, slow_gain, y2_avg)
        y2_avg += avg_gain * (yk * yk - y2_avg)
        # sums over the filters
        s2 = p0 = p1 = p2 = p3 = q2 = 0.0
        for i in range(m):
            s2, p0, p1, p2, p3, q2 = filter_sums(lam[i], xi[i], s2, p0, p1, p2, p3, q2)
        s = math.sqrt(s2)
        env = max(s, env * env_decay)
        pred_valid = 0.0
        defined, good, det, a_sin, a_cos, wts, rr, ff = undefined_sample()
        if s > ABS_FLOOR and s >= silence_ratio * env:  # else "xi near 0": undefined
            inv, det, mu, solved, z0, z1, z2 = inverse_map(s_ll, s_l, s_11, p0, p1, p2, p3, q2, s, ell)
            if solved:
                sq = math.sqrt(z2)
                wts = w_ref * sq * Ts  # omega Ts
                if wts < math.pi:  # below Nyquist
                    defined = True
                    sh, ch, g = half_step(wts)
                    a_sin, a_cos, y_pred = read_out(w_ref, s, z0, z1, sq, sh, ch, g)
                    pred_valid = 1.0
                    # least-squares residual of (13), zero on T(O)
                    ff = 0.0
                    for i in range(m):
                        res, t = fit_residual(lam[i], xi[i] * inv, z0, z1, z2)
                        rr += res * res
                        ff += t * t
                    good = consistent(mu, rr, ff, max_fit2, e2_avg, max_pred2, y2_avg, jump, wts, wts_lo, wts_hi)
        # converged after n_settle consecutive good samples; omega = omega_ref sqrt(x3~); the
        # model has no offset: 0 whenever defined
        offset = 0.0 if defined else np.nan
        n_good = record_sample(rec, k, last_only, good, n_good, n_settle, defined, wts, a_sin, a_cos, offset, det,
                               rr, ff, e2_avg, y2_avg)  # fmt: skip
    write_rows(out, ext, rec, last_only, good, n_good, n_settle, defined, wts, Ts, a_sin, a_cos, offset, det, ell,
               rr, ff, e2_avg, y2_avg)  # fmt: skip
    tail = np.array([y_prev, have_prev, y_pred, pred_valid, n_good, env, e2_avg, y2_avg, e2_fast, e2_slow])
    return out, ext, sse, packed_state(xi, tail)


# ---- bank: the channels of a frame together (sinewatch.estimators.bank) -------------------
LANES = 8  # channels advanced together
# rows of the bank's lane-major work array S (one row of LANES doubles per quantity): the
# state's scalars, the per-sample quantities, then the m filters' xi (rows _RXI + i) last, so
# that every other row sits at a constant offset below them
_RY, _RYP, _RHP, _RYPRED, _RPV, _RNG, _RENV, _RE2, _RLEV, _REF, _RES, _RSSE = range(12)
_RS2, _RP0, _RP1, _RP2, _RP3, _RQ2 = range(12, 18)  # the sums of filter_sums
_RINV, _RDET, _RMU, _RZ0, _RZ1, _RZ2, _RSQ, _RWTS, _RHALF, _RSH = range(18, 28)
_RDEF, _RJUMP, _RASIN, _RACOS, _RRR, _RFF, _RGOOD, _RS, _RV = range(28, 37)
_RXI = 37


@kernel(inline="always")
def bank_filter(S: np.ndarray, r: int, a: float, b0: float, b1: float, yp: float, yk: float, hp: float) -> float:
    """One filter of (12) in entry ``r`` of a bank's work array (as :func:`filter_one`, not
    before the first sample, ``hp`` = 0): its new value."""
    xo = S[r]
    v = filter_one(a, b0, b1, xo, yp, yk)
    v = select(hp != 0.0, v, frozen(xo))  # (frozen: a blend and a plain store, see lanes.frozen)
    S[r] = v
    return v


@kernel(inline="always")
def _bank_filters(
    S: np.ndarray, lane: int, lam: tuple[float, ...], fa: tuple[float, ...], fb0: tuple[float, ...],
    fb1: tuple[float, ...],
) -> None:  # fmt: skip
    """Lane ``lane``: the filters (12) over the sample in row ``_RY`` (as :func:`filter_step`,
    not before the first sample) and the sums of :func:`filter_sums` into their rows. The
    constants are tuples, whose length the compiler knows: the loop over the filters is
    unrolled, so every row sits at a constant offset and the lanes run as one vector."""
    L = LANES
    yp, yk, hp = S[_RYP * L + lane], S[_RY * L + lane], S[_RHP * L + lane]
    s2 = p0 = p1 = p2 = p3 = q2 = 0.0
    for i in range(len(lam)):
        v = bank_filter(S, (_RXI + i) * L + lane, fa[i], fb0[i], fb1[i], yp, yk, hp)
        s2, p0, p1, p2, p3, q2 = filter_sums(lam[i], v, s2, p0, p1, p2, p3, q2)
    S[_RS2 * L + lane], S[_RP0 * L + lane], S[_RP1 * L + lane] = s2, p0, p1
    S[_RP2 * L + lane], S[_RP3 * L + lane], S[_RQ2 * L + lane] = p2, p3, q2


@kernel(inline="always")
def _bank_fit(S: np.ndarray, lane: int, lam: tuple[float, ...]) -> None:
    """Lane ``lane``: the least-squares residual of (13) and |F^2 xi/|xi||^2 summed over the
    filters in their order (as :func:`kkl_kernel`), into rows ``_RRR`` and ``_RFF``."""
    L = LANES
    inv, z0, z1, z2 = S[_RINV * L + lane], S[_RZ0 * L + lane], S[_RZ1 * L + lane], S[_RZ2 * L + lane]
    rr = 0.0
    ff = 0.0
    for i in range(len(lam)):
        res, t = fit_residual(lam[i], S[(_RXI + i) * L + lane] * inv, z0, z1, z2)
        rr += res * res
        ff += t * t
    S[_RRR * L + lane] = rr
    S[_RFF * L + lane] = ff


@kernel(inline="always")
def _bank_front(
    S: np.ndarray, lane: int, s_ll: float, s_l: float, s_11: float, ell: float, w_ref: float, Ts: float,
    silence_ratio: float, env_decay: float, avg_gain: float, fast_gain: float, slow_gain: float,
) -> None:  # fmt: skip
    """Lane ``lane`` of one sample of :func:`kkl_kernel` after the filters, up to omega Ts:
    the prediction error, the jump detector, the level of y, |xi|, the envelope and the
    inverse map, each value kept or replaced as the single kernel's branches would (selects,
    so that the lanes run as one vector)."""
    L = LANES
    yk = S[_RY * L + lane]
    e2, sse, e2_avg = prediction_error(
        yk, S[_RYPRED * L + lane], S[_RPV * L + lane], S[_RSSE * L + lane], S[_RE2 * L + lane], avg_gain
    )
    jump, e2_fast, e2_slow = jump_detector(
        e2, S[_REF * L + lane], S[_RES * L + lane], fast_gain, slow_gain, S[_RLEV * L + lane]
    )
    lev = S[_RLEV * L + lane]
    S[_RLEV * L + lane] = lev + avg_gain * (yk * yk - lev)
    S[_RSSE * L + lane], S[_RE2 * L + lane], S[_REF * L + lane], S[_RES * L + lane] = sse, e2_avg, e2_fast, e2_slow
    S[_RHP * L + lane] = 1.0
    S[_RYP * L + lane] = yk
    S[_RJUMP * L + lane] = select(jump, 1.0, 0.0)
    s = sqrt(S[_RS2 * L + lane])
    decayed = S[_RENV * L + lane] * env_decay
    env = select(decayed > s, decayed, s)  # max(s, decayed), as Python's max
    S[_RENV * L + lane] = env
    S[_RS * L + lane] = s
    inv, det, mu, solved, z0, z1, z2 = inverse_map(
        s_ll, s_l, s_11, S[_RP0 * L + lane], S[_RP1 * L + lane], S[_RP2 * L + lane], S[_RP3 * L + lane],
        S[_RQ2 * L + lane], s, ell,
    )  # fmt: skip
    live = (s > ABS_FLOOR) & (s >= silence_ratio * env)  # else "xi near 0": undefined
    solved = live & solved
    sq = sqrt(z2)  # (NaN where z2 < 0: not solved, not used)
    wts = select(solved, w_ref * sq * Ts, 0.0)
    S[_RDEF * L + lane] = select(solved & (wts < math.pi), 1.0, 0.0)
    S[_RINV * L + lane], S[_RDET * L + lane], S[_RMU * L + lane] = inv, select(live, det, 0.0), mu
    S[_RZ0 * L + lane], S[_RZ1 * L + lane], S[_RZ2 * L + lane], S[_RSQ * L + lane] = z0, z1, z2, sq
    S[_RWTS * L + lane] = wts
    S[_RHALF * L + lane] = 0.5 * wts


@kernel(inline="always")
def _bank_read_out(S: np.ndarray, lane: int, w_ref: float) -> None:
    """Lane ``lane``: amplitude terms and prediction from the sine in row ``_RSH``, kept
    where the sample is defined (else as :func:`undefined_sample` leaves them)."""
    L = LANES
    defined = S[_RDEF * L + lane] != 0.0
    sh, ch, g = half_step_of(S[_RHALF * L + lane], S[_RSH * L + lane])
    a_sin, a_cos, y_pred = read_out(
        w_ref, S[_RS * L + lane], S[_RZ0 * L + lane], S[_RZ1 * L + lane], S[_RSQ * L + lane], sh, ch, g
    )
    S[_RASIN * L + lane] = select(defined, a_sin, 0.0)
    S[_RACOS * L + lane] = select(defined, a_cos, 0.0)
    S[_RYPRED * L + lane] = select(defined, y_pred, frozen(S[_RYPRED * L + lane]))  # (see lanes.frozen)
    S[_RPV * L + lane] = select(defined, 1.0, 0.0)


@kernel(inline="always")
def bank_good(
    S: np.ndarray, lane: int, settled: bool, n_settle: float, max_fit2: float, max_pred2: float, wts_lo: float,
    wts_hi: float,
) -> None:  # fmt: skip
    """Lane ``lane``: the fit residual's sums as the single kernel leaves them, ``good`` (also
    ``settled``: kkl-biased waits for its filters) and the run of good samples."""
    L = LANES
    defined = S[_RDEF * L + lane] != 0.0
    rr, ff = S[_RRR * L + lane], S[_RFF * L + lane]  # loaded whatever the lane, then kept or not
    rr = select(defined, rr, 0.0)
    ff = select(defined, ff, 1.0)
    S[_RRR * L + lane], S[_RFF * L + lane] = rr, ff
    good = defined & settled & consistent(
        S[_RMU * L + lane], rr, ff, max_fit2, S[_RE2 * L + lane], max_pred2, S[_RLEV * L + lane],
        S[_RJUMP * L + lane] != 0.0, S[_RWTS * L + lane], wts_lo, wts_hi,
    )  # fmt: skip
    S[_RGOOD * L + lane] = select(good, 1.0, 0.0)
    S[_RNG * L + lane] = count_good(good, S[_RNG * L + lane], n_settle)


@kernel(inline="always")
def bank_lane_row(
    S: np.ndarray, lane: int, roff: int
) -> tuple[bool, float, bool, float, float, float, float, float, float, float, float, float]:
    """Lane ``lane``'s values for :func:`record_row` / :func:`write_sample`: good, n_good,
    defined, omega Ts, A sin, A cos, offset, det, rr, ff, e2_avg, level. The offset from row
    ``roff``; ``roff < 0``: a model without one (0 where defined)."""
    L = LANES
    defined = S[_RDEF * L + lane] != 0.0
    offset = (0.0 if defined else np.nan) if roff < 0 else S[roff * L + lane]
    return (
        S[_RGOOD * L + lane] != 0.0, S[_RNG * L + lane], defined, S[_RWTS * L + lane], S[_RASIN * L + lane],
        S[_RACOS * L + lane], offset, S[_RDET * L + lane], S[_RRR * L + lane], S[_RFF * L + lane],
        S[_RE2 * L + lane], S[_RLEV * L + lane],
    )  # fmt: skip


_TAIL = (_RYP, _RHP, _RYPRED, _RPV, _RNG, _RENV, _RE2, _RLEV, _REF, _RES)  # the state's tail, in order


@kernel(inline="always")
def bank_arrays(
    n: int, nc: int, m: int, n_tail: int, rxi: int, last_only: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A bank's arrays for ``nc`` channels of ``n`` samples, ``m`` filters: ``out`` (nc, rows,
    5), ``extras`` (nc, rows, 3), ``sse`` (nc,), the new state (m + n_tail, nc), the work
    array S (rows up to ``rxi``, then the filters'), the lanes' samples and their rows (S and
    the samples with their rows on 64-byte boundaries, :func:`aligned_lanes`)."""
    rows = 1 if last_only else n
    return (
        np.empty((nc, rows, 5)), np.empty((nc, rows, 3)), np.empty(nc), np.empty((m + n_tail, nc)),
        aligned_lanes((rxi + m) * LANES), aligned_lanes(n * LANES), np.empty((LANES, 0 if last_only else n, RECORD_SIZE)),
    )  # fmt: skip


@kernel(inline="always")
def bank_load(
    S: np.ndarray, ys: np.ndarray, y: np.ndarray, state: np.ndarray, g: int, tail: tuple[int, ...], rxi: int,
    ry: int,
) -> int:  # fmt: skip
    """Channels g .. g + width - 1 into the lanes of a bank's work array ``S``: the filters'
    xi into rows ``rxi + i``, the state's scalars into the rows ``tail`` (in the state's
    order), their samples into ``ys`` (lane-major) and the first sample into row ``ry``.
    Lanes past the last channel run on zeros (never defined); their results are dropped.
    Returns ``width``: the channels loaded, up to LANES."""
    L = LANES
    width = int(min(L, y.shape[1] - g))
    m = state.shape[0] - len(tail)
    S[:] = 0.0
    ys[:] = 0.0
    for c in range(width):
        for i in range(m):
            S[(rxi + i) * L + c] = state[i, g + c]
        for j in range(len(tail)):
            S[tail[j] * L + c] = state[m + j, g + c]
    for k in range(y.shape[0]):
        for c in range(width):
            ys[k * L + c] = y[k, g + c]
    for lane in range(L):
        S[ry * L + lane] = ys[lane]
    return width


@kernel(inline="always")
def bank_sines(S: np.ndarray) -> None:
    """The sine of the first-order hold's correction for every lane, by
    :func:`sinewatch.estimators.detmath.sin` (plain arithmetic, no library call): the
    compiler vectorises it across the lanes, each lane rounding as the single kernel's."""
    L = LANES
    for lane in range(L):
        S[_RSH * L + lane] = detmath.sin(S[_RHALF * L + lane])


@kernel(inline="always")
def bank_next_sample(
    S: np.ndarray, ys: np.ndarray, rec: np.ndarray, k: int, width: int, last_only: bool, roff: int
) -> None:
    """After sample ``k`` of a bank's block: its rows kept (unless only the last is wanted;
    the offset from row ``roff``, see :func:`bank_lane_row`), then the next sample into row
    ``_RY``, in place once this one is done with it, as one vector store: the next sample's lane
    loop loads that row as a vector, which waits for 8 scalar stores to reach the cache (store
    forwarding fails) but is forwarded one vector store."""
    L = LANES
    if not last_only:
        for c in range(width):
            bank_record(rec[c], k, bank_lane_row(S, c, roff))
    nxt = min(k + 1, ys.shape[0] // L - 1) * L
    copy_lanes(S, _RY * L, ys, nxt)


@kernel(inline="always")
def bank_store(
    S: np.ndarray, new_state: np.ndarray, sse_out: np.ndarray, g: int, width: int, tail: tuple[int, ...],
    rxi: int, rsse: int,
) -> None:  # fmt: skip
    """The inverse of :func:`bank_load` after the block: each lane's state back into its
    channel's column of ``new_state``, its sum of squared prediction errors into ``sse_out``."""
    L = LANES
    m = new_state.shape[0] - len(tail)
    for c in range(width):
        sse_out[g + c] = S[rsse * L + c]
        for i in range(m):
            new_state[i, g + c] = S[(rxi + i) * L + c]
        for j in range(len(tail)):
            new_state[m + j, g + c] = S[tail[j] * L + c]


@kernel(inline="always")
def bank_write(
    out: np.ndarray, ext: np.ndarray, rec: np.ndarray, last_only: bool,
    row: tuple[bool, float, bool, float, float, float, float, float, float, float, float, float], n_settle: float,
    Ts: float, ell: float,
) -> None:  # fmt: skip
    """One channel's rows after a bank's block, by the single kernel's own functions: the
    last sample's from its lane's final values ``row``, or every sample's from ``rec``."""
    good, n_good, defined, wts, a_sin, a_cos, offset, det, rr, ff, e2_avg, lev = row
    write_rows(out, ext, rec, last_only, good, n_good, n_settle, defined, wts, Ts, a_sin, a_cos, offset, det, ell,
               rr, ff, e2_avg, lev)  # fmt: skip


@kernel(inline="always")
def bank_record(
    rec: np.ndarray,
    k: int,
    row: tuple[bool, float, bool, float, float, float, float, float, float, float, float, float],
) -> None:
    """Sample k's row of one lane (its values ``row``) kept in ``rec``, as :func:`record_sample`."""
    good, n_good, defined, wts, a_sin, a_cos, offset, det, rr, ff, e2_avg, lev = row
    record_row(rec, k, good, n_good, defined, wts, a_sin, a_cos, offset, det, rr, ff, e2_avg, lev)


def kkl_bank_kernel(
    y: np.ndarray, state: np.ndarray, lam: np.ndarray, fa: np.ndarray, fb0: np.ndarray, fb1: np.ndarray,
    consts: np.ndarray, last_only: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """:func:`kkl_kernel` for C channels at once (:func:`_kkl_bank`), the filters' constants
    passed as tuples: the compiled bank is specialised on their number m."""
    return _kkl_bank(y, state, lam, tuple(lam.tolist()), tuple(fa.tolist()), tuple(fb0.tolist()),
                     tuple(fb1.tolist()), consts, last_only)  # fmt: skip


@kernel
def _kkl_bank(
    y: np.ndarray, state: np.ndarray, lam: np.ndarray, lam_t: tuple[float, ...], fa: tuple[float, ...],
    fb0: tuple[float, ...], fb1: tuple[float, ...], consts: np.ndarray, last_only: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """:func:`kkl_kernel` for C channels at once: ``y`` (N, C), ``state`` (m + 10, C), one
    channel per column; returns ``out`` (C, rows, 5), ``extras`` (C, rows, 3), ``sse`` (C,)
    and the new state (m + 10, C). Channels go ``LANES`` at a time through a lane-major work
    array: each step of a sample is a loop over the lanes of literal trip count, over one
    array at constant offsets (the filters, the inverse map, the read-out, the fit residual,
    the sine of the first-order hold's correction: one vector each, 8 doubles wide where the
    CPU has AVX-512). The rows are written after the block, channel by channel, by the single
    kernel's own functions."""
    detmath.prefer_512_bit_vectors()  # 8 lanes: one 512-bit vector
    Ts, w_ref, ell, silence_ratio, env_decay, n_settle, max_fit2, max_pred2, avg_gain, wts_lo, wts_hi, fast_gain, slow_gain = (
        observer_constants(consts)
    )  # fmt: skip
    n, nc = y.shape
    m = lam.shape[0]
    s_ll = 0.0  # constant entries of L^T L, as kkl_kernel sums them
    s_l = 0.0
    for i in range(m):
        s_ll += lam[i] * lam[i]
        s_l += lam[i]
    s_11 = float(m)
    L = LANES
    out, ext, sse_out, new_state, S, ys, rec = bank_arrays(n, nc, m, len(_TAIL), _RXI, last_only)
    for g in range(0, nc, L):
        width = bank_load(S, ys, y, state, g, _TAIL, _RXI, _RY)
        for k in range(n):
            for lane in range(L):  # (12), the sums over the filters, the inverse map (8)-(9)
                _bank_filters(S, lane, lam_t, fa, fb0, fb1)
                _bank_front(S, lane, s_ll, s_l, s_11, ell, w_ref, Ts, silence_ratio, env_decay, avg_gain,
                            fast_gain, slow_gain)  # fmt: skip
            bank_sines(S)
            for lane in range(L):  # read-out, fit residual of (13), converged
                _bank_read_out(S, lane, w_ref)
                _bank_fit(S, lane, lam_t)
                bank_good(S, lane, True, n_settle, max_fit2, max_pred2, wts_lo, wts_hi)
            bank_next_sample(S, ys, rec, k, width, last_only, -1)
        for c in range(width):
            bank_write(out[g + c], ext[g + c], rec[c], last_only, bank_lane_row(S, c, -1), n_settle, Ts, ell)
        bank_store(S, new_state, sse_out, g, width, _TAIL, _RXI, _RSSE)
    return out, ext, sse_out, new_state
