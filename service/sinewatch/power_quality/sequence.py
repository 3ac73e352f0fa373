"""Symmetrical components of three phasors (Fortescue) and the unbalance ratios of
IEC 61000-4-30.

References:

* [F] C. L. Fortescue, "Method of symmetrical co-ordinates applied to the solution of
  polyphase networks", Transactions of the AIEE 37(2), 1027-1140, 1918: the transform
  below (the three-phase case of his n-phase decomposition).
* [4-30] IEC 61000-4-30:2015, clause 5.7 (supply voltage unbalance, class A: the method
  of symmetrical components on the fundamental; ``u2`` in the range 1-5 % with an
  uncertainty of +-0.15 percentage points), as recalled; check the standard before
  quoting compliance.

With the operator ``a = exp(j 2 pi / 3)`` and the phase phasors ``V_a, V_b, V_c``
(complex, any one convention for all three: RMS or peak, sine or cosine reference):

(F1) ``V_0 = (V_a + V_b + V_c) / 3``            zero sequence
(F2) ``V_1 = (V_a + a V_b + a^2 V_c) / 3``      positive sequence (a-b-c order)
(F3) ``V_2 = (V_a + a^2 V_b + a V_c) / 3``      negative sequence
(U)  ``u_2 = |V_2| / |V_1|``, ``u_0 = |V_0| / |V_1|`` [4-30 5.7.1] (ratios; x 100 for %),
     NaN when ``V_1 = 0``.

A balanced positive-sequence set ``V_b = a^2 V_a``, ``V_c = a V_a`` gives ``V_1 = V_a``,
``V_0 = V_2 = 0``. The inverse, ``V_a = V_0 + V_1 + V_2``, ``V_b = V_0 + a^2 V_1 + a V_2``,
``V_c = V_0 + a V_1 + a^2 V_2``, is :func:`phases_from_sequence` (used to build test
signals with exact truth).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

A = np.exp(2j * np.pi / 3.0)  # the Fortescue operator a


@dataclass(frozen=True)
class SequenceComponents:
    """Zero, positive and negative sequence phasors (same shape as the inputs) and the
    unbalance ratios."""

    zero: np.ndarray
    positive: np.ndarray
    negative: np.ndarray

    @property
    def u2(self) -> np.ndarray:
        """(U) negative-sequence unbalance |V2| / |V1| (NaN where V1 = 0)."""
        return _ratio(self.negative, self.positive)

    @property
    def u0(self) -> np.ndarray:
        """(U) zero-sequence unbalance |V0| / |V1| (NaN where V1 = 0)."""
        return _ratio(self.zero, self.positive)


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    d = np.abs(den)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(d > 0.0, np.abs(num) / np.where(d > 0.0, d, 1.0), np.nan)


def symmetrical_components(
    va: np.ndarray | complex, vb: np.ndarray | complex, vc: np.ndarray | complex
) -> SequenceComponents:
    """(F1)-(F3) for phasors (scalars or arrays of one shape)."""
    a, b, c = (np.asarray(v, dtype=np.complex128) for v in (va, vb, vc))
    return SequenceComponents(
        zero=(a + b + c) / 3.0,  # (F1)
        positive=(a + A * b + A * A * c) / 3.0,  # (F2)
        negative=(a + A * A * b + A * c) / 3.0,  # (F3)
    )


def phases_from_sequence(
    v0: np.ndarray | complex, v1: np.ndarray | complex, v2: np.ndarray | complex
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inverse of (F1)-(F3): the phase phasors of given sequence phasors."""
    z, p, n = (np.asarray(v, dtype=np.complex128) for v in (v0, v1, v2))
    return z + p + n, z + A * A * p + A * n, z + A * p + A * A * n
