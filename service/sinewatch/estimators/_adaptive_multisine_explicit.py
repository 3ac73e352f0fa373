"""The explicit-gain implementation of ``adaptive-multisine`` (its behaviour up to the
automatic design): the paper's gains given per example, integrated with RK4 sub-steps.

Kept, unchanged in arithmetic, so that recordings made with it still replay bit for bit:
``adaptive-multisine`` runs this kernel whenever its parameters give no ``band_hz`` (see
:mod:`sinewatch.estimators.adaptive_multisine`, which documents the model (1)-(25) both
implementations share). Paper: B. Chen, G. Pin, W. M. Ng, S. Y. Hui, T. Parisini, "An
adaptive observer-based robust estimator of multi-sinusoidal signals", IEEE Trans.
Automatic Control 63(6), 2018. The departures from its Algorithm 1, D1-D8:

D1, the unconstrained law (22) as implemented::

    thetah'_unc = -mu V Psi V^T Xi^T C_z^T (C_z zh - eta)

with ``V`` the generalised eigenvectors ``Phi_Xi v = lambda M v`` normalised by
``V^T M V = I`` (Cholesky ``M = R R^T``, Jacobi on ``R^-1 Phi_Xi R^-T``), so
``Phi_Psi = V Lambda V^-1`` and ``V V^T = M^-1``. Why: ``Phi_Psi`` is the product of two
symmetric matrices and is not symmetric, so the paper's ``U_Psi S_Psi U_Psi^T`` (23) and the
pairing of the i-th eigenvalue of ``Phi_Psi`` with the i-th of ``Phi_Xi`` (24) are only
defined when ``Xi^T Xi`` and ``Phi_Xi`` commute; taken literally (SVD of ``Phi_Psi``, our
forward-Euler prototype, without D4) the law drove Example 1 to ``Omegah < 0`` within 10 s. Under the commuting assumption the paper itself
reduces (22) to ``-mu M^-1 Psi Xi^T C_z^T (...)`` (33), which is what the form above gives
when every ``psi_i = 1``. With partial excitation it freezes exactly the under-excited
generalised eigen-directions, and in the coordinates ``u = V^T M theta~`` each excited
direction decays at ``mu lambda_i >= mu delta_low``, the rate the proof of Theorem 4.1 uses.
With all ``psi_i`` equal the kernel skips the eigen-decomposition (Cholesky only).

D2, discretisation (the paper: forward Euler at Ts = 0.3 ms and 0.1 ms). Time is scaled,
``tau = omega_unit_rad_s t``, and every rate-like parameter (a_i, poles, filter poles and
gains, mu, rho, omega0, omega_max, the times) is in these units: ``omega_unit_rad_s = 1`` runs
the paper's rad/s examples with the paper's gains, ``2 pi f0`` gives the same design relative
to f0 (the equations are covariant: a -> a/s^2; poles, F_f, B_f, mu -> /s; rho -> rho s^2;
mu_A unchanged). The input is divided by ``amplitude_unit`` (rho and the excitation levels
are in signal units: Xi scales with the amplitude). Between samples the measurement is
interpolated linearly (first-order hold, no delay) and the whole state is integrated with
classical RK4 in ``m`` equal sub-steps per sample, ``m`` fixed in ``_setup`` so that
``h omega_max <= 0.25`` (RK4 phase error ~(h omega)^5/120 per step: frequency bias
< 4e-6 relative), ``h omega_ball <= 2`` (stability for any frequency the projection admits)
and ``h rate <= 1`` (observer and filter poles, mu, mu_A omega_ball^2). The projection is
the continuous (21) inside the stages, followed by a radial clip; ``Ah >= 0`` likewise.
Checked against an independent forward-Euler Algorithm 1 (tests): Richardson-extrapolated
Euler and RK4 at 1 kHz agree within 4e-4 rad/s after 8 s of Example 1.

D3: the first-order hold scales a tone's amplitude by ``sinc^2(omega h / 2)`` (no phase
shift); the reported amplitude is divided by it (5 % at 8 samples per period).

D4, the settling dwell (``adaptation_delay``, default 2 / |slowest pole|): thetah adapts
only once some psi_i has been on that long, and a total dis-excitation re-arms it. The
observer starts from zero, and its start-up transient is output error that the law reads as
parameter error: without the dwell, Example 1 from the paper's (3, 4) leaves omegah_2
hovering near 3 rad/s for 150 s (it never reaches 5), and Example 2 started at the true
frequencies is thrown 25 % off within 15 s (and diverged before the guard D7 existed).

D5, the signal-level gate (``level_time``, ``level_ratio``, ``min_amplitude``): smoothed AC
power of the input over ``level_time`` and over ten times as long; the signal is absent when
the short-term power is below ``min_amplitude^2 / 2`` or below ``level_ratio`` times the
long-term one. While absent nothing adapts; at the loss thetah rolls back to a snapshot
taken 3-4 ``level_time`` earlier (the gate needs ~1.4 ``level_time`` to close, during which
the law ran on the observer's free response), and the dwell counts from ``-delay`` (twice as
long: the restarted observer's slow modes otherwise kick thetah by several per cent).
Without the gate, 100 s of silence in Example 2 drags both frequencies to ~0.01 rad/s.

D6, minimum separation (``min_separation``, 0.05 of the higher frequency): two components on
one line form an unobservable pair (their states can cancel in C_x) that no output error
damps; the law's motion that would close a gap below the minimum is removed and the gap is
restored after each step. ``omega_ranges`` are the per-component clips of Remark 3.1.

D7, a guard: if the state leaves ``1e4 (1 + level of the input)`` (a frozen observer with
thetah far from the truth can be unstable: with Example 2's L_x it is stable only for
omegah_1 - omegah_2 in about [0, 1.3] rad/s) the observer restarts from zero with thetah
rolled back, and ``observer_reset`` is raised for that sample.

D8, outputs beyond Algorithm 1: a component whose corrected amplitude falls below
``max(min_amplitude, fade_ratio max_j A_j)`` is faded (extras ``component_faded``): frequency
and phase NaN, amplitude the small estimate; ``Omegah_i <= 0`` (no real frequency, (8)) is
NaN throughout. ``converged`` needs every component present with a real frequency, the dwell
passed with a signal, the components apart by more than ``convergence_tol``, and the
smoothed ``|omegah_i - smoothed omegah_i|`` (over ``convergence_time``) below
``convergence_tol omegah_i``. Extras per sample: ``excitation_level`` (lambda_i, (N, n)),
``adaptation_enabled`` (psi_i, (N, n)), ``component_faded`` ((N, n)), ``signal_present``
and ``observer_reset`` ((N,)). The residual is the one-step prediction of each sample from
the previous estimates (x propagated by the oscillator at Omegah_i over one sample, with
the amplitude correction).

Defaults: the paper's tuning for n = 2 (Example 2 with bias, Example 1 without), in the
paper's units; other n need an explicit design. Example 2's initial frequencies are not
given: (3.5, 2.5) is ours, inside the band where its frozen observer is stable.

Its length (a little over 800 lines) is one mode's whole kernel: the RK4 sub-step of the
observer, filters and adaptation written out, with the symmetric eigen-solver and the
Cholesky factor it calls at every sample; split further, its pieces would only be called
from here.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sinewatch.estimators import detlinalg
from sinewatch.estimators.base import kernel
from sinewatch.schemas.errors import ParameterError

# ---- packed constants -------------------------------------------------------------------------
# Numba charges ~15 ns per array argument of a call (reference counting), so the kernel's
# helpers take four packed arrays instead of twenty: ``ci`` (int64) = n, nx, nf, nz, sub-steps,
# bias; ``cf`` (float64) = the scalars below,
# then a (n), L (nz, its first column), F_f (nf), B_f (nf), theta0 (n), and the bounds
# of thetah from omega_ranges, theta_lo (n) and theta_hi (n);
# ``work`` (float64) = C_z Xi, R, R^-1, R^-1 Phi_Xi R^-T, W (n*n each, row-major), lambda, e,
# g, q, psi_eff (n each).
_C_H, _C_MU, _C_RHO2, _C_MUA, _C_DHI, _C_DLO, _C_TBAR = 0, 1, 2, 3, 4, 5, 6
_C_AMPU, _C_OMU, _C_MINA, _C_FADE, _C_CALPHA, _C_CTOL, _C_DELAY, _C_ZMAX = 7, 8, 9, 10, 11, 12, 13, 14
_C_LALPHA, _C_RINGP, _C_LRATIO, _C_SEP = 15, 16, 17, 18
_N_CONSTS = 19
_RING = 4  # snapshots of thetah kept for the roll-back on loss of signal
_I_N, _I_NX, _I_NF, _I_NZ, _I_MSUB, _I_BIAS = 0, 1, 2, 3, 4, 5
# the scalars of the state, after the per-component statistics (see AdaptiveMultisine._initial_state)
_Y_PREV, _Y_PRED, _STARTED, _CLOCK = 0, 1, 2, 3  # y(k-1), its prediction, started, settling clock
_LVL_MEAN, _LVL_POW, _PRESENT = 4, 5, 6  # signal-level gate: mean, AC power, signal present
_RING_COUNT, _RING_SLOT, _LVL_POW_LONG = 7, 8, 9  # samples since the last snapshot, next slot, AC power (10x slower)
_N_SCALARS = 10


@kernel
def _sym_eig(work: np.ndarray, n: int) -> None:
    """Cyclic Jacobi on the symmetric n x n matrix S held in ``work`` (destroyed): eigenvalues
    into lambda, sorted in decreasing order, orthonormal eigenvectors into the columns of W."""
    nn = n * n
    wS = 3 * nn
    wW = 4 * nn
    wl = 5 * nn
    for i in range(n):
        for j in range(n):
            work[wW + i * n + j] = 1.0 if i == j else 0.0
    for _sweep in range(30):
        off = 0.0
        tot = 0.0
        for i in range(n):
            tot += work[wS + i * n + i] ** 2
            for j in range(i + 1, n):
                off += work[wS + i * n + j] ** 2
        if off <= 1e-30 * tot or off == 0.0:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = work[wS + p * n + q]
                if apq == 0.0:
                    continue
                theta = (work[wS + q * n + q] - work[wS + p * n + p]) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):  # S <- S J (columns p, q)
                    skp = work[wS + k * n + p]
                    skq = work[wS + k * n + q]
                    work[wS + k * n + p] = c * skp - s * skq
                    work[wS + k * n + q] = s * skp + c * skq
                for k in range(n):  # S <- J^T S (rows p, q)
                    spk = work[wS + p * n + k]
                    sqk = work[wS + q * n + k]
                    work[wS + p * n + k] = c * spk - s * sqk
                    work[wS + q * n + k] = s * spk + c * sqk
                for k in range(n):  # W <- W J
                    wkp = work[wW + k * n + p]
                    wkq = work[wW + k * n + q]
                    work[wW + k * n + p] = c * wkp - s * wkq
                    work[wW + k * n + q] = s * wkp + c * wkq
    for i in range(n):
        work[wl + i] = work[wS + i * n + i]
    for i in range(n):  # selection sort, decreasing
        best = i
        for j in range(i + 1, n):
            if work[wl + j] > work[wl + best]:
                best = j
        if best != i:
            tmp = work[wl + i]
            work[wl + i] = work[wl + best]
            work[wl + best] = tmp
            for k in range(n):
                tmp = work[wW + k * n + i]
                work[wW + k * n + i] = work[wW + k * n + best]
                work[wW + k * n + best] = tmp


@kernel
def _chol(s: np.ndarray, work: np.ndarray, cf: np.ndarray, ci: np.ndarray) -> None:
    """C_z Xi, and the Cholesky factor R (lower) of M = Xi^T Xi + rho^2 I of (23) and R^-1."""
    n, nx, nf, nz = ci[_I_N], ci[_I_NX], ci[_I_NF], ci[_I_NZ]
    rho2 = cf[_C_RHO2]
    oxi = nf + nz
    nn = n * n
    wR = nn
    wRi = 2 * nn
    wS = 3 * nn
    for i in range(n):
        base = oxi + i * nz
        acc = s[base + nx - 1] if nx > 2 * n else 0.0  # row 0 of C_z Xi: C_x xi_i
        for r in range(n):
            acc += s[base + 2 * r]
        work[i] = acc
        for j in range(1, n):  # the filter rows: yf part of xi_i
            work[j * n + i] = s[base + nx + j - 1]
    for i in range(n):  # M = Xi^T Xi + rho^2 I (lower triangle, into S)
        for j in range(i + 1):
            acc = rho2 if i == j else 0.0
            bi = oxi + i * nz
            bj = oxi + j * nz
            for r in range(nz):
                acc += s[bi + r] * s[bj + r]
            work[wS + i * n + j] = acc
    for j in range(n):  # Cholesky M = R R^T
        d = work[wS + j * n + j]
        for k in range(j):
            d -= work[wR + j * n + k] ** 2
        d = math.sqrt(d) if d > rho2 else math.sqrt(rho2)  # M >= rho^2 I: guards rounding only
        work[wR + j * n + j] = d
        for i in range(j + 1, n):
            acc = work[wS + i * n + j]
            for k in range(j):
                acc -= work[wR + i * n + k] * work[wR + j * n + k]
            work[wR + i * n + j] = acc / d
        for i in range(j):
            work[wR + i * n + j] = 0.0
    for j in range(n):  # R^-1 (lower)
        for i in range(n):
            work[wRi + i * n + j] = 0.0
        work[wRi + j * n + j] = 1.0 / work[wR + j * n + j]
        for i in range(j + 1, n):
            acc = 0.0
            for k in range(j, i):
                acc -= work[wR + i * n + k] * work[wRi + k * n + j]
            work[wRi + i * n + j] = acc / work[wR + i * n + i]


@kernel
def _eig(work: np.ndarray, n: int) -> None:
    """After :func:`_chol`: S = R^-1 Phi_Xi R^-T = (C_z Xi R^-T)^T (C_z Xi R^-T), then its
    eigen-decomposition W, lambda (decreasing): Phi_Xi v = lambda M v with v = R^-T w, so
    lambda are the eigenvalues of Phi_Psi (23)."""
    nn = n * n
    wRi = 2 * nn
    wS = 3 * nn
    for i in range(n):  # S = (C_z Xi R^-T)^T (C_z Xi R^-T)
        for j in range(i + 1):
            acc = 0.0
            for r in range(n):
                bi = 0.0
                bj = 0.0
                for k in range(i + 1):
                    bi += work[r * n + k] * work[wRi + i * n + k]
                for k in range(j + 1):
                    bj += work[r * n + k] * work[wRi + j * n + k]
                acc += bi * bj
            work[wS + i * n + j] = acc
            work[wS + j * n + i] = acc
    _sym_eig(work, n)


@kernel
def _excitation(s: np.ndarray, work: np.ndarray, cf: np.ndarray, ci: np.ndarray) -> None:
    """Generalised eigen-decomposition of (Phi_Xi, M), (23)."""
    _chol(s, work, cf, ci)
    _eig(work, ci[_I_N])


@kernel
def _rk4_substep(
    s: np.ndarray,
    x: np.ndarray,
    K: np.ndarray,
    work: np.ndarray,
    cf: np.ndarray,
    ci: np.ndarray,
    ya: float,
    yb: float,
    hs: float,
    fresh: float,
) -> None:
    """One classical RK4 step of length ``hs`` of (12), (16), (17), (19)-(22) and (11) on the
    integrated part of ``s`` (updated in place), the measurement going linearly from ``ya`` to
    ``yb`` and the switching held in psi_eff. ``x`` (ns) and ``K`` (4 ns) are scratch; ``fresh``
    (1.0 or 0.0: a float, which numba has no literal type for, so that it compiles this one
    function once and not again for a literal ``False`` met while typing the caller's loop):
    ``work`` already holds the decomposition of ``s``. One function with the right-hand side
    written out, because every call of a compiled helper costs ~15 ns per array argument."""
    n, nx, nf, nz = ci[_I_N], ci[_I_NX], ci[_I_NF], ci[_I_NZ]
    mu, mu_a, tbar, sep = cf[_C_MU], cf[_C_MUA], cf[_C_TBAR], cf[_C_SEP]
    oa_c = _N_CONSTS
    oL = oa_c + n
    oFf = oL + nz
    oBf = oFf + nf
    olo = oBf + nf + n  # theta_lo, then theta_hi
    oz = nf
    oxi = oz + nz
    oth = oxi + nz * n
    oa = oth + n
    ns = oa + n
    nn = n * n
    wRi = 2 * nn
    wW = 4 * nn
    wev = 5 * nn + n
    wg = wev + n
    wq = wg + n
    wps = wq + n
    n_on = 0
    for i in range(n):
        if work[wps + i] != 0.0:
            n_on += 1
    for r in range(ns):
        x[r] = s[r]
    for st in range(4):
        d = st * ns  # this stage's derivative: K[d : d + ns]
        yin = ya if st == 0 else (yb if st == 3 else 0.5 * (ya + yb))
        # (12) measured-output filter
        for j in range(nf):
            K[d + j] = cf[oFf + j] * x[j] + cf[oBf + j] * yin
        # output error e = C_z zh - eta_hat
        cz = x[oz + nx - 1] if nx > 2 * n else 0.0  # C_x zh: positions and bias
        for i in range(n):
            cz += x[oz + 2 * i]
        work[wev] = cz - yin
        for j in range(1, n):
            work[wev + j] = x[oz + nx + j - 1] - x[j - 1]
        # (22) as -mu V Psi V^T Xi^T C_z^T e; V V^T = M^-1, so with every psi_i = 1 it is
        # -mu M^-1 Xi^T C_z^T e (33) and needs no eigen-decomposition; with none it is 0
        for i in range(n):
            K[d + oth + i] = 0.0
        if n_on > 0:
            if st > 0 or fresh == 0.0:
                _chol(x, work, cf, ci)
                if n_on < n:
                    _eig(work, n)
            for i in range(n):  # g = (C_z Xi)^T e
                acc = 0.0
                for r in range(n):
                    acc += work[r * n + i] * work[wev + r]
                work[wg + i] = acc
            for i in range(n):  # q = R^-1 g
                acc = 0.0
                for kk in range(i + 1):
                    acc += work[wRi + i * n + kk] * work[wg + kk]
                work[wq + i] = acc
            if n_on < n:
                for i in range(n):  # p = Psi W^T q  (into g)
                    acc = 0.0
                    for kk in range(n):
                        acc += work[wW + kk * n + i] * work[wq + kk]
                    work[wg + i] = acc * work[wps + i]
                for i in range(n):  # q = W p
                    acc = 0.0
                    for kk in range(n):
                        acc += work[wW + i * n + kk] * work[wg + kk]
                    work[wq + i] = acc
            tt = 0.0
            tu = 0.0
            for i in range(n):  # thetah'_unc = -mu R^-T q
                acc = 0.0
                for kk in range(i, n):
                    acc += work[wRi + kk * n + i] * work[wq + kk]
                K[d + oth + i] = -mu * acc
                tt += x[oth + i] * x[oth + i]
                tu += x[oth + i] * K[d + oth + i]
            if tt >= tbar * tbar and tu > 0.0:  # projection (19)-(21)
                for i in range(n):
                    K[d + oth + i] -= x[oth + i] * tu / (tbar * tbar)
            for i in range(n):  # frequency clips of Remark 3.1 (inactive without omega_ranges)
                if (x[oth + i] <= cf[olo + i] and K[d + oth + i] < 0.0) or (
                    x[oth + i] >= cf[olo + n + i] and K[d + oth + i] > 0.0
                ):
                    K[d + oth + i] = 0.0
            if sep > 0.0:  # minimum separation: no motion that closes a too-small gap
                for i in range(n):
                    wi = math.sqrt(max(x[oth + i] - cf[oa_c + i], 0.0))
                    for i2 in range(i + 1, n):
                        wj = math.sqrt(max(x[oth + i2] - cf[oa_c + i2], 0.0))
                        if abs(wi - wj) <= sep * max(wi, wj):
                            sg = 1.0 if wi >= wj else -1.0
                            closing = sg * (K[d + oth + i] - K[d + oth + i2])
                            if closing < 0.0:
                                K[d + oth + i] -= 0.5 * sg * closing
                                K[d + oth + i2] += 0.5 * sg * closing
        # (16) zh' = A_L zh + L y + G_z(zh) thetah + Xi thetah' and (17) xi_i' = A_L xi_i +
        # G_z_i(zh), with A_L = F_z - L C_z applied by structure: blockdiag(J_i, 0) - L_x C_x
        # on the oscillator rows, B_f C_x + F_f on the filter rows; G_z_i(zh) = -x_{2i-1} e_{2i}
        for v in range(n + 1):
            src = oz if v == 0 else oxi + (v - 1) * nz
            c = x[src + nx - 1] if nx > 2 * n else 0.0  # C_x applied to this vector
            for i in range(n):
                c += x[src + 2 * i]
            for i in range(n):
                K[d + src + 2 * i] = x[src + 2 * i + 1] - cf[oL + 2 * i] * c
                K[d + src + 2 * i + 1] = cf[oa_c + i] * x[src + 2 * i] - cf[oL + 2 * i + 1] * c
            if nx > 2 * n:
                K[d + src + nx - 1] = -cf[oL + nx - 1] * c
            for j in range(nf):
                K[d + src + nx + j] = cf[oBf + j] * c + cf[oFf + j] * x[src + nx + j]
            if v == 0:
                for r in range(nx):
                    acc = cf[oL + r] * yin
                    for i in range(n):
                        acc += x[oxi + i * nz + r] * K[d + oth + i]
                    K[d + oz + r] += acc
                for r in range(nx, nz):
                    acc = 0.0
                    for i in range(n):
                        acc += x[oxi + i * nz + r] * K[d + oth + i]
                    K[d + oz + r] += acc
                for i in range(n):
                    K[d + oz + 2 * i + 1] -= x[oz + 2 * i] * x[oth + i]
            else:
                K[d + src + 2 * (v - 1) + 1] -= x[oz + 2 * (v - 1)]
        # (11): amplitude adaptation, held at 0 from below
        for i in range(n):
            om2 = x[oth + i] - cf[oa_c + i]  # (8)
            x1 = x[oz + 2 * i]
            x2 = x[oz + 2 * i + 1]
            da = 0.0
            if om2 > 0.0:
                w = math.sqrt(om2)
                inst = om2 * x1 * x1 + x2 * x2
                da = -mu_a * w * (w * x[oa + i] - math.sqrt(max(0.0, inst)))
            if x[oa + i] <= 0.0 and da < 0.0:
                da = 0.0
            K[d + oa + i] = da
        # next stage's point
        if st < 3:
            f = hs if st == 2 else 0.5 * hs
            for r in range(ns):
                x[r] = s[r] + f * K[d + r]
    for r in range(ns):
        s[r] += hs / 6.0 * (K[r] + 2.0 * K[ns + r] + 2.0 * K[2 * ns + r] + K[3 * ns + r])


@kernel
def _osc_step(om2: float, h: float) -> tuple[float, float]:
    """(C, S) with x(h) = C x(0) + S x'(0) for x'' = -om2 x."""
    if om2 > 0.0:
        w = math.sqrt(om2)
        return math.cos(w * h), math.sin(w * h) / w
    if om2 < 0.0:
        w = math.sqrt(-om2)
        return math.cosh(w * h), math.sinh(w * h) / w
    return 1.0, h


@kernel
def _sinc2(x: float) -> float:
    """sinc^2(x) = (sin x / x)^2, the amplitude factor of linear interpolation at x = w h / 2."""
    if abs(x) < 1e-4:
        return 1.0 - x * x / 3.0
    v = math.sin(x) / x
    return v * v


@kernel
def explicit_kernel(
    y: np.ndarray, state: np.ndarray, cf: np.ndarray, ci: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Run the estimator over block ``y`` from ``state``; return ``(out, extras, sse, new_state)``.

    ``cf``/``ci``: packed constants (see above). ``state`` is the ``s`` array (layout:
    :meth:`AdaptiveMultisine._initial_state`). ``out`` columns:
    frequency_hz (n), amplitude (n), phase (n), offset, converged; ``extras`` columns: lambda
    (n), psi (n), faded (n), reset. One row per sample, or only the last with ``last_only``.
    Pure: the inputs are not modified.
    """
    n, nx, nf, nz, m_sub, bias = ci[_I_N], ci[_I_NX], ci[_I_NF], ci[_I_NZ], ci[_I_MSUB], ci[_I_BIAS]
    h = cf[_C_H]
    amp_u = cf[_C_AMPU]
    om_u = cf[_C_OMU]
    d_hi, d_lo, tbar = cf[_C_DHI], cf[_C_DLO], cf[_C_TBAR]
    min_a, fade, c_alpha, c_tol = cf[_C_MINA], cf[_C_FADE], cf[_C_CALPHA], cf[_C_CTOL]
    zmax = cf[_C_ZMAX]
    delay = cf[_C_DELAY]
    oa_c = _N_CONSTS
    oth0 = oa_c + n + nz + 2 * nf
    olo = oth0 + n  # theta_lo, then theta_hi
    l_alpha = cf[_C_LALPHA]
    sep = cf[_C_SEP]
    oz = nf
    oxi = oz + nz
    oth = oxi + nz * n
    oa = oth + n
    ops = oa + n
    odv = ops + n
    owb = odv + n
    oyp = owb + n
    orng = oyp + _N_SCALARS  # ring of _RING snapshots of thetah
    ring_p = cf[_C_RINGP]
    ns = oa + n  # the integrated part
    nn = n * n
    wl = 5 * nn
    wps = wl + 4 * n
    s = state.copy()
    kbuf = np.empty(4 * ns)
    tmp = np.empty(ns)
    work = np.zeros(5 * nn + 5 * n)
    nrow = 1 if last_only else y.shape[0]
    out = np.empty((nrow, 3 * n + 2))
    ext = np.empty((nrow, 3 * n + 2))
    hs = h / m_sub
    sse = 0.0
    fresh = 0.0  # 1.0: work holds the decomposition of s (a float: see _rk4_substep)
    nsamp = y.shape[0]
    for k in range(nsamp):
        yk = y[k] / amp_u
        e = yk - s[oyp + _Y_PRED]  # one-step prediction error
        sse += e * e
        reset = False
        # signal-level gate: smoothed mean and AC power of the input over level_time and over
        # ten times as long; the signal is absent below min_amplitude, or when the short-term
        # power falls under level_ratio times the long-term one (the signal stopped)
        s[oyp + _LVL_MEAN] += l_alpha * (yk - s[oyp + _LVL_MEAN])
        dev = yk - s[oyp + _LVL_MEAN]
        s[oyp + _LVL_POW] += l_alpha * (dev * dev - s[oyp + _LVL_POW])
        s[oyp + _LVL_POW_LONG] += 0.1 * l_alpha * (dev * dev - s[oyp + _LVL_POW_LONG])
        present = (
            2.0 * s[oyp + _LVL_POW] >= min_a * min_a and s[oyp + _LVL_POW] >= cf[_C_LRATIO] * s[oyp + _LVL_POW_LONG]
        )
        lost = s[oyp + _PRESENT] != 0.0 and not present
        if lost:
            # loss of signal: the adaptation ran on the observer's free response while the
            # level gate was catching up; roll thetah back to the oldest snapshot
            slot = int(s[oyp + _RING_SLOT])
            for i in range(n):
                s[oth + i] = s[orng + slot * n + i]
        s[oyp + _PRESENT] = 1.0 if present else 0.0
        # snapshots of thetah every ring_p samples while the signal is present
        if present:
            s[oyp + _RING_COUNT] += 1.0
            if s[oyp + _RING_COUNT] >= ring_p:
                s[oyp + _RING_COUNT] = 0.0
                slot = int(s[oyp + _RING_SLOT])
                for i in range(n):
                    s[orng + slot * n + i] = s[oth + i]
                s[oyp + _RING_SLOT] = float((slot + 1) % _RING)
        zlim = zmax * (1.0 + math.sqrt(2.0 * s[oyp + _LVL_POW]) + abs(s[oyp + _LVL_MEAN]))
        if s[oyp + _STARTED] != 0.0:
            y0 = s[oyp + _Y_PREV]
            # Algorithm 1: psi(k-1) acts over (t_{k-1}, t_k]; the settling dwell holds the
            # adaptation off until some psi_i has been on for adaptation_delay with a signal
            warm = s[oyp + _CLOCK] >= delay and present
            for i in range(n):
                work[wps + i] = s[ops + i] if warm else 0.0
            for j in range(m_sub):
                ua = y0 + (yk - y0) * (j / m_sub)  # first-order hold between samples
                ub = y0 + (yk - y0) * ((j + 1.0) / m_sub)
                _rk4_substep(s, tmp, kbuf, work, cf, ci, ua, ub, hs, fresh)
                fresh = 0.0
                # projection: radial clip to |thetah| <= theta_bar (19); Ah >= 0 (11)
                tt = 0.0
                for i in range(n):
                    tt += s[oth + i] * s[oth + i]
                if tt > tbar * tbar:
                    sc = tbar / math.sqrt(tt)
                    for i in range(n):
                        s[oth + i] *= sc
                for i in range(n):  # Remark 3.1 clips
                    s[oth + i] = min(max(s[oth + i], cf[olo + i]), cf[olo + n + i])
                if sep > 0.0:  # minimum separation, restored symmetrically about the mid-point
                    for i in range(n):
                        for i2 in range(i + 1, n):
                            wi = math.sqrt(max(s[oth + i] - cf[oa_c + i], 0.0))
                            wj = math.sqrt(max(s[oth + i2] - cf[oa_c + i2], 0.0))
                            gap = sep * max(wi, wj)
                            if abs(wi - wj) < gap and wi + wj > 0.0:
                                mid = 0.5 * (wi + wj)
                                half = 0.5 * sep * mid / (1.0 - 0.5 * sep)  # gap = sep * (mid + half)
                                sg = 1.0 if wi >= wj else -1.0
                                s[oth + i] = cf[oa_c + i] + (mid + sg * half) ** 2
                                s[oth + i2] = cf[oa_c + i2] + (mid - sg * half) ** 2
                for i in range(n):
                    s[oa + i] = max(s[oa + i], 0.0)
                # guard: the state stays finite and commensurate with the input; otherwise
                # (a frozen observer can be unstable far from the true frequencies) restart
                # the observer and roll thetah back to the oldest snapshot
                bad = False
                for r in range(ns):
                    if not abs(s[r]) <= zlim:  # also catches NaN
                        bad = True
                if bad:
                    reset = True
                    slot = int(s[oyp + _RING_SLOT])
                    for r in range(ns):
                        s[r] = 0.0
                    for i in range(n):
                        th = s[orng + slot * n + i]
                        s[oth + i] = th if abs(th) <= tbar else cf[oth0 + i]
                        s[ops + i] = 0.0
                        work[wps + i] = 0.0
                    s[oyp + _CLOCK] = 0.0
            # (23)-(25) at t_k: excitation levels and hysteretic switching
            _excitation(s, work, cf, ci)
            fresh = 1.0
            any_on = False
            for i in range(n):
                if work[wl + i] >= d_hi:
                    s[ops + i] = 1.0
                elif work[wl + i] < d_lo:
                    s[ops + i] = 0.0
                if s[ops + i] != 0.0:
                    any_on = True
            # total dis-excitation re-arms the settling dwell; a loss of signal re-arms it twice
            # as long (thetah is known good then, the observer restarts from its free response)
            if not present:
                s[oyp + _CLOCK] = -delay if (lost or s[oyp + _CLOCK] < 0.0) else 0.0
            elif any_on:
                s[oyp + _CLOCK] = min(s[oyp + _CLOCK] + h, delay)
            else:
                s[oyp + _CLOCK] = min(s[oyp + _CLOCK], 0.0)
        else:
            s[oyp + _STARTED] = 1.0
            _excitation(s, work, cf, ci)
            fresh = 1.0
        s[oyp + _Y_PREV] = yk
        # ---- outputs at t_k: (8), (10), (11); convergence statistics; next-sample prediction
        amax = 0.0
        for i in range(n):
            om2 = s[oth + i] - cf[oa_c + i]
            corr = 1.0 / _sinc2(0.5 * h * math.sqrt(om2)) if om2 > 0.0 else 1.0
            v = s[oa + i] * corr
            amax = max(amax, v)
        thr = max(fade * amax, min_a)
        ypred = s[oz + nx - 1] if bias else 0.0
        all_ok = s[oyp + _CLOCK] >= delay  # adapting: past start-up, excited, with a signal
        j = 0 if last_only else k
        write = (not last_only) or k == nsamp - 1
        for i in range(n):
            om2 = s[oth + i] - cf[oa_c + i]
            x1 = s[oz + 2 * i]
            x2 = s[oz + 2 * i + 1]
            cc, ss = _osc_step(om2, h)
            w = math.nan
            corr = 1.0
            if om2 > 0.0:
                w = math.sqrt(om2)
                corr = 1.0 / _sinc2(0.5 * h * w)
                s[owb + i] += c_alpha * (w - s[owb + i])
                s[odv + i] += c_alpha * (abs(w - s[owb + i]) - s[odv + i])
            else:
                all_ok = False
            ypred += corr * (cc * x1 + ss * x2)
            amp = s[oa + i] * corr
            faded = not amp >= thr or amp <= 0.0
            if faded or not (s[odv + i] <= c_tol * w):
                all_ok = False
            if write:
                if om2 > 0.0 and not faded:
                    out[j, i] = w * om_u / (2.0 * math.pi)
                    ph = math.atan2(w * x1, x2)  # (10)
                    out[j, 2 * n + i] = math.pi if ph <= -math.pi else ph
                else:
                    out[j, i] = math.nan
                    out[j, 2 * n + i] = math.nan
                out[j, n + i] = amp * amp_u if om2 > 0.0 else math.nan
                ext[j, i] = work[wl + i]
                ext[j, n + i] = s[ops + i]
                ext[j, 2 * n + i] = 1.0 if faded else 0.0
        s[oyp + _Y_PRED] = ypred
        for i in range(n):  # two components on one frequency are not a converged estimate
            for i2 in range(i + 1, n):
                if not abs(s[owb + i] - s[owb + i2]) > c_tol * max(s[owb + i], s[owb + i2]):
                    all_ok = False
        if write:
            out[j, 3 * n] = s[oz + nx - 1] * amp_u if bias else 0.0
            out[j, 3 * n + 1] = 1.0 if all_ok else 0.0
            ext[j, 3 * n] = 1.0 if present else 0.0
            ext[j, 3 * n + 1] = 1.0 if reset else 0.0
    return out, ext, sse * amp_u * amp_u, s


# ---- design, constants and state of the explicit-gain mode ------------------------------------
def theta_bar(p: Any, a: list[float]) -> float:
    """Radius of the ball Theta* of Assumption 1: |theta*_i| <= max(|a_i|, |a_i + omega_bar^2|)."""
    wb2 = p.omega_max**2
    return float(np.sqrt(sum(max(abs(ai), abs(ai + wb2)) ** 2 for ai in a)))


def check(p: Any, sample_rate_hz: float) -> None:
    """The explicit design's checks that need the sample rate (``p``: AdaptiveMultisineParams)."""
    d = p.design()
    a = d["a"]
    if len(set(a)) != len(a) or (p.bias and any(v == 0 for v in a)):
        raise ParameterError(f"a: expected distinct values, non-zero with bias (observability of (F_x, C_x)), got {a}")
    if not all(0 < w < p.omega_max for w in d["omega0"]):
        raise ParameterError(f"omega0: expected values in (0, omega_max={p.omega_max}), got {d['omega0']}")
    w0 = d["omega0"]
    if any(
        abs(w0[i] - w0[j]) < p.min_separation * max(w0[i], w0[j]) for i in range(len(w0)) for j in range(i + 1, len(w0))
    ):
        raise ParameterError(
            f"omega0: expected values at least min_separation={p.min_separation} (relative) apart, got {w0}"
        )
    if p.omega_ranges is not None and not all(
        lo <= w <= hi for w, (lo, hi) in zip(d["omega0"], p.omega_ranges, strict=True)
    ):
        raise ParameterError(f"omega0: expected values inside omega_ranges {p.omega_ranges}, got {d['omega0']}")
    tbar = theta_bar(p, a)
    w_ball = math.sqrt(tbar - min(a))
    nyq = math.pi * sample_rate_hz
    if w_ball * p.omega_unit_rad_s >= nyq:
        raise ParameterError(
            "omega_max: expected the projection ball |theta| <= theta_bar to admit only frequencies "
            f"below Nyquist ({nyq:.6g} rad/s), got up to {w_ball * p.omega_unit_rad_s:.6g} rad/s "
            f"(omega_max={p.omega_max}, a={a}, omega_unit_rad_s={p.omega_unit_rad_s})"
        )


def observer_matrices(a: np.ndarray, bias: bool) -> tuple[np.ndarray, np.ndarray]:
    """(3): F_x = blockdiag(J_i, 0), J_i = [[0, 1], [a_i, 0]]; C_x = [c_1 .. c_n 1], c_i = [1 0]
    (the offset's state and its 1 only with ``bias``)."""
    n = a.shape[0]
    nx = 2 * n + int(bias)
    Fx = np.zeros((nx, nx))
    Cx = np.zeros(nx)
    for i in range(n):
        Fx[2 * i, 2 * i + 1] = 1.0
        Fx[2 * i + 1, 2 * i] = a[i]
        Cx[2 * i] = 1.0
    if bias:
        Cx[nx - 1] = 1.0
    return Fx, Cx


def setup(p: Any, sample_rate_hz: float) -> dict[str, Any]:
    """Constants of the explicit design: ``cf``, ``ci`` (with the mode flag 0 appended),
    ``L_x``, ``theta_bar``, ``substeps``, ``settling_time``, ``theta0``, ``nf``, ``nz``."""
    n = p.n_sinusoids
    bias = p.bias
    d = p.design()
    a = np.asarray(d["a"], dtype=np.float64)
    nx = 2 * n + int(bias)
    nf = n - 1
    nz = nx + nf
    Fx, Cx = observer_matrices(a, bias)
    # (16): L_x by pole placement of F_x - L_x C_x (Algorithm 1, initialisation), by
    # Ackermann's formula in exactly rounded sums (detlinalg): scipy's place_poles goes through
    # OpenBLAS, whose kernels (chosen by CPU) round differently from host to host, and L_x's
    # last bits reach every output, so a recording would not replay bit for bit elsewhere
    poles = np.asarray(d["poles"], dtype=np.float64)
    try:
        Lx = np.array(detlinalg.observer_gain(Fx.tolist(), Cx.tolist(), poles.tolist()))
    except detlinalg.SingularMatrixError as exc:
        raise ParameterError(f"poles: expected placeable observer poles, got {list(poles)} ({exc})") from exc
    got = np.sort(np.linalg.eigvals(Fx - np.outer(Lx, Cx)).real)  # a check only: its bits go nowhere
    if not np.allclose(got, np.sort(poles), rtol=1e-6, atol=1e-9):
        raise ParameterError(f"poles: expected placeable observer poles, got {list(poles)} (placed {list(got)})")
    Ff = np.asarray(d["filter_poles"], dtype=np.float64)
    Bf = np.asarray(d["filter_gains"], dtype=np.float64)
    Lfull = np.zeros(nz)
    Lfull[:nx] = Lx
    tbar = theta_bar(p, list(a))
    w_ball = math.sqrt(tbar - float(a.min()))
    h = p.omega_unit_rad_s / sample_rate_hz  # sample period in scaled time
    # RK4 sub-steps: accuracy on the modelled band (phase error ~ (h w)^5 / 120 per step),
    # stability (|h lambda| < 2.78) over all the projection admits and over the linear rates
    # the linear part [[F_x - L_x C_x, 0], [B_f C_x, F_f]] is block lower triangular: its
    # eigenvalues are the placed poles (checked above) and F_f's
    rate = max(float(np.max(np.abs(np.concatenate([poles, Ff])))), d["mu"], d["mu_a"] * w_ball**2)
    m_sub = max(1, math.ceil(h * p.omega_max / 0.25), math.ceil(h * w_ball / 2.0), math.ceil(h * rate / 1.0))
    if m_sub > 256:
        raise ParameterError(
            f"sample_rate_hz: expected at most 256 RK4 sub-steps per sample, got {m_sub} "
            f"(raise the sample rate, or lower mu, the poles or omega_max)"
        )
    theta0 = a + np.asarray(d["omega0"], dtype=np.float64) ** 2  # (4)
    if p.omega_ranges is None:  # inactive bounds: the ball keeps |theta| <= theta_bar
        th_lo = np.full(n, -2.0 * tbar)
        th_hi = np.full(n, 2.0 * tbar)
    else:  # Remark 3.1: omega_i in [lo_i, hi_i]  <=>  theta_i in [a_i + lo_i^2, a_i + hi_i^2]
        th_lo = a + np.array([lo * lo for lo, _ in p.omega_ranges])
        th_hi = a + np.array([hi * hi for _, hi in p.omega_ranges])
    delay = p.adaptation_delay if p.adaptation_delay is not None else 2.0 / float(np.min(np.abs(poles)))
    consts = np.zeros(_N_CONSTS)
    consts[_C_H] = h
    consts[_C_MU] = d["mu"]
    consts[_C_RHO2] = d["rho"] ** 2
    consts[_C_MUA] = d["mu_a"]
    consts[_C_DHI] = p.delta_high
    consts[_C_DLO] = p.delta_low
    consts[_C_TBAR] = tbar
    consts[_C_AMPU] = p.amplitude_unit
    consts[_C_OMU] = p.omega_unit_rad_s
    consts[_C_MINA] = p.min_amplitude
    consts[_C_FADE] = p.fade_ratio
    consts[_C_CALPHA] = -math.expm1(-h / p.convergence_time)
    consts[_C_CTOL] = p.convergence_tol
    consts[_C_DELAY] = delay
    consts[_C_ZMAX] = 1e4  # relative to 1 + the input's level
    consts[_C_LALPHA] = -math.expm1(-h / p.level_time)
    consts[_C_RINGP] = max(1, round(p.level_time / h))
    consts[_C_LRATIO] = p.level_ratio
    consts[_C_SEP] = p.min_separation
    return {
        "ci": np.array([n, nx, nf, nz, m_sub, int(bias), 0], dtype=np.int64),
        "cf": np.concatenate([consts, a, Lfull, Ff, Bf, theta0, th_lo, th_hi]),
        "L_x": Lx,
        "theta_bar": tbar,
        "substeps": m_sub,
        "settling_time": float(delay),
        "theta0": theta0,
        "nf": nf,
        "nz": nz,
    }


def initial_state(n: int, nf: int, nz: int, theta0: np.ndarray) -> np.ndarray:
    """``s``: yf (nf) | zh (nz) | Xi (nz n, xi_i contiguous) | thetah (n) | Ah (n), the
    part RK4 integrates, then psi (n) | smoothed |deviation| of omegah (n) | smoothed
    omegah (n) | the _N_SCALARS scalars named _Y_PREV .. _LVL_POW_LONG | a ring of
    _RING snapshots of thetah (n each), for the roll-back on loss of signal (D5)."""
    s = np.zeros(nf + nz + nz * n + 5 * n + _N_SCALARS + _RING * n)
    oth = nf + nz + nz * n
    s[oth : oth + n] = theta0
    s[s.size - _RING * n :] = np.tile(theta0, _RING)
    return s
