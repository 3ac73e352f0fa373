"""Multi-tone signals (tag "multitone"): K = 2 or 3 sinusoids plus an offset, for the
estimators that track several components (the single-tone ones are reported "n/a").

All at 1 kHz for 10 s, white Gaussian noise at 40 dB SNR relative to the first tone
(sigma = 0.00707); the steady window is the last 5 s.

* ``multitone-2-separated``: 50 Hz (A = 1) + 120 Hz (A = 0.5), offset 0.2;
* ``multitone-2-close``: 50 Hz + 55 Hz, both A = 1 (resolution: 5 Hz apart);
* ``multitone-2-weak``: 50 Hz (A = 1) + 80 Hz (A = 0.05, 26 dB below);
* ``multitone-3``: 50, 110, 170 Hz with A = 1, 0.5, 0.3, offset 0.2.

The nominal frequencies handed to the estimators are 10 % off the true ones.
"""

from __future__ import annotations

from sinewatch.scenarios import BenchInfo, Component, declare, snr_noise_std


def _multi(
    name: str, summary: str, tones: list[tuple[float, float, float]], offset: float, quick: bool = False
) -> None:
    declare(
        name,
        summary,
        [Component(f, a0=a, phi0=p) for f, a, p in tones],
        BenchInfo(
            nominal_frequency_hz=tuple(0.9 * f if i % 2 == 0 else 1.1 * f for i, (f, _, _) in enumerate(tones)),
            frequency_range_hz=(10.0, 250.0),
            steady_windows=((5.0, 10.0),),
        ),
        offset=offset,
        tags=("multitone",) + (("quick",) if quick else ()),
        defaults={"sample_rate_hz": 1000.0, "duration_s": 10.0, "noise_std": snr_noise_std(1.0, 40.0)},
    )


_multi(
    "multitone-2-separated",
    "50 Hz (A 1) + 120 Hz (A 0.5) + 0.2 at 1 kHz, 40 dB SNR",
    [(50.0, 1.0, 0.3), (120.0, 0.5, 1.2)],
    0.2,
    quick=True,
)
_multi("multitone-2-close", "50 Hz + 55 Hz (A 1 each) at 1 kHz, 40 dB SNR", [(50.0, 1.0, 0.3), (55.0, 1.0, 2.0)], 0.0)
_multi(
    "multitone-2-weak", "50 Hz (A 1) + 80 Hz (A 0.05) at 1 kHz, 40 dB SNR", [(50.0, 1.0, 0.3), (80.0, 0.05, 0.9)], 0.0
)
_multi(
    "multitone-3",
    "50 + 110 + 170 Hz (A 1, 0.5, 0.3) + 0.2 at 1 kHz, 40 dB SNR",
    [(50.0, 1.0, 0.3), (110.0, 0.5, 1.2), (170.0, 0.3, -0.7)],
    0.2,
)
