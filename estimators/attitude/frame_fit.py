"""The maths of one rolling-shutter frame's attitude-and-rate fit from star positions.

Model and linearisation: :mod:`rollingstar.estimators.attitude.rs_bundle` (module docstring).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.so3 import rotate_at_rate, skew


def star_times(stars, t_ref_ns: int) -> np.ndarray:
    """``dt_i = t_i - t_ref`` (s) of the stars' own times."""
    return (np.asarray(stars.t_ns, dtype=np.int64) - np.int64(t_ref_ns)) * S_PER_NS


def predicted_directions(R: Rotation, omega: np.ndarray, ref: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Camera directions ``w_i = (R Exp(omega dt_i))^T r_i = Exp(-omega dt_i) R^T r_i`` (n, 3)."""
    return rotate_at_rate(-np.asarray(omega, dtype=float), ref @ R.as_matrix(), dt)  # R^T r as r^T R


def position_normal(R: Rotation, omega: np.ndarray, ref: np.ndarray, dt: np.ndarray, d, k: int,
                    huber_k: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations ``(sum w_i H_i^T W_i H_i, sum w_i H_i^T W_i e_i)`` of the position fit at
    ``(R, omega)``: ``e_i`` the tangent-plane residual of star ``i`` (``d``: the stars'
    :class:`~rollingstar.estimators.attitude.star_covariance.DirectionCovariance`), ``H_i`` its
    Jacobian in the first ``k`` of ``(delta, eps)`` (3: attitude only, 6: attitude and rate).
    ``huber_k``: Huber weights ``w_i = min(1, huber_k / m_i)`` on the Mahalanobis residuals
    ``m_i = sqrt(e_i^T W_i e_i)`` (iteratively reweighted least squares: a fragment of a streak or a
    misidentified star pulls with a bounded influence); None: ``w_i = 1``."""
    Et = np.swapaxes(d.basis, -1, -2)
    w = predicted_directions(R, omega, ref, dt)
    S = Et @ skew(w)  # (n, 2, 3): tangent-plane motion per unit rotation
    H = np.concatenate([S, S * dt[:, None, None]], axis=2)[:, :, :k]
    e = np.einsum("nki,ni->nk", Et, d.body - w)
    info = d.info
    if huber_k is not None:
        m = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", e, info, e), 1e-300))
        info = info * np.minimum(1.0, huber_k / m)[:, None, None]
    HtW = np.swapaxes(H, -1, -2) @ info
    return np.sum(HtW @ H, axis=0), np.einsum("nik,nk->i", HtW, e)


def apply_step(R: Rotation, omega: np.ndarray, step: np.ndarray) -> tuple[Rotation, np.ndarray]:
    """``R Exp(delta)`` and ``omega + eps`` for ``step = (delta[, eps])``."""
    omega = np.array(omega, dtype=float)
    if step.size == 6:
        omega = omega + step[3:]
    return R * Rotation.from_rotvec(step[:3]), omega


def fit_positions(R: Rotation, omega: np.ndarray, ref: np.ndarray, dt: np.ndarray, d, iterations: int,
                  fit_rate: bool, huber_k: float | None = None) -> tuple[Rotation, np.ndarray, np.ndarray]:
    """Gauss-Newton fit of the attitude at ``t_ref`` and the rate to the stars' directions
    (:func:`position_normal`, with Huber weights after the first iteration when ``huber_k`` is
    given). Returns ``R``, ``omega`` and the information matrix (unweighted): 6 x 6 (attitude, rate),
    or 3 x 3 (attitude) when ``fit_rate`` is False and ``omega`` is held."""
    k = 6 if fit_rate else 3
    for it in range(iterations):
        normal, rhs = position_normal(R, omega, ref, dt, d, k, huber_k if it else None)
        R, omega = apply_step(R, omega, np.linalg.solve(normal, rhs))
    normal, _ = position_normal(R, omega, ref, dt, d, k)
    return R, np.asarray(omega, dtype=float), 0.5 * (normal + normal.T)


def velocity_rate(camera, stars) -> np.ndarray | None:
    """A body rate from the stars' image velocities ``v_i = P(w_i) (w_i x omega)`` (linear least
    squares; ``w_i`` the unprojected positions), or None without three stars carrying velocities."""
    ok = np.isfinite(stars.vx) & np.isfinite(stars.vy) & np.isfinite(stars.x) & np.isfinite(stars.y)
    if np.count_nonzero(ok) < 3:
        return None
    w = camera.unproject(stars.x[ok], stars.y[ok])
    A = camera.projection_jacobian(w) @ skew(w)  # v = P (w x omega) = P [w]x omega
    v = np.column_stack([stars.vx[ok], stars.vy[ok]])
    sol, *_ = np.linalg.lstsq(A.reshape(-1, 3), v.reshape(-1), rcond=None)
    return sol
