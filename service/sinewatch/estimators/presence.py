"""Signal presence: is there a signal to estimate, and for how long has there been one?

Not an estimator: the pipeline runs it beside every channel's estimator to fill
``diagnostics.valid`` (an estimate is a measurement only while the signal it describes is
present, and only once the estimator's own memory holds nothing but that signal).

The level is the one-cycle RMS of the AC part, as IEC 61000-4-30 (Sec. 5.4, voltage dips and
interruptions) measures it (there refreshed every half cycle; here at every sample): over the
last M = round(fs / f_nominal) samples (at least 2),

(L)  ``L_n^2 = max(0, S2 / M - (S1 / M)^2)``, ``S1 = sum x``, ``S2 = sum x^2`` over the window,

so a DC offset is not a signal. The reference is the recent level, a peak hold that decays
with time constant ``tau`` while the signal is present and is frozen while it is absent:

(R)  ``R_n = max(L_n, R_{n-1} exp(-1 / (tau fs)))`` while present, ``R_n = R_{n-1}`` while absent.

(A)  The signal is absent at sample n when ``L_n <= ratio R_n`` (default ratio 0.1: IEEE Std
     1159-2019 Table 2 calls a fall below 0.1 pu an interruption) or ``L_n = 0``.

Freezing R while absent keeps a lost signal absent however long it stays lost (noise at 30 dB
below the signal never becomes "the signal"); letting it decay while present lets a sustained
change of operating level become the new reference within a few ``tau``. A sag to 0.3 pu is
a signal (valid); its transitions are what ``converged`` is for.

Each sample's output is the run length: the number of consecutive samples, up to and
including this one, at which the signal was present (capped at 2^62). The pipeline calls an
estimate valid when the run length at its sample is at least the estimator's memory
(:attr:`sinewatch.estimators.base.Estimator.memory_samples`): present now, and present
throughout the span of input the estimate depends on. At a channel's start the run length
starts at 0, so the first estimates (before one memory of signal) are not valid either.

Onset latency: the level of a one-cycle window falls below 0.1 of R only once about 99 % of
the window is the interruption, so valid turns false within one nominal cycle of the onset.

S1 and S2 are running sums, recomputed exactly from the window each time the write position
wraps (every M samples), so rounding does not accumulate; the outputs depend only on the
samples, not on how they are cut into blocks.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sinewatch.estimators.base import decode_array, encode_array, kernel
from sinewatch.schemas.errors import ParameterError

PRESENCE_STATE_VERSION = 1
DEFAULT_RATIO = 0.1  # IEEE 1159: below 0.1 pu is an interruption
DEFAULT_TAU_S = 1.0  # decay of the reference level while the signal is present
RUN_CAP = 1 << 62

# slots of "sums": S1, S2, R
_S1, _S2, _R = 0, 1, 2
# slots of "counters": write position, fill, run length
_POS, _FILL, _RUN = 0, 1, 2


@kernel
def presence_kernel(
    x: np.ndarray,
    ring: np.ndarray,
    sums: np.ndarray,
    counters: np.ndarray,
    decay: float,
    ratio: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run (L), (R), (A) over ``x``; return ``(run, level, new_ring, new_sums, new_counters)``:
    per sample the run length of presence and the level L. Pure: the inputs are not modified."""
    M = ring.shape[0]
    b = ring.copy()
    s1, s2, r = sums[_S1], sums[_S2], sums[_R]
    pos, fill, run = counters[_POS], counters[_FILL], counters[_RUN]
    n = x.shape[0]
    run_out = np.empty(n, dtype=np.int64)
    level_out = np.empty(n)
    for j in range(n):
        xj = x[j]
        old = b[pos]
        b[pos] = xj
        s1 += xj - old
        s2 += xj * xj - old * old
        pos += 1
        if pos == M:
            pos = 0
            s1 = 0.0  # exact recomputation once per window: no accumulated rounding
            s2 = 0.0
            for i in range(M):
                s1 += b[i]
                s2 += b[i] * b[i]
        if fill < M:
            fill += 1
        m = s1 / M
        ms = s2 / M - m * m
        level = math.sqrt(ms) if ms > 0.0 else 0.0
        if fill < M:  # the first cycle: not a level yet
            present = False
        else:
            rd = r * decay
            ref = level if level > rd else rd
            present = level > 0.0 and level > ratio * ref
            if present:
                r = ref
        if present:
            if run < RUN_CAP:
                run += 1
        else:
            run = 0
        run_out[j] = run
        level_out[j] = level
    new_sums = np.array([s1, s2, r])
    new_counters = np.array([pos, fill, run], dtype=np.int64)
    return run_out, level_out, b, new_sums, new_counters


class SignalPresence:
    """The presence detector of one channel: owns the state, runs :func:`presence_kernel`."""

    def __init__(
        self,
        sample_rate_hz: float,
        nominal_frequency_hz: float = 50.0,
        *,
        ratio: float = DEFAULT_RATIO,
        tau_s: float = DEFAULT_TAU_S,
    ) -> None:
        if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
            raise ParameterError(f"sample_rate_hz: expected a finite value > 0, got {sample_rate_hz}")
        if not (math.isfinite(nominal_frequency_hz) and nominal_frequency_hz > 0):
            raise ParameterError(f"nominal_frequency_hz: expected a finite value > 0, got {nominal_frequency_hz}")
        if not (0 < ratio < 1):
            raise ParameterError(f"ratio: expected 0 < ratio < 1, got {ratio}")
        self.sample_rate_hz = float(sample_rate_hz)
        self.nominal_frequency_hz = float(nominal_frequency_hz)
        self.window_samples = max(2, round(sample_rate_hz / nominal_frequency_hz))
        self.ratio = float(ratio)
        self.decay = math.exp(-1.0 / (tau_s * sample_rate_hz))
        self.reset()

    def reset(self) -> None:
        self.ring = np.zeros(self.window_samples)
        self.sums = np.zeros(3)
        self.counters = np.zeros(3, dtype=np.int64)

    def update(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-sample (run length of presence, level) over ``samples`` (float64, 1-D)."""
        x = np.ascontiguousarray(samples, dtype=np.float64)
        run, level, self.ring, self.sums, self.counters = presence_kernel(
            x, self.ring, self.sums, self.counters, self.decay, self.ratio
        )
        return run, level

    @property
    def run_samples(self) -> int:
        """The run length after the last sample seen."""
        return int(self.counters[_RUN])

    def get_state(self) -> dict[str, Any]:
        return {
            "format_version": PRESENCE_STATE_VERSION,
            "window_samples": self.window_samples,
            "ring": encode_array(self.ring),
            "sums": encode_array(self.sums),
            "counters": encode_array(self.counters),
        }

    def set_state(self, snapshot: dict[str, Any]) -> None:
        if snapshot.get("format_version") != PRESENCE_STATE_VERSION:
            raise ParameterError(
                f"presence format_version: expected {PRESENCE_STATE_VERSION}, got {snapshot.get('format_version')!r}"
            )
        ring = decode_array(snapshot["ring"])
        if ring.shape != (self.window_samples,):
            raise ParameterError(f"presence ring: expected ({self.window_samples},) samples, got {ring.shape}")
        self.ring = ring
        self.sums = decode_array(snapshot["sums"])
        self.counters = decode_array(snapshot["counters"])


__all__ = ["DEFAULT_RATIO", "DEFAULT_TAU_S", "SignalPresence", "presence_kernel"]
