"""``adaptive-multisine``: adaptive observer for n biased sinusoids with excitation switching.

Paper: ``shared/papers/004_880a59a5c07ec15b.txt``, Chen, Pin, Ng, Hui, Parisini, "An
adaptive observer-based robust estimator of multi-sinusoidal signals". Algorithm 1 is the
reference; the departures from it are listed at the end of this docstring.

Signal (1)-(2): ``y(t) = A0 + sum_i A_i sin(phi_i(t)) + d(t)``, ``phi_i' = omega_i``.

Biased multi-oscillator (3)-(7), ``x in R^(2n+1)`` (``R^(2n)`` with ``bias=False``)::

    x' = F_x x + G_x(x) theta*,       y = C_x x
    F_x = blockdiag(J_1, ..., J_n, 0),  J_i = [[0, 1], [a_i, 0]],  C_x = [1 0 1 0 ... 1 0 | 1]
    G_x_i(x) = -x_{2i-1} e_{2i}                                                      (6)-(7)
    theta*_i = a_i + Omega_i,  Omega_i = omega_i^2                                   (4)

so that ``x_{2i-1} = A_i sin(phi_i)``, ``x_{2i} = A_i omega_i cos(phi_i)`` and
``x_{2n+1} = A0``. *Rebuilt:* the extraction prints ``G_x_i = +x_{2i-1} e_{2i}``; with
(4) and the -1 entry of F_i that gives ``x_{2i}' = (2 a_i + Omega_i) x_{2i-1}``, not an
oscillator, so the sign is ``-`` (checked numerically in the tests: the model (3) with the
minus sign reproduces ``sin``/``cos`` exactly).

Output filter (12): ``yf' = F_f yf + B_f y`` with ``n_f = n - 1`` states (``F_f`` diagonal
with the ``filter_poles``, ``B_f`` the ``filter_gains``). Augmented state (15):
``z = [x; yf]``, ``n_z = 2n + 1 + n_f``, ``F_z = [[F_x, 0], [B_f C_x, F_f]]``,
``C_z = blockdiag(C_x, I_{n-1})``, output ``eta = [y; yf]``, ``G_z = [G_x; 0]``.

Estimator, with ``L = [[L_x, 0], [0, 0]]`` and ``L_x`` by pole placement of
``F_x - L_x C_x`` on ``poles`` (``scipy.signal.place_poles``), ``A_L = F_z - L C_z``::

    zh'  = A_L zh + L eta + G_z(zh) thetah + Xi thetah'                              (16)
    xi_i' = A_L xi_i + G_z_i(zh),   Xi = [xi_1 ... xi_n]                        (17)-(18)
    thetah' = P[thetah'_unc]  (projection on |thetah| <= theta_bar)            (19)-(21)
    Ah_i' = -mu_A omegah_i (omegah_i Ah_i - sqrt(Omegah_i x_{2i-1}^2 + x_{2i}^2)),
            held at 0 from below                                                     (11)
    omegah_i = sqrt(thetah_i - a_i)                                                  (8)
    phih_i = angle(x_{2i} + j omegah_i x_{2i-1})                                     (10)
    A0h = x_{2n+1}

Excitation, (23)-(25): ``M = Xi^T Xi + rho^2 I``, ``Phi_Xi = Xi^T C_z^T C_z Xi``,
``Phi_Psi = M^-1 Phi_Xi``; its eigenvalues ``lambda_i`` lie in ``[0, 1)`` (``|C_z| = 1``)
and ``psi_i`` switches on at ``lambda_i >= delta_high``, off at ``lambda_i < delta_low``,
and holds in between (25). ``lambda`` is sorted in decreasing order, so ``psi_1`` belongs to
the best-excited direction (the paper does not say how it orders them).

Unconstrained law (22), as implemented (*departure 1*)::

    thetah'_unc = -mu V Psi V^T Xi^T C_z^T (C_z zh - eta)

where ``V`` holds the generalised eigenvectors ``Phi_Xi v = lambda M v`` normalised by
``V^T M V = I`` (Cholesky ``M = R R^T``, Jacobi on ``R^-1 Phi_Xi R^-T``), so
``Phi_Psi = V Lambda V^-1`` and ``V V^T = M^-1``. Why: ``Phi_Psi`` is the product of two
symmetric matrices and is not symmetric, so the paper's ``U_Psi S_Psi U_Psi^T`` (23) and the
pairing of the i-th eigenvalue of ``Phi_Psi`` with the i-th one of ``Phi_Xi`` (24) are only
defined when ``Xi^T Xi`` and ``Phi_Xi`` commute. Under that assumption the paper itself reduces
(22) to ``-mu M^-1 Psi Xi^T C_z^T (...)`` (33), which is exactly what the form above gives
when every ``psi_i = 1`` (``V V^T = M^-1``). With partial excitation it freezes exactly the
under-excited generalised eigen-directions (the over-parametrisation case of Example 2), and
in the coordinates ``u = V^T M theta~`` each excited direction decays at the rate
``mu lambda_i >= mu delta_low``, the rate the proof of Theorem 4.1 uses.

Discretisation (*departure 2*; the paper uses forward Euler at Ts = 0.3 ms and 0.1 ms):
time is scaled, ``tau = omega_unit_rad_s * t``, and every rate-like parameter (a_i, poles,
filter poles and gains, mu, rho, omega0, omega_max) is given in these units, so
``omega_unit_rad_s = 1`` runs the paper's rad/s examples with the paper's gains and
``omega_unit_rad_s = 2 pi f0`` gives them relative to a nominal frequency f0 (the equations
are covariant: a -> a/s^2, poles, F_f, B_f, mu -> /s, rho -> rho s^2, mu_A unchanged). The
input is divided by ``amplitude_unit`` (rho and the excitation thresholds are in signal
units). Between two samples the measurement is interpolated linearly (first-order hold, no
delay) and the whole state is integrated with classical RK4 in ``m`` equal sub-steps, ``m``
chosen once so that ``h omega_ball <= 0.25`` and ``h * rate <= 0.5`` for the fastest linear
rate (observer and filter poles, mu, mu_A omega_ball^2). The switching signals are updated
once per sub-step (held during the RK4 stages), the projection is the continuous (21) inside
the stages followed by a radial clip, and ``Ah >= 0`` is clipped likewise. The RK4 phase error
biases the frequency by ~(h omega)^4/120 relative (< 4e-6 at the bound above).
The linear interpolation scales a tone's amplitude by ``sinc^2(omega h / 2)`` (without phase
shift); the reported amplitude is divided by that factor (*departure 3*).

Outputs and flags (*departure 4*, beyond Algorithm 1): a component whose amplitude estimate
falls below ``max(min_amplitude, fade_ratio * max_j A_j)`` is reported as faded (extras
``component_faded``): its frequency and phase are NaN, its amplitude is the (small)
estimate. A component with ``Omegah_i <= 0`` (no real frequency, (8)) is NaN throughout.
``converged`` requires every component present with a real frequency, every ``psi_i = 1``,
and a smoothed frequency drift ``tau_c |d omegah_i / d tau| <= convergence_tol * omegah_i``
(exponential smoothing over ``convergence_time``). Extras per sample: ``excitation_level``
(lambda_i of (25), (N, n)), ``adaptation_enabled`` (psi_i, (N, n)), ``component_faded``
((N, n)) and ``observer_reset`` ((N,)): if the state ever becomes non-finite or absurdly large
(a guard, never seen in the paper's examples), the observer restarts from zero with the last
finite parameter estimate. The residual is the one-step prediction of the sample from the
previous estimates (x propagated by the oscillator at Omegah_i over one sample, with the
amplitude correction).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from pydantic import Field, model_validator
from scipy.signal import place_poles

from sinewatch.errors import ParameterError
from sinewatch.estimators import register
from sinewatch.estimators.base import Estimator, EstimatorParams, Track

# ---- constants index (float consts vector) --------------------------------------------------
_C_H, _C_MU, _C_RHO2, _C_MUA, _C_DHI, _C_DLO, _C_TBAR = 0, 1, 2, 3, 4, 5, 6
_C_AMPU, _C_OMU, _C_MINA, _C_FADE, _C_CALPHA, _C_CTOL, _C_CTIME, _C_ZMAX = 7, 8, 9, 10, 11, 12, 13, 14
_N_CONSTS = 15


class AdaptiveMultisineParams(EstimatorParams):
    """Rates are in units of ``omega_unit_rad_s`` (see the module docstring)."""

    n_sinusoids: int = Field(2, ge=1, le=8, description="n, the number of sinusoids modelled")
    bias: bool = Field(True, description="Model the offset A0 (state x_{2n+1}); False: zero-mean")
    omega_unit_rad_s: float = Field(
        1.0, gt=0, allow_inf_nan=False,
        description="Angular frequency (rad/s) that counts as 1 in every rate parameter; 1 = paper units",
    )
    amplitude_unit: float = Field(
        1.0, gt=0, allow_inf_nan=False, description="Signal value that counts as 1 (the input is divided by it)"
    )
    a: list[float] | None = Field(
        None, description="a_i of (4), distinct (non-zero with bias); default -0.5 i / s^2 of the defaults"
    )
    poles: list[float] | None = Field(
        None, description="2n (+1 with bias) distinct negative poles of F_x - L_x C_x"
    )
    filter_poles: list[float] | None = Field(None, description="n-1 distinct negative poles of F_f (12)")
    filter_gains: list[float] | None = Field(None, description="n-1 non-zero entries of B_f (12)")
    mu: float = Field(2.0, gt=0, allow_inf_nan=False, description="Frequency adaptation gain mu (22)")
    rho: float = Field(2.0, gt=0, allow_inf_nan=False, description="Regularisation rho (23)")
    mu_a: float = Field(0.15, gt=0, allow_inf_nan=False, description="Amplitude adaptation gain mu_A (11)")
    delta_low: float = Field(3e-5, allow_inf_nan=False, description="Lower switching threshold (25)")
    delta_high: float = Field(3e-4, allow_inf_nan=False, description="Upper switching threshold (25)")
    omega0: list[float] | None = Field(None, description="Initial frequencies omegah_i(0) > 0")
    omega_max: float = Field(
        4.0, gt=0, allow_inf_nan=False, description="Frequency bound omega_bar (Assumption 1) -> theta_bar"
    )
    min_amplitude: float = Field(
        0.01, ge=0, allow_inf_nan=False, description="Amplitude (in amplitude_unit) below which a component is faded"
    )
    fade_ratio: float = Field(
        0.02, ge=0, lt=1, allow_inf_nan=False,
        description="A component is faded below this fraction of the largest amplitude",
    )
    convergence_time: float = Field(
        10.0, gt=0, allow_inf_nan=False, description="Smoothing time of the convergence test (scaled time)"
    )
    convergence_tol: float = Field(
        0.02, gt=0, allow_inf_nan=False, description="Allowed relative frequency drift over convergence_time"
    )

    @model_validator(mode="after")
    def _check(self) -> AdaptiveMultisineParams:
        n = self.n_sinusoids
        if not 0 < self.delta_low < self.delta_high < 1:
            raise ValueError(
                f"expected 0 < delta_low < delta_high < 1, got delta_low={self.delta_low}, "
                f"delta_high={self.delta_high}"
            )

        def _finite_list(name: str, v: list[float] | None, length: int) -> None:
            if v is None:
                return
            if len(v) != length:
                raise ValueError(f"{name}: expected {length} values, got {len(v)}")
            if not all(math.isfinite(x) for x in v):
                raise ValueError(f"{name}: expected finite values, got {v}")

        _finite_list("a", self.a, n)
        _finite_list("poles", self.poles, 2 * n + int(self.bias))
        _finite_list("filter_poles", self.filter_poles, n - 1)
        _finite_list("filter_gains", self.filter_gains, n - 1)
        _finite_list("omega0", self.omega0, n)
        if self.a is not None:
            if len(set(self.a)) != n:
                raise ValueError(f"a: expected distinct values (observability), got {self.a}")
            if self.bias and any(v == 0 for v in self.a):
                raise ValueError(f"a: expected non-zero values with bias=True (observability), got {self.a}")
        for name, v in (("poles", self.poles), ("filter_poles", self.filter_poles)):
            if v is not None:
                if any(p >= 0 for p in v):
                    raise ValueError(f"{name}: expected values in the left half-plane (< 0), got {v}")
                if len(set(v)) != len(v):
                    raise ValueError(f"{name}: expected distinct values, got {v}")
        if self.filter_gains is not None and any(b == 0 for b in self.filter_gains):
            raise ValueError(f"filter_gains: expected non-zero values (controllability), got {self.filter_gains}")
        if self.omega0 is not None and not all(0 < w < self.omega_max for w in self.omega0):
            raise ValueError(f"omega0: expected values in (0, omega_max={self.omega_max}), got {self.omega0}")
        return self


def default_design(n: int, bias: bool) -> dict[str, list[float]]:
    """Defaults for the per-component lists (scaled units, signal frequencies ~0.5-2).

    They are the paper's Example 1 gains for n = 2 (a, poles, F_f, B_f) rescaled by s = 3.5
    (its tones at 2 and 5 rad/s become 0.57 and 1.43), extended to other n and to the bias.
    """
    s = 3.5
    a = [-0.5 * (i + 1) / s**2 for i in range(n)]
    m = 2 * n + int(bias)
    poles = list(-np.geomspace(0.2, 2.0, m) / s)
    filter_poles = [-(4.0 + k + 1) / s for k in range(n - 1)]
    filter_gains = [0.9 * (4.0 + k + 1) / s for k in range(n - 1)]
    omega0 = list(np.linspace(0.75, 1.25, n)) if n > 1 else [1.0]
    return {"a": a, "poles": poles, "filter_poles": filter_poles, "filter_gains": filter_gains, "omega0": omega0}


# ---- kernel helpers ---------------------------------------------------------------------------
@njit(cache=True, nogil=True, error_model="numpy")
def _sym_eig(S, n, lam, W):
    """Cyclic Jacobi on the symmetric n x n ``S`` (destroyed): eigenvalues ``lam`` sorted in
    decreasing order, orthonormal eigenvectors in the columns of ``W``."""
    for i in range(n):
        for j in range(n):
            W[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(30):
        off = 0.0
        tot = 0.0
        for i in range(n):
            tot += S[i, i] * S[i, i]
            for j in range(i + 1, n):
                off += S[i, j] * S[i, j]
        if off <= 1e-30 * tot or off == 0.0:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = S[p, q]
                if apq == 0.0:
                    continue
                theta = (S[q, q] - S[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):  # S <- S J (columns p, q)
                    skp = S[k, p]
                    skq = S[k, q]
                    S[k, p] = c * skp - s * skq
                    S[k, q] = s * skp + c * skq
                for k in range(n):  # S <- J^T S (rows p, q)
                    spk = S[p, k]
                    sqk = S[q, k]
                    S[p, k] = c * spk - s * sqk
                    S[q, k] = s * spk + c * sqk
                for k in range(n):
                    wkp = W[k, p]
                    wkq = W[k, q]
                    W[k, p] = c * wkp - s * wkq
                    W[k, q] = s * wkp + c * wkq
    for i in range(n):
        lam[i] = S[i, i]
    for i in range(n):  # selection sort, decreasing
        best = i
        for j in range(i + 1, n):
            if lam[j] > lam[best]:
                best = j
        if best != i:
            tmp = lam[i]
            lam[i] = lam[best]
            lam[best] = tmp
            for k in range(n):
                tmp = W[k, i]
                W[k, i] = W[k, best]
                W[k, best] = tmp


@njit(cache=True, nogil=True, error_model="numpy")
def _excitation(s, oxi, n, nz, nx, cx, rho2, CX, R, Rinv, S, W, lam):
    """Generalised eigen-decomposition of (Phi_Xi, M) of (23): fills ``CX = C_z Xi`` (n x n),
    the Cholesky factor ``R`` of ``M``, its inverse, ``W`` and ``lam`` (decreasing)."""
    for i in range(n):
        acc = 0.0
        for r in cx:  # row 0 of C_z Xi: C_x xi_i
            acc += s[oxi + i * nz + r]
        CX[0, i] = acc
        for j in range(1, n):  # the filter rows: yf part of xi_i
            CX[j, i] = s[oxi + i * nz + nx + j - 1]
    # M = Xi^T Xi + rho^2 I, Cholesky M = R R^T (R lower)
    for i in range(n):
        for j in range(i + 1):
            acc = 0.0
            for r in range(nz):
                acc += s[oxi + i * nz + r] * s[oxi + j * nz + r]
            if i == j:
                acc += rho2
            S[i, j] = acc
    for j in range(n):
        d = S[j, j]
        for k in range(j):
            d -= R[j, k] * R[j, k]
        d = math.sqrt(d) if d > 0.0 else math.sqrt(rho2)
        R[j, j] = d
        for i in range(j + 1, n):
            acc = S[i, j]
            for k in range(j):
                acc -= R[i, k] * R[j, k]
            R[i, j] = acc / d
        for i in range(j):
            R[i, j] = 0.0
    for j in range(n):  # Rinv (lower)
        for i in range(n):
            Rinv[i, j] = 0.0
        Rinv[j, j] = 1.0 / R[j, j]
        for i in range(j + 1, n):
            acc = 0.0
            for k in range(j, i):
                acc -= R[i, k] * Rinv[k, j]
            Rinv[i, j] = acc / R[i, i]
    # S = Rinv Phi_Xi Rinv^T = (CX Rinv^T)^T (CX Rinv^T)
    for i in range(n):
        for j in range(i + 1):
            acc = 0.0
            for r in range(n):
                bi = 0.0
                bj = 0.0
                for k in range(i + 1):
                    bi += CX[r, k] * Rinv[i, k]
                for k in range(j + 1):
                    bj += CX[r, k] * Rinv[j, k]
                acc += bi * bj
            S[i, j] = acc
            S[j, i] = acc
    _sym_eig(S, n, lam, W)


@njit(cache=True, nogil=True, error_model="numpy")
def _deriv(s, yin, psi, ds, dims, cx, a, AL, Lx, Ff, Bf, consts, CX, R, Rinv, S, W, lam, ev, g, q):
    """Right-hand side of (12), (16), (17), (19)-(22), (11) at state ``s`` and input ``yin``."""
    n, nx, nf, nz = dims[0], dims[1], dims[2], dims[3]
    oz = nf
    oxi = oz + nz
    oth = oxi + nz * n
    oa = oth + n
    mu, rho2, mu_a, tbar = consts[_C_MU], consts[_C_RHO2], consts[_C_MUA], consts[_C_TBAR]
    # (12) measured-output filter
    for j in range(nf):
        ds[j] = Ff[j] * s[j] + Bf[j] * yin
    # output error C_z zh - eta_hat (n-vector)
    acc = 0.0
    for r in cx:
        acc += s[oz + r]
    ev[0] = acc - yin
    for j in range(1, n):
        ev[j] = s[oz + nx + j - 1] - s[j - 1]
    # (23)-(25): generalised eigen-decomposition, then (22) as V Psi V^T Xi^T C_z^T e
    _excitation(s, oxi, n, nz, nx, cx, rho2, CX, R, Rinv, S, W, lam)
    for i in range(n):  # g = (C_z Xi)^T e
        acc = 0.0
        for r in range(n):
            acc += CX[r, i] * ev[r]
        g[i] = acc
    for i in range(n):  # q = Rinv g
        acc = 0.0
        for k in range(i + 1):
            acc += Rinv[i, k] * g[k]
        q[i] = acc
    for i in range(n):  # p = Psi W^T q  (stored in g)
        acc = 0.0
        for k in range(n):
            acc += W[k, i] * q[k]
        g[i] = acc * psi[i]
    for i in range(n):  # q = W p
        acc = 0.0
        for k in range(n):
            acc += W[i, k] * g[k]
        q[i] = acc
    tt = 0.0
    tu = 0.0
    for i in range(n):  # thetah'_unc = -mu Rinv^T q  (22)
        acc = 0.0
        for k in range(i, n):
            acc += Rinv[k, i] * q[k]
        ds[oth + i] = -mu * acc
        tt += s[oth + i] * s[oth + i]
        tu += s[oth + i] * ds[oth + i]
    if tt >= tbar * tbar and tu > 0.0:  # projection (19)-(21)
        for i in range(n):
            ds[oth + i] -= s[oth + i] * tu / (tbar * tbar)
    # (16): zh' = A_L zh + L_x y + G_z(zh) thetah + Xi thetah'
    for r in range(nz):
        acc = Lx[r] * yin
        for c in range(nz):
            acc += AL[r, c] * s[oz + c]
        for i in range(n):
            acc += s[oxi + i * nz + r] * ds[oth + i]
        ds[oz + r] = acc
    for i in range(n):
        ds[oz + 2 * i + 1] -= s[oz + 2 * i] * s[oth + i]  # G_z_i(zh) = -x_{2i-1} e_{2i}
    # (17): xi_i' = A_L xi_i + G_z_i(zh)
    for i in range(n):
        base = oxi + i * nz
        for r in range(nz):
            acc = 0.0
            for c in range(nz):
                acc += AL[r, c] * s[base + c]
            ds[base + r] = acc
        ds[base + 2 * i + 1] -= s[oz + 2 * i]
    # (11): amplitude adaptation, held at 0 from below
    for i in range(n):
        om2 = s[oth + i] - a[i]  # (8)
        x1 = s[oz + 2 * i]
        x2 = s[oz + 2 * i + 1]
        if om2 > 0.0:
            w = math.sqrt(om2)
            inst = om2 * x1 * x1 + x2 * x2
            d = -mu_a * w * (w * s[oa + i] - math.sqrt(inst if inst > 0.0 else 0.0))
        else:
            d = 0.0
        if s[oa + i] <= 0.0 and d < 0.0:
            d = 0.0
        ds[oa + i] = d


@njit(cache=True, nogil=True, error_model="numpy")
def _osc_step(om2, h):
    """(C, S) with x(h) = C x(0) + S x'(0) for x'' = -om2 x."""
    if om2 > 0.0:
        w = math.sqrt(om2)
        return math.cos(w * h), math.sin(w * h) / w
    if om2 < 0.0:
        w = math.sqrt(-om2)
        return math.cosh(w * h), math.sinh(w * h) / w
    return 1.0, h


@njit(cache=True, nogil=True, error_model="numpy")
def _sinc2(x):
    """sinc^2(x) = (sin x / x)^2, the amplitude factor of linear interpolation at x = w h / 2."""
    if abs(x) < 1e-4:
        return 1.0 - x * x / 3.0
    v = math.sin(x) / x
    return v * v


@njit(cache=True, nogil=True, error_model="numpy")
def adaptive_multisine_kernel(y, state, dims, cx, a, AL, Lx, Ff, Bf, theta0, consts, last_only):
    """Run the estimator over block ``y`` from ``state``; return ``(out, extras, sse, new_state)``.

    ``dims`` = (n, nx, nf, nz, substeps, bias); ``cx`` the z-indices summed by C_x; ``a`` the
    a_i; ``AL`` = F_z - L C_z; ``Lx`` the first column of L (length nz); ``Ff``, ``Bf`` the
    diagonal filter (12); ``theta0`` the initial thetah (used by the reset guard); ``consts``
    see the ``_C_*`` indices. State layout: yf (nf) | zh (nz) | Xi (nz*n, column xi_i
    contiguous) | thetah (n) | Ah (n) | psi (n) | drift (n) | omega_prev (n) | y_prev | y_pred |
    started. ``out`` columns: frequency_hz (n), amplitude (n), phase (n), offset, converged;
    ``extras`` columns: lambda (n), psi (n), faded (n), reset. Pure: inputs are not modified.
    """
    n, nx, nf, nz, m_sub, bias = dims[0], dims[1], dims[2], dims[3], dims[4], dims[5]
    h = consts[_C_H]
    amp_u = consts[_C_AMPU]
    om_u = consts[_C_OMU]
    d_hi, d_lo, tbar = consts[_C_DHI], consts[_C_DLO], consts[_C_TBAR]
    min_a, fade, c_alpha, c_tol, c_time = (
        consts[_C_MINA], consts[_C_FADE], consts[_C_CALPHA], consts[_C_CTOL], consts[_C_CTIME],
    )
    zmax = consts[_C_ZMAX]
    rho2 = consts[_C_RHO2]
    oz = nf
    oxi = oz + nz
    oth = oxi + nz * n
    oa = oth + n
    ops = oa + n
    odr = ops + n
    owp = odr + n
    oyp = owp + n
    ns = oxi + nz * n + 2 * n  # integrated part
    s = state.copy()
    k1 = np.empty(ns)
    k2 = np.empty(ns)
    k3 = np.empty(ns)
    k4 = np.empty(ns)
    tmp = np.empty(ns)
    psi = np.empty(n)
    CX = np.empty((n, n))
    R = np.zeros((n, n))
    Rinv = np.zeros((n, n))
    S = np.empty((n, n))
    W = np.empty((n, n))
    lam = np.empty(n)
    ev = np.empty(n)
    g = np.empty(n)
    q = np.empty(n)
    nrow = 1 if last_only else y.shape[0]
    out = np.empty((nrow, 3 * n + 2))
    ext = np.empty((nrow, 3 * n + 1))
    hs = h / m_sub
    sse = 0.0
    nyield = y.shape[0]
    for k in range(nyield):
        yk = y[k] / amp_u
        e = yk - s[oyp + 1]  # one-step prediction error
        sse += e * e
        reset = False
        if s[oyp + 2] != 0.0:
            y0 = s[oyp]
            for i in range(n):
                psi[i] = s[ops + i]
            for j in range(m_sub):
                ua = y0 + (yk - y0) * (j / m_sub)
                um = y0 + (yk - y0) * ((j + 0.5) / m_sub)
                ub = y0 + (yk - y0) * ((j + 1.0) / m_sub)
                _deriv(s, ua, psi, k1, dims, cx, a, AL, Lx, Ff, Bf, consts, CX, R, Rinv, S, W, lam, ev, g, q)
                for r in range(ns):
                    tmp[r] = s[r] + 0.5 * hs * k1[r]
                _deriv(tmp, um, psi, k2, dims, cx, a, AL, Lx, Ff, Bf, consts, CX, R, Rinv, S, W, lam, ev, g, q)
                for r in range(ns):
                    tmp[r] = s[r] + 0.5 * hs * k2[r]
                _deriv(tmp, um, psi, k3, dims, cx, a, AL, Lx, Ff, Bf, consts, CX, R, Rinv, S, W, lam, ev, g, q)
                for r in range(ns):
                    tmp[r] = s[r] + hs * k3[r]
                _deriv(tmp, ub, psi, k4, dims, cx, a, AL, Lx, Ff, Bf, consts, CX, R, Rinv, S, W, lam, ev, g, q)
                for r in range(ns):
                    s[r] += hs / 6.0 * (k1[r] + 2.0 * k2[r] + 2.0 * k3[r] + k4[r])
                # projection: radial clip to |thetah| <= theta_bar (19); Ah >= 0 (11)
                tt = 0.0
                for i in range(n):
                    tt += s[oth + i] * s[oth + i]
                if tt > tbar * tbar:
                    sc = tbar / math.sqrt(tt)
                    for i in range(n):
                        s[oth + i] *= sc
                for i in range(n):
                    if s[oa + i] < 0.0:
                        s[oa + i] = 0.0
                # guard: the state stays finite and bounded
                bad = False
                for r in range(ns):
                    if not abs(s[r]) <= zmax:  # also catches NaN
                        bad = True
                if bad:
                    reset = True
                    for r in range(oth):
                        s[r] = 0.0
                    tt = 0.0
                    for i in range(n):
                        if not math.isfinite(s[oth + i]):
                            tt = math.nan
                    for i in range(n):
                        if not math.isfinite(tt):
                            s[oth + i] = theta0[i]
                        s[oa + i] = 0.0
                        psi[i] = 0.0
                # (25): hysteretic switching on the excitation at the end of the sub-step
                _excitation(s, oxi, n, nz, nx, cx, rho2, CX, R, Rinv, S, W, lam)
                for i in range(n):
                    if lam[i] >= d_hi:
                        psi[i] = 1.0
                    elif lam[i] < d_lo:
                        psi[i] = 0.0
            for i in range(n):
                s[ops + i] = psi[i]
        else:
            s[oyp + 2] = 1.0
            _excitation(s, oxi, n, nz, nx, cx, rho2, CX, R, Rinv, S, W, lam)
        s[oyp] = yk
        # ---- outputs at t_k: (8), (10), (11); drift smoothing; prediction of the next sample
        amax = 0.0
        for i in range(n):
            om2 = s[oth + i] - a[i]
            corr = 1.0 / _sinc2(0.5 * h * math.sqrt(om2)) if om2 > 0.0 else 1.0
            v = s[oa + i] * corr
            if v > amax:
                amax = v
        thr = min_a if min_a > fade * amax else fade * amax
        ypred = s[oz + nx - 1] if bias else 0.0
        all_ok = True
        j = 0 if last_only else k
        write = (not last_only) or k == nyield - 1
        for i in range(n):
            om2 = s[oth + i] - a[i]
            x1 = s[oz + 2 * i]
            x2 = s[oz + 2 * i + 1]
            cc, ss = _osc_step(om2, h)
            if om2 > 0.0:
                w = math.sqrt(om2)
                corr = 1.0 / _sinc2(0.5 * h * w)
                d = abs(w - s[owp + i]) / h
                s[odr + i] += c_alpha * (d - s[odr + i])
                s[owp + i] = w
            else:
                w = math.nan
                corr = 1.0
                all_ok = False
            ypred += corr * (cc * x1 + ss * x2)
            amp = s[oa + i] * corr
            faded = not amp >= thr or amp <= 0.0
            if faded:
                all_ok = False
            if not (s[odr + i] * c_time <= c_tol * w):
                all_ok = False
            if s[ops + i] == 0.0:
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
                ext[j, n + i] = s[ops + i]
                ext[j, 2 * n + i] = 1.0 if faded else 0.0
        s[oyp + 1] = ypred
        if write:
            out[j, 3 * n] = s[oz + nx - 1] * amp_u if bias else 0.0
            out[j, 3 * n + 1] = 1.0 if all_ok else 0.0
            for i in range(n):
                ext[j, i] = lam[i]
            ext[j, 3 * n] = 1.0 if reset else 0.0
    return out, ext, sse * amp_u * amp_u, s


@register
class AdaptiveMultisine(Estimator):
    """Adaptive observer with excitation-based switching for n biased sinusoids (paper 004)."""

    name = "adaptive-multisine"
    Params = AdaptiveMultisineParams
    summary = "Adaptive observer for n biased sinusoids with SVD excitation switching (paper 004)"
    paper = "004_880a59a5c07ec15b.txt"
    example_sample_rate_hz = 1000.0
    example_frequency_hz = 10.0
    example_params = {"n_sinusoids": 2, "omega_unit_rad_s": 2 * math.pi * 10.0}

    @classmethod
    def example_signal(cls, n: int, seed: int = 0) -> np.ndarray:
        """Two tones at 0.7 and 1.3 times the 10 Hz nominal frequency, offset 0.5, 1 % noise."""
        rng = np.random.default_rng(seed)
        t = np.arange(n) / cls.example_sample_rate_hz
        f0 = cls.example_frequency_hz
        return (
            0.5
            + np.sin(2 * np.pi * 0.7 * f0 * t + 0.3)
            + 0.6 * np.sin(2 * np.pi * 1.3 * f0 * t + 1.1)
            + 0.01 * rng.standard_normal(n)
        )

    @property
    def n_components(self) -> int:
        return self.params.n_sinusoids

    # ---- derived design --------------------------------------------------------------------
    def _design(self) -> dict[str, list[float]]:
        p = self.params
        d = default_design(p.n_sinusoids, p.bias)
        for key in d:
            v = getattr(p, key)
            if v is not None:
                d[key] = list(v)
        return d

    def _theta_bar(self, a: list[float]) -> float:
        wb2 = self.params.omega_max**2
        return float(np.sqrt(sum(max(abs(ai), abs(ai + wb2)) ** 2 for ai in a)))

    def _check_params(self) -> None:
        p = self.params
        d = self._design()
        a = d["a"]
        if len(set(a)) != len(a) or (p.bias and any(v == 0 for v in a)):
            raise ParameterError(f"a: expected distinct (and, with bias, non-zero) values, got {a}")
        if not all(0 < w < p.omega_max for w in d["omega0"]):
            raise ParameterError(f"omega0: expected values in (0, omega_max={p.omega_max}), got {d['omega0']}")
        tbar = self._theta_bar(a)
        w_ball = math.sqrt(tbar - min(a))
        nyq = math.pi * self.sample_rate_hz
        if w_ball * p.omega_unit_rad_s >= nyq:
            raise ParameterError(
                "omega_max: expected the projection ball |theta| <= theta_bar to admit only frequencies "
                f"below Nyquist ({nyq:.6g} rad/s), got up to {w_ball * p.omega_unit_rad_s:.6g} rad/s "
                f"(omega_max={p.omega_max}, a={a}, omega_unit_rad_s={p.omega_unit_rad_s})"
            )

    def _setup(self) -> None:
        p = self.params
        n = p.n_sinusoids
        bias = p.bias
        d = self._design()
        a = np.asarray(d["a"], dtype=np.float64)
        nx = 2 * n + int(bias)
        nf = n - 1
        nz = nx + nf
        Fx = np.zeros((nx, nx))  # noqa: N806 (paper's names)
        Cx = np.zeros(nx)  # noqa: N806
        for i in range(n):
            Fx[2 * i, 2 * i + 1] = 1.0
            Fx[2 * i + 1, 2 * i] = a[i]
            Cx[2 * i] = 1.0
        if bias:
            Cx[nx - 1] = 1.0
        poles = np.asarray(d["poles"], dtype=np.float64)
        try:
            res = place_poles(Fx.T, Cx[:, None], poles)
        except (ValueError, np.linalg.LinAlgError) as exc:
            raise ParameterError(f"poles: expected placeable observer poles, got {list(poles)} ({exc})") from exc
        Lx = res.gain_matrix.T[:, 0]  # noqa: N806
        got = np.sort(np.linalg.eigvals(Fx - np.outer(Lx, Cx)).real)
        if not np.allclose(got, np.sort(poles), rtol=1e-6, atol=1e-9):
            raise ParameterError(f"poles: expected placeable observer poles, got {list(poles)} (placed {list(got)})")
        Ff = np.asarray(d["filter_poles"], dtype=np.float64)  # noqa: N806
        Bf = np.asarray(d["filter_gains"], dtype=np.float64)  # noqa: N806
        AL = np.zeros((nz, nz))  # noqa: N806  A_L = F_z - L C_z
        AL[:nx, :nx] = Fx - np.outer(Lx, Cx)
        AL[nx:, :nx] = np.outer(Bf, Cx)
        AL[nx:, nx:] = np.diag(Ff)
        Lfull = np.zeros(nz)  # noqa: N806
        Lfull[:nx] = Lx
        tbar = self._theta_bar(list(a))
        w_ball = math.sqrt(tbar - float(a.min()))
        h = p.omega_unit_rad_s / self.sample_rate_hz
        rate = max(
            float(np.max(np.abs(np.linalg.eigvals(AL)))), p.mu, p.mu_a * w_ball**2, float(np.max(np.abs(Ff), initial=0.0))
        )
        m_sub = max(1, math.ceil(h * w_ball / 0.25), math.ceil(h * rate / 0.5))
        if m_sub > 512:
            raise ParameterError(
                f"sample_rate_hz: expected at most 512 RK4 sub-steps per sample, got {m_sub} "
                f"(raise the sample rate or lower mu, the poles or omega_max)"
            )
        theta0 = a + np.asarray(d["omega0"], dtype=np.float64) ** 2  # (4)
        consts = np.zeros(_N_CONSTS)
        consts[_C_H] = h
        consts[_C_MU] = p.mu
        consts[_C_RHO2] = p.rho**2
        consts[_C_MUA] = p.mu_a
        consts[_C_DHI] = p.delta_high
        consts[_C_DLO] = p.delta_low
        consts[_C_TBAR] = tbar
        consts[_C_AMPU] = p.amplitude_unit
        consts[_C_OMU] = p.omega_unit_rad_s
        consts[_C_MINA] = p.min_amplitude
        consts[_C_FADE] = p.fade_ratio
        consts[_C_CALPHA] = -math.expm1(-h / p.convergence_time)
        consts[_C_CTOL] = p.convergence_tol
        consts[_C_CTIME] = p.convergence_time
        consts[_C_ZMAX] = 1e12
        self._dims = np.array([n, nx, nf, nz, m_sub, int(bias)], dtype=np.int64)
        self._cx = np.flatnonzero(Cx).astype(np.int64)
        self._a = a
        self._AL = np.ascontiguousarray(AL)
        self._Lx = Lfull
        self._Ff = np.ascontiguousarray(Ff)
        self._Bf = np.ascontiguousarray(Bf)
        self._theta0 = theta0
        self._consts = consts
        self.L_x = Lx  # exposed for tests and docs
        self.theta_bar = tbar
        self.substeps = m_sub

    def _initial_state(self) -> dict[str, np.ndarray]:
        n, nf, nz = self.params.n_sinusoids, int(self._dims[2]), int(self._dims[3])
        s = np.zeros(nf + nz + nz * n + 5 * n + 3)
        oth = nf + nz + nz * n
        s[oth : oth + n] = self._theta0
        return {"s": s}

    def _run(self, samples, state, last_only):
        out, ext, sse, s = adaptive_multisine_kernel(
            samples, state["s"], self._dims, self._cx, self._a, self._AL, self._Lx, self._Ff, self._Bf,
            self._theta0, self._consts, last_only,
        )
        n = self.params.n_sinusoids
        track = Track(
            frequency_hz=out[:, 0:n],
            amplitude=out[:, n : 2 * n],
            phase_rad=out[:, 2 * n : 3 * n],
            offset=out[:, 3 * n],
            converged=out[:, 3 * n + 1] != 0.0,
            residual_rms=math.sqrt(sse / samples.shape[0]),
            extras={
                "excitation_level": ext[:, 0:n],
                "adaptation_enabled": ext[:, n : 2 * n] != 0.0,
                "component_faded": ext[:, 2 * n : 3 * n] != 0.0,
                "observer_reset": ext[:, 3 * n] != 0.0,
            },
        )
        return track, {"s": s}
