"""``differential-rls``: the compiled kernels of the estimator. The real-input front end
(reference oscillator, quadrature demodulation, the low-pass of two biquads and its
re-tuning on a re-centring, decimation by cyclic intervals, outputs held between decimated
samples) around the baseband estimator of :mod:`sinewatch.estimators._differential_rls_core`,
and the I/Q kernel (the paper's own setting). The equations are in
:mod:`sinewatch.estimators.differential_rls`.
"""

from __future__ import annotations

import math

import numpy as np

from sinewatch.estimators._differential_rls_core import (
    A_IM,
    A_RE,
    C_PREV_IM,
    C_PREV_RE,
    K_FS,
    K_MIN_AMP,
    K_REBASE_EVERY,
    K_RECENTER,
    K_T0,
    K_W_NOM,
    K_W_RANGE,
    K_WARM,
    NH_IM,
    NH_RE,
    SINCE_REBASE,
    TWO_PI,
    _wrap,
    core_status,
    core_step,
    rebase,
    working_core,
)
from sinewatch.estimators.base import kernel
from sinewatch.schemas.errors import ParameterError

# front end (real-input kernel)
F_PSI, F_WREF, F_LREF, F_B = 0, 1, 2, 3  # reference phase (rad), frequency (rad/s), ramp (rad/s^2), offset
F_ZI = 4  # 3 channels x 2 biquads x 2 delays = 12 values: offset, in-phase-mix re, im
F_SNAP_W, F_SNAP_L, F_SNAP_PH, F_SNAP_A = 16, 17, 18, 19  # snapshot at the last decimated step
F_SNAP_VALID, F_SNAP_CONV, F_SNAP_STD, F_SINCE = 20, 21, 22, 23
F_LO_RE, F_LO_IM, F_LS_RE, F_LS_IM = 24, 25, 26, 27  # e^{j psi} and its per-sample step
F_BB_RE, F_BB_IM, F_BS_RE, F_BS_IM = 28, 29, 30, 31  # predicted baseband phasor and its step
FE_SIZE = 32


@kernel
def _biquads_steady(x: float, sos: np.ndarray, zi: np.ndarray, off: int) -> None:
    """Delays of the biquad cascade in steady state for a constant input x."""
    y = x
    for s in range(2):
        b0 = sos[s, 0]
        b1 = sos[s, 1]
        b2 = sos[s, 2]
        a1 = sos[s, 4]
        a2 = sos[s, 5]
        out = y * (b0 + b1 + b2) / (1.0 + a1 + a2)
        zi[off + 2 * s + 1] = b2 * y - a2 * out
        zi[off + 2 * s] = out - b0 * y
        y = out


@kernel(inline="always")
def _bq(
    x: float, b0: float, b1: float, b2: float, a1: float, a2: float, z1: float, z2: float
) -> tuple[float, float, float]:
    """One DF2T biquad step: (y, z1', z2')."""
    y = b0 * x + z1
    return y, b1 * x - a1 * y + z2, b2 * x - a2 * y


@kernel
def _biquads(x: float, sos: np.ndarray, zi: np.ndarray, off: int) -> float:
    """Two cascaded DF2T biquads (:func:`_bq`) on one channel; zi[off:off+4] are the delays.
    The kernel runs the same steps on register copies of the delays."""
    y = x
    for s in range(2):
        j = off + 2 * s
        y, zi[j], zi[j + 1] = _bq(y, sos[s, 0], sos[s, 1], sos[s, 2], sos[s, 4], sos[s, 5], zi[j], zi[j + 1])
    return y


@kernel(inline="always")
def _cis_small(a: float) -> complex:
    """e^{j a} for a tiny angle (a chirp's per-sample step change), to 1e-22 relative."""
    a2 = a * a
    return complex(1.0 - 0.5 * a2, a * (1.0 - a2 / 6.0))


@kernel(inline="always")
def _stage_response(sos: np.ndarray, s: int, zc: complex) -> complex:
    """H_s(z) of biquad s at z = zc (complex)."""
    return _stage_response_inv(sos, s, 1.0 / zc)


@kernel(inline="always")
def _stage_response_inv(sos: np.ndarray, s: int, zi1: complex) -> complex:
    """H_s(z) of biquad s given zi1 = 1 / z (shared by the stages: one complex division)."""
    zi2 = zi1 * zi1
    h: complex = (sos[s, 0] + sos[s, 1] * zi1 + sos[s, 2] * zi2) / (1.0 + sos[s, 4] * zi1 + sos[s, 5] * zi2)
    return h


@kernel(refcount=False)
def lowpass_response(sos: np.ndarray, om: float) -> complex:
    """H(e^{j om}) of the biquad cascade, om in rad per input sample."""
    zi1 = 1.0 / complex(math.cos(om), math.sin(om))
    return _stage_response_inv(sos, 0, zi1) * _stage_response_inv(sos, 1, zi1)


@kernel(refcount=False)
def _lowpass_retune(sos: np.ndarray, fe: np.ndarray, X: complex, om_old: float, om_new: float) -> None:
    """Move the tonal part of the demodulator's low-pass state from baseband frequency
    om_old to om_new (rad/sample), for a tone of phasor X at the current sample: the steady
    state of a DF2T biquad driven by X z^n is z1 = (H - b0) X z, z2 = (b2 - a2 H) X before
    the next sample. Used when the reference oscillator is re-centred, so that the low-pass
    output continues as if the reference had always been at the new frequency."""
    zo = complex(math.cos(om_old), math.sin(om_old))
    zn = complex(math.cos(om_new), math.sin(om_new))
    _retune_stages(sos, fe, X, zo, zn, _stage_response(sos, 0, zo), _stage_response(sos, 1, zo),
                   _stage_response(sos, 0, zn), _stage_response(sos, 1, zn))  # fmt: skip


@kernel(inline="always")
def _retune_stages(
    sos: np.ndarray, fe: np.ndarray, X: complex, zo: complex, zn: complex, ho0: complex, ho1: complex,
    hn0: complex, hn1: complex,
) -> None:  # fmt: skip
    """:func:`_lowpass_retune` given z = e^{j om} and the stages' responses there."""
    xo = X
    xn = X
    for s in range(2):
        ho = ho0 if s == 0 else ho1
        hn = hn0 if s == 0 else hn1
        d1 = (hn - sos[s, 0]) * xn * zn - (ho - sos[s, 0]) * xo * zo
        d2 = (sos[s, 2] - sos[s, 5] * hn) * xn - (sos[s, 2] - sos[s, 5] * ho) * xo
        fe[F_ZI + 4 + 2 * s] += d1.real
        fe[F_ZI + 8 + 2 * s] += d1.imag
        fe[F_ZI + 4 + 2 * s + 1] += d2.real
        fe[F_ZI + 8 + 2 * s + 1] += d2.imag
        xo = ho * xo
        xn = hn * xn


@kernel(refcount=False)
def _retune_responses(
    sos: np.ndarray, fe: np.ndarray, a_now: complex, om_old: float, om_new: float
) -> tuple[complex, complex]:
    """``h_old = H(om_old)``, ``h_new = H(om_new)`` (:func:`lowpass_response`) and
    :func:`_lowpass_retune` for the tone ``a_now / h_old``, each stage's response computed
    once for both (the same values, the same bits)."""
    zo = complex(math.cos(om_old), math.sin(om_old))
    zn = complex(math.cos(om_new), math.sin(om_new))
    zoi = 1.0 / zo
    zni = 1.0 / zn
    ho0 = _stage_response_inv(sos, 0, zoi)
    ho1 = _stage_response_inv(sos, 1, zoi)
    hn0 = _stage_response_inv(sos, 0, zni)
    hn1 = _stage_response_inv(sos, 1, zni)
    h_old = ho0 * ho1
    h_new = hn0 * hn1
    _retune_stages(sos, fe, a_now / h_old, zo, zn, ho0, ho1, hn0, hn1)
    return h_old, h_new


@kernel(inline="always")
def _demodulate(
    xi: float, b_prev: float, snap_valid: float, snap_a: float, lo_re: float, lo_im: float, bb_re: float, bb_im: float,
    s0b0: float, s0b1: float, s0b2: float, s0a1: float, s0a2: float,
    s1b0: float, s1b1: float, s1b2: float, s1a1: float, s1a2: float,
    o1: float, o2: float, o3: float, o4: float, r1: float, r2: float, r3: float, r4: float,
    q1: float, q2: float, q3: float, q4: float,
) -> tuple[
    float, float, float, float, float, float, float, float,
    float, float, float, float, float, float, float, float,
]:  # fmt: skip
    """One input sample of the real-input front end, branch-free: the one-step prediction
    error of x(i) (for residual_rms), the offset B^ (the low-pass on x itself), and c = cr + j ci
    (quadrature demodulation and low-pass); then the 12 new biquad delays. The one definition,
    called by :func:`differential_rls_kernel` and, one lane per channel, by its bank."""
    # one-step prediction of x(i) from the estimate so far (computed either way, then chosen:
    # a select, which a bank's lanes run as one vector, where a branch would keep them apart)
    held = b_prev + snap_a * (lo_re * bb_im + lo_im * bb_re)  # (lo bb).imag, as complex product computes it
    pred = held if snap_valid != 0.0 else b_prev
    e = xi - pred
    # offset: the same low-pass on x itself
    y1, o1, o2 = _bq(xi, s0b0, s0b1, s0b2, s0a1, s0a2, o1, o2)
    bh, o3, o4 = _bq(y1, s1b0, s1b1, s1b2, s1a1, s1a2, o3, o4)
    # quadrature demodulation: m = 2j (x - B^) e^{-j psi}, so that LPF(m) = A e^{j phi_d}
    # for x = B + A sin(psi + phi_d) (c = z + j y of eqs. 1-2)
    d2 = 2.0 * (xi - bh)
    y1, r1, r2 = _bq(d2 * lo_im, s0b0, s0b1, s0b2, s0a1, s0a2, r1, r2)
    cr, r3, r4 = _bq(y1, s1b0, s1b1, s1b2, s1a1, s1a2, r3, r4)
    y1, q1, q2 = _bq(d2 * lo_re, s0b0, s0b1, s0b2, s0a1, s0a2, q1, q2)
    ci, q3, q4 = _bq(y1, s1b0, s1b1, s1b2, s1a1, s1a2, q3, q4)
    return e, bh, cr, ci, o1, o2, o3, o4, r1, r2, r3, r4, q1, q2, q3, q4


@kernel(inline="always")
def _store_reference(fe: np.ndarray, psi: float, w: float, lam: float, pred: complex, step: complex) -> None:
    """The reference oscillator's phase, frequency and ramp and the prediction rotator and its
    step into the state vector at the end of a block."""
    fe[F_PSI] = psi
    fe[F_WREF] = w
    fe[F_LREF] = lam
    fe[F_BB_RE] = pred.real
    fe[F_BB_IM] = pred.imag
    fe[F_BS_RE] = step.real
    fe[F_BS_IM] = step.imag


@kernel(inline="always")
def _write_snapshot(
    fe: np.ndarray, w: float, lam: float, amp: float, valid: bool, conv: bool, std: float, T0: float
) -> None:
    """The snapshot of a decimated sample that the outputs hold until the next one (frequency
    offset rad/s, ramp rad/s^2, amplitude, validity, convergence, std in Hz), its age reset."""
    fe[F_SNAP_W] = w
    fe[F_SNAP_L] = lam
    fe[F_SNAP_A] = amp
    fe[F_SNAP_VALID] = 1.0 if valid else 0.0
    fe[F_SNAP_CONV] = 1.0 if (conv and valid) else 0.0
    fe[F_SNAP_STD] = std / (TWO_PI * T0) if math.isfinite(std) else -1.0  # state stays finite
    fe[F_SINCE] = 0.0


@kernel(inline="always")
def front_constants(consts: np.ndarray) -> tuple[float, float, float, float, float]:
    """``(1 / fs, T0, d0 = T0 fs, w_lo, w_hi)``: the sample interval, the decimated interval T0
    (s) and its length in input samples, and the reference's tracking range (rad/s), read from
    ``consts`` once: every kernel of the front end and its bank starts from them."""
    fs = consts[K_FS]
    T0 = consts[K_T0]
    return 1.0 / fs, T0, T0 * fs, consts[K_W_NOM] - consts[K_W_RANGE], consts[K_W_NOM] + consts[K_W_RANGE]


@kernel(inline="always")
def lowpass_coefficients(
    sos: np.ndarray,
) -> tuple[float, float, float, float, float, float, float, float, float, float]:
    """The two biquads' coefficients (b0, b1, b2, a1, a2 of each; a0 = 1) as floats, so that the
    low-pass of :func:`_demodulate` runs from registers."""
    return sos[0, 0], sos[0, 1], sos[0, 2], sos[0, 4], sos[0, 5], sos[1, 0], sos[1, 1], sos[1, 2], sos[1, 4], sos[1, 5]


@kernel(inline="always")
def _step_status(
    cr: float, ci: float, u: float, core: np.ndarray, theta: np.ndarray, P: np.ndarray, tab: np.ndarray,
    consts: np.ndarray, rr: np.ndarray, ri: np.ndarray, xr_: np.ndarray, xi_: np.ndarray, px: np.ndarray,
) -> tuple[float, float, float, bool, bool, bool, float, bool]:  # fmt: skip
    """The start of every decimated step, real or I/Q input: :func:`core_step` on c = cr + j ci,
    :func:`core_status` after it, and whether a re-centring is due (last: every
    ``K_REBASE_EVERY`` decimated samples)."""
    core_step(cr, ci, u, core, theta, P, tab, consts, rr, ri, xr_, xi_, px)
    w, lb, std, val, confident, conv, lsig = core_status(core, theta, P, consts)
    return w, lb, std, val, confident, conv, lsig, core[SINCE_REBASE] >= consts[K_REBASE_EVERY]


@kernel(inline="always")
def _decimated_step(
    cr: float, ci: float, u: float, core: np.ndarray, theta: np.ndarray, P: np.ndarray, tab: np.ndarray,
    consts: np.ndarray, rr: np.ndarray, ri: np.ndarray, xr_: np.ndarray, xi_: np.ndarray, px: np.ndarray,
    idx: np.ndarray, T: np.ndarray, b0: np.ndarray, work: np.ndarray, sos: np.ndarray, fe: np.ndarray,
    wref: float, lref: float, r1: float, r2: float, r3: float, r4: float,
    q1: float, q2: float, q3: float, q4: float,
) -> tuple[
    float, float, float, float, float, float, float, float, float, float, float, float, complex, complex,
]:  # fmt: skip
    """One decimated sample c = cr + j ci (dt = u T0) of the real-input estimator:
    :func:`core_step`, the periodic re-centring of the reference (with the low-pass state
    moved to the new frequency) and the snapshot the outputs hold until the next one (written
    into ``fe``). Returns the new reference frequency and ramp, the 8 delays of the
    demodulator's low-pass, ``a^ / H * |H|^2`` (whose argument is the snapshot's phase) and
    the prediction rotator and its step. The one definition, called by
    :func:`differential_rls_kernel` and, lane by lane, by its bank."""
    inv_fs, T0, d0, w_lo, w_hi = front_constants(consts)
    recenter = consts[K_RECENTER] != 0.0
    w, lb, std, val, confident, conv, lsig, due = _step_status(
        cr, ci, u, core, theta, P, tab, consts, rr, ri, xr_, xi_, px
    )
    if due:
        dw = 0.0
        dl = 0.0
        if recenter and confident:
            # periodic re-centring of the reference oscillator on the estimate (frequency
            # and, with the derivative model, its ramp), clamped to the tracking range
            wnew = wref + w / T0
            lnew = lref + lsig / (T0 * T0)
            if wnew > w_hi:
                wnew = w_hi
                lnew = 0.0
            elif wnew < w_lo:
                wnew = w_lo
                lnew = 0.0
            dw = (wnew - wref) * T0
            dl = (lnew - lref) * T0 * T0
            if dw != 0.0:
                om_old = w / d0
                om_new = (w - dw) / d0
                a_now = complex(core[A_RE], core[A_IM])
                fe[F_ZI + 4], fe[F_ZI + 5], fe[F_ZI + 6], fe[F_ZI + 7] = r1, r2, r3, r4
                fe[F_ZI + 8], fe[F_ZI + 9], fe[F_ZI + 10], fe[F_ZI + 11] = q1, q2, q3, q4
                h_old, h_new = _retune_responses(sos, fe, a_now, om_old, om_new)
                r1, r2, r3, r4 = fe[F_ZI + 4], fe[F_ZI + 5], fe[F_ZI + 6], fe[F_ZI + 7]
                q1, q2, q3, q4 = fe[F_ZI + 8], fe[F_ZI + 9], fe[F_ZI + 10], fe[F_ZI + 11]
                g = h_new / h_old  # c(k-1), a^, n^ as if filtered at the new frequency
                cp = complex(core[C_PREV_RE], core[C_PREV_IM]) * g
                core[C_PREV_RE] = cp.real
                core[C_PREV_IM] = cp.imag
                a_now = a_now * g
                core[A_RE] = a_now.real
                core[A_IM] = a_now.imag
                nh = complex(core[NH_RE], core[NH_IM]) * g
                core[NH_RE] = nh.real
                core[NH_IM] = nh.imag
            wref = wnew
            lref = lnew
        rebase(core, theta, P, tab, consts, dw, dl, idx, T, b0, work)
        w, lb, std, val, confident, conv, lsig = core_status(core, theta, P, consts)
    # snapshot, compensated for the low-pass response at the estimated baseband frequency
    h = lowpass_response(sos, w / d0)
    ah = complex(core[A_RE], core[A_IM]) * h.conjugate()  # a^ / H * |H|^2
    habs2 = h.real * h.real + h.imag * h.imag
    aah = abs(ah)
    amp = aah / habs2  # |a^ / H|
    val = val and amp > consts[K_MIN_AMP] and math.isfinite(amp)
    wb_s = w / T0
    lb_s = lb / (T0 * T0)
    # arg(a^ / H) = atan2(ah): only outputs read it, so it is taken when one is written
    # (or the block ends), from the same ah: the same bits, one atan2 a block at last_only
    ah_re = ah.real
    ah_im = ah.imag
    _write_snapshot(fe, wb_s, lb_s, amp, val, conv, std, T0)
    bb = ah / aah if amp > 0.0 else complex(1.0, 0.0)  # e^{j ph0}
    a_ = (wb_s + 0.5 * lb_s * inv_fs) * inv_fs
    bs = complex(math.cos(a_), math.sin(a_))
    return wref, lref, r1, r2, r3, r4, q1, q2, q3, q4, ah_re, ah_im, bb, bs


@kernel(inline="always")
def _write_outputs(
    out: np.ndarray,
    ext: np.ndarray,
    j: int,
    fe: np.ndarray,
    at: int,
    stride: int,
    b: float,
    psi: float,
    wref: float,
    lref: float,
    ts: float,
) -> None:
    """Row ``j`` of the real-input outputs: the snapshot of the last decimated sample held,
    its phase advanced by ``ts`` seconds at the estimated frequency; ``b`` the offset B^. The
    snapshot's slot ``F_x`` is ``fe[at + F_x * stride]`` (0 and 1 for a channel's own state
    vector, lane and LANES in a bank's lane-major work array)."""
    if fe[at + F_SNAP_VALID * stride] != 0.0:
        wbb = fe[at + F_SNAP_W * stride]
        lbb = fe[at + F_SNAP_L * stride]
        out[j, 0] = (wref + wbb + lbb * ts) / TWO_PI
        out[j, 1] = fe[at + F_SNAP_A * stride]
        out[j, 2] = _wrap(psi + fe[at + F_SNAP_PH * stride] + (wbb + 0.5 * lbb * ts) * ts)
        out[j, 3] = b
        out[j, 4] = fe[at + F_SNAP_CONV * stride]
        ext[j, 0] = (lref + lbb) / TWO_PI
        ext[j, 1] = fe[at + F_SNAP_STD * stride] if fe[at + F_SNAP_STD * stride] >= 0.0 else np.nan
    else:
        out[j, 0] = np.nan
        out[j, 1] = np.nan
        out[j, 2] = np.nan
        out[j, 3] = b
        out[j, 4] = 0.0
        ext[j, 0] = np.nan
        ext[j, 1] = np.nan
    ext[j, 2] = wref / TWO_PI


@kernel(inline="always")
def _kernel_start(
    fe_in: np.ndarray, ist_in: np.ndarray, n: int, last_only: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The working copies of the front end's state (a kernel never writes its inputs) and the
    outputs of a block of ``n`` samples: (fe, ist, out (N or 1, 5), extras (N or 1, 3))."""
    nout = 1 if last_only else n
    return fe_in.copy(), ist_in.copy(), np.empty((nout, 5)), np.empty((nout, 3))


@kernel
def differential_rls_kernel(
    x: np.ndarray, fe_in: np.ndarray, core_in: np.ndarray, theta_in: np.ndarray, P_in: np.ndarray, ist_in: np.ndarray,
    sos: np.ndarray, tab: np.ndarray, cyc: np.ndarray, consts: np.ndarray, last_only: bool,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Real input -> quadrature demodulation against the reference oscillator -> low-pass
    (two biquads, ``sos``) -> decimation by the cyclic intervals ``cyc`` (input samples)
    -> :func:`core_step` at every decimated sample; outputs at every input sample.

    Returns (out (N or 1, 5), extras (N or 1, 3), sse, fe, core, theta, P, ist). Pure.
    """
    fe, ist, out, ext = _kernel_start(fe_in, ist_in, x.shape[0], last_only)
    core, theta, P, rr, ri, xr_, xi_, px, idx, T, b0, work = working_core(core_in, theta_in, P_in, tab)
    n = x.shape[0]
    inv_fs, _, d0, w_lo, w_hi = front_constants(consts)
    warm = consts[K_WARM]
    ncyc = cyc.shape[0]
    sse = 0.0
    psi = fe[F_PSI]
    wref = fe[F_WREF]
    lref = fe[F_LREF]
    lo = complex(fe[F_LO_RE], fe[F_LO_IM])  # e^{j psi}
    ls = complex(fe[F_LS_RE], fe[F_LS_IM])  # its per-sample step
    bb = complex(fe[F_BB_RE], fe[F_BB_IM])  # e^{j phi_bb} predicted for this sample
    bs = complex(fe[F_BS_RE], fe[F_BS_IM])  # its per-sample step
    # the chirp corrections of the two steps, _cis_small of (ramp / fs^2): computed once per
    # value of the ramp, not per sample (the same function of the same value: the same bits)
    cb_for = 0.0
    cb = complex(1.0, 0.0)
    cl_for = 0.0
    cl = complex(1.0, 0.0)
    ph_pending = False  # fe[F_SNAP_PH] still to take from (ah_re, ah_im)
    ah_re = 0.0
    ah_im = 0.0
    # e^{j a} of the reference's per-sample step a: recomputed only when a changes (on a
    # re-centring or with a ramp), the same function of the same value: the same bits
    ls_for = math.nan
    ls_exact = complex(1.0, 0.0)
    if ist[2] == 0:  # first sample ever: start the offset low-pass in steady state at x(0)
        _biquads_steady(x[0], sos, fe, F_ZI)
    # the low-pass coefficients and the 12 delays of its three channels live in registers
    s0b0, s0b1, s0b2, s0a1, s0a2, s1b0, s1b1, s1b2, s1a1, s1a2 = lowpass_coefficients(sos)
    o1, o2, o3, o4 = fe[F_ZI], fe[F_ZI + 1], fe[F_ZI + 2], fe[F_ZI + 3]
    r1, r2, r3, r4 = fe[F_ZI + 4], fe[F_ZI + 5], fe[F_ZI + 6], fe[F_ZI + 7]
    q1, q2, q3, q4 = fe[F_ZI + 8], fe[F_ZI + 9], fe[F_ZI + 10], fe[F_ZI + 11]
    for i in range(n):
        xi = x[i]
        if ist[2] < warm:
            ist[2] += 1
        e, bh, cr, ci, o1, o2, o3, o4, r1, r2, r3, r4, q1, q2, q3, q4 = _demodulate(
            xi, fe[F_B], fe[F_SNAP_VALID], fe[F_SNAP_A], lo.real, lo.imag, bb.real, bb.imag, s0b0, s0b1, s0b2, s0a1, s0a2,
            s1b0, s1b1, s1b2, s1a1, s1a2, o1, o2, o3, o4, r1, r2, r3, r4, q1, q2, q3, q4,
        )  # fmt: skip
        sse += e * e
        fe[F_B] = bh
        # ---- decimation with the cyclic intervals (nonuniform cyclic sampling, Section 5)
        ist[0] += 1
        stepped = False
        if ist[0] >= cyc[ist[1]] and ist[2] >= warm:  # the core starts once the low-pass settled
            stepped = True
            u = cyc[ist[1]] / d0
            ist[0] = 0
            ist[1] = (ist[1] + 1) % ncyc
            wref, lref, r1, r2, r3, r4, q1, q2, q3, q4, ah_re, ah_im, bb, bs = _decimated_step(
                cr, ci, u, core, theta, P, tab, consts, rr, ri, xr_, xi_, px, idx, T, b0, work, sos, fe,
                wref, lref, r1, r2, r3, r4, q1, q2, q3, q4,
            )  # fmt: skip
            ph_pending = True
        else:
            fe[F_SINCE] += 1.0
        # ---- outputs at this input sample (hold the decimated estimate, phase propagated)
        if not last_only or i == n - 1:
            j = 0 if last_only else i
            ts = fe[F_SINCE] * inv_fs
            if ph_pending:
                fe[F_SNAP_PH] = math.atan2(ah_im, ah_re)
                ph_pending = False
            _write_outputs(out, ext, j, fe, 0, 1, fe[F_B], psi, wref, lref, ts)
        # ---- advance the baseband prediction rotator by one sample
        bb = bb * bs
        snap_l = fe[F_SNAP_L]
        if snap_l != 0.0:
            if snap_l != cb_for:
                cb = _cis_small(snap_l * inv_fs * inv_fs)
                cb_for = snap_l
            bs = bs * cb
        # ---- advance the reference oscillator (linear frequency ramp, exact phase integral)
        psi = _wrap(psi + (wref + 0.5 * lref * inv_fs) * inv_fs)
        wref += lref * inv_fs
        clamped = False
        if wref > w_hi:
            wref = w_hi
            lref = 0.0
            clamped = True
        elif wref < w_lo:
            wref = w_lo
            lref = 0.0
            clamped = True
        if stepped or clamped:  # re-synchronise the rotator on psi (exact, once per decimated step)
            lo = complex(math.cos(psi), math.sin(psi))
            a_ = (wref + 0.5 * lref * inv_fs) * inv_fs
            if a_ != ls_for:
                ls_exact = complex(math.cos(a_), math.sin(a_))
                ls_for = a_
            ls = ls_exact
        else:
            lo = lo * ls
        if lref != 0.0:
            if lref != cl_for:
                cl = _cis_small(lref * inv_fs * inv_fs)
                cl_for = lref
            ls = ls * cl
    if ph_pending:
        fe[F_SNAP_PH] = math.atan2(ah_im, ah_re)
    fe[F_ZI], fe[F_ZI + 1], fe[F_ZI + 2], fe[F_ZI + 3] = o1, o2, o3, o4
    fe[F_ZI + 4], fe[F_ZI + 5], fe[F_ZI + 6], fe[F_ZI + 7] = r1, r2, r3, r4
    fe[F_ZI + 8], fe[F_ZI + 9], fe[F_ZI + 10], fe[F_ZI + 11] = q1, q2, q3, q4
    _store_reference(fe, psi, wref, lref, bb, bs)
    fe[F_LO_RE] = lo.real
    fe[F_LO_IM] = lo.imag
    fe[F_LS_RE] = ls.real
    fe[F_LS_IM] = ls.imag
    return out, ext, sse, fe, core, theta, P, ist


@kernel(inline="always")
def _iq_recenter(
    move: bool, w: float, lsig: float, w2: float, l2: float, w_max: float
) -> tuple[float, float, float, float]:
    """The I/Q kernel's periodic re-centring of its digital reference on the estimate (Section 10),
    when ``move`` (re-centring on, the estimate confident): ``(dw, dl, w2, l2)``, the shift of the
    baseband model (rad/T0, rad/T0^2) and the reference's new offset and ramp, clamped to the
    tracking range +- ``w_max``; no shift otherwise."""
    dw = 0.0
    dl = 0.0
    if move:
        dw = w
        dl = lsig
        wnew = w2 + dw
        if wnew > w_max or wnew < -w_max:  # clamped to the tracking range
            wnew = w_max if wnew > 0.0 else -w_max
            dw = wnew - w2
            dl = -l2
        w2 = wnew
        l2 += dl
    return dw, dl, w2, l2


@kernel
def differential_rls_iq_kernel(
    x: np.ndarray, fe_in: np.ndarray, core_in: np.ndarray, theta_in: np.ndarray, P_in: np.ndarray, ist_in: np.ndarray,
    tab: np.ndarray, cyc: np.ndarray, consts: np.ndarray, last_only: bool,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """In-phase/quadrature input (the paper's own setting, eqs. 1-2): ``x`` is (N, 2), column
    0 the in-phase y = A sin(w t + phi), column 1 the quadrature z = A cos(w t + phi), taken
    against an external oscillator at consts[K_W_NOM]. c(k) = z + j y is taken every
    cyc[0], cyc[1], ... input samples (nonuniform cyclic sampling, Section 5; the first
    sample ever is the first c), rotated by the digital reference oscillator (phase psi2,
    offset w2 rad/T0 and ramp l2 rad/T0^2 from the external one, re-centred on the
    estimate as in :func:`iq_kernel`, kept within +- consts[K_W_RANGE]) and handed to
    :func:`core_step`; outputs at every input sample, held between decimated samples with
    the phase advanced at the estimated frequency. The one-step prediction error is that
    of the in-phase column (y = A sin(phase_rad), the output convention).

    Returns what :func:`differential_rls_kernel` returns. Pure.
    """
    fe, ist, out, ext = _kernel_start(fe_in, ist_in, x.shape[0], last_only)
    core, theta, P, rr, ri, xr_, xi_, px, idx, T, b0, work = working_core(core_in, theta_in, P_in, tab)
    n = x.shape[0]
    inv_fs, T0, d0, _, _ = front_constants(consts)
    w_nom = consts[K_W_NOM]
    w_max = consts[K_W_RANGE] * T0  # the digital reference stays within +- the tracking range
    recenter = consts[K_RECENTER] != 0.0
    ncyc = cyc.shape[0]
    psi2 = fe[F_PSI]
    w2 = fe[F_WREF]
    l2 = fe[F_LREF]
    pp = complex(fe[F_BB_RE], fe[F_BB_IM])  # predicted c for this sample (A e^{j phase})
    ps = complex(fe[F_BS_RE], fe[F_BS_IM])  # its per-sample step
    sse = 0.0
    for i in range(n):
        yi = x[i, 0]
        zi = x[i, 1]
        # ---- one-step prediction of the in-phase sample from the estimate so far (residual_rms)
        e = yi - pp.imag if fe[F_SNAP_VALID] != 0.0 else yi
        sse += e * e
        # ---- nonuniform cyclic sampling (Section 5): c(k) every cyc[j] input samples
        ist[0] += 1
        first = ist[2] == 0
        if first or ist[0] >= cyc[ist[1]]:
            if first:
                u = 0.0  # no interval before the first sample (core_step only stores it)
                ist[2] = 1
            else:
                u = cyc[ist[1]] / d0
                ist[1] = (ist[1] + 1) % ncyc
                # advance the digital reference over dt_k = u T0 (as iq_kernel does)
                psi2 += w2 * u + 0.5 * l2 * u * u
                w2 += l2 * u
                psi2 = math.pi - ((math.pi - psi2) % TWO_PI)
                if w2 > w_max or w2 < -w_max:
                    w2 = w_max if w2 > 0.0 else -w_max
                    l2 = 0.0
            ist[0] = 0
            c0 = math.cos(psi2)
            s0 = math.sin(psi2)
            cr = zi * c0 + yi * s0  # c e^{-j psi2}, c = z + j y (eqs. 1-2)
            ci = yi * c0 - zi * s0
            # the order of _decimated_step (step, status, re-centring, status), with this kernel's own
            # re-centring: a digital reference within +- the range, no low-pass to re-tune
            w, lb, std, val, confident, conv, lsig, due = _step_status(
                cr, ci, u, core, theta, P, tab, consts, rr, ri, xr_, xi_, px
            )
            if due:
                dw, dl, w2, l2 = _iq_recenter(recenter and confident, w, lsig, w2, l2, w_max)
                rebase(core, theta, P, tab, consts, dw, dl, idx, T, b0, work)
                w, lb, std, val, confident, conv, lsig = core_status(core, theta, P, consts)
            amp = math.hypot(core[A_RE], core[A_IM])  # A^ = |a^|, eq. (23)
            val = val and amp > consts[K_MIN_AMP] and math.isfinite(amp)
            wt = (w + w2) / T0  # offset from the external oscillator, rad/s
            lt = (lb + l2) / (T0 * T0)
            ph = _wrap(math.atan2(core[A_IM], core[A_RE]) + psi2)  # phi^(t_k), eq. (23)
            fe[F_SNAP_PH] = ph
            _write_snapshot(fe, wt, lt, amp, val, conv, std, T0)
            pp = complex(amp * math.cos(ph), amp * math.sin(ph)) if val else complex(0.0, 0.0)
            a_ = (wt + 0.5 * lt * inv_fs) * inv_fs
            ps = complex(math.cos(a_), math.sin(a_))
        else:
            fe[F_SINCE] += 1.0
        # ---- outputs at this input sample (hold the decimated estimate, phase propagated)
        if not last_only or i == n - 1:
            j = 0 if last_only else i
            ts = fe[F_SINCE] * inv_fs
            if fe[F_SNAP_VALID] != 0.0:
                wt = fe[F_SNAP_W]
                lt = fe[F_SNAP_L]
                out[j, 0] = (w_nom + wt + lt * ts) / TWO_PI
                out[j, 1] = fe[F_SNAP_A]
                out[j, 2] = _wrap(fe[F_SNAP_PH] + (wt + 0.5 * lt * ts) * ts)
                out[j, 3] = 0.0  # the model (eqs. 1-2) has no offset
                out[j, 4] = fe[F_SNAP_CONV]
                ext[j, 0] = lt / TWO_PI
                ext[j, 1] = fe[F_SNAP_STD] if fe[F_SNAP_STD] >= 0.0 else np.nan
            else:
                out[j, 0] = np.nan
                out[j, 1] = np.nan
                out[j, 2] = np.nan
                out[j, 3] = np.nan
                out[j, 4] = 0.0
                ext[j, 0] = np.nan
                ext[j, 1] = np.nan
            ext[j, 2] = (w_nom + w2 / T0) / TWO_PI
        # ---- advance the prediction by one sample (a chirp's step turns at lt / fs^2)
        pp = pp * ps
        if fe[F_SNAP_L] != 0.0:
            ps = ps * _cis_small(fe[F_SNAP_L] * inv_fs * inv_fs)
    _store_reference(fe, psi2, w2, l2, pp, ps)
    return out, ext, sse, fe, core, theta, P, ist


def settling_samples(sos: np.ndarray, fs: float, bandwidth_hz: float, tol: float = 1e-2) -> int:
    """Input samples after which the low-pass impulse response has shed all but ``tol`` of
    its absolute area (the start-up transient of the demodulator)."""
    n = math.ceil(40.0 * fs / bandwidth_hz) + 8
    imp = np.zeros(n)
    imp[0] = 1.0
    from scipy import signal  # here, not with the module: listing the estimators need not import it (~1 s CPU)

    h = np.abs(signal.sosfilt(sos, imp))
    tail = np.cumsum(h[::-1])[::-1]
    return int(np.argmax(tail < tol * tail[0]))


def lowpass_noise_correlation(sos: np.ndarray, fs: float, bandwidth_hz: float, lag: int) -> float:
    """Correlation coefficient of white noise after the low-pass at ``lag`` input samples,
    sum h(i) h(i + lag) / sum h(i)^2: the r1 of the decimated noise (cf. eq. 14)."""
    n = math.ceil(40.0 * fs / bandwidth_hz) + lag + 8
    imp = np.zeros(n)
    imp[0] = 1.0
    from scipy import signal  # here, not with the module (see settling_samples)

    h = signal.sosfilt(sos, imp)
    return float(np.dot(h[:-lag], h[lag:]) / np.dot(h, h)) if lag < n else 0.0


def decimation_pattern(fs: float, bandwidth_hz: float, oversampling: float, n: int, spacing: float) -> list[int]:
    """Input samples between decimated samples, cycled: D0, D0 - s, ... (ceil(n/2) values when n > 2)."""
    d0 = round(fs / (2.0 * bandwidth_hz * oversampling))
    if d0 < 1:
        raise ParameterError(
            f"oversampling: expected 2 * bandwidth_hz * oversampling <= sample_rate_hz "
            f"(decimation factor >= 1), got 2 * {bandwidth_hz} * {oversampling} > {fs}"
        )
    if n <= 2:
        return [d0]
    step = max(1, round(spacing * d0))
    pattern = [d0 - j * step for j in range((n + 1) // 2)]
    if pattern[-1] < 1:
        raise ParameterError(
            f"n_terms: expected ceil(n/2) = {len(pattern)} distinct sampling intervals "
            f"(nonuniform cyclic sampling), got a decimation factor of only {d0} input samples: "
            "raise the sample rate or lower oversampling"
        )
    return pattern
