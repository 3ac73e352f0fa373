"""pqopen-lib on sinewatch's waveforms: the reference a power-quality engineer would reach
for, run on the same samples for comparison (the optional extra ``pqopen``).

pqopen (``pqopen.powersystem.PowerSystem``) windows 10/12 cycles between detected zero
crossings (whole samples), resamples each window linearly to a power of two
(``pqopen.powerquality.resample_and_fft``) and groups the FFT into harmonic subgroups
(``calc_harmonics``), THD over orders 2..40 (``calc_thd``) and the unbalance of the
fundamental phasors (``calc_unbalance``). :func:`run_pqopen` feeds it a waveform and
returns its 10/12-cycle values; nothing else in sinewatch imports pqopen.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

SCALE = 230.0  # pqopen's zero-crossing detector has a 1 V threshold: feed it volts


@dataclass(frozen=True)
class PqopenResult:
    """pqopen's 10/12-cycle values; arrays have one row per window."""

    end_index: np.ndarray  # (W,) sample index of each window's end
    harmonic_rms: np.ndarray  # (W, P, H+1) harmonic subgroups per phase, orders 0..H (the input's unit)
    thd: np.ndarray  # (W, P) ratio (pqopen reports %, over orders 2..40)
    u2: np.ndarray | None  # (W,) ratio, three phases only
    u0: np.ndarray | None


def available() -> bool:
    try:
        import pqopen.powersystem  # noqa: F401
    except ImportError:
        return False
    return True


def max_harmonic(sample_rate_hz: float, nominal_frequency_hz: float) -> int:
    """The highest order pqopen can group: its FFT has ``2^floor(log2(N fs / f_nom))``
    points and its interharmonic grouping needs ``N (H + 1)`` bins (at 10 kHz: 50 at
    50 Hz, 41 at 60 Hz; it raises beyond)."""
    nper = 10 if nominal_frequency_hz == 50.0 else 12
    size = 2 ** int(np.floor(np.log2(sample_rate_hz / nominal_frequency_hz * nper)))
    return int(min(50, (size // 2 + 1) // nper - 1))


def run_pqopen(
    samples: np.ndarray, sample_rate_hz: float, nominal_frequency_hz: float, block: int = 1000
) -> PqopenResult:
    """Run pqopen's PowerSystem over ``samples`` ((n,) or (n, P), per unit) in blocks,
    harmonics up to :func:`max_harmonic` (``harmonic_rms`` has that many + 1 columns)."""
    from daqopen.channelbuffer import AcqBuffer
    from pqopen.powersystem import PowerSystem

    x = np.asarray(samples, dtype=np.float64)
    x = x.reshape(-1, 1) if x.ndim == 1 else x
    n, n_ph = x.shape
    nper = 10 if nominal_frequency_hz == 50.0 else 12
    bufs = [AcqBuffer(size=n + 1, dtype=np.float64, name=f"U{p + 1}") for p in range(n_ph)]
    ps = PowerSystem(
        zcd_channel=bufs[0],
        input_samplerate=float(sample_rate_hz),
        zcd_cutoff_freq=nominal_frequency_hz,
        nominal_frequency=nominal_frequency_hz,
        nper=nper,
    )
    for p, b in enumerate(bufs):
        ps.add_phase(u_channel=b, name=str(p + 1))
    ps.enable_harmonic_calculation(max_harmonic(sample_rate_hz, nominal_frequency_hz))
    for i in range(0, n, block):
        for p, b in enumerate(bufs):
            b.put_data(SCALE * x[i : i + block, p])
        ps.process()
    ch: dict[str, Any] = ps.output_channels
    harm, idx = [], None
    for p in range(n_ph):
        h, idx = ch[f"U{p + 1}_H_rms"].read_data_by_acq_sidx(0, n)
        harm.append(np.asarray(h, dtype=np.float64) / SCALE)
    thd = [
        np.asarray(ch[f"U{p + 1}_THD"].read_data_by_acq_sidx(0, n)[0], dtype=np.float64) / 100.0 for p in range(n_ph)
    ]
    u2 = u0 = None
    if n_ph == 3 and "U_unbal_2" in ch:
        u2 = np.asarray(ch["U_unbal_2"].read_data_by_acq_sidx(0, n)[0], dtype=np.float64) / 100.0
        u0 = np.asarray(ch["U_unbal_0"].read_data_by_acq_sidx(0, n)[0], dtype=np.float64) / 100.0
    return PqopenResult(
        end_index=np.asarray(idx),
        harmonic_rms=np.stack(harm, axis=1),
        thd=np.stack(thd, axis=1),
        u2=u2,
        u0=u0,
    )
