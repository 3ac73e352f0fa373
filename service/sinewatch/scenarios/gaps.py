"""Data gaps (tag "gap"): the signal stops and resumes, or samples are lost.

A 50.3 Hz tone (amplitude 1, offset 0.2) at 1 kHz, white Gaussian noise at 40 dB SNR
(nominal frequency 50 Hz):

* ``gap-dropout-200ms``: the sensor reads zero (plus the noise) for 0.2 s from t = 2 s,
  then the signal resumes with its phase continued (the source never stopped);
* ``gap-dropout-5s``: the same for 5 s, long enough for an estimator's state to decay
  (it must stay finite and reacquire);
* ``gap-skip-105ms``: 105 ms of samples are lost at t = 2 s and the stream continues as
  if contiguous: the estimator sees a phase jump of 2 pi 50.3 * 0.105 = 33.2 rad (0.28
  cycle modulo 2 pi).

The bench measures the reacquisition time from the end of the gap (event "resume").
"""

from __future__ import annotations

from sinewatch.scenarios import BenchInfo, Component, Event, declare, snr_noise_std

F0 = 50.3
NOMINAL_HZ = 50.0


def _gap(
    name: str,
    summary: str,
    *,
    dropout: tuple[float, float] | None = None,
    skip: tuple[float, float] | None = None,
    t_resume: float,
    duration: float,
    quick: bool = False,
) -> None:
    declare(
        name,
        summary,
        [Component(F0, phi0=0.3)],
        BenchInfo(
            nominal_frequency_hz=(NOMINAL_HZ,),
            frequency_range_hz=(25.0, 100.0),
            steady_windows=((1.0, 2.0), (duration - 1.0, duration)),
            events=(Event(t_resume, "resume"),),
        ),
        offset=0.2,
        dropout=dropout,
        skip=skip,
        tags=("gap",) + (("quick",) if quick else ()),
        defaults={"sample_rate_hz": 1000.0, "duration_s": duration, "noise_std": snr_noise_std(1.0, 40.0)},
    )


_gap(
    "gap-dropout-200ms",
    "50.3 Hz at 1 kHz, 40 dB SNR; reads zero for 0.2 s from t = 2 s",
    dropout=(2.0, 2.2),
    t_resume=2.2,
    duration=5.0,
    quick=True,
)
_gap(
    "gap-dropout-5s",
    "50.3 Hz at 1 kHz, 40 dB SNR; reads zero for 5 s from t = 2 s",
    dropout=(2.0, 7.0),
    t_resume=7.0,
    duration=10.0,
)
_gap(
    "gap-skip-105ms",
    "50.3 Hz at 1 kHz, 40 dB SNR; 105 ms of samples lost at t = 2 s",
    skip=(2.0, 0.105),
    t_resume=2.0,
    duration=5.0,
)
