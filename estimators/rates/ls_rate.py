"""Single-frame 3-axis angular rate by least squares on angular-distance invariance.

The problem is fu2022's (eqs 7-16, see :mod:`rollingstar.estimators.rates.pso`): the catalogue angle between two
identified stars equals the angle between their camera directions once both are moved to one common
time. Here it is solved by damped Gauss-Newton (Levenberg-Marquardt) with the analytic Jacobian
below, for the full rate ``omega = (wx, wy, wz)`` -- the paper's ``omega_z = 0`` installation
assumption is not needed -- over the pairs of every identified star, and with the estimate's
covariance.

Model
-----
Star ``i`` is measured at pixel ``(x_i, y_i)`` at time ``t_i`` (the StarTable ``t_ns``: mid-exposure
of its own row). Its camera direction ``w_i = unproject(x_i, y_i)`` (he2021b eq 2) moved to the
reference time ``t_ref`` is, exactly for a constant rate over the frame,

    a_i(omega) = Exp(omega dt_i) w_i,        dt_i = t_i - t_ref                       (1)

(``w(t) = R(t)^T u``, ``R(t + s) = R(t) Exp(omega s)``; the ``model="rotation"`` of pso.py, in 3 axes).
The residual of pair ``(i, j)`` is fu2022 eq 15/16's angle difference, signed:

    r_ij(omega) = angle(a_i, a_j) - theta_ij,   theta_ij = angle(ref_i, ref_j)  (catalogue)   (2)

Because both rotations in (1) share the axis, ``angle(a_i, a_j) = angle(w_i, Exp(omega (dt_j - dt_i)) w_j)``:
only the row-time differences matter and ``t_ref`` is a labelling choice.

Jacobian (derived here; checked against finite differences in tests/estimators/test_ls_rate.py).
With the left Jacobian ``J_l`` of SO(3), ``d(Exp(phi) v) = -[Exp(phi) v]x J_l(phi) dphi``, and
``d cos(theta) = b.da + a.db``, ``d theta = -d cos(theta) / sin(theta)``::

    d r_ij / d omega = n_ij^T (J_l(omega dt_j) dt_j - J_l(omega dt_i) dt_i),   n_ij = a_i x a_j / |a_i x a_j|   (3)

(to first order ``n_ij (dt_j - dt_i)``: a pair senses the rate component along its great circle's
normal, times its row-time separation; ``omega_z`` only through the normals' z components, i.e. pairs
whose great circle passes far from the boresight).

Weighting. Pair residuals share stars, so they are correlated (and with more than ``2n - 3`` pairs
their covariance is singular: the angles have only ``2n - 3`` degrees of freedom, a common rotation
changes none). With isotropic centroid noise ``sigma_i`` the first-order residual covariance is
``C = G S G^T``, ``d theta_ij / d(x_i, y_i) = -t_ij^T d w_i / d(x_i, y_i)`` (``t_ij`` the unit tangent
at ``w_i`` towards ``w_j``). From the thin SVD ``G S^(1/2) = U D V^T`` the residuals are whitened by
``D^-1 U^T`` (the pseudo-inverse of C, generalised least squares), so all pairs are used without
double counting; the covariance of the estimate is ``(J_w^T J_w)^-1`` with the whitened Jacobian
``J_w``. Stars with a 2 x 2 position covariance ``C_i`` (anisotropic: a smeared spot) enter the same
way with ``S = blockdiag(C_i)`` and ``S^(1/2)`` its Cholesky factors (``sigma_px`` is then an
(n, 2, 2) array of covariances instead of (n,) sigmas). The weighting's first-order model is the
pinhole's (``d theta / d(x, y)`` with the focal length; a radial distortion of the frame's camera
changes the weights by ``O(k1 r^2)``, the directions themselves come from its ``unproject``). To first order this is the maximum-likelihood estimate of the rate with the attitude as a
nuisance, i.e. it attains the single-frame Cramér-Rao bound of :func:`rollingstar.pipelines.truth.rate_crb_rad2`.

Hand-written parts: the residual/Jacobian (the model is ours), the whitening, and the solver: a
damped Gauss-Newton loop on the 3x3 normal equations (:func:`_levenberg_marquardt`), because for a
3-parameter problem ``scipy.optimize.least_squares``' per-call overhead cost more than the problem
(~1.6 ms/frame with it, ~0.3 ms without; ``benchmarks/rate_solvers.py`` runs both). The
least_squares version stays as the reference, :func:`solve_rate_least_squares` (``solver:
least_squares``), built from the numpy functions below, and the tests check the two agree. Per
frame the omega-independent parts (unit vectors, pair indices, catalogue angles, whitening) are
computed once (:class:`_Problem`); an evaluation of eqs 1-3 is one compiled loop over the pairs
(:mod:`rollingstar.estimators.rates.ls_rate_kernel`, numba: ~4 us instead of ~45 us of numpy calls, each
checked against the numpy functions here); the whitening uses the known
null space of a common rotation and a Cholesky inverse instead of an eigendecomposition
(:func:`whitening_rotation_null`, falling back to :func:`whitening`). No warm start from the
previous frame: from ``omega = 0`` the solver needs 3 evaluations, a warm start would save at most one
and would make a frame's estimate depend on the frames before it (``run --resume``, determinism).
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.linalg import lapack
from scipy.optimize import least_squares

from rollingstar.estimators.attitude.star_covariance import anisotropic_covariance
from rollingstar.estimators.data import DEFAULT_CENTROID_SIGMA_PX, FrameData, RateEstimate, StarTable, frame_camera
from rollingstar.estimators.rates.base import RateEstimator, Reference, reference_time_ns
from rollingstar.estimators.rates.ls_rate_kernel import (
    pair_setup_kernel,
    residual_jacobian_kernel,
)
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.so3 import cross, rotate_at_rate, skew


# ------------------------------------------------------------------------------------ model
def _jl_coefficients(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``c1 = (1 - cos t)/t^2``, ``c2 = (t - sin t)/t^3`` of the left Jacobian, for angles ``t >= 0``.

    Below 0.05 rad (always, in one frame: |omega| dt < 5 deg/s x 0.1 s = 0.009 rad) the Taylor
    series to t^4 (truncation < 1e-12 relative); the closed forms above.
    """
    t2 = t * t
    if t.size == 0 or float(np.max(t)) < 0.05:
        return 0.5 - t2 / 24.0 + t2 * t2 / 720.0, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
    small = t < 0.05
    safe = np.where(small, 1.0, t)
    c1 = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - np.cos(safe)) / safe**2)
    c2 = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (safe - np.sin(safe)) / safe**3)
    return c1, c2


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian ``J_l(phi) = I + (1 - cos t)/t^2 [phi]x + (t - sin t)/t^3 [phi]x^2`` (..., 3, 3)."""
    c1, c2 = _jl_coefficients(np.linalg.norm(phi, axis=-1))
    K = skew(phi)
    return np.eye(3) + c1[..., None, None] * K + c2[..., None, None] * (K @ K)


def _angles(ai: np.ndarray, aj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angle between rows (atan2 of |cross| and dot: accurate at all angles) and the cross products."""
    n = cross(ai, aj)
    return np.arctan2(np.sqrt(np.sum(n * n, axis=-1)), np.sum(ai * aj, axis=-1)), n


def pair_residuals(omega, w, dt_s, i, j, cat_angles) -> np.ndarray:
    """Eq (2): measured minus catalogue angle (rad) of every pair ``(i[k], j[k])``."""
    a = rotate_at_rate(omega, w, dt_s)
    return _angles(a[i], a[j])[0] - cat_angles


def pair_jacobian(omega, w, dt_s, i, j, a: np.ndarray | None = None, pair_cross: np.ndarray | None = None) -> np.ndarray:
    """Eq (3): ``d r / d omega``, (m, 3). ``a`` = eq (1) (:func:`~rollingstar.sensors.so3.rotate_at_rate`) and
    ``pair_cross`` = ``a[i] x a[j]`` when already computed.

    Evaluated without forming 3x3 matrices: ``n^T J_l(phi) = n + c1 (n x phi) + c2 ((n x phi) x phi)``
    (from ``n^T [phi]x v = (n x phi) . v``) with :func:`left_jacobian`'s coefficients, and
    ``phi_k = omega dt_k``, so ``n x phi_k = dt_k p``, ``(n x phi_k) x phi_k = dt_k^2 q`` with
    ``p = n x omega``, ``q = p x omega`` shared by both stars of a pair.
    """
    omega = np.asarray(omega, dtype=float)
    if pair_cross is None:
        if a is None:
            a = rotate_at_rate(omega, w, dt_s)
        pair_cross = cross(a[i], a[j])
    n = pair_cross / np.sqrt(np.sum(pair_cross * pair_cross, axis=-1))[:, None]
    c1, c2 = _jl_coefficients(float(np.sqrt(omega @ omega)) * np.abs(dt_s))  # at |phi_k|
    dt2 = dt_s * dt_s
    c1 = c1 * dt2  # c1 dt^2
    c2 = c2 * dt2 * dt_s  # c2 dt^3
    p = cross(n, omega[None, :])
    q = cross(p, omega[None, :])
    ddt = (dt_s[j] - dt_s[i])[:, None]
    return ddt * n + (c1[j] - c1[i])[:, None] * p + (c2[j] - c2[i])[:, None] * q


def pixel_sensitivity(camera, w: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """``G = d theta / d(x_0, y_0, x_1, y_1, ...)`` (m, 2n) at ``omega = 0`` (the weighting's first-order model).

    ``d theta_ij / d w_i = -t_ij`` (unit tangent at ``w_i`` towards ``w_j``) and
    ``d w / d(x, y) = -(I - w w^T) [e_x, e_y] / |W|`` with ``W = [-(x - cx), -(y - cy), F]``, so
    ``d theta_ij / d(x_i, y_i) = (t_ij,x, t_ij,y) / |W_i|`` (``t_ij`` is already orthogonal to ``w_i``).
    ``|w_j - cos w_i| = |w_i - cos w_j| = sin theta_ij`` normalises both tangents.
    """
    n_stars = w.shape[0]
    inv_W = w[:, 2] / camera.focal_px  # 1 / |W| = w_z / F for the unit vector w
    wi, wj = w[i], w[j]
    cos = np.einsum("ij,ij->i", wi, wj)[:, None]
    t_ij = wj - cos * wi
    t_ji = wi - cos * wj
    inv_sin = 1.0 / np.sqrt(np.einsum("ij,ij->i", t_ij, t_ij))
    m = i.shape[0]
    G = np.zeros((m, n_stars, 2))
    rows = np.arange(m)
    G[rows, i] = t_ij[:, :2] * (inv_W[i] * inv_sin)[:, None]
    G[rows, j] = t_ji[:, :2] * (inv_W[j] * inv_sin)[:, None]
    return G.reshape(m, 2 * n_stars)


def _scaled(G: np.ndarray, sigma_px) -> np.ndarray:
    """``B = G S^(1/2)``: columns scaled by each star's sigma (``sigma_px`` (n,)), or each star's
    column pair multiplied by the Cholesky factor of its 2 x 2 covariance (``sigma_px`` (n, 2, 2))."""
    sigma_px = np.asarray(sigma_px, dtype=float)
    if sigma_px.ndim == 1:
        return G * np.repeat(sigma_px, 2)[None, :]
    L = np.linalg.cholesky(sigma_px)  # (n, 2, 2)
    return np.einsum("mnj,njk->mnk", G.reshape(G.shape[0], -1, 2), L).reshape(G.shape)


def whitening(G: np.ndarray, sigma_px, rtol: float = 1e-10) -> np.ndarray:
    """``D^-1 U^T`` for the thin SVD ``B = G S^(1/2) = U D V^T`` (``S^(1/2) = diag(sigma)``, or the
    stars' 2 x 2 Cholesky factors, :func:`_scaled`): the pseudo-inverse square root of
    ``C = G S G^T`` (so ``|Wh r|^2 = r^T C^+ r``). Computed from the small Gram matrix
    ``B^T B = V D^2 V^T`` (2n x 2n instead of an m x 2n SVD; 3x cheaper):
    ``D^-1 U^T = D^-2 V^T B^T``. ``B`` has the 3 null directions of a common rotation; eigenvalues
    below ``rtol`` times the largest are dropped.

    The reference form (any null space); :func:`whitening_rotation_null` is the fast form the solver
    uses when the null space is exactly the common rotation (always, for >= 3 stars not on one great circle).
    """
    B = _scaled(G, sigma_px)
    d2, V = np.linalg.eigh(B.T @ B)
    keep = d2 > d2[-1] * rtol
    return (V[:, keep] / d2[keep][None, :]).T @ B.T


def rotation_null_space(w: np.ndarray, sigma_px) -> np.ndarray:
    """Basis (2n, 3) of the null space of ``B = G S^(1/2)``: the pixel displacements of the stars
    under a common infinitesimal rotation (which changes no angle), divided by ``sigma`` (or
    multiplied by the inverse Cholesky factor of each star's 2 x 2 covariance).

    A rotation ``dphi = e_k`` moves ``w`` by ``e_k x w``; through ``x = cx - F w_x / w_z``,
    ``y = cy - F w_y / w_z`` that is, with ``a = w_x / w_z``, ``b = w_y / w_z`` and up to the common
    factor ``F``: ``(a b, 1 + b^2)`` about x, ``(-(1 + a^2), -a b)`` about y, ``(b, -a)`` about z.
    """
    a = w[:, 0] / w[:, 2]
    b = w[:, 1] / w[:, 2]
    ab = a * b
    U = np.empty((w.shape[0], 2, 3))
    U[:, 0, 0], U[:, 1, 0] = ab, 1.0 + b * b
    U[:, 0, 1], U[:, 1, 1] = -(1.0 + a * a), -ab
    U[:, 0, 2], U[:, 1, 2] = b, -a
    sigma_px = np.asarray(sigma_px, dtype=float)
    if sigma_px.ndim == 1:
        U /= sigma_px[:, None, None]
    else:
        U = np.linalg.solve(np.linalg.cholesky(sigma_px), U)
    return U.reshape(-1, 3)


def whitening_rotation_null(G: np.ndarray, sigma_px, U: np.ndarray, rtol: float = 1e-10) -> np.ndarray | None:
    """A whitening ``Wh`` (2n, m) with ``Wh^T Wh = C^+`` (as :func:`whitening`), without an eigensolver.

    With ``M = B^T B``, ``U`` a basis of its null space (:func:`rotation_null_space`) and the
    positive semi-definite ``P = U U^T`` (unit columns), ``M~ = M + c P`` (``c = trace(M) / 2n``: same
    scale) is positive definite and ``M~^-1 B^T = M^+ B^T`` (``M~ M^+ y = y`` for ``y`` in the range of
    ``M``, where the columns of ``B^T`` lie, since ``U^T M^+ y = 0``), so
    ``(M^+ B^T)^T (M^+ B^T) = B (M^+)^2 B^T = U_B D^-2 U_B^T = C^+`` for the SVD ``B = U_B D V^T``.
    A Cholesky factorisation and inverse (LAPACK potrf/potri) instead of :func:`whitening`'s
    eigendecomposition: 3-5x cheaper for 10-25 stars, where the eigensolver dominated the solver's
    set-up. Returns None when ``M~`` is not numerically positive definite or its Cholesky pivots
    spread by more than ``1/rtol`` (a geometry with more null directions than a common rotation,
    e.g. all stars on one great circle): the caller then uses :func:`whitening`, which drops them.
    """
    B = _scaled(G, sigma_px)
    M = B.T @ B
    # any positive semi-definite term whose range is the null space works; unit columns keep M~'s scale
    U = U / np.sqrt(np.sum(U * U, axis=0))[None, :]
    Mt = M + (np.trace(M) / M.shape[0]) * (U @ U.T)
    R, info = lapack.dpotrf(Mt, lower=0, clean=1)
    if info != 0:
        return None
    piv = np.diag(R) ** 2  # lambda_min <= min(piv), lambda_max >= max(piv)
    if not piv.min() > piv.max() * rtol:
        return None
    inv, info = lapack.dpotri(R, lower=0)  # upper triangle of M~^-1
    if info != 0:
        return None
    inv = inv + inv.T  # potri fills the upper triangle; R's lower one was zeroed (clean=1)
    inv.flat[:: inv.shape[0] + 1] *= 0.5
    return inv @ B.T


@lru_cache(maxsize=128)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.triu_indices(n, 1)`` cached per star count (read-only: shared between calls)."""
    i, j = np.triu_indices(n, k=1)
    i.flags.writeable = j.flags.writeable = False
    return i, j


class _Problem:
    """One frame's least-squares problem (eqs 1-3, whitened): everything that does not depend on omega
    (unit vectors, pairs, catalogue angles, whitening) is computed once here; an evaluation is one
    compiled pass over the pairs (:mod:`rollingstar.estimators.rates.ls_rate_kernel`) and one matrix product."""

    __slots__ = ("w", "dt", "i", "j", "cat", "Wh", "rank", "k", "_X")

    def __init__(self, camera, x, y, dt_s, ref_icrs, sigma_px, k: int):
        n = x.shape[0]
        self.w = camera.unproject(x, y)
        self.dt = np.ascontiguousarray(dt_s, dtype=float)
        self.i, self.j = _pairs(n)
        m = self.i.shape[0]
        G = np.zeros((m, 2 * n))
        self.cat = np.empty(m)
        pair_setup_kernel(self.w, np.ascontiguousarray(ref_icrs, dtype=float), self.w[:, 2] / camera.focal_px,
                          self.i, self.j, G, self.cat)
        Wh = whitening_rotation_null(G, sigma_px, rotation_null_space(self.w, sigma_px))
        self.Wh = whitening(G, sigma_px) if Wh is None else Wh
        self.rank = 2 * n - 3 if Wh is not None else self.Wh.shape[0]  # independent whitened residuals
        self.k = k
        self._X = np.empty((m, 4))

    def evaluate(self, omega: np.ndarray) -> np.ndarray:
        """``Wh [r | dr/domega[:, :k]]`` (2n rows, or the rank with the fallback whitening; 1 + k columns) at ``omega`` (3,):
        whitened residuals (column 0, eq 2) and Jacobian (eq 3), from one compiled pass over the pairs."""
        residual_jacobian_kernel(self.w, self.dt, self.i, self.j, self.cat, omega, self._X)
        return (self.Wh @ self._X)[:, : 1 + self.k]

    def gram(self, omega: np.ndarray) -> np.ndarray:
        """``Q = [rw | Jw]^T [rw | Jw]`` ((1 + k) x (1 + k)) of :meth:`evaluate`: all the solver needs."""
        Y = self.evaluate(omega)
        return Y.T @ Y


class LsRateResult:
    """Solution of :func:`solve_rate`: ``omega`` (3,), ``covariance`` (3, 3), cost, evaluations, status."""

    __slots__ = ("omega", "covariance", "chi2", "dof", "nfev", "success", "message")

    def __init__(self, omega, covariance, chi2, dof, nfev, success, message):
        self.omega, self.covariance, self.chi2, self.dof = omega, covariance, chi2, dof
        self.nfev, self.success, self.message = nfev, success, message


def _levenberg_marquardt(evaluate, p0: np.ndarray, max_nfev: int, step_tol: float):
    """Damped Gauss-Newton (Levenberg-Marquardt, Marquardt's diagonal scaling) on whitened residuals.

    Hand-written rather than ``scipy.optimize.least_squares``: with 2-3 parameters an evaluation is a
    few dozen vectorised operations over the pairs (tens of microseconds), and least_squares'
    per-call set-up, checks and MINPACK wrapping cost more than the problem itself (profiled:
    1.2-1.6 ms/frame with least_squares, 0.3-0.5 ms without; benchmarks/rate_solvers.py).

    ``evaluate(p) -> Q``, the Gram matrix ``[rw | Jw]^T [rw | Jw]`` of the whitened residuals and
    Jacobian (cost ``Q[0, 0]``, ``A = Q[1:, 1:]``, ``g = Q[1:, 0]``). Each iteration solves the 3x3 (or 2x2) normal equations
    ``(A + lam diag(A)) d = -g``, ``A = Jw^T Jw``, ``g = Jw^T rw``. ``lam`` starts at 0 (pure
    Gauss-Newton: over one frame the model is nearly linear in omega, so the iteration converges
    linearly with a tiny factor, about 1e-5 on the fu2022 scenario) and grows 10x on a step that does
    not lower the cost, shrinks 10x on one that does.

    Stopping, with step lengths ``L = sqrt(d^T A d)`` in standard deviations of the estimate: at a
    point whose Gauss-Newton step ``L_k <= step_tol`` (converged); or, after an undamped step of
    length ``L_{k-1}``, when ``L_k^2 <= step_tol L_{k-1}`` (and ``L_k <= L_{k-1} / 2``): the
    iteration's contraction factor is then about ``rho = L_k / L_{k-1}`` and the error left after
    taking the step, ``~ rho L_k``, is below ``step_tol``, so the step is taken without another
    evaluation (the returned ``Q`` is the last evaluated one, ``L_k`` standard deviations
    away; its chi^2 and covariance differ by ``O(L_k^2)``). Returns
    ``(p, Q, evaluations, converged, message)``.
    """
    p = p0
    Q = evaluate(p)
    nfev = 1
    if not math.isfinite(Q[0, 0]):
        return p, Q, nfev, False, "residuals not finite at the starting point"
    lam, previous = 0.0, math.inf  # previous: length of the last undamped step taken
    while True:
        A, g = Q[1:, 1:], Q[1:, 0]
        try:
            gn = np.linalg.solve(A, -g)
            length2 = -float(gn @ g)  # gn^T A gn
        except np.linalg.LinAlgError:
            gn, length2 = None, math.nan
        if math.isfinite(length2):
            if length2 <= step_tol * step_tol:
                return p, Q, nfev, True, "converged: Gauss-Newton step below tolerance"
            length = math.sqrt(max(length2, 0.0))
            if previous < math.inf and length2 <= step_tol * previous and length <= 0.5 * previous:
                return p + gn, Q, nfev, True, "converged: last Gauss-Newton step taken, remaining error below tolerance"
        if nfev >= max_nfev:
            return p, Q, nfev, False, f"max_nfev = {max_nfev} evaluations reached"
        undamped = lam == 0.0 and math.isfinite(length2)
        if undamped:
            d = gn
        else:
            try:
                d = np.linalg.solve(A + lam * np.diag(np.diag(A)), -g)
            except np.linalg.LinAlgError:
                d = None
            if d is None or not np.all(np.isfinite(d)):
                if lam > 1e12:
                    return p, Q, nfev, False, "normal equations singular"
                lam = max(10.0 * lam, 1e-6)
                continue
        trial = evaluate(p + d)
        nfev += 1
        if math.isfinite(trial[0, 0]) and trial[0, 0] <= Q[0, 0] * (1.0 + 1e-12):  # rounding at the minimum
            p, Q = p + d, trial
            previous = length if undamped else math.inf
            lam = 0.0 if lam <= 1e-6 else lam / 10.0
        else:
            if lam > 1e12:
                return p, Q, nfev, False, "no step lowers the cost"
            lam = max(10.0 * lam, 1e-6)


def _checked_stars(x, y, dt_s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x, y, dt_s`` as float arrays; ``ValueError`` with the flag reason when the rate cannot be
    estimated from them (fewer than 3 stars, or every star at one time)."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    dt_s = np.asarray(dt_s, dtype=float)
    if x.shape[0] < 3:
        raise ValueError(f"too_few_stars: {x.shape[0]} identified, the rate needs >= 3")
    if not dt_s.max() > dt_s.min():
        raise ValueError("rate_unobservable: every star refers to the same time (global shutter or already corrected)")
    return x, y, dt_s


def solve_rate(camera, x, y, dt_s, ref_icrs, sigma_px, estimate_z: bool = True, max_nfev: int = 50,
               x0: np.ndarray | None = None, max_condition: float = 1e12, step_tol: float = 1e-6) -> LsRateResult:
    """Least-squares rate (rad/s, camera frame) from ``n >= 3`` identified stars (eqs 1-3, GLS weighted).

    ``dt_s``: each star's time minus the reference time (s); ``sigma_px`` (n,) centroid sigma per axis,
    or (n, 2, 2) the stars' position covariances (px^2).
    ``estimate_z=False`` fixes ``omega_z = 0`` (fu2022's assumption). ``x0``: starting rate (default
    0). ``step_tol``: convergence threshold on the Gauss-Newton step in standard deviations of the
    estimate (:func:`_levenberg_marquardt`). Raises ``ValueError`` with a reason when the rate is not
    observable (all stars at one time, or a singular normal matrix).
    """
    x, y, dt_s = _checked_stars(x, y, dt_s)
    k = 3 if estimate_z else 2
    prob = _Problem(camera, x, y, dt_s, ref_icrs, sigma_px, k)
    full = np.zeros(3)

    def gram(p):
        full[:k] = p
        return prob.gram(full)

    p0 = np.zeros(k) if x0 is None else np.array(x0, dtype=float)[:k]
    p, Q, nfev, success, message = _levenberg_marquardt(gram, p0, max_nfev, step_tol)
    normal = Q[1:, 1:]  # Jw^T Jw
    if not np.all(np.isfinite(normal)):
        raise ValueError("rate_unobservable: normal matrix not finite (star geometry or timing)")
    ev, V = np.linalg.eigh(normal)
    cond = ev[-1] / ev[0] if ev[0] > 0 else np.inf
    if not np.isfinite(cond) or cond > max_condition:
        raise ValueError(f"rate_unobservable: normal matrix condition {cond:.3g} (star geometry or timing)")
    cov = np.zeros((3, 3))
    cov[:k, :k] = (V / ev) @ V.T  # (Jw^T Jw)^-1
    omega = np.zeros(3)
    omega[:k] = p
    return LsRateResult(omega, cov, float(Q[0, 0]), int(prob.rank - k), nfev, success, message)


def solve_rate_least_squares(camera, x, y, dt_s, ref_icrs, sigma_px, estimate_z: bool = True, max_nfev: int = 50,
                             max_condition: float = 1e12, **tolerances) -> LsRateResult:
    """The reference for :func:`solve_rate`: the same estimate by ``scipy.optimize.least_squares``
    (MINPACK ``lm``) over :func:`pair_residuals` / :func:`pair_jacobian`, whitened by :func:`whitening`
    (eigendecomposition) -- independent code for the residuals, the weighting and the solver.
    ``tolerances``: least_squares' ``xtol``, ``ftol``, ``gtol`` (default 1e-8 each). Same errors as
    :func:`solve_rate`. About 4x slower (benchmarks/rate_solvers.py); kept for tests and benchmarks.
    """
    x, y, dt_s = _checked_stars(x, y, dt_s)
    w = camera.unproject(x, y)
    i, j = np.triu_indices(x.shape[0], k=1)
    ref = np.asarray(ref_icrs, dtype=float)
    cat = _angles(ref[i], ref[j])[0]
    Wh = whitening(pixel_sensitivity(camera, w, i, j), sigma_px)
    k = 3 if estimate_z else 2

    def full(p):
        return p if estimate_z else np.array([p[0], p[1], 0.0])

    def fun(p):
        return Wh @ pair_residuals(full(p), w, dt_s, i, j, cat)

    def jac(p):
        return Wh @ pair_jacobian(full(p), w, dt_s, i, j)[:, :k]

    method = "lm" if Wh.shape[0] >= k else "trf"
    sol = least_squares(fun, np.zeros(k), jac=jac, method=method, max_nfev=max_nfev, x_scale="jac", **tolerances)
    normal = jac(sol.x).T @ jac(sol.x)
    ev = np.linalg.eigvalsh(normal) if np.all(np.isfinite(normal)) else np.array([np.nan])
    cond = ev[-1] / ev[0] if ev[0] > 0 else np.inf
    if not np.isfinite(cond) or cond > max_condition:
        raise ValueError(f"rate_unobservable: normal matrix condition {cond:.3g} (star geometry or timing)")
    cov = np.zeros((3, 3))
    cov[:k, :k] = np.linalg.inv(normal)
    return LsRateResult(full(sol.x).copy(), cov, float(np.sum(sol.fun**2)), int(Wh.shape[0] - k), int(sol.nfev),
                        bool(sol.success), str(sol.message))


# ---------------------------------------------------------------------------------- plugins
class LsRateParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    estimate_z: bool = Field(default=True, description="Estimate omega_z too; False fixes it to 0 (fu2022's assumption).")
    reference: Reference = Field(
        default="frame_mid",
        description="t_ref: 'frame_start' = row 0 exposure start; 'frame_mid' = mid-exposure of the middle row.")
    max_nfev: int = Field(default=50, ge=1, description="Maximum residual evaluations of the LM solver.")
    default_sigma_px: float = Field(
        default=DEFAULT_CENTROID_SIGMA_PX, gt=0,
        description="Centroid sigma (px per axis) when neither the stars nor the sensor give one.")
    min_sigma_px: float = Field(
        default=1e-3, gt=0, description="Floor on the centroid sigma used for weighting (noise-free recordings state 0).")
    max_condition: float = Field(default=1e12, gt=1, description="Normal-matrix condition number above which the rate is flagged unobservable.")
    star_covariance: bool = Field(
        default=True, description="Weight by the stars' 2 x 2 position covariances (cov_xx, cov_xy, cov_yy) when a "
        "star of the frame carries one that is not isotropic; False: by the scalar sigma_px alone.")
    solver: Literal["gauss-newton", "least_squares"] = Field(
        default="gauss-newton",
        description="'gauss-newton': the hand-written damped Gauss-Newton (solve_rate, ~4x faster); "
        "'least_squares': scipy's MINPACK LM (solve_rate_least_squares), the reference. Same estimate.")


class LsRateEstimator(RateEstimator):
    """Single-frame 3-axis rate by Levenberg-Marquardt on fu2022's angular-distance invariance, with covariance.

    Every identified star of ``frame.stars`` (raw ``t_ns``: mid-exposure of its own row) and all their
    pairs, GLS-weighted (module docstring, eqs 1-3). Sets ``frame.rate`` (camera frame, rad/s, at
    ``t_ref``) with ``covariance`` (3x3, (rad/s)^2; the z row/column is 0 when ``estimate_z`` is
    False) and ``iterations`` = residual evaluations. Fewer than three identified stars, or a
    geometry/timing that does not determine the rate: an invalid estimate whose reason says which,
    and frame flag ``rate_invalid``. Stars are not modified (``rate-correction`` after this stage
    moves them to ``t_ref`` with the rate).

    Centroid sigma of a star without its own: the sensor context's ``centroid_sigma_px`` when the
    context states one (also 0, for noise-free recordings), else ``default_sigma_px``; floored at
    ``min_sigma_px``. When a star of the frame carries a 2 x 2 position covariance that is not
    isotropic (``star_covariance``), every star is weighted by its 2 x 2 covariance
    (:meth:`StarTable.position_covariance` with that fallback; eigenvalues floored at
    ``min_sigma_px^2``). Directions come from the frame's camera
    (:func:`~rollingstar.estimators.data.frame_camera`).
    """

    name = "ls-rate"
    Params = LsRateParams

    def _sigma(self, stars: StarTable) -> np.ndarray:
        """Each star's sigma (n,) px, or its 2 x 2 covariance (n, 2, 2) px^2 when the frame's stars
        carry anisotropic ones (class docstring)."""
        p = self.params
        fallback = getattr(self.context, "centroid_sigma_px", None)
        fallback = p.default_sigma_px if fallback is None else float(fallback)
        cov = anisotropic_covariance(stars, max(fallback, p.min_sigma_px), True, p.star_covariance)
        if cov is not None:
            ev, V = np.linalg.eigh(cov)
            return (V * np.maximum(ev, p.min_sigma_px**2)[:, None, :]) @ np.swapaxes(V, -1, -2)
        s = np.where(np.isfinite(stars.sigma_px), stars.sigma_px, fallback)
        return np.maximum(s, p.min_sigma_px)

    def estimate(self, frame: FrameData) -> RateEstimate:
        """The rate estimate of ``frame`` at ``t_ref`` (invalid, with the reason, when there is none)."""
        p = self.params
        t_ref = reference_time_ns(p.reference, frame.t0_ns, self.context.timing)
        stars = frame.stars if frame.stars is not None else StarTable.empty()
        ident = np.flatnonzero(stars.identified & np.isfinite(stars.x) & np.isfinite(stars.y)
                               & np.all(np.isfinite(stars.ref_icrs), axis=1))
        dt = (stars.t_ns[ident] - np.int64(t_ref)).astype(float) * S_PER_NS
        try:
            solve = solve_rate if p.solver == "gauss-newton" else solve_rate_least_squares
            res = solve(frame_camera(frame, self.context), stars.x[ident], stars.y[ident], dt, stars.ref_icrs[ident],
                        self._sigma(stars.take(ident)), p.estimate_z, p.max_nfev, max_condition=p.max_condition)
        except ValueError as exc:
            return RateEstimate(t_ns=t_ref, omega_rad_s=np.full(3, np.nan), valid=False, reason=str(exc))
        if not np.all(np.isfinite(res.omega)):
            return RateEstimate(t_ns=t_ref, omega_rad_s=np.full(3, np.nan), valid=False,
                                reason=f"solver_failed: {res.message}")
        return RateEstimate(t_ns=t_ref, omega_rad_s=res.omega, valid=True, covariance=res.covariance,
                            iterations=res.nfev)
