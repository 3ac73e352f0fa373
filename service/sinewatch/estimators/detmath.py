"""Deterministic transcendental functions for the kernels: sin, cos, tan, log and exp written in
plain IEEE 754 arithmetic (additions, multiplications, divisions, ``fma`` and integer operations
on the bits), with no call to the C library and no fast-math.

Why: an estimator's bank must give each channel the bits the single-channel kernel gives it.
``math.sin`` and friends compile to a call of the C library, which LLVM does not vectorise (numba
has no SVML here, and a vectorised library would round differently from the scalar one), so a
bank with a library call per lane and sample keeps that step scalar. These functions are
straight-line code (selects instead of branches), so LLVM vectorises them across a bank's lanes,
and every lane rounds exactly as the scalar path does: the same operations in the same order,
each correctly rounded by the hardware whatever the vector width.

The algorithms are those of fdlibm (Sun Microsystems, 1993; as in FreeBSD's and musl's libm):
Cody and Waite's additive range reduction (W. J. Cody and W. Waite, *Software Manual for the
Elementary Functions*, 1980, ch. 8 and 6), then fdlibm's minimax polynomials on the reduced
range (``k_sin.c``, ``k_cos.c``, ``e_log.c``, ``e_exp.c``), evaluated with ``fma`` on the
Horner steps. Accuracy against numpy (which calls the C library), tested in
``tests/test_detmath.py`` over dense grids: at most 1 ulp from the C library's value for sin,
cos, log and exp, 3 for tan (the quotient of the two kernels, each within 1).

Domain of the trigonometric functions: the reduction by pi/2 is exact to ~2^-100 for
``|x| <= TRIG_MAX`` (2^20 pi/2, about 1.6e6 rad): beyond it these return NaN rather than a value
of unknown accuracy (the C library switches to Payne and Hanek's reduction there, a loop this
module does not have). The kernels call them with bounded arguments (a half step's phase, half a
sample's angle).
"""

from __future__ import annotations

from typing import Any

import numba
from llvmlite import ir as llvm_ir
from numba.extending import intrinsic

from sinewatch.estimators.base import fma, kernel

TRIG_MAX = 1647099.3291652855  # 2^20 * pi / 2: n * PIO2_1 exact for |n| <= 2^20

# pi/2 in three 33-bit pieces and their tails (fdlibm e_rem_pio2.c): n * PIO2_k is exact
_INVPIO2 = 6.36619772367581382433e-01
_PIO2_1 = 1.57079632673412561417e00
_PIO2_2 = 6.07710050630396597660e-11
_PIO2_2T = 2.02226624879595063154e-21
_PIO2_3 = 2.02226624871116645580e-21
_PIO2_3T = 8.47842766036889956997e-32
_ROUND = 6755399441055744.0  # 1.5 * 2^52: (x + _ROUND) - _ROUND rounds x to an integer (|x| < 2^51)

# sin on [-pi/4, pi/4] (fdlibm k_sin.c)
_S1, _S2, _S3 = -1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04
_S4, _S5, _S6 = 2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10
# cos on [-pi/4, pi/4] (fdlibm k_cos.c)
_C1, _C2, _C3 = 4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05
_C4, _C5, _C6 = -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11

# log (fdlibm e_log.c): log(1+f) = f - f^2/2 + s (f^2/2 + R(s^2)), s = f / (2 + f)
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
_LG1 = 6.666666666666735130e-01
_LG2 = 3.999999999940941908e-01
_LG3 = 2.857142874366239149e-01
_LG4 = 2.222219843214978396e-01
_LG5 = 1.818357216161805012e-01
_LG6 = 1.531383769920937332e-01
_LG7 = 1.479819860511658591e-01
_TWO54 = 18014398509481984.0  # 2^54: scales a subnormal argument to a normal one

# exp (fdlibm e_exp.c)
_INVLN2 = 1.44269504088896338700e00
_EXP_P1 = 1.66666666666666019037e-01
_EXP_P2 = -2.77777777770155933842e-03
_EXP_P3 = 6.61375632143793436117e-05
_EXP_P4 = -1.65339022054652515390e-06
_EXP_P5 = 4.13813679705723846039e-08
_EXP_OVER = 7.09782712893383973096e02  # above: +inf
_EXP_UNDER = -7.45133219101941108420e02  # below: +0

_INF = float("inf")
_NAN = float("nan")


@intrinsic
def _bits_intrinsic(typingctx: Any, x: Any) -> Any:
    sig = numba.types.int64(numba.types.float64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return builder.bitcast(args[0], llvm_ir.IntType(64))

    return sig, codegen


@intrinsic
def _float_intrinsic(typingctx: Any, i: Any) -> Any:
    sig = numba.types.float64(numba.types.int64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return builder.bitcast(args[0], llvm_ir.DoubleType())

    return sig, codegen


@kernel(inline="always", refcount=False)
def bits(x: float) -> int:
    """The IEEE 754 bit pattern of ``x`` as a signed 64-bit integer (no conversion)."""
    return _bits_intrinsic(x)  # type: ignore[call-arg]  # numba passes the typing context


@kernel(inline="always", refcount=False)
def from_bits(i: int) -> float:
    """The float64 whose bit pattern is ``i`` (the inverse of :func:`bits`)."""
    return _float_intrinsic(i)  # type: ignore[call-arg]  # numba passes the typing context


@kernel(inline="always", refcount=False)
def _pow2(k: int) -> float:
    """2^k for -1022 <= k <= 1023, built from its exponent bits."""
    return from_bits((k + 1023) << 52)


@kernel(inline="always", refcount=False)
def _reduce(x: float) -> tuple[float, float, int]:
    """x = n pi/2 + (y + yt), |y + yt| <= ~pi/4 (fdlibm's medium reduction, all three steps:
    branch-free, exact to ~2^-100 relative to pi/2 for |x| <= TRIG_MAX)."""
    fn = (x * _INVPIO2 + _ROUND) - _ROUND
    r = x - fn * _PIO2_1  # exact: n * PIO2_1 has at most 53 bits
    t = r
    w = fn * _PIO2_2
    r = t - w
    w = fn * _PIO2_2T - ((t - r) - w)
    t = r
    w = fn * _PIO2_3
    r = t - w
    w = fn * _PIO2_3T - ((t - r) - w)
    y = r - w
    yt = (r - y) - w
    return y, yt, int(fn)


@kernel(inline="always", refcount=False)
def _k_sin(x: float, y: float) -> float:
    """sin(x + y) for |x + y| <= ~pi/4, y the tail of x (fdlibm k_sin.c, < 1 ulp)."""
    z = x * x
    v = z * x
    r = fma(z, fma(z, fma(z, fma(z, _S6, _S5), _S4), _S3), _S2)
    return x - ((z * (0.5 * y - v * r) - y) - v * _S1)


@kernel(inline="always", refcount=False)
def _k_cos(x: float, y: float) -> float:
    """cos(x + y) for |x + y| <= ~pi/4, y the tail of x (FreeBSD's k_cos.c, < 1 ulp)."""
    z = x * x
    w = z * z
    r = z * fma(z, fma(z, _C3, _C2), _C1) + w * w * fma(z, fma(z, _C6, _C5), _C4)
    hz = 0.5 * z
    w = 1.0 - hz
    return w + (((1.0 - w) - hz) + (z * r - x * y))


@kernel(inline="always", refcount=False)
def sincos(x: float) -> tuple[float, float]:
    """(sin x, cos x), each within 1 ulp of the C library's for |x| <= TRIG_MAX;
    NaN for larger |x|, infinities and NaN."""
    big = not abs(x) <= TRIG_MAX  # also NaN
    xr = 0.0 if big else x
    y, yt, n = _reduce(xr)
    s = _k_sin(y, yt)
    c = _k_cos(y, yt)
    q = n & 3  # sin(y + q pi/2): q = 0 (s, c), 1 (c, -s), 2 (-s, -c), 3 (-c, s)
    sn = c if q & 1 else s
    cn = s if q & 1 else c
    sn = -sn if q & 2 else sn
    cn = -cn if (q + 1) & 2 else cn
    return (_NAN if big else sn), (_NAN if big else cn)


@kernel(inline="always", refcount=False)
def sin(x: float) -> float:
    """sin x within 1 ulp of the C library's for |x| <= TRIG_MAX, NaN beyond (see :func:`sincos`)."""
    return sincos(x)[0]


@kernel(inline="always", refcount=False)
def cos(x: float) -> float:
    """cos x within 1 ulp of the C library's for |x| <= TRIG_MAX, NaN beyond (see :func:`sincos`)."""
    return sincos(x)[1]


@kernel(inline="always", refcount=False)
def tan(x: float) -> float:
    """tan x within 3 ulp of the C library's for |x| <= TRIG_MAX, NaN beyond: the quotient of
    the two kernels on the reduced argument (sin/cos, or -cos/sin in the odd quadrants)."""
    big = not abs(x) <= TRIG_MAX
    xr = 0.0 if big else x
    y, yt, n = _reduce(xr)
    s = _k_sin(y, yt)
    c = _k_cos(y, yt)
    odd = n & 1
    num = -c if odd else s
    den = s if odd else c
    return _NAN if big else num / den


@kernel(inline="always", refcount=False)
def log(x: float) -> float:
    """The natural logarithm within 1 ulp (fdlibm e_log.c): -inf at +-0, NaN below 0 and at
    NaN, +inf at +inf. Subnormal arguments are scaled by 2^54 first."""
    sub = x < 2.2250738585072014e-308  # below the smallest normal (and <= 0, NaN: fixed below)
    xs = x * _TWO54 if sub else x
    k0 = -54 if sub else 0
    hx = bits(xs) + (0x3FF0000000000000 - 0x3FE6A09E00000000)  # 1 + f in [sqrt(2)/2, sqrt(2))
    k = k0 + ((hx >> 52) & 0x7FF) - 1023
    m = (hx & 0x000FFFFFFFFFFFFF) + 0x3FE6A09E00000000
    f = from_bits(m) - 1.0
    hfsq = 0.5 * f * f
    s = f / (2.0 + f)
    z = s * s
    w = z * z
    t1 = w * fma(w, fma(w, _LG6, _LG4), _LG2)
    t2 = z * fma(w, fma(w, fma(w, _LG7, _LG5), _LG3), _LG1)
    dk = float(k)
    r = s * (hfsq + (t2 + t1)) + dk * _LN2_LO - hfsq + f + dk * _LN2_HI
    r = _INF if x == _INF else r
    r = -_INF if x == 0.0 else r
    return _NAN if (x < 0.0 or x != x) else r


@kernel(inline="always", refcount=False)
def exp(x: float) -> float:
    """e^x within 1 ulp (fdlibm e_exp.c): +inf above ~709.78, +0 below ~-745.13, NaN at NaN."""
    over = x > _EXP_OVER
    under = x < _EXP_UNDER
    xr = 0.0 if (over or under or x != x) else x
    fk = (xr * _INVLN2 + _ROUND) - _ROUND
    hi = xr - fk * _LN2_HI  # exact: |k| < 1100 and LN2_HI has 32 bits
    lo = fk * _LN2_LO
    r = hi - lo
    t = r * r
    c = r - t * fma(t, fma(t, fma(t, fma(t, _EXP_P5, _EXP_P4), _EXP_P3), _EXP_P2), _EXP_P1)
    y = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi)
    k = int(fk)
    ka = k >> 1  # 2^k in two normal factors: one rounding, also into the subnormals
    y = y * _pow2(ka) * _pow2(k - ka)
    y = _INF if over else y
    y = 0.0 if under else y
    return x if x != x else y


@intrinsic
def _prefer_512_intrinsic(typingctx: Any) -> Any:
    sig = numba.types.none()

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        # a string attribute, which llvmlite's checked ``add`` does not know: the set's own add
        set.add(builder.function.attributes, '"prefer-vector-width"="512"')
        return context.get_dummy_value()

    return sig, codegen


@kernel(inline="always", refcount=False)
def prefer_512_bit_vectors() -> None:
    """Let LLVM vectorise the calling kernel's loops with 512-bit vectors (8 doubles) on a CPU
    with AVX-512: it marks the compiled function ``"prefer-vector-width"="512"`` (clang's
    ``-mprefer-vector-width=512``), overriding the 256-bit preference LLVM's tuning gives
    Intel's AVX-512 cores. For a kernel only: it changes no value (every lane's operations are
    the same IEEE 754 operations at either width), not numba's cache key, and nothing on a CPU
    without AVX-512. Called first in a bank kernel whose lanes are 8 channels."""
    _prefer_512_intrinsic()  # type: ignore[call-arg]  # numba passes the typing context
