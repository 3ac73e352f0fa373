"""Stationary biased tones at SNR 0 to 60 dB (tags "stationary", "snr"): the scenarios on
which the accuracy bench compares every estimator with the Cramer-Rao bound
(:mod:`sinewatch.crlb`).

``tone-snr-XXdb``: ``0.5 + sin(2 pi 50 t + 0.3) + v``, v white Gaussian with
``sigma = A / sqrt(2 * 10^(SNR/10))`` (SNR = A^2 / 2 sigma^2), sampled at 1 kHz for 2 s
(20 samples per cycle, far from 0 and Nyquist, where the asymptotic bound holds). The
steady-state window is the second half.
"""

from __future__ import annotations

from typing import Any

from sinewatch.scenarios import register
from sinewatch.scenarios._library import BenchInfo, Component, Composite, snr_noise_std

SNR_DB = (0, 10, 20, 30, 40, 50, 60)
FREQUENCY_HZ = 50.0
AMPLITUDE = 1.0
OFFSET = 0.5
PHASE = 0.3


def _tone(snr_db: int, **kw: Any) -> Composite:
    tags = ("stationary", "snr") + (("quick",) if snr_db in (20, 40) else ())
    return Composite(
        f"tone-snr-{snr_db:02d}db",
        f"0.5 + sin(2 pi 50 t + 0.3) at 1 kHz, 2 s, white Gaussian noise at SNR {snr_db} dB",
        [Component(FREQUENCY_HZ, a0=AMPLITUDE, phi0=PHASE)],
        BenchInfo(
            nominal_frequency_hz=(FREQUENCY_HZ,),
            frequency_range_hz=(5.0, 250.0),
            steady_windows=((1.0, 2.0),),
        ),
        offset=OFFSET,
        tags=tags,
        **{"sample_rate_hz": 1000.0, "duration_s": 2.0, "noise_std": snr_noise_std(AMPLITUDE, snr_db), **kw},
    )


def _make(snr_db: int):
    def factory(**kw: Any) -> Composite:
        return _tone(snr_db, **kw)

    factory.__name__ = f"tone_snr_{snr_db:02d}db"
    return factory


for _snr in SNR_DB:
    register(f"tone-snr-{_snr:02d}db")(_make(_snr))
