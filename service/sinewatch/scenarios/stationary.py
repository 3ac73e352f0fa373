"""Stationary biased tones at SNR 0 to 60 dB (tags "stationary", "snr"): the scenarios on
which the accuracy bench compares every estimator with the Cramer-Rao bound
(:mod:`sinewatch.crlb`).

``tone-snr-XXdb``: ``0.5 + sin(2 pi 50.5 t + 0.3) + v``, v white Gaussian with
``sigma = A / sqrt(2 * 10^(SNR/10))`` (SNR = A^2 / 2 sigma^2), sampled at 1 kHz for 2 s
(20 samples per cycle, far from 0 and Nyquist, where the asymptotic bound holds). The
nominal frequency handed to the estimators that take one is 50 Hz, 1 % off the truth (an
estimator that does not adapt must not look perfect). The steady-state window is the
second half.

``tone-nobias-snr-XXdb`` (0, 20, 40, 60 dB): the same without the offset, for the
estimators whose model has none (paper 003's KKL observer). The bound is still the
four-parameter one (the offset is unknown to an estimator that estimates it; asymptotically
the frequency, amplitude and phase bounds do not depend on whether it is).
"""

from __future__ import annotations

from sinewatch.scenarios import BenchInfo, Component, declare, snr_noise_std

SNR_DB = (0, 10, 20, 30, 40, 50, 60)
FREQUENCY_HZ = 50.5
NOMINAL_HZ = 50.0
AMPLITUDE = 1.0
OFFSET = 0.5
PHASE = 0.3


NOBIAS_SNR_DB = (0, 20, 40, 60)


def _tone(snr_db: int, offset: float) -> None:
    declare(
        f"tone-snr-{snr_db:02d}db" if offset else f"tone-nobias-snr-{snr_db:02d}db",
        f"{offset:g} + sin(2 pi 50.5 t + 0.3) at 1 kHz, 2 s, white Gaussian noise at SNR {snr_db} dB",
        [Component(FREQUENCY_HZ, a0=AMPLITUDE, phi0=PHASE)],
        BenchInfo(
            nominal_frequency_hz=(NOMINAL_HZ,),
            frequency_range_hz=(25.0, 100.0),
            steady_windows=((1.0, 2.0),),
        ),
        offset=offset,
        tags=("stationary", "snr") + (("quick",) if snr_db in (20, 40) and offset else ()),
        defaults={"sample_rate_hz": 1000.0, "duration_s": 2.0, "noise_std": snr_noise_std(AMPLITUDE, snr_db)},
    )


for _snr in SNR_DB:
    _tone(_snr, OFFSET)
for _snr in NOBIAS_SNR_DB:
    _tone(_snr, 0.0)
