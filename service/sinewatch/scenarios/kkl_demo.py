"""Demo scenarios for the KKL observers (paper 003): ``kkl-demo`` and ``kkl-biased-demo``.

Both are 10 kHz, 10 s, mains-range signals of the kind the KKL design handles: one 50 Hz
tone with a small component far above the filters (5 % switching ripple at 2.5 kHz, which
the first-order filters attenuate, as in the paper's Section V), a little noise, and a
step to 51 Hz and 80 % amplitude at t = 5 s so that the tracking shows. The KKL observer
has no noise filtering beyond its first-order filters (lambda ~ omega), so the noise is
kept small (std 0.002). ``kkl-biased-demo`` adds an offset of 0.5 for ``kkl-biased``.

Watch the daemon on them with ``sinewatch demo --scenarios kkl-demo`` (or
``sinewatch feed --scenario kkl-demo``). Measured with the suggested parameters
(seed 1, t in 1-5 s and 6-10 s): frequency error std 0.087 Hz (kkl-biased: 0.152 Hz),
amplitude error std 0.0016 (0.0012); converged drops 7 ms (4.4 ms) after the step.
"""

from __future__ import annotations

from sinewatch.scenarios import Component, declare

KKL_MAINS_PARAMS = {"f_min_hz": 45.0, "f_max_hz": 65.0}

_TONES = [Component(50.0, 1.0, 0.3, t_step=5.0, f_step_to=51.0, a_step_factor=0.8)]
_RIPPLE = [Component(2500.0, 0.05, 0.0)]  # switching ripple, 1.7 decades above the filters (not truth)


for _name, _summary, _offset, _estimator in (
    ("kkl-demo", "50 Hz + 5 % ripple at 2.5 kHz, steps to 51 Hz / 80 % at t = 5 s (kkl, 45-65 Hz)", 0.0, "kkl"),
    ("kkl-biased-demo", "kkl-demo with an offset of 0.5 (kkl-biased, 45-65 Hz)", 0.5, "kkl-biased"),
):
    declare(
        _name,
        _summary,
        _TONES,
        offset=_offset,
        tags=("demo", "kkl"),
        disturbances=_RIPPLE,
        defaults={
            "sample_rate_hz": 10_000.0,
            "duration_s": 10.0,
            "noise_std": 0.002,
            "suggested_estimator": _estimator,
            "suggested_params": KKL_MAINS_PARAMS,
        },
    )
