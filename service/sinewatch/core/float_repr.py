"""Python's ``repr`` of many floats in one compiled call: the shortest decimal that reads
back as the same double, written as ``repr`` writes it, byte for byte.

Why: an Estimate's JSON writes each float as ``repr`` (what the pydantic model, replay and
every recording hold), and CPython's ``repr`` of a float (David Gay's ``dtoa``, mode 0, with
big-integer arithmetic) costs about 0.5-1.7 us a float: most of an Estimate's bytes' time.
Here the digits come from Ryu (Ulf Adams, "Ryu: fast float-to-string conversion", PLDI 2018,
Sec. 3, the d2d step with 128-bit products of 125-bit powers of five), which gives the same
digits as ``dtoa`` mode 0: the shortest that round-trip, the nearest to the double among
those, a tie to the even digit; tests/test_float_repr.py compares the two on every exponent and on millions of
random doubles.

The layout is CPython's ``float_repr_style = 'short'`` (``PyOS_double_to_string`` with
``'r'``): with ``decpt`` the decimal point's position (value = 0.d1d2... x 10^decpt), positional
while ``-4 < decpt <= 16`` (``".0"`` added to an integer), otherwise ``d1.d2...e+XX`` with at
least two exponent digits; ``nan``, ``inf``, ``-inf``, ``-0.0`` as ``repr`` writes them.
"""

from __future__ import annotations

import numpy as np

from sinewatch.estimators.base import kernel

_POW5_INV_BITCOUNT = 125
_POW5_BITCOUNT = 125
_MASK64 = (1 << 64) - 1


def _pow5_tables() -> tuple[np.ndarray, np.ndarray]:
    """Ryu's tables, exactly (Python integers): ``inv[q]`` = floor(2^(bits(5^q) - 1 + 125) / 5^q)
    + 1 for q < 342 and ``pos[i]`` = 5^i scaled to 125 bits (truncated) for i < 326, each as
    (low 64 bits, high 64 bits)."""
    inv = np.zeros((342, 2), dtype=np.uint64)
    for q in range(342):
        p = 5**q
        v = (1 << (p.bit_length() - 1 + _POW5_INV_BITCOUNT)) // p + 1
        inv[q] = (v & _MASK64, v >> 64)
    pos = np.zeros((326, 2), dtype=np.uint64)
    for i in range(326):
        p = 5**i
        shift = p.bit_length() - _POW5_BITCOUNT
        v = p >> shift if shift >= 0 else p << -shift
        pos[i] = (v & _MASK64, v >> 64)
    return inv, pos


_POW5_INV_SPLIT, _POW5_SPLIT = _pow5_tables()

# typed constants: numba promotes a uint64 combined with an int64 to float64
_U0 = np.uint64(0)
_U1 = np.uint64(1)
_U2 = np.uint64(2)
_U4 = np.uint64(4)
_U5 = np.uint64(5)
_U10 = np.uint64(10)
_U32 = np.uint64(32)
_U64 = np.uint64(64)
_M32 = np.uint64(0xFFFFFFFF)
_MANTISSA_MASK = np.uint64((1 << 52) - 1)
_HIDDEN = np.uint64(1 << 52)
MAX_CHARS = 25  # the longest repr of a double: "-1.2345678901234567e-308" is 24


@kernel(inline="always", refcount=False)
def _umul128_hi_lo(a: np.uint64, b: np.uint64) -> tuple[np.uint64, np.uint64]:
    """The 128-bit product a b as (low, high) 64-bit words, from 32-bit halves."""
    a_lo, a_hi, b_lo, b_hi = a & _M32, a >> _U32, b & _M32, b >> _U32
    b00 = a_lo * b_lo
    b01 = a_lo * b_hi
    b10 = a_hi * b_lo
    b11 = a_hi * b_hi
    mid1 = b10 + (b00 >> _U32)
    mid2 = b01 + (mid1 & _M32)
    return ((mid2 & _M32) << _U32) | (b00 & _M32), b11 + (mid1 >> _U32) + (mid2 >> _U32)


@kernel(inline="always", refcount=False)
def _mul_shift(m: np.uint64, lo: np.uint64, hi: np.uint64, j: int) -> np.uint64:
    """(m (hi 2^64 + lo)) >> j for m < 2^55 and 64 < j < 128 (Ryu's mulShift64)."""
    low1, high1 = _umul128_hi_lo(m, hi)
    _, high0 = _umul128_hi_lo(m, lo)
    total = high0 + low1
    if total < high0:
        high1 += _U1
    dist = np.uint64(j - 64)
    return (high1 << (_U64 - dist)) | (total >> dist)


@kernel(inline="always", refcount=False)
def _pow5_factor(value: np.uint64) -> int:
    count = 0
    while value > _U0:
        q = value // _U5
        if value - _U5 * q != _U0:
            break
        value = q
        count += 1
    return count


@kernel(inline="always", refcount=False)
def _pow5_bits(e: int) -> int:
    return ((e * 1217359) >> 19) + 1  # ceil(log2(5^e)) for e > 0, 1 for e = 0


@kernel(refcount=False)
def _shortest(ieee_mantissa: np.uint64, ieee_exponent: int) -> tuple[np.uint64, int]:
    """The shortest round-trip digits of a finite, non-zero double and their power of ten:
    (digits, e10), value = digits x 10^e10 (Ryu's d2d, Adams 2018, Sec. 3)."""
    if ieee_exponent == 0:
        e2 = 1 - 1023 - 52 - 2
        m2 = ieee_mantissa
    else:
        e2 = ieee_exponent - 1023 - 52 - 2
        m2 = _HIDDEN | ieee_mantissa
    even = (m2 & _U1) == _U0
    mv = _U4 * m2
    mm_shift = np.uint64(1 if (ieee_mantissa != _U0 or ieee_exponent <= 1) else 0)
    vm_trailing = False
    vr_trailing = False
    if e2 >= 0:
        q = ((e2 * 78913) >> 18) - (1 if e2 > 3 else 0)  # log10(2^e2), one less past 3
        e10 = q
        k = _POW5_INV_BITCOUNT + _pow5_bits(q) - 1
        i = -e2 + q + k
        lo, hi = _POW5_INV_SPLIT[q, 0], _POW5_INV_SPLIT[q, 1]
        vr = _mul_shift(mv, lo, hi, i)
        vp = _mul_shift(mv + _U2, lo, hi, i)
        vm = _mul_shift(mv - _U1 - mm_shift, lo, hi, i)
        if q <= 21:
            if mv % _U5 == _U0:
                vr_trailing = _pow5_factor(mv) >= q
            elif even:
                vm_trailing = _pow5_factor(mv - _U1 - mm_shift) >= q
            elif _pow5_factor(mv + _U2) >= q:
                vp -= _U1
    else:
        q = ((-e2 * 732923) >> 20) - (1 if -e2 > 1 else 0)  # log10(5^-e2), one less past 1
        e10 = q + e2
        i = -e2 - q
        k = _pow5_bits(i) - _POW5_BITCOUNT
        j = q - k
        lo, hi = _POW5_SPLIT[i, 0], _POW5_SPLIT[i, 1]
        vr = _mul_shift(mv, lo, hi, j)
        vp = _mul_shift(mv + _U2, lo, hi, j)
        vm = _mul_shift(mv - _U1 - mm_shift, lo, hi, j)
        if q <= 1:
            vr_trailing = True  # mv has at least q trailing zero bits
            if even:
                vm_trailing = mm_shift == _U1
            else:
                vp -= _U1
        elif q < 63:
            vr_trailing = (mv & ((_U1 << np.uint64(q)) - _U1)) == _U0
    removed = 0
    last_removed = np.uint64(0)
    if vm_trailing or vr_trailing:  # the general case (rare)
        while vp // _U10 > vm // _U10:
            vm_trailing = vm_trailing and vm % _U10 == _U0
            vr_trailing = vr_trailing and last_removed == _U0
            last_removed = vr % _U10
            vr, vp, vm = vr // _U10, vp // _U10, vm // _U10
            removed += 1
        if vm_trailing:
            while vm % _U10 == _U0:
                vr_trailing = vr_trailing and last_removed == _U0
                last_removed = vr % _U10
                vr, vp, vm = vr // _U10, vp // _U10, vm // _U10
                removed += 1
        if vr_trailing and last_removed == _U5 and vr % _U2 == _U0:
            last_removed = np.uint64(4)  # exactly halfway: to the even digit
        up = (vr == vm and (not even or not vm_trailing)) or last_removed >= _U5
        output = vr + (_U1 if up else _U0)
    else:
        round_up = False
        while vp // _U10 > vm // _U10:
            round_up = bool(vr % _U10 >= _U5)
            vr, vp, vm = vr // _U10, vp // _U10, vm // _U10
            removed += 1
        output = vr + (_U1 if (vr == vm or round_up) else _U0)
    return output, e10 + removed


@kernel(refcount=False)
def _write_one(bits: np.uint64, out: np.ndarray, at: int, digits: np.ndarray) -> int:
    """``repr`` of the double whose IEEE 754 bits are ``bits``, as ASCII at ``out[at:]``;
    returns the index after it."""
    negative = (bits >> np.uint64(63)) != _U0
    ieee_exponent = int((bits >> np.uint64(52)) & np.uint64(0x7FF))
    ieee_mantissa = bits & _MANTISSA_MASK
    if ieee_exponent == 0x7FF:
        if ieee_mantissa != _U0:
            out[at], out[at + 1], out[at + 2] = 110, 97, 110  # nan (repr has no sign for it)
            return at + 3
        if negative:
            out[at] = 45
            at += 1
        out[at], out[at + 1], out[at + 2] = 105, 110, 102  # inf
        return at + 3
    if negative:
        out[at] = 45  # -
        at += 1
    if ieee_exponent == 0 and ieee_mantissa == _U0:
        out[at], out[at + 1], out[at + 2] = 48, 46, 48  # 0.0
        return at + 3
    output, e10 = _shortest(ieee_mantissa, ieee_exponent)
    n = 0
    while output > _U0:  # the digits, last first
        digits[n] = 48 + int(output % _U10)
        output //= _U10
        n += 1
    decpt = n + e10
    if -4 < decpt <= 16:  # positional
        if decpt <= 0:
            out[at], out[at + 1] = 48, 46  # 0.
            at += 2
            for _ in range(-decpt):
                out[at] = 48
                at += 1
            for d in range(n - 1, -1, -1):
                out[at] = digits[d]
                at += 1
        elif decpt < n:
            for d in range(n - 1, n - 1 - decpt, -1):
                out[at] = digits[d]
                at += 1
            out[at] = 46
            at += 1
            for d in range(n - 1 - decpt, -1, -1):
                out[at] = digits[d]
                at += 1
        else:
            for d in range(n - 1, -1, -1):
                out[at] = digits[d]
                at += 1
            for _ in range(decpt - n):
                out[at] = 48
                at += 1
            out[at], out[at + 1] = 46, 48  # .0
            at += 2
        return at
    out[at] = digits[n - 1]  # d1[.d2...]e+XX
    at += 1
    if n > 1:
        out[at] = 46
        at += 1
        for d in range(n - 2, -1, -1):
            out[at] = digits[d]
            at += 1
    exp10 = decpt - 1
    out[at] = 101  # e
    out[at + 1] = 45 if exp10 < 0 else 43
    at += 2
    exp10 = abs(exp10)
    if exp10 >= 100:
        out[at] = 48 + exp10 // 100
        at += 1
    out[at], out[at + 1] = 48 + (exp10 // 10) % 10, 48 + exp10 % 10
    return at + 2


@kernel
def repr_floats_kernel(bits: np.ndarray) -> np.ndarray:
    """``",".join(repr(v) for v in values)`` as ASCII bytes (uint8), ``bits`` the values'
    IEEE 754 bits (``values.view(np.uint64)``)."""
    n = bits.shape[0]
    out = np.empty(max(1, n * (MAX_CHARS + 1)), dtype=np.uint8)
    digits = np.empty(20, dtype=np.uint8)
    at = 0
    for i in range(n):
        if i:
            out[at] = 44  # ,
            at += 1
        at = _write_one(bits[i], out, at, digits)
    return out[:at]


def repr_floats(values: np.ndarray) -> list[str]:
    """``[repr(v) for v in values]`` of a float64 array, in one compiled call."""
    if values.shape[0] == 0:
        return []
    bits = np.ascontiguousarray(values, dtype=np.float64).view(np.uint64)
    return repr_floats_kernel(bits).tobytes().decode("ascii").split(",")


# one float's repr into a byte buffer, for kernels that write whole messages (an Estimate's)
write_repr = _write_one

__all__ = ["MAX_CHARS", "repr_floats", "repr_floats_kernel", "write_repr"]
