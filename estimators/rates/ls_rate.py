"""Single-frame 3-axis angular rate by least squares on angular-distance invariance.

The problem is fu2022's (eqs 7-16, see :mod:`estimators.rates.pso`): the catalogue angle between two
identified stars equals the angle between their camera directions once both are moved to one common
time. Here it is solved by Gauss-Newton / Levenberg-Marquardt (``scipy.optimize.least_squares``,
MINPACK ``lm``) with the analytic Jacobian below, for the full rate ``omega = (wx, wy, wz)`` -- the
paper's ``omega_z = 0`` installation assumption is not needed -- over the pairs of every identified
star, and with the estimate's covariance.

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
``d cos(theta) = b.da + a.db``, ``d theta = -d cos(theta) / sin(theta)``:

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
``J_w``. To first order this is the maximum-likelihood estimate of the rate with the attitude as a
nuisance, i.e. it attains the single-frame Cramér-Rao bound of :func:`pipelines.truth.rate_crb_rad2`.

Hand-written parts: the residual/Jacobian (the model is ours) and the whitening (a 2-line SVD);
the solver is scipy's MINPACK Levenberg-Marquardt.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.optimize import least_squares

from estimators.corrections.base import Correction
from estimators.data import FrameData, RateEstimate, StarTable
from estimators.rates.base import RateEstimator

DEG = np.pi / 180.0


# ------------------------------------------------------------------------------------ model
def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]x`` for (..., 3) -> (..., 3, 3)."""
    s = np.zeros(v.shape[:-1] + (3, 3))
    s[..., 0, 1], s[..., 0, 2] = -v[..., 2], v[..., 1]
    s[..., 1, 0], s[..., 1, 2] = v[..., 2], -v[..., 0]
    s[..., 2, 0], s[..., 2, 1] = -v[..., 1], v[..., 0]
    return s


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
    K = _skew(phi)
    return np.eye(3) + c1[..., None, None] * K + c2[..., None, None] * (K @ K)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` over the last axis; written out because ``np.cross`` costs ~10x more on small arrays
    (this runs in the solver's inner loop)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def moved_directions(omega: np.ndarray, w: np.ndarray, dt_s: np.ndarray) -> np.ndarray:
    """Eq (1): ``Exp(omega dt_i) w_i`` for ``omega`` (3,), ``w`` (n, 3), ``dt_s`` (n,) (Rodrigues).

    With ``k = omega / |omega|`` and ``t_i = |omega| dt_i``:
    ``w cos t + (k x w) sin t + k (k . w)(1 - cos t)``.
    """
    omega = np.asarray(omega, dtype=float)
    norm = float(np.sqrt(omega @ omega))
    if norm == 0.0:
        return w
    k = omega / norm
    t = norm * dt_s
    c, s = np.cos(t)[:, None], np.sin(t)[:, None]
    return w * c + _cross(k[None, :], w) * s + np.outer(w @ k, k) * (1.0 - c)


def _angles(ai: np.ndarray, aj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angle between rows (atan2 of |cross| and dot: accurate at all angles) and the cross products."""
    n = _cross(ai, aj)
    return np.arctan2(np.sqrt(np.sum(n * n, axis=-1)), np.sum(ai * aj, axis=-1)), n


def pair_residuals(omega, w, dt_s, i, j, cat_angles) -> np.ndarray:
    """Eq (2): measured minus catalogue angle (rad) of every pair ``(i[k], j[k])``."""
    a = moved_directions(omega, w, dt_s)
    return _angles(a[i], a[j])[0] - cat_angles


def pair_jacobian(omega, w, dt_s, i, j, a: np.ndarray | None = None, cross: np.ndarray | None = None) -> np.ndarray:
    """Eq (3): ``d r / d omega``, (m, 3). ``a`` = :func:`moved_directions` and ``cross`` =
    ``a[i] x a[j]`` when already computed (the solver reuses the residual's).

    Evaluated without forming 3x3 matrices: ``n^T J_l(phi) = n + c1 (n x phi) + c2 ((n x phi) x phi)``
    (from ``n^T [phi]x v = (n x phi) . v``) with :func:`left_jacobian`'s coefficients, and
    ``phi_k = omega dt_k``, so ``n x phi_k = dt_k p``, ``(n x phi_k) x phi_k = dt_k^2 q`` with
    ``p = n x omega``, ``q = p x omega`` shared by both stars of a pair.
    """
    omega = np.asarray(omega, dtype=float)
    if cross is None:
        if a is None:
            a = moved_directions(omega, w, dt_s)
        cross = _cross(a[i], a[j])
    n = cross / np.sqrt(np.sum(cross * cross, axis=-1))[:, None]
    c1, c2 = _jl_coefficients(float(np.sqrt(omega @ omega)) * np.abs(dt_s))  # at |phi_k|
    dt2 = dt_s * dt_s
    c1 = c1 * dt2  # c1 dt^2
    c2 = c2 * dt2 * dt_s  # c2 dt^3
    p = _cross(n, omega[None, :])
    q = _cross(p, omega[None, :])
    ddt = (dt_s[j] - dt_s[i])[:, None]
    return ddt * n + (c1[j] - c1[i])[:, None] * p + (c2[j] - c2[i])[:, None] * q


def pixel_sensitivity(camera, w: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """``G = d theta / d(x_0, y_0, x_1, y_1, ...)`` (m, 2n) at ``omega = 0`` (the weighting's first-order model).

    ``d theta_ij / d w_i = -t_ij`` (unit tangent at ``w_i`` towards ``w_j``) and
    ``d w / d(x, y) = -(I - w w^T) [e_x, e_y] / |W|`` with ``W = [-(x - cx), -(y - cy), F]``, so
    ``d theta_ij / d(x_i, y_i) = (t_ij,x, t_ij,y) / |W_i|`` (``t_ij`` is already orthogonal to ``w_i``).
    """
    n_stars = w.shape[0]
    norm_W = camera.focal_px / w[:, 2]  # |W| = F / w_z for the unit vector w
    wi, wj = w[i], w[j]
    cos = np.sum(wi * wj, axis=-1, keepdims=True)
    t_ij = wj - cos * wi
    t_ij /= np.linalg.norm(t_ij, axis=-1, keepdims=True)
    t_ji = wi - cos * wj
    t_ji /= np.linalg.norm(t_ji, axis=-1, keepdims=True)
    m = i.shape[0]
    G = np.zeros((m, 2 * n_stars))
    rows = np.arange(m)
    G[rows, 2 * i] = t_ij[:, 0] / norm_W[i]
    G[rows, 2 * i + 1] = t_ij[:, 1] / norm_W[i]
    G[rows, 2 * j] = t_ji[:, 0] / norm_W[j]
    G[rows, 2 * j + 1] = t_ji[:, 1] / norm_W[j]
    return G


def whitening(G: np.ndarray, sigma_px: np.ndarray, rtol: float = 1e-10) -> np.ndarray:
    """``D^-1 U^T`` for the thin SVD ``B = G diag(sigma) = U D V^T``: the pseudo-inverse square root of
    ``C = G S G^T`` (so ``|Wh r|^2 = r^T C^+ r``). Computed from the small Gram matrix
    ``B^T B = V D^2 V^T`` (2n x 2n instead of an m x 2n SVD; 3x cheaper):
    ``D^-1 U^T = D^-2 V^T B^T``. ``B`` has the 3 null directions of a common rotation; eigenvalues
    below ``rtol`` times the largest are dropped.
    """
    B = G * np.repeat(np.asarray(sigma_px, dtype=float), 2)[None, :]
    d2, V = np.linalg.eigh(B.T @ B)
    keep = d2 > d2[-1] * rtol
    return (V[:, keep] / d2[keep][None, :]).T @ B.T


class LsRateResult:
    """Solution of :func:`solve_rate`: ``omega`` (3,), ``covariance`` (3, 3), cost, evaluations, status."""

    __slots__ = ("omega", "covariance", "chi2", "dof", "nfev", "success", "message")

    def __init__(self, omega, covariance, chi2, dof, nfev, success, message):
        self.omega, self.covariance, self.chi2, self.dof = omega, covariance, chi2, dof
        self.nfev, self.success, self.message = nfev, success, message


def solve_rate(camera, x, y, dt_s, ref_icrs, sigma_px, estimate_z: bool = True, max_nfev: int = 50,
               x0: np.ndarray | None = None, max_condition: float = 1e12) -> LsRateResult:
    """Least-squares rate (rad/s, camera frame) from ``n >= 3`` identified stars (eqs 1-3, GLS weighted).

    ``dt_s``: each star's time minus the reference time (s); ``sigma_px`` (n,) centroid sigma per axis.
    ``estimate_z=False`` fixes ``omega_z = 0`` (fu2022's assumption). Raises ``ValueError`` with a
    reason when the rate is not observable (all stars at one time, or a singular normal matrix).
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    dt_s = np.asarray(dt_s, dtype=float)
    n = x.shape[0]
    if n < 3:
        raise ValueError(f"too_few_stars: {n} identified, the rate needs >= 3")
    if np.ptp(dt_s) <= 0.0:
        raise ValueError("rate_unobservable: every star refers to the same time (global shutter or already corrected)")
    w = camera.unproject(x, y)
    i, j = np.triu_indices(n, k=1)
    ref = np.asarray(ref_icrs, dtype=float)
    cat = _angles(ref[i], ref[j])[0]
    Wh = whitening(pixel_sensitivity(camera, w, i, j), sigma_px)
    k = 3 if estimate_z else 2

    def full(p):
        return p if estimate_z else np.array([p[0], p[1], 0.0])

    cache: dict = {}

    def at(p):
        """Residual and Jacobian share the rotated stars' cross products, and least_squares asks for
        both at its starting point twice (its checks, then MINPACK's): compute each once per point."""
        key = p.tobytes()
        if cache.get("key") != key:
            a = moved_directions(full(p), w, dt_s)
            cache.clear()
            cache["key"] = key
            cache["ang"], cache["cross"] = _angles(a[i], a[j])
        return cache

    def fun(p):
        c = at(p)
        if "fun" not in c:
            c["fun"] = Wh @ (c["ang"] - cat)
        return c["fun"]

    def jac(p):
        c = at(p)
        if "jac" not in c:
            c["jac"] = Wh @ pair_jacobian(full(p), w, dt_s, i, j, cross=c["cross"])[:, :k]
        return c["jac"]

    p0 = np.zeros(k) if x0 is None else np.asarray(x0, dtype=float)[:k]
    method = "lm" if Wh.shape[0] >= k else "trf"
    sol = least_squares(fun, p0, jac=jac, method=method, max_nfev=max_nfev, x_scale="jac")
    Jw = jac(sol.x)
    normal = Jw.T @ Jw
    ev = np.linalg.eigvalsh(normal) if np.all(np.isfinite(normal)) else np.array([np.nan])
    cond = ev[-1] / ev[0] if ev[0] > 0 else np.inf
    if not np.isfinite(cond) or cond > max_condition:
        raise ValueError(f"rate_unobservable: normal matrix condition {cond:.3g} (star geometry or timing)")
    cov_k = np.linalg.inv(normal)
    cov = np.zeros((3, 3))
    cov[:k, :k] = cov_k
    chi2 = float(np.sum(sol.fun**2))
    return LsRateResult(full(sol.x).copy(), cov, chi2, int(Wh.shape[0] - k), int(sol.nfev), bool(sol.success),
                        str(sol.message))


# ---------------------------------------------------------------------------------- plugins
class LsRateParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    estimate_z: bool = Field(default=True, description="Estimate omega_z too; False fixes it to 0 (fu2022's assumption).")
    reference: Literal["frame_start", "frame_mid"] = Field(
        default="frame_mid",
        description="t_ref: 'frame_start' = row 0 exposure start; 'frame_mid' = mid-exposure of the middle row.")
    max_nfev: int = Field(default=50, ge=1, description="Maximum residual evaluations of the LM solver.")
    default_sigma_px: float = Field(
        default=0.05, gt=0, description="Centroid sigma (px per axis) when neither the stars nor the sensor give one.")
    min_sigma_px: float = Field(
        default=1e-3, gt=0, description="Floor on the centroid sigma used for weighting (noise-free recordings state 0).")
    max_condition: float = Field(default=1e12, gt=1, description="Normal-matrix condition number above which the rate is flagged unobservable.")


class _LsCore:
    params: LsRateParams

    def _reference_ns(self, frame: FrameData) -> int:
        if self.params.reference == "frame_start":
            return int(frame.t0_ns)
        return int(self.context.timing.frame_reference_ns(frame.t0_ns))

    def _sigma(self, stars: StarTable) -> np.ndarray:
        p = self.params
        fallback = getattr(self.context, "centroid_sigma_px", None)
        fallback = p.default_sigma_px if fallback is None else float(fallback)
        s = np.where(np.isfinite(stars.sigma_px), stars.sigma_px, fallback)
        return np.maximum(s, p.min_sigma_px)

    def estimate(self, frame: FrameData) -> tuple[RateEstimate, int]:
        t_ref = self._reference_ns(frame)
        stars = frame.stars if frame.stars is not None else StarTable.empty()
        ident = np.flatnonzero(stars.identified & np.isfinite(stars.x) & np.isfinite(stars.y)
                               & np.all(np.isfinite(stars.ref_icrs), axis=1))
        s = stars.take(ident)
        dt = (s.t_ns - np.int64(t_ref)).astype(float) * 1e-9
        try:
            res = solve_rate(self.context.camera, s.x, s.y, dt, s.ref_icrs, self._sigma(s), self.params.estimate_z,
                             self.params.max_nfev, max_condition=self.params.max_condition)
        except ValueError as exc:
            return RateEstimate(t_ns=t_ref, omega_rad_s=np.full(3, np.nan), valid=False, reason=str(exc)), t_ref
        if not np.all(np.isfinite(res.omega)):
            return RateEstimate(t_ns=t_ref, omega_rad_s=np.full(3, np.nan), valid=False,
                                reason=f"solver_failed: {res.message}"), t_ref
        return RateEstimate(t_ns=t_ref, omega_rad_s=res.omega, valid=True, covariance=res.covariance,
                            iterations=res.nfev), t_ref


class LsRateEstimator(_LsCore, RateEstimator):
    """Single-frame 3-axis rate by Levenberg-Marquardt on fu2022's angular-distance invariance, with covariance.

    Every identified star of ``frame.stars`` (raw ``t_ns``: mid-exposure of its own row) and all their
    pairs, GLS-weighted (module docstring, eqs 1-3). Sets ``frame.rate`` (camera frame, rad/s, at
    ``t_ref``) with ``covariance`` (3x3, (rad/s)^2; the z row/column is 0 when ``estimate_z`` is
    False) and ``iterations`` = residual evaluations. Fewer than three identified stars, or a
    geometry/timing that does not determine the rate: an invalid estimate whose reason says which,
    and frame flag ``rate_invalid``. Stars are not modified.
    """

    name = "ls-rate"
    Params = LsRateParams

    def process(self, frame: FrameData) -> FrameData:
        rate, _ = self.estimate(frame)
        out = frame.evolve(rate=rate)
        return out if rate.valid else out.flagged("rate_invalid")


class LsRateCorrection(_LsCore, Correction):
    """Rolling-shutter correction with the ``ls-rate`` estimate: every star rotated to ``t_ref`` (eq 1).

    Estimates the 3-axis rate as ``ls-rate`` does, then moves **every** star of ``frame.stars``
    (identified or not): ``Exp(omega (t_i - t_ref)) w_i`` re-projected, and sets ``t_ns = t_ref``
    and ``frame.rate``. When the rate cannot be estimated the stars are returned unchanged and the
    frame is flagged ``rate_invalid``.
    """

    name = "ls-correction"
    Params = LsRateParams

    def process(self, frame: FrameData) -> FrameData:
        rate, t_ref = self.estimate(frame)
        stars = frame.stars
        if not rate.valid or stars is None:
            return frame.evolve(rate=rate).flagged("rate_invalid")
        cam = self.context.camera
        dt = (stars.t_ns - np.int64(t_ref)).astype(float) * 1e-9
        u = moved_directions(rate.omega_rad_s, cam.unproject(stars.x, stars.y), dt)
        x, y, _ = cam.project(u)
        new = stars.with_columns(x=x, y=y, t_ns=np.full(stars.n, t_ref, dtype=np.int64))
        return frame.evolve(stars=new, rate=rate)
