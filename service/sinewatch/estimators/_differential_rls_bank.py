"""``differential-rls``: the compiled bank (:mod:`sinewatch.estimators.bank`), the channels of a
frame through one kernel call, each channel's outputs and state bit for bit those of
:func:`differential_rls_kernel` run on it alone.
"""

from __future__ import annotations

import math

import numpy as np

from sinewatch.estimators._differential_rls_core import (
    CORE_SIZE,
    K_WARM,
    TWO_PI,
    _wrap,
    transform_scratch,
)
from sinewatch.estimators._differential_rls_front import (
    F_B,
    F_BB_IM,
    F_BB_RE,
    F_BS_IM,
    F_BS_RE,
    F_LO_IM,
    F_LO_RE,
    F_LREF,
    F_LS_IM,
    F_LS_RE,
    F_PSI,
    F_SINCE,
    F_SNAP_A,
    F_SNAP_L,
    F_SNAP_PH,
    F_SNAP_VALID,
    F_WREF,
    F_ZI,
    FE_SIZE,
    _biquads_steady,
    _cis_small,
    _decimated_step,
    _demodulate,
    _write_outputs,
    front_constants,
    lowpass_coefficients,
)
from sinewatch.estimators.base import bank_outputs, kernel

# ---- bank: the channels of a frame together (sinewatch.estimators.bank) -------------------
LANES = 8  # channels advanced together: 8 doubles, one AVX-512 register
# rows of the bank's lane-major work array, LANES doubles each: the FE_SIZE slots of ``fe``
# (rows 0..31, the same slot numbers), then the sample in, c = cr + j ci out of the front end,
# the sse, the lanes' fix-up flags of the advance, psi before its wrap
_RX, _RCR, _RCI, _RSSE, _RFIX, _RPRE = FE_SIZE, FE_SIZE + 1, FE_SIZE + 2, FE_SIZE + 3, FE_SIZE + 4, FE_SIZE + 5
_ROWS = FE_SIZE + 6
_FIX_CLAMPED, _FIX_WRAP = 1.0, 2.0  # _RFIX: the reference was clamped; psi needs more than one wrap


@kernel(inline="always")
def _bank_front(
    S: np.ndarray, lane: int,
    s0b0: float, s0b1: float, s0b2: float, s0a1: float, s0a2: float,
    s1b0: float, s1b1: float, s1b2: float, s1a1: float, s1a2: float,
) -> None:  # fmt: skip
    """:func:`_demodulate` on lane ``lane`` of ``S``: reads and writes that one array at
    constant offsets, so that the compiler runs the lanes as one vector."""
    L = LANES
    z = F_ZI * L + lane
    e, bh, cr, ci, o1, o2, o3, o4, r1, r2, r3, r4, q1, q2, q3, q4 = _demodulate(
        S[_RX * L + lane], S[F_B * L + lane], S[F_SNAP_VALID * L + lane], S[F_SNAP_A * L + lane],
        S[F_LO_RE * L + lane], S[F_LO_IM * L + lane], S[F_BB_RE * L + lane], S[F_BB_IM * L + lane],
        s0b0, s0b1, s0b2, s0a1, s0a2, s1b0, s1b1, s1b2, s1a1, s1a2,
        S[z], S[z + L], S[z + 2 * L], S[z + 3 * L], S[z + 4 * L], S[z + 5 * L], S[z + 6 * L], S[z + 7 * L],
        S[z + 8 * L], S[z + 9 * L], S[z + 10 * L], S[z + 11 * L],
    )  # fmt: skip
    S[_RSSE * L + lane] += e * e
    S[F_B * L + lane] = bh
    S[z], S[z + L], S[z + 2 * L], S[z + 3 * L] = o1, o2, o3, o4
    S[z + 4 * L], S[z + 5 * L], S[z + 6 * L], S[z + 7 * L] = r1, r2, r3, r4
    S[z + 8 * L], S[z + 9 * L], S[z + 10 * L], S[z + 11 * L] = q1, q2, q3, q4
    S[_RCR * L + lane] = cr
    S[_RCI * L + lane] = ci


@kernel(inline="always")
def _cmul(a: float, b: float, c: float, d: float) -> tuple[float, float]:
    """(a + j b)(c + j d) on floats, in the operations and order of numba's complex product
    (ac - bd, ad + bc): the same bits, and no complex value, which keeps a bank's loop over its
    lanes from being vectorised."""
    return a * c - b * d, a * d + b * c


@kernel(inline="always")
def _cis_small_parts(a: float) -> tuple[float, float]:
    """:func:`_cis_small` as two floats (the same operations)."""
    a2 = a * a
    return 1.0 - 0.5 * a2, a * (1.0 - a2 / 6.0)


@kernel(inline="always")
def _bank_advance(S: np.ndarray, lane: int, inv_fs: float, w_lo: float, w_hi: float) -> None:
    """The end of an input sample in :func:`differential_rls_kernel` on lane ``lane`` of ``S``,
    branch-free and on floats: the prediction rotator and its chirp step, the reference
    oscillator's phase (one wrap: more is flagged), frequency and ramp (clamped: flagged), its
    rotator advanced by its step. A flagged lane and a lane that took a decimated step are
    finished by :func:`_bank_fixup`, as the single kernel's branches do. A cached
    ``_cis_small`` there is recomputed here: the same function of the same value, the same
    bits. Every value is computed, then chosen (selects keep the lanes one vector)."""
    L = LANES
    bbr, bbi = S[F_BB_RE * L + lane], S[F_BB_IM * L + lane]
    bsr, bsi = S[F_BS_RE * L + lane], S[F_BS_IM * L + lane]
    snap_l = S[F_SNAP_L * L + lane]
    bbr, bbi = _cmul(bbr, bbi, bsr, bsi)
    cr_, ci_ = _cis_small_parts(snap_l * inv_fs * inv_fs)
    chr_, chi_ = _cmul(bsr, bsi, cr_, ci_)
    chirp = snap_l != 0.0
    bsr = chr_ if chirp else bsr
    bsi = chi_ if chirp else bsi
    wref = S[F_WREF * L + lane]
    lref = S[F_LREF * L + lane]
    pre = S[F_PSI * L + lane] + (wref + 0.5 * lref * inv_fs) * inv_fs
    down = pre - TWO_PI
    up = pre + TWO_PI
    psi = down if pre > math.pi else (up if pre <= -math.pi else pre)
    wref += lref * inv_fs
    hi = wref > w_hi
    low = wref < w_lo
    clamped = hi | low
    wref = w_hi if hi else (w_lo if low else wref)
    lref = 0.0 if clamped else lref
    lsr, lsi = S[F_LS_RE * L + lane], S[F_LS_IM * L + lane]
    lor, loi = _cmul(S[F_LO_RE * L + lane], S[F_LO_IM * L + lane], lsr, lsi)
    cr_, ci_ = _cis_small_parts(lref * inv_fs * inv_fs)
    chr_, chi_ = _cmul(lsr, lsi, cr_, ci_)
    chirp = lref != 0.0
    lsr = chr_ if chirp else lsr
    lsi = chi_ if chirp else lsi
    wrap = (psi <= -math.pi) | (psi > math.pi) | (psi != psi)  # out of (-pi, pi], or NaN
    S[_RFIX * L + lane] = (_FIX_CLAMPED if clamped else 0.0) + (_FIX_WRAP if wrap else 0.0)
    S[_RPRE * L + lane] = pre
    S[F_BB_RE * L + lane], S[F_BB_IM * L + lane] = bbr, bbi
    S[F_BS_RE * L + lane], S[F_BS_IM * L + lane] = bsr, bsi
    S[F_PSI * L + lane] = psi
    S[F_WREF * L + lane] = wref
    S[F_LREF * L + lane] = lref
    S[F_LO_RE * L + lane], S[F_LO_IM * L + lane] = lor, loi
    S[F_LS_RE * L + lane], S[F_LS_IM * L + lane] = lsr, lsi


@kernel(inline="always")
def _bank_fixup(S: np.ndarray, lane: int, stepped: bool, inv_fs: float) -> None:
    """The branches :func:`_bank_advance` left to lane ``lane``: psi wrapped in full, and after
    a decimated step or a clamp the reference's rotator re-synchronised on psi."""
    L = LANES
    fix = S[_RFIX * L + lane]
    if fix >= _FIX_WRAP:
        S[F_PSI * L + lane] = _wrap(S[_RPRE * L + lane])
    if stepped or fix == _FIX_CLAMPED or fix == _FIX_CLAMPED + _FIX_WRAP:
        psi = S[F_PSI * L + lane]
        wref = S[F_WREF * L + lane]
        lref = S[F_LREF * L + lane]
        lo = complex(math.cos(psi), math.sin(psi))
        a_ = (wref + 0.5 * lref * inv_fs) * inv_fs
        ls = complex(math.cos(a_), math.sin(a_))
        if lref != 0.0:
            ls = ls * _cis_small(lref * inv_fs * inv_fs)
        S[F_LO_RE * L + lane], S[F_LO_IM * L + lane] = lo.real, lo.imag
        S[F_LS_RE * L + lane], S[F_LS_IM * L + lane] = ls.real, ls.imag


# the arguments of differential_rls_kernel, by the bank's calling convention (sinewatch.estimators.bank):
# the same list (it must be: the bank calls one with the other's arguments), each state array with a
# channel axis added
@kernel
def differential_rls_bank_kernel(
    x: np.ndarray, fe_in: np.ndarray, core_in: np.ndarray, theta_in: np.ndarray, P_in: np.ndarray,
    ist_in: np.ndarray, sos: np.ndarray, tab: np.ndarray, cyc: np.ndarray, consts: np.ndarray, last_only: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """:func:`differential_rls_kernel` for C channels at once: ``x`` (N, C), the state arrays
    stacked with the channel last (``fe`` (FE_SIZE, C), ``core`` (CORE_SIZE, C), ``theta``
    (p, C), ``P`` (p, p, C), ``ist`` (3, C)); returns ``out`` (C, rows, 5), ``ext`` (C, rows, 3),
    ``sse`` (C,) and the new stacked state. Channels go ``LANES`` at a time through a
    lane-major work array: every input sample's front end (:func:`_demodulate`) and advance
    (:func:`_bank_advance`) run the lanes as one vector; the decimated steps
    (:func:`_decimated_step`: the RLS pair, the sin/cos/atan2/hypot/sqrt of the core, scalar
    library calls) and the output rows run lane by lane, as the single kernel runs them."""
    n, nc = x.shape
    p = theta_in.shape[0]
    out, ext, sse = bank_outputs(nc, n, last_only, 3)
    new_fe = np.empty((FE_SIZE, nc))
    new_core = np.empty((CORE_SIZE, nc))
    new_theta = np.empty((p, nc))
    new_P = np.empty((p, p, nc))
    new_ist = np.empty((3, nc), dtype=np.int64)
    inv_fs, _, d0, w_lo, w_hi = front_constants(consts)
    warm = consts[K_WARM]
    ncyc = cyc.shape[0]
    s0b0, s0b1, s0b2, s0a1, s0a2, s1b0, s1b1, s1b2, s1a1, s1a2 = lowpass_coefficients(sos)
    L = LANES
    S = np.empty(_ROWS * L)
    fel = np.empty(FE_SIZE)  # one lane's fe, for the decimated step
    core = np.empty((L, CORE_SIZE))
    theta = np.empty((L, p))
    P = np.empty((L, p, p))
    ist = np.zeros((3, L), dtype=np.int64)
    rr, ri, xr_, xi_, px, idx, T, b0, work = _bank_scratch(tab)
    stepped = np.zeros(L, dtype=np.bool_)
    pending = np.zeros(L, dtype=np.bool_)  # fe[F_SNAP_PH] still to take from ah
    ah = np.zeros((2, L))
    for g in range(0, nc, L):
        width = min(L, nc - g)
        S[:] = 0.0  # lanes past the last channel run on zeros, their results dropped
        for c in range(width):
            for k in range(FE_SIZE):
                fel[k] = fe_in[k, g + c]
            if ist_in[2, g + c] == 0:  # first sample ever: the offset low-pass in steady state at x(0)
                _biquads_steady(x[0, g + c], sos, fel, F_ZI)
            for k in range(FE_SIZE):
                S[k * L + c] = fel[k]
            for k in range(CORE_SIZE):
                core[c, k] = core_in[k, g + c]
            for a in range(p):
                theta[c, a] = theta_in[a, g + c]
                for b in range(p):
                    P[c, a, b] = P_in[a, b, g + c]
            for k in range(3):
                ist[k, c] = ist_in[k, g + c]
            pending[c] = False
        for i in range(n):
            for c in range(width):
                S[_RX * L + c] = x[i, g + c]
            for lane in range(L):  # literal trip count: one vector
                _bank_front(S, lane, s0b0, s0b1, s0b2, s0a1, s0a2, s1b0, s1b1, s1b2, s1a1, s1a2)
            for c in range(width):  # decimation, lane by lane (nonuniform cyclic sampling, Section 5)
                if ist[2, c] < warm:
                    ist[2, c] += 1
                ist[0, c] += 1
                stepped[c] = ist[0, c] >= cyc[ist[1, c]] and ist[2, c] >= warm
                if stepped[c]:
                    u = cyc[ist[1, c]] / d0
                    ist[0, c] = 0
                    ist[1, c] = (ist[1, c] + 1) % ncyc
                    _bank_step(S, c, u, core[c], theta[c], P[c], tab, consts, rr, ri, xr_, xi_, px,
                               idx, T, b0, work, sos, fel, ah)  # fmt: skip
                    pending[c] = True
                else:
                    S[F_SINCE * L + c] += 1.0
            if not last_only or i == n - 1:
                j = 0 if last_only else i
                for c in range(width):
                    if pending[c]:
                        S[F_SNAP_PH * L + c] = math.atan2(ah[1, c], ah[0, c])
                        pending[c] = False
                    _write_outputs(out[g + c], ext[g + c], j, S, c, L, S[F_B * L + c], S[F_PSI * L + c],
                                   S[F_WREF * L + c], S[F_LREF * L + c], S[F_SINCE * L + c] * inv_fs)  # fmt: skip
            for lane in range(L):
                _bank_advance(S, lane, inv_fs, w_lo, w_hi)
            for c in range(width):
                if stepped[c] or S[_RFIX * L + c] != 0.0:
                    _bank_fixup(S, c, stepped[c], inv_fs)
        for c in range(width):
            ch = g + c
            if pending[c]:
                S[F_SNAP_PH * L + c] = math.atan2(ah[1, c], ah[0, c])
            sse[ch] = S[_RSSE * L + c]
            for k in range(FE_SIZE):
                new_fe[k, ch] = S[k * L + c]
            for k in range(CORE_SIZE):
                new_core[k, ch] = core[c, k]
            for a in range(p):
                new_theta[a, ch] = theta[c, a]
                for b in range(p):
                    new_P[a, b, ch] = P[c, a, b]
            for k in range(3):
                new_ist[k, ch] = ist[k, c]
    return out, ext, sse, new_fe, new_core, new_theta, new_P, new_ist


@kernel
def _bank_scratch(
    tab: np.ndarray,
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
]:  # fmt: skip
    """The scratch of :func:`core_step` and :func:`recenter_transform` (see
    :func:`working_core`), shared by the lanes: each call writes its scratch before reading it."""
    p = tab.shape[0]
    idx, T, b0, work = transform_scratch(tab)
    return np.zeros(p), np.zeros(p), np.zeros(p), np.zeros(p), np.zeros(p), idx, T, b0, work


@kernel(inline="always")
def _bank_step(
    S: np.ndarray, c: int, u: float, core: np.ndarray, theta: np.ndarray, P: np.ndarray, tab: np.ndarray,
    consts: np.ndarray, rr: np.ndarray, ri: np.ndarray, xr_: np.ndarray, xi_: np.ndarray, px: np.ndarray,
    idx: np.ndarray, T: np.ndarray, b0: np.ndarray, work: np.ndarray, sos: np.ndarray, fel: np.ndarray,
    ah: np.ndarray,
) -> None:  # fmt: skip
    """:func:`_decimated_step` on lane ``c`` of ``S``: its fe gathered into ``fel`` and
    scattered back, ``a^ / H * |H|^2`` into ``ah[:, c]``."""
    L = LANES
    for k in range(FE_SIZE):
        fel[k] = S[k * L + c]
    z = F_ZI + 4
    wref, lref, r1, r2, r3, r4, q1, q2, q3, q4, ah_re, ah_im, bb, bs = _decimated_step(
        S[_RCR * L + c], S[_RCI * L + c], u, core, theta, P, tab, consts, rr, ri, xr_, xi_, px, idx, T, b0, work,
        sos, fel, fel[F_WREF], fel[F_LREF], fel[z], fel[z + 1], fel[z + 2], fel[z + 3],
        fel[z + 4], fel[z + 5], fel[z + 6], fel[z + 7],
    )  # fmt: skip
    fel[F_WREF], fel[F_LREF] = wref, lref
    fel[z], fel[z + 1], fel[z + 2], fel[z + 3] = r1, r2, r3, r4
    fel[z + 4], fel[z + 5], fel[z + 6], fel[z + 7] = q1, q2, q3, q4
    fel[F_BB_RE], fel[F_BB_IM], fel[F_BS_RE], fel[F_BS_IM] = bb.real, bb.imag, bs.real, bs.imag
    for k in range(FE_SIZE):
        S[k * L + c] = fel[k]
    ah[0, c], ah[1, c] = ah_re, ah_im
