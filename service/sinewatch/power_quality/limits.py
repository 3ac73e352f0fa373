"""Accuracy limits of IEC 61000-4-7 class I (harmonics) and IEC 61000-4-30 class A
(unbalance, magnitude, frequency), as recalled here: check the standards before quoting
compliance."""

from __future__ import annotations

import numpy as np

# IEC 61000-4-7 class I (voltage): |error| <= 5 % of the reading when the reading is >= 1 %
# of nominal, <= 0.05 % of nominal below; IEC 61000-4-30 class A: u2 within +-0.15
# percentage points, magnitude within +-0.1 % of the declared input, frequency +-10 mHz.
LIMITS = {
    "harmonic_relative": 0.05,
    "harmonic_threshold": 0.01,
    "harmonic_absolute": 0.0005,
    "u2_absolute": 0.0015,
    "magnitude_relative": 0.001,
    "frequency_hz": 0.01,
}


def class_i_limit(true_rms: np.ndarray, nominal_rms: float) -> np.ndarray:
    """IEC 61000-4-7 class I: the permitted |error| of each reading."""
    rel = LIMITS["harmonic_relative"] * np.abs(true_rms)
    small = LIMITS["harmonic_absolute"] * nominal_rms
    return np.where(np.abs(true_rms) >= LIMITS["harmonic_threshold"] * nominal_rms, rel, small)
