"""Deterministic small linear algebra for estimator designs: matrix products, a linear solve and
single-output pole placement in plain Python floats, the same bits on every x86-64 host.

Why: numpy's matrix products (``@``, ``np.dot``) and scipy's ``place_poles`` (QR through
LAPACK) call OpenBLAS, which picks its kernels by CPU when it loads (AVX-512 on one host, AVX2
with FMA on another, SSE on a third): their results differ in the last bits from host to host,
and a design constant that differs in its last bit makes an estimator's outputs differ, so a
recording made on one host would not replay bit for bit on another. Here every sum of products
is ``math.fsum`` of the products (each product rounded once, the sum exactly rounded: no order,
no FMA contraction, no vector width can change it), and the elimination runs in a fixed order.
The designs are small (an observer of at most a few tens of states), so the cost is nothing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

Matrix = list[list[float]]


class SingularMatrixError(ArithmeticError):
    """The matrix of a solve has no usable pivot (singular, or numerically so)."""


def dot(u: Sequence[float], v: Sequence[float]) -> float:
    """sum_k u_k v_k, exactly rounded from the rounded products."""
    return math.fsum(a * b for a, b in zip(u, v, strict=True))


def matmul(a: Matrix, b: Matrix) -> Matrix:
    """The product a b of two lists of rows."""
    cols = [list(c) for c in zip(*b, strict=True)]
    return [[dot(row, col) for col in cols] for row in a]


def matvec(a: Matrix, x: Sequence[float]) -> list[float]:
    """The product a x."""
    return [dot(row, x) for row in a]


def identity(n: int) -> Matrix:
    return [[1.0 if i == j else 0.0 for j in range(n)] for i in range(n)]


def solve(a: Matrix, b: Sequence[float]) -> list[float]:
    """x with a x = b: Gaussian elimination with partial pivoting (the row of largest
    magnitude in the column, the first of equals), then back substitution. Raises
    SingularMatrixError when a pivot is zero or below n eps times the largest entry."""
    n = len(a)
    m = [[*row, float(bi)] for row, bi in zip(a, b, strict=True)]
    scale = max((abs(v) for row in a for v in row), default=0.0)
    tiny = n * 2.220446049250313e-16 * scale
    for col in range(n):
        piv = max(range(col, n), key=lambda r: abs(m[r][col]))
        if not abs(m[piv][col]) > tiny:
            raise SingularMatrixError(f"pivot {col}: expected |pivot| > {tiny:.3g}, got {m[piv][col]!r}")
        m[col], m[piv] = m[piv], m[col]
        for r in range(col + 1, n):
            f = m[r][col] / m[col][col]
            if f != 0.0:
                m[r] = [x - f * y for x, y in zip(m[r], m[col], strict=True)]
    x = [0.0] * n
    for i in range(n - 1, -1, -1):
        x[i] = (m[i][n] - dot(m[i][i + 1 : n], x[i + 1 :])) / m[i][i]
    return x


def poly_from_roots(roots: Sequence[float]) -> list[float]:
    """Coefficients [1, c_1, .., c_n] of prod_i (s - r_i), highest power first (real roots),
    multiplied out in the order given."""
    c = [1.0]
    for r in roots:
        c = [x - r * y for x, y in zip([*c, 0.0], [0.0, *c], strict=True)]
    return c


def observer_gain(f: Matrix, c: Sequence[float], poles: Sequence[float]) -> list[float]:
    """L with eig(F - L C) = poles for a single-output pair (F, C): Ackermann's formula
    (J. Ackermann, "Der Entwurf linearer Regelungssysteme im Zustandsraum",
    Regelungstechnik 20, 1972; the dual form for observers)::

        L = phi(F) O^-1 e_n,   O = [C; C F; ..; C F^(n-1)],   phi(s) = prod_i (s - p_i)

    with phi(F) by Horner's rule. Raises SingularMatrixError when (F, C) is not observable."""
    n = len(f)
    rows = [list(c)]
    for _ in range(n - 1):
        rows.append([dot(rows[-1], col) for col in zip(*f, strict=True)])  # C F^k = (C F^(k-1)) F
    e_n = [0.0] * (n - 1) + [1.0]
    q = solve(rows, e_n)  # O q = e_n
    coeffs = poly_from_roots(poles)
    phi = identity(n)
    for ck in coeffs[1:]:  # Horner: phi <- phi F + c_k I
        phi = matmul(phi, f)
        for i in range(n):
            phi[i][i] += ck
    return matvec(phi, q)
