"""The maths of one rolling-shutter frame's attitude-and-rate fit from star positions.

Model and linearisation: :mod:`rollingstar.estimators.attitude.rs_bundle` (module docstring).
"""
from __future__ import annotations

import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.so3 import quat_from_matrix, quat_times_exp, quat_to_matrix, rotate_at_rate, skew


def star_times(stars, t_ref_ns: int) -> np.ndarray:
    """``dt_i = t_i - t_ref`` (s) of the stars' own times."""
    return (np.asarray(stars.t_ns, dtype=np.int64) - np.int64(t_ref_ns)) * S_PER_NS


def predicted_directions(R: Rotation, omega: np.ndarray, ref: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Camera directions ``w_i = (R Exp(omega dt_i))^T r_i = Exp(-omega dt_i) R^T r_i`` (n, 3)."""
    return rotate_at_rate(-np.asarray(omega, dtype=float), ref @ R.as_matrix(), dt)  # R^T r as r^T R


def apply_step(R: Rotation, omega: np.ndarray, step: np.ndarray) -> tuple[Rotation, np.ndarray]:
    """``R Exp(delta)`` and ``omega + eps`` for ``step = (delta[, eps])`` (the quaternion product of
    :func:`rollingstar.sensors.so3.quat_times_exp`: scipy's composition of two ``Rotation`` objects
    costs several times more)."""
    omega = np.array(omega, dtype=float)
    if step.size == 6:
        omega = omega + step[3:]
    return Rotation.from_quat(quat_times_exp(R.as_quat(), np.ascontiguousarray(step[:3], dtype=float))), omega


def fit_positions(R: Rotation | np.ndarray, omega: np.ndarray, ref: np.ndarray, dt: np.ndarray, d, iterations: int,
                  fit_rate: bool, huber_k: float | None = None) -> tuple[Rotation, np.ndarray, np.ndarray]:
    """Gauss-Newton fit of the attitude at ``t_ref`` and the rate to the stars' directions, from ``R``
    (a ``Rotation`` or a camera -> ICRS rotation matrix). Each
    iteration solves the normal equations ``(sum w_i H_i^T W_i H_i) step = sum w_i H_i^T W_i e_i``:
    ``e_i`` the tangent-plane residual of star ``i`` (``d``: the stars'
    :class:`~rollingstar.estimators.attitude.star_covariance.DirectionCovariance`), ``H_i`` its
    Jacobian in ``(delta, eps)`` (attitude and rate; attitude alone when ``fit_rate`` is False and
    ``omega`` is held), and after the first iteration, when ``huber_k`` is given, Huber weights
    ``w_i = min(1, huber_k / m_i)`` on the Mahalanobis residuals ``m_i = sqrt(e_i^T W_i e_i)``
    (iteratively reweighted least squares: a fragment of a streak or a misidentified star pulls
    with a bounded influence). Returns ``R``, ``omega`` and the unweighted information matrix at the
    solution: 6 x 6 (attitude, rate), or 3 x 3 (attitude).

    Compiled (:func:`_position_fit`): the fit of a frame's few tens of stars is some ten small
    array operations per iteration, and numpy's per-call overhead was most of its time."""
    q0 = np.asarray(R.as_quat(), dtype=float) if isinstance(R, Rotation) else quat_from_matrix(np.asarray(R, dtype=float))
    q, omega, normal = _position_fit(q0, np.array(omega, dtype=float),
                                     np.ascontiguousarray(ref, dtype=float), np.ascontiguousarray(dt, dtype=float),
                                     np.ascontiguousarray(d.body, dtype=float), np.ascontiguousarray(d.basis, dtype=float),
                                     np.ascontiguousarray(d.info, dtype=float), int(iterations), 6 if fit_rate else 3,
                                     -1.0 if huber_k is None else float(huber_k))
    return Rotation.from_quat(q), omega, normal


@njit(cache=True, nogil=True)
def _position_normal(q, omega, ref, dt, body, basis, info, k, huber_k):  # pragma: no cover - compiled
    """Normal equations of :func:`fit_positions` at ``(q, omega)``; ``huber_k < 0``: unweighted.
    Written out in scalars: numba's ``@`` on 2 x 3 arrays calls BLAS, slower than the loops."""
    R = quat_to_matrix(q)
    rate = np.sqrt(omega[0] ** 2 + omega[1] ** 2 + omega[2] ** 2)
    axis = -omega / rate if rate > 0 else np.zeros(3)
    normal, rhs = np.zeros((k, k)), np.zeros(k)
    H, v, e, HtW = np.zeros((2, 6)), np.zeros(3), np.zeros(2), np.zeros((6, 2))
    for i in range(ref.shape[0]):
        for j in range(3):  # R^T r
            v[j] = ref[i, 0] * R[0, j] + ref[i, 1] * R[1, j] + ref[i, 2] * R[2, j]
        if rate > 0:  # w = Exp(-omega dt) R^T r, Rodrigues' formula (rollingstar.sensors.so3.rotate_at_rate)
            c, s = np.cos(rate * dt[i]), np.sin(rate * dt[i])
            kv = (axis[0] * v[0] + axis[1] * v[1] + axis[2] * v[2]) * (1.0 - c)
            k0, k1, k2 = axis[1] * v[2] - axis[2] * v[1], axis[2] * v[0] - axis[0] * v[2], axis[0] * v[1] - axis[1] * v[0]
            v[0], v[1], v[2] = v[0] * c + k0 * s + axis[0] * kv, v[1] * c + k1 * s + axis[1] * kv, v[2] * c + k2 * s + axis[2] * kv
        for a in range(2):  # row a of E^T [w]x and E^T [w]x dt, and the residual E^T (body - w)
            e0, e1, e2 = basis[i, 0, a], basis[i, 1, a], basis[i, 2, a]
            H[a, 0], H[a, 1], H[a, 2] = e1 * v[2] - e2 * v[1], e2 * v[0] - e0 * v[2], e0 * v[1] - e1 * v[0]
            for b in range(3):
                H[a, 3 + b] = H[a, b] * dt[i]
            e[a] = e0 * (body[i, 0] - v[0]) + e1 * (body[i, 1] - v[1]) + e2 * (body[i, 2] - v[2])
        w00, w01, w10, w11 = info[i, 0, 0], info[i, 0, 1], info[i, 1, 0], info[i, 1, 1]
        if huber_k >= 0:
            m = np.sqrt(max(e[0] * (w00 * e[0] + w01 * e[1]) + e[1] * (w10 * e[0] + w11 * e[1]), 1e-300))
            scale = min(1.0, huber_k / m)
            w00, w01, w10, w11 = w00 * scale, w01 * scale, w10 * scale, w11 * scale
        for a in range(k):
            HtW[a, 0] = H[0, a] * w00 + H[1, a] * w10
            HtW[a, 1] = H[0, a] * w01 + H[1, a] * w11
            rhs[a] += HtW[a, 0] * e[0] + HtW[a, 1] * e[1]
            for b in range(k):
                normal[a, b] += HtW[a, 0] * H[0, b] + HtW[a, 1] * H[1, b]
    return normal, rhs


@njit(cache=True, nogil=True)
def _position_fit(q, omega, ref, dt, body, basis, info, iterations, k, huber_k):  # pragma: no cover - compiled
    """:func:`fit_positions` on the quaternion ``q``: ``(q, omega, information)``."""
    for it in range(iterations):
        normal, rhs = _position_normal(q, omega, ref, dt, body, basis, info, k, huber_k if it else -1.0)
        step = np.linalg.solve(normal, rhs)
        q = quat_times_exp(q, step[:3])
        if k == 6:
            omega = omega + step[3:]
    normal, _ = _position_normal(q, omega, ref, dt, body, basis, info, k, -1.0)
    return q, omega, 0.5 * (normal + normal.T)


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
