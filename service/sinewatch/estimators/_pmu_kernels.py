"""The ``pmu`` estimator's compiled kernels: (D)-(R) and (U) of ``_pmu_design`` run over a
block of samples (:func:`pmu_kernel`, pure: block + state -> outputs + new state), and the
transition test (T) over the reports (:func:`transition_kernel`).

(T)  converged: a report is converged when its magnitude is above ``min_amplitude`` and no
     transition has been seen for one kernel length (``ceil(T Fs)`` reports: the window of
     the report has refilled since). A report is a transition when it departs from the
     previous report's prediction (magnitude unchanged, frequency ``f + ROCOF / Fs``) by
     more than ``max(floor, 6 s)``, s the running mean of those departures (each clipped to
     the threshold; the plain mean of the first 20, then weight 0.05 a report), so that noise and sustained modulation raise the
     threshold with them while a step does not: floors 0.1 % of the magnitude and 0.006 Hz
     (module constants, from the C37.118.1 step tests: the first report of a step whose TVE
     exceeds 1 % already departs by more). The start, a restart on the grid (a gap in time,
     a reset) and an undefined report start it over; the first report after one is not
     converged (there is nothing to check it against). Consequences: converged is false
     from the first report a magnitude or phase step moves (before the step's instant, as
     the window reaches it) until one window after the last such report; a modulation at
     the edge of the measurement bandwidth reads as transitions until the scale has risen
     to it (about 1 s).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sinewatch.estimators._pmu_design import N_IMAGE_PASSES
from sinewatch.estimators.base import cyclic_next, kernel, wrap_pi

# converged (T): a report is a transition when it departs from the previous report's
# prediction by more than max(floor, TRANSITION_K x the running scale of such departures).
# Floors from the C37.118.1 step tests (``sinewatch bench compliance``): at the first report
# whose TVE exceeds 1 % the magnitude has moved >= 0.12 % from the report before (10 %
# steps) or the frequency >= 0.0075 Hz from its prediction (10 degree steps), where the
# steady, harmonic, ramp and out-of-band tests move < 0.06 % and < 0.0056 Hz.
TRANSITION_MAG_FLOOR = 1e-3  # relative change of the RMS magnitude
TRANSITION_FREQ_FLOOR_HZ = 6e-3
TRANSITION_K = 6.0
TRANSITION_ALPHA = 0.05  # weight of each report in the running scale (~20 reports)


# istate: 0 n (samples since the anchor), 1 j (next decimated index), 2 k_next (grid
# index of the next report), 3 k0 (first grid index at/after the anchor), 4 held (a
# report has been made), 5 defined (it has a finite estimate)
# fstate: 0 delta0 (samples from the anchor to grid point k0), 1 beta (2 pi f0 t_anchor
# mod 2 pi), 2-3 acc_cur (re, im), 4-5 acc_next, 6 dc_cur, 7 dc_next,
# 8 f, 9 A (peak), 10 theta (phase at the current sample), 11 B (offset), 12 rocof,
# 13 converged, 14 cos theta, 15 sin theta (rotor at the current sample)
N_ISTATE = 6
N_FSTATE = 16
#: (U) noise probes per report, and the time constant (s) of their average over reports
N_PROBES = 4  # written out as four chains in _noise_update
NOISE_TIME_CONSTANT_S = 1.0
#: report rows: the 8 values, then (U) the standard deviations of frequency, ROCOF, amplitude,
#: phase, offset and TVE
N_REPORT_COLUMNS = 14


@kernel
def _interp(table: np.ndarray, x0: float, step: float, x: float) -> Any:
    """Cubic (4-point Lagrange) interpolation of a table sampled at x0 + i step; clamped."""
    u = (x - x0) / step
    n = table.shape[0]
    i = math.floor(u)
    if i < 1:
        i = 1
    if i > n - 3:
        i = n - 3
    s = u - i
    if s < -1.0:
        s = -1.0
    if s > 2.0:
        s = 2.0
    ym, y0, y1, y2 = table[i - 1], table[i], table[i + 1], table[i + 2]
    return (
        -s * (s - 1.0) * (s - 2.0) / 6.0 * ym
        + (s + 1.0) * (s - 1.0) * (s - 2.0) / 2.0 * y0
        - (s + 1.0) * s * (s - 2.0) / 2.0 * y1
        + (s + 1.0) * s * (s - 1.0) / 6.0 * y2
    )


@kernel
def _report(
    ring: np.ndarray,
    dcring: np.ndarray,
    start: int,
    kern: np.ndarray,
    osc: np.ndarray,
    n_r: int,
    fconsts: np.ndarray,
    gp: np.ndarray,
    bias: np.ndarray,
    gc: np.ndarray,
    gi3: np.ndarray,
    gram: np.ndarray,
    taper: np.ndarray,
    pgram: np.ndarray,
    noise: np.ndarray,
    out: np.ndarray,
) -> None:
    """(K)-(E) from the M decimated samples ring[start:start+M] (oldest first): fills
    out = (nu, Re X, Im X, rocof, B, defined) at input sample n_r (anchor frame), then (U):
    updates the noise average ``noise`` (in place) and fills out[6:12] = the standard
    deviations of frequency, ROCOF, amplitude (peak), phase, offset and TVE (NaN when
    undefined)."""
    M = kern.shape[1]
    f0, nu_p0, nu_i0, step = fconsts[0], fconsts[2], fconsts[3], fconsts[4]
    # taps run m = m_lo .. m_lo + M - 1 over c_{q - m}: newest sample first
    p0r = p0i = p1r = p1i = p2r = p2i = b = 0.0
    last = start + M - 1
    for i in range(M):
        cr = ring[last - i, 0]
        ci = ring[last - i, 1]
        k0v = kern[0, i]
        k1v = kern[1, i]
        k2v = kern[2, i]
        p0r += k0v * cr
        p0i += k0v * ci
        p1r += k1v * cr
        p1i += k1v * ci
        p2r += k2v * cr
        p2i += k2v * ci
        b += k0v * dcring[last - i]
    p0 = complex(p0r, p0i)
    p1 = complex(p1r, p1i)
    p2 = complex(p2r, p2i)
    if not (abs(p0) > 0.0) or not math.isfinite(abs(p0)):
        out[5] = 0.0
        return
    # e^{-j 4 pi f0 n_r / fs} from the oscillator table
    P = osc.shape[0]
    ph = n_r % P
    e1 = complex(osc[ph, 0], -osc[ph, 1])
    e2 = e1 * e1
    q0, q1, q2 = p0, p1, p2
    nu = 0.0
    for _ in range(N_IMAGE_PASSES):  # (I) image cancellation passes [R]
        nu = (q1 / q0).imag / (2.0 * math.pi)
        x1 = q0 / _interp(gp, nu_p0, step, nu)
        nu_i = -2.0 * f0 - nu
        xi = x1.conjugate() * e2
        q0 = p0 - _interp(gi3[0], nu_i0, step, nu_i) * xi
        q1 = p1 - _interp(gi3[1], nu_i0, step, nu_i) * xi
        q2 = p2 - _interp(gi3[2], nu_i0, step, nu_i) * xi
        if not (abs(q0) > 0.0):
            out[5] = 0.0
            return
    r1 = q1 / q0
    nu = r1.imag / (2.0 * math.pi)  # (E)
    a2 = q2 / q0 - r1 * r1 - _interp(bias, nu_p0, step, nu)  # (B): d^2 log X / dt^2
    rocof = a2.imag / (2.0 * math.pi)
    x = q0 / (_interp(gp, nu_p0, step, nu) + 0.5 * a2 * _interp(gc, nu_p0, step, nu))  # (C)
    out[0] = nu
    out[1] = x.real
    out[2] = x.imag
    out[3] = rocof
    out[4] = b
    out[5] = 1.0 if (math.isfinite(nu) and math.isfinite(rocof) and math.isfinite(abs(x))) else 0.0
    for c in range(6, 12):
        out[c] = np.nan
    if out[5] == 0.0:
        return
    sig2 = _noise_update(ring, start, M, taper, pgram, f0 + nu, fconsts, noise)
    dn = _interp(gp, nu_p0, step, nu) + 0.5 * a2 * _interp(gc, nu_p0, step, nu)
    _report_std(q0, q1, q2, r1, dn, _interp(gc, nu_p0, step, nu), x, gram, sig2, out)


@kernel
def _noise_update(
    ring: np.ndarray,
    start: int,
    M: int,
    taper: np.ndarray,
    pgram: np.ndarray,
    f_hz: float,
    fconsts: np.ndarray,
    noise: np.ndarray,
) -> float:
    """(U) the noise variance sigma^2 of the raw samples: N_PROBES probes (the Nuttall taper
    modulated to raw frequencies (i + 1/2) f, halfway between the signal's harmonics, relative
    to the estimated f so that neither the tone nor its harmonics, the offset or the image
    fall in their main lobes) read the noise beside the tone in this window; their power over
    their gram, averaged over the probes and over reports (weights ``lambda^age``, the
    average in ``noise`` = (weighted sum, sum of weights)), is sigma^2. Returns it."""
    f_osc, lam, dstep = fconsts[0], fconsts[7], fconsts[8]
    last = start + M - 1
    # the four probes are independent chains (each rotor e waits on its previous value): they
    # advance together, one tap at a time, so the CPU overlaps them; each probe's operations
    # are those of a loop over its taps alone, in the same order (the same bits)
    w0 = _probe_w(0, f_hz, f_osc, dstep)
    w1 = _probe_w(1, f_hz, f_osc, dstep)
    w2 = _probe_w(2, f_hz, f_osc, dstep)
    w3 = _probe_w(3, f_hz, f_osc, dstep)
    rot0 = complex(math.cos(w0), math.sin(w0))
    rot1 = complex(math.cos(w1), math.sin(w1))
    rot2 = complex(math.cos(w2), math.sin(w2))
    rot3 = complex(math.cos(w3), math.sin(w3))
    e0 = e1 = e2 = e3 = complex(1.0, 0.0)
    pr0 = pr1 = pr2 = pr3 = complex(0.0, 0.0)
    for i in range(M):
        c = complex(ring[last - i, 0], ring[last - i, 1])
        t = taper[i]
        pr0 += t * e0 * c
        pr1 += t * e1 * c
        pr2 += t * e2 * c
        pr3 += t * e3 * c
        e0 *= rot0
        e1 *= rot1
        e2 *= rot2
        e3 *= rot3
    acc = 0.0
    acc += _probe_power(pr0, w0, pgram)
    acc += _probe_power(pr1, w1, pgram)
    acc += _probe_power(pr2, w2, pgram)
    acc += _probe_power(pr3, w3, pgram)
    noise[0] = lam * noise[0] + acc / N_PROBES
    noise[1] = lam * noise[1] + 1.0
    sig2: float = noise[0] / noise[1]
    return sig2


@kernel(inline="always")
def _probe_w(k: int, f_hz: float, f_osc: float, dstep: float) -> float:
    """(U) probe k's frequency after demodulation, in radians per decimated sample."""
    dk = (k + 0.5) * f_hz - f_osc
    w: float = 2.0 * math.pi * dk * dstep
    return w


@kernel(inline="always")
def _probe_power(pr: complex, w: float, pgram: np.ndarray) -> float:
    """(U) a probe's power over its gram (the noise variance it reads)."""
    g = pgram[0] + 2.0 * pgram[1] * math.cos(w)
    p: float = (pr.real * pr.real + pr.imag * pr.imag) / (2.0 * g)
    return p


@kernel(inline="always")
def _qform(c0: complex, c1: complex, c2: complex, gram: np.ndarray) -> float:
    """c^H Gamma c for a real symmetric 3x3 Gamma: the variance of Re(c^T e) (and of Im) per
    unit sigma^2, for the kernels' noise e (E[e e^H] = 2 sigma^2 Gamma, E[e e^T] ~ 0)."""
    v: float = (
        gram[0, 0] * (c0.real * c0.real + c0.imag * c0.imag)
        + gram[1, 1] * (c1.real * c1.real + c1.imag * c1.imag)
        + gram[2, 2] * (c2.real * c2.real + c2.imag * c2.imag)
        + 2.0 * gram[0, 1] * (c0.conjugate() * c1).real
        + 2.0 * gram[0, 2] * (c0.conjugate() * c2).real
        + 2.0 * gram[1, 2] * (c1.conjugate() * c2).real
    )
    return v if v > 0.0 else 0.0


@kernel
def _report_std(
    q0: complex,
    q1: complex,
    q2: complex,
    r1: complex,
    dn: complex,
    gcv: complex,
    x: complex,
    gram: np.ndarray,
    sig2: float,
    out: np.ndarray,
) -> None:
    """(U) the estimates of (E) and (C) linearised in the kernels' noise (the image
    cancellation's and the tables' own dependence on nu left out: second order): out[6:12] =
    std of nu, ROCOF, amplitude (peak, sqrt 2 |X|), arg X, offset, and the RMS TVE
    ``sqrt(E |dX|^2) / |X|``."""
    inv = 1.0 / q0
    two_pi = 2.0 * math.pi
    # nu = Im(q1 / q0) / 2 pi
    out[6] = math.sqrt(sig2 * _qform(-r1 * inv, inv, 0j, gram)) / two_pi
    # a2 = q2/q0 - r1^2 - b: da2 = ca0 dq0 + ca1 dq1 + ca2 dq2; ROCOF = Im(a2) / 2 pi
    ca0 = (2.0 * r1 * r1 - q2 * inv) * inv
    ca1 = -2.0 * r1 * inv
    ca2 = inv
    out[7] = math.sqrt(sig2 * _qform(ca0, ca1, ca2, gram)) / two_pi
    # X = q0 / dn, dn = G + a2 G2 / 2
    s = -0.5 * gcv * q0 / (dn * dn)
    cx0 = 1.0 / dn + s * ca0
    cx1 = s * ca1
    cx2 = s * ca2
    mag = abs(x)
    u = x.conjugate() / mag
    out[8] = math.sqrt(2.0 * sig2 * _qform(u * cx0, u * cx1, u * cx2, gram))
    out[9] = math.sqrt(sig2 * _qform(u * cx0, u * cx1, u * cx2, gram)) / mag
    out[10] = math.sqrt(sig2 * gram[0, 0])  # b = sum_n h0[n] x_n: no sqrt 2, no demodulation
    out[11] = math.sqrt(2.0 * sig2 * _qform(cx0, cx1, cx2, gram)) / mag


@kernel(inline="always")
def _next_report(
    delta0: float, k_next: int, k0: int, spr: float, D: int, m_lo: int, M: int, j: int
) -> tuple[int, float, int, int, int]:
    """Grid report ``k_next`` against the newest decimated sample ``j``: (due, u, n_r, ph_r,
    oldest): due 0, not yet (its newest tap is after c_j); 1, never (its window reaches
    before the anchor, or past c_j); 2, now. ``u``: its fractional input sample, ``n_r`` the
    nearest, ``ph_r`` that sample's decimation phase, ``oldest`` its oldest tap's index."""
    u = delta0 + (k_next - k0) * spr
    n_r = math.floor(u + 0.5)
    q = n_r // D
    newest = q - m_lo
    oldest = newest - M + 1
    if newest > j:
        return 0, u, n_r, 0, oldest
    if oldest < 1 or newest < j:
        return 1, u, n_r, 0, oldest
    return 2, u, n_r, n_r - q * D, oldest


@kernel(inline="always")
def _held_model(
    est: np.ndarray,
    u: float,
    n_r: int,
    n: int,
    k_next: int,
    beta: float,
    f0: float,
    fs: float,
    min_amp: float,
    reps: np.ndarray,
    n_rep: int,
    cstep: float,
    sstep: float,
) -> tuple[int, float, float, float, float, float, float, float, float, float, int]:
    """The report ``est`` (from :func:`_report`, made at input sample ``n_r`` for the grid
    point at fractional sample ``u``) as grid report row ``n_rep`` of ``reps`` (when there is
    room) and as the held model the rows after it report: returns (defined, f, A, B, rocof,
    converged, cos theta, sin theta at the current sample ``n``, the rotor's step, the next
    row). Shared by :func:`pmu_kernel` and the lane-major bank (the same operations)."""
    cap = reps.shape[0]
    tau = (u - n_r) / fs
    if est[5] != 0.0:
        nu = est[0]
        xr = complex(est[1], est[2]) * complex(math.cos(2 * math.pi * nu * tau), math.sin(2 * math.pi * nu * tau))
        mag = abs(xr)
        rocof = est[3]
        f = f0 + nu + rocof * tau
        B = est[4]
        conv = 1.0 if mag > min_amp else 0.0
        arg = math.atan2(xr.imag, xr.real)
        # phase of the nominal oscillator at u: 2 pi f0 u / fs (mod 2 pi)
        nom = 2.0 * math.pi * ((f0 * u / fs) - math.floor(f0 * u / fs))
        theta_r = arg + nom + 0.5 * math.pi  # sine convention
        A = math.sqrt(2.0) * mag
        if n_rep < cap:
            reps[n_rep, 0] = k_next
            reps[n_rep, 1] = f
            reps[n_rep, 2] = rocof
            reps[n_rep, 3] = mag
            reps[n_rep, 4] = wrap_pi(arg - beta)
            reps[n_rep, 5] = A
            reps[n_rep, 6] = wrap_pi(theta_r)
            reps[n_rep, 7] = B
            for c in range(6):  # (U): frequency, ROCOF, amplitude, phase, offset, TVE
                reps[n_rep, 8 + c] = est[6 + c]
            n_rep += 1
        # rotor at the current sample n (predicts sample n + 1 after a step)
        th = theta_r + 2.0 * math.pi * f * (n - u) / fs
        cstep = math.cos(2.0 * math.pi * f / fs)
        sstep = math.sin(2.0 * math.pi * f / fs)
        return 1, f, A, B, rocof, conv, math.cos(th), math.sin(th), cstep, sstep, n_rep
    if n_rep < cap:
        reps[n_rep, 0] = k_next
        for c in range(1, N_REPORT_COLUMNS):
            reps[n_rep, c] = np.nan
        n_rep += 1
    return 0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, cstep, sstep, n_rep


@kernel(inline="always")
def _out_row(
    out: np.ndarray,
    row: int,
    live: bool,
    f: float,
    A: float,
    B: float,
    conv: float,
    rocof: float,
    cth: float,
    sth: float,
) -> None:
    """Output row ``row``: the held model at the current sample (``live``: a defined report
    is held), else undefined."""
    if live:
        out[row, 0] = f
        out[row, 1] = A
        out[row, 2] = math.atan2(sth, cth)
        out[row, 3] = B
        out[row, 4] = conv
        out[row, 5] = rocof
    else:
        for c in range(4):
            out[row, c] = np.nan
        out[row, 4] = 0.0
        out[row, 5] = np.nan


@kernel
def pmu_kernel(
    x: np.ndarray,
    ring: np.ndarray,
    dcring: np.ndarray,
    istate: np.ndarray,
    fstate: np.ndarray,
    anchor: np.ndarray,
    noise: np.ndarray,
    kernels: np.ndarray,
    osc: np.ndarray,
    weights: np.ndarray,
    iconsts: np.ndarray,
    fconsts: np.ndarray,
    g_pass: np.ndarray,
    a2_bias: np.ndarray,
    g_chirp: np.ndarray,
    g_image: np.ndarray,
    noise_gram: np.ndarray,
    probe_taper: np.ndarray,
    probe_gram: np.ndarray,
    last_only: bool,
) -> tuple[np.ndarray, np.ndarray, float, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run (D)-(R) over block ``x``. Returns (out (N or 1, 6), reports (R, 14), sse,
    n_pred, new_ring, new_dcring, new_istate, new_fstate, new_anchor, new_noise) (``anchor``,
    the time anchor the class keeps, passes through unchanged; ``noise``, the (U) average).

    ``ring`` (2L, 2) holds the decimated c_j twice (so any window is contiguous), dcring
    (2L,) the decimated raw samples; ``iconsts`` = (D, M, m_lo, L); ``fconsts`` = (f0, fs,
    nu_pass0, nu_image0, table step, samples per report fs/Fs, min_amplitude). Output
    columns: frequency_hz, amplitude, phase_rad, offset, converged, rocof. Report rows:
    k, f, rocof, RMS magnitude, synchrophasor angle, amplitude (peak), phase_rad (sine,
    instantaneous), offset, then the std of frequency, ROCOF, amplitude, phase, offset and
    the RMS TVE (U). Pure: no input is modified."""
    D, M, m_lo, L = iconsts[0], iconsts[1], iconsts[2], iconsts[3]
    f0, fs, spr, min_amp = fconsts[0], fconsts[1], fconsts[5], fconsts[6]
    rg = ring.copy()
    dr = dcring.copy()
    ist = istate.copy()
    fst = fstate.copy()
    n, j, k_next, k0, held, defined = ist[0], ist[1], ist[2], ist[3], ist[4], ist[5]
    delta0, beta = fst[0], fst[1]
    acr, aci, anr, ani, dcc, dcn = fst[2], fst[3], fst[4], fst[5], fst[6], fst[7]
    f, A, B, rocof, conv = fst[8], fst[9], fst[11], fst[12], fst[13]
    cth, sth = fst[14], fst[15]
    n_in = x.shape[0]
    out = np.empty((1 if last_only else n_in, 6))
    cap = n_in // max(1, int(spr)) + 2
    reps = np.empty((cap, N_REPORT_COLUMNS))
    n_rep = 0
    est = np.zeros(12)
    nz = noise.copy()
    Q = weights.shape[0]
    ph = n % Q  # sample phase (weights) and decimation phase of sample n, then counted
    rho = n % D
    sse = 0.0
    n_pred = 0
    cstep = 1.0
    sstep = 0.0
    if held and defined:
        cstep = math.cos(2.0 * math.pi * f / fs)
        sstep = math.sin(2.0 * math.pi * f / fs)
    for i in range(n_in):
        xi = x[i]
        if held and defined:  # one-step prediction of the held model
            e = xi - (B + A * sth)
            sse += e * e
            n_pred += 1
        # (D) demodulate and accumulate the triangle
        acr += xi * weights[ph, 0]
        aci += xi * weights[ph, 1]
        anr += xi * weights[ph, 2]
        ani += xi * weights[ph, 3]
        dcc += xi * weights[ph, 4]
        dcn += xi * weights[ph, 5]
        if rho == D - 1:  # c_j complete
            slot = j % L
            rg[slot, 0] = acr
            rg[slot, 1] = aci
            rg[slot + L, 0] = acr
            rg[slot + L, 1] = aci
            dr[slot] = dcc
            dr[slot + L] = dcc
            acr, aci, dcc = anr, ani, dcn
            anr = ani = dcn = 0.0
            # reports whose newest tap is c_j (or that can never be made)
            while True:
                due, u, n_r, ph_r, oldest = _next_report(delta0, k_next, k0, spr, D, m_lo, M, j)
                if due == 0:
                    break
                if due == 1:  # window reaches before the anchor: skip
                    k_next += 1
                    continue
                _report(
                    rg,
                    dr,
                    oldest % L,
                    kernels[ph_r],
                    osc,
                    n_r,
                    fconsts,
                    g_pass[ph_r],
                    a2_bias[ph_r],
                    g_chirp[ph_r],
                    g_image[ph_r],
                    noise_gram[ph_r],
                    probe_taper[ph_r],
                    probe_gram[ph_r],
                    nz,
                    est,
                )
                held = 1
                defined, f, A, B, rocof, conv, cth, sth, cstep, sstep, n_rep = _held_model(
                    est, u, n_r, n, k_next, beta, f0, fs, min_amp, reps, n_rep, cstep, sstep
                )
                k_next += 1
            j += 1
        if not (last_only and i != n_in - 1):
            _out_row(out, 0 if last_only else i, held and defined, f, A, B, conv, rocof, cth, sth)
        # advance the rotor to sample n + 1
        if held and defined:
            c2 = cth * cstep - sth * sstep
            sth = sth * cstep + cth * sstep
            cth = c2
        n += 1
        ph = cyclic_next(ph, Q)
        rho = cyclic_next(rho, D)
    ist2 = np.array([n, j, k_next, k0, held, defined], dtype=np.int64)
    fst2 = np.array([delta0, beta, acr, aci, anr, ani, dcc, dcn, f, A, 0.0, B, rocof, conv, cth, sth])
    return out, reps[:n_rep].copy(), sse, n_pred, rg, dr, ist2, fst2, anchor.copy(), nz


N_TRANSITION = 9


def fresh_transition() -> np.ndarray:
    """(T)'s state at the start: no last report."""
    return np.zeros(N_TRANSITION)


@kernel
def transition_kernel(
    mag: np.ndarray, freq: np.ndarray, rocof: np.ndarray, trans: np.ndarray, fs_rep: float, n_hold: int, min_amp: float
) -> tuple[np.ndarray, np.ndarray]:
    """(T) over reports in order: their converged and the new state (``trans`` is not
    modified; layout in :meth:`Pmu._converged`). Slot 7 is the last report's converged."""
    st = trans.copy()
    n = mag.shape[0]
    conv = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        m, f, r = mag[i], freq[i], rocof[i]
        if not (math.isfinite(m) and math.isfinite(f) and math.isfinite(r)):
            for c in range(N_TRANSITION):
                st[c] = 0.0  # an undefined report: start over
            continue
        if st[4] == 0.0:  # the first report: nothing to check it against
            st[3] = n_hold - 1.0
        else:
            dm = abs(m / st[0] - 1.0) if st[0] > 0.0 else math.inf
            df = abs(f - st[1] - st[2] / fs_rep)
            tm = max(TRANSITION_MAG_FLOOR, TRANSITION_K * st[5])
            tf = max(TRANSITION_FREQ_FLOOR_HZ, TRANSITION_K * st[6])
            st[8] += 1.0
            w = max(TRANSITION_ALPHA, 1.0 / st[8])  # the plain mean of the first reports, then a running one
            st[5] += w * (min(dm, tm) - st[5])
            st[6] += w * (min(df, tf) - st[6])
            st[3] = 0.0 if (dm > tm or df > tf) else min(st[3] + 1.0, float(n_hold))
        st[0], st[1], st[2], st[4] = m, f, r, 1.0
        conv[i] = st[3] >= n_hold and m > min_amp
        st[7] = 1.0 if conv[i] else 0.0
    return conv, st
