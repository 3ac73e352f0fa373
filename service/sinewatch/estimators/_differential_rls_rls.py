"""``differential-rls``: the recursive least-squares update, eq. (12) of "Differential signal
model and sampling techniques for recursive (extended) least-squares estimation of frequency,
frequency derivatives, phase and amplitude": ``P <- (P - P x x' P / (f + x' P x)) / f``,
``theta <- theta + P x e / (f + x' P x)``, each complex sample two real updates.

Two forms of the same update stand here, on purpose. :func:`_rls_scalar` is the general one
(any number of parameters p, loops over P). :func:`_rls5` is one update for p = 5 (n = 2 with
the derivative model, the default), written out with P's upper triangle, theta and x in
registers: the loops' loads and stores through P cost about half the decimated step, and numba
does not keep a loop's array in registers; :func:`_rls_pair5` makes a decimated sample's pair
of updates with it. It performs the same operations in the same order as two calls of
:func:`_rls_scalar`, hence the same bits (the tests run both on the same data and compare them
bit for bit), so recordings replay the same whichever runs. Its rows are :func:`_row5` and
:func:`_shrink5` (the two loops' bodies), inlined: a change to the update must be made in both
forms.
"""

from __future__ import annotations

import math

import numpy as np

from sinewatch.estimators.base import kernel


@kernel(refcount=False)
def _rls_scalar(P: np.ndarray, theta: np.ndarray, x: np.ndarray, y: float, f: float, px: np.ndarray) -> None:
    """One scalar RLS update with forgetting f (eq. 12): P <- (P - P x x' P / (f + x' P x)) / f."""
    p = theta.shape[0]
    den = f
    e = y
    for a in range(p):
        s = 0.0
        for b in range(p):
            s += P[a, b] * x[b]
        px[a] = s
        den += x[a] * s
        e -= x[a] * theta[a]
    if not (den > 0.0):
        return
    ge = e / den
    inv_f = 1.0 / f
    for a in range(p):
        theta[a] += px[a] * ge
        pa = px[a] / den
        for b in range(a, p):
            v = (P[a, b] - pa * px[b]) * inv_f
            P[a, b] = v
            P[b, a] = v


@kernel(refcount=False)
def _row5(
    r0: float,
    r1: float,
    r2: float,
    r3: float,
    r4: float,
    x0: float,
    x1: float,
    x2: float,
    x3: float,
    x4: float,
    xa: float,
    ta: float,
    den: float,
    e: float,
) -> tuple[float, float, float]:
    """Row a of :func:`_rls_scalar`'s first loop for p = 5 (row ``r`` of P, ``xa`` = x[a], ``ta``
    = theta[a]): (P x)[a] summed in its order from 0.0, then ``den`` and ``e`` advanced."""
    s = 0.0
    s += r0 * x0
    s += r1 * x1
    s += r2 * x2
    s += r3 * x3
    s += r4 * x4
    return s, den + xa * s, e - xa * ta


@kernel(refcount=False)
def _shrink5(
    ta: float,
    qa: float,
    ge: float,
    den: float,
    inv_f: float,
    c0: float,
    c1: float,
    c2: float,
    c3: float,
    c4: float,
    q0: float,
    q1: float,
    q2: float,
    q3: float,
    q4: float,
) -> tuple[float, float, float, float, float, float]:
    """Row a of :func:`_rls_scalar`'s second loop for p = 5: theta[a] and the row's entries
    ``c`` of P (from the diagonal on), with ``q`` = (P x)[b] for the same columns."""
    pa = qa / den
    return (
        ta + qa * ge, (c0 - pa * q0) * inv_f, (c1 - pa * q1) * inv_f, (c2 - pa * q2) * inv_f,
        (c3 - pa * q3) * inv_f, (c4 - pa * q4) * inv_f,
    )  # fmt: skip


@kernel(refcount=False)
def _rls5(
    p00: float, p01: float, p02: float, p03: float, p04: float, p11: float, p12: float, p13: float, p14: float,
    p22: float, p23: float, p24: float, p33: float, p34: float, p44: float,
    t0: float, t1: float, t2: float, t3: float, t4: float,
    x0: float, x1: float, x2: float, x3: float, x4: float, y: float, f: float,
) -> tuple[float, float, float, float, float, float, float, float, float, float, float, float, float, float, float,
           float, float, float, float, float]:  # fmt: skip
    """One scalar update of :func:`_rls_scalar` for p = 5 on values in registers: P's upper
    triangle and theta in, the same updated out; the same operations in the same order."""
    den = f
    e = y
    q0, den, e = _row5(p00, p01, p02, p03, p04, x0, x1, x2, x3, x4, x0, t0, den, e)
    q1, den, e = _row5(p01, p11, p12, p13, p14, x0, x1, x2, x3, x4, x1, t1, den, e)
    q2, den, e = _row5(p02, p12, p22, p23, p24, x0, x1, x2, x3, x4, x2, t2, den, e)
    q3, den, e = _row5(p03, p13, p23, p33, p34, x0, x1, x2, x3, x4, x3, t3, den, e)
    q4, den, e = _row5(p04, p14, p24, p34, p44, x0, x1, x2, x3, x4, x4, t4, den, e)
    if den > 0.0:
        ge = e / den
        inv_f = 1.0 / f
        # row a of P from its diagonal on (rows shorter than 5 padded with 0.0, whose results
        # are dropped and the arithmetic on them removed by the compiler)
        t0, p00, p01, p02, p03, p04 = _shrink5(t0, q0, ge, den, inv_f, p00, p01, p02, p03, p04, q0, q1, q2, q3, q4)
        t1, p11, p12, p13, p14, _ = _shrink5(t1, q1, ge, den, inv_f, p11, p12, p13, p14, 0.0, q1, q2, q3, q4, 0.0)
        t2, p22, p23, p24, _, _ = _shrink5(t2, q2, ge, den, inv_f, p22, p23, p24, 0.0, 0.0, q2, q3, q4, 0.0, 0.0)
        t3, p33, p34, _, _, _ = _shrink5(t3, q3, ge, den, inv_f, p33, p34, 0.0, 0.0, 0.0, q3, q4, 0.0, 0.0, 0.0)
        t4, p44, _, _, _, _ = _shrink5(t4, q4, ge, den, inv_f, p44, 0.0, 0.0, 0.0, 0.0, q4, 0.0, 0.0, 0.0, 0.0)
    return p00, p01, p02, p03, p04, p11, p12, p13, p14, p22, p23, p24, p33, p34, p44, t0, t1, t2, t3, t4


@kernel(inline="always")
def _rls_pair5(
    P: np.ndarray, theta: np.ndarray, xr: np.ndarray, yr: float, f: float, xi: np.ndarray, yi: float
) -> None:
    """The two scalar updates of :func:`core_step` (xr with forgetting f, then xi without),
    as :func:`_rls_scalar` computes them, for p = 5 (n = 2 with the derivative model, the
    default): P (symmetric: its upper triangle), theta and x in registers (:func:`_rls5` twice;
    the second's f = 1 multiplies by 1.0, exact, as _rls_scalar does); the same operations in
    the same order, hence the same bits. Written out because numba keeps no loop's array in
    registers; a change to the update goes here and in _rls_scalar."""
    p00, p01, p02, p03, p04, p11, p12, p13, p14, p22, p23, p24, p33, p34, p44, t0, t1, t2, t3, t4 = _rls5(
        P[0, 0], P[0, 1], P[0, 2], P[0, 3], P[0, 4], P[1, 1], P[1, 2], P[1, 3], P[1, 4], P[2, 2], P[2, 3], P[2, 4],
        P[3, 3], P[3, 4], P[4, 4], theta[0], theta[1], theta[2], theta[3], theta[4],
        xr[0], xr[1], xr[2], xr[3], xr[4], yr, f,
    )  # fmt: skip
    p00, p01, p02, p03, p04, p11, p12, p13, p14, p22, p23, p24, p33, p34, p44, t0, t1, t2, t3, t4 = _rls5(
        p00, p01, p02, p03, p04, p11, p12, p13, p14, p22, p23, p24, p33, p34, p44, t0, t1, t2, t3, t4,
        xi[0], xi[1], xi[2], xi[3], xi[4], yi, 1.0,
    )  # fmt: skip
    P[0, 0] = p00
    P[0, 1] = p01
    P[1, 0] = p01
    P[0, 2] = p02
    P[2, 0] = p02
    P[0, 3] = p03
    P[3, 0] = p03
    P[0, 4] = p04
    P[4, 0] = p04
    P[1, 1] = p11
    P[1, 2] = p12
    P[2, 1] = p12
    P[1, 3] = p13
    P[3, 1] = p13
    P[1, 4] = p14
    P[4, 1] = p14
    P[2, 2] = p22
    P[2, 3] = p23
    P[3, 2] = p23
    P[2, 4] = p24
    P[4, 2] = p24
    P[3, 3] = p33
    P[3, 4] = p34
    P[4, 3] = p34
    P[4, 4] = p44
    theta[0], theta[1], theta[2], theta[3], theta[4] = t0, t1, t2, t3, t4


@kernel(inline="always")
def _all_finite_sum(theta: np.ndarray, P: np.ndarray) -> bool:
    """Whether sum(theta) + sum(P), added in row order, is finite. Every entry finite and below
    1e300 in magnitude cannot overflow (checked row by row, independent chains); otherwise the
    sum itself decides, in the original order (NaN, Inf or an overflow: not finite)."""
    p = theta.shape[0]
    small = True
    for q in range(p):
        row = abs(theta[q]) < 1e300
        for r in range(p):
            row = row and abs(P[q, r]) < 1e300
        small = small and row
    if small:
        return True
    acc = 0.0
    for q in range(p):
        acc += theta[q]
        for r in range(p):
            acc += P[q, r]
    return math.isfinite(acc)
