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
bit for bit), so recordings replay the same whichever runs. Its repeated lines (five rows) are
that unrolling, not copied logic: a change to the update must be made in both functions.
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


@kernel(inline="always")
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
    s = 0.0
    s += p00 * x0
    s += p01 * x1
    s += p02 * x2
    s += p03 * x3
    s += p04 * x4
    q0 = s
    den += x0 * s
    e -= x0 * t0
    s = 0.0
    s += p01 * x0
    s += p11 * x1
    s += p12 * x2
    s += p13 * x3
    s += p14 * x4
    q1 = s
    den += x1 * s
    e -= x1 * t1
    s = 0.0
    s += p02 * x0
    s += p12 * x1
    s += p22 * x2
    s += p23 * x3
    s += p24 * x4
    q2 = s
    den += x2 * s
    e -= x2 * t2
    s = 0.0
    s += p03 * x0
    s += p13 * x1
    s += p23 * x2
    s += p33 * x3
    s += p34 * x4
    q3 = s
    den += x3 * s
    e -= x3 * t3
    s = 0.0
    s += p04 * x0
    s += p14 * x1
    s += p24 * x2
    s += p34 * x3
    s += p44 * x4
    q4 = s
    den += x4 * s
    e -= x4 * t4
    if den > 0.0:
        ge = e / den
        inv_f = 1.0 / f
        t0 += q0 * ge
        pa = q0 / den
        p00 = (p00 - pa * q0) * inv_f
        p01 = (p01 - pa * q1) * inv_f
        p02 = (p02 - pa * q2) * inv_f
        p03 = (p03 - pa * q3) * inv_f
        p04 = (p04 - pa * q4) * inv_f
        t1 += q1 * ge
        pa = q1 / den
        p11 = (p11 - pa * q1) * inv_f
        p12 = (p12 - pa * q2) * inv_f
        p13 = (p13 - pa * q3) * inv_f
        p14 = (p14 - pa * q4) * inv_f
        t2 += q2 * ge
        pa = q2 / den
        p22 = (p22 - pa * q2) * inv_f
        p23 = (p23 - pa * q3) * inv_f
        p24 = (p24 - pa * q4) * inv_f
        t3 += q3 * ge
        pa = q3 / den
        p33 = (p33 - pa * q3) * inv_f
        p34 = (p34 - pa * q4) * inv_f
        t4 += q4 * ge
        pa = q4 / den
        p44 = (p44 - pa * q4) * inv_f
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
