"""Line-of-sight geometry shared by the effects: small rotations and direction changes in pixels.

All functions are vectorised over ``n`` observations and exact (no small-angle approximation
beyond what the docstrings say). ``P(w)`` is the pinhole projection Jacobian for *unnormalised*
camera vectors (:meth:`rollingstar.sensors.camera.PinholeCamera.projection_jacobian`), so a direction change
``dw`` moves the image by ``P(w) dw`` whatever the length of ``w``.
"""
from __future__ import annotations

import numpy as np

from rollingstar.sensors.motion import so3_right_jacobian
from rollingstar.sensors.so3 import cross, rotate_by_rotvec, skew


def project(camera, w) -> tuple[np.ndarray, np.ndarray]:
    x, y, _ = camera.project(w)
    return x, y


def rotate_line_of_sight(camera, x, y, rotvec, jacobian: bool = True):
    """Image positions after the camera turns by the body-frame rotation ``Exp(rotvec)``.

    A camera-frame direction ``w`` becomes ``w' = Exp(rotvec)^T w`` (``R' = R Exp(rotvec)``, the
    kinematics convention of :mod:`rollingstar.sensors.motion`). Returns ``(x', y', J)`` with
    ``J = d(x', y') / d rotvec = P(w') [w']x J_r(rotvec)`` (n, 2, 3), from
    ``Exp(d + e) = Exp(d) Exp(J_r(d) e)`` to first order in ``e`` (``J`` is None when
    ``jacobian`` is False: forward models skip its cost).
    """
    w = camera.unproject(x, y).reshape(-1, 3)
    d = np.broadcast_to(np.asarray(rotvec, dtype=float).reshape(-1, 3), w.shape)
    w2 = rotate_by_rotvec(-d, w)  # Exp(d)^T w = Exp(-d) w, Rodrigues (scipy's Rotation objects cost ~3x)
    x2, y2 = project(camera, w2)
    if not jacobian:
        return x2, y2, None
    jac = camera.projection_jacobian(w2) @ skew(w2) @ so3_right_jacobian(d)
    return x2, y2, jac


def rotation_jacobian(camera, x, y) -> np.ndarray:
    """``d(x, y) / d rotvec`` at zero rotation: the image signature of a small attitude change (n, 2, 3)."""
    w = camera.unproject(x, y).reshape(-1, 3)
    return camera.projection_jacobian(w) @ skew(w)


def image_velocity(camera, x, y, omega_rad_s) -> tuple[np.ndarray, np.ndarray]:
    """Image velocity (px/s) of fixed stars for body rate ``omega``: ``P(w) (w x omega)``."""
    w = camera.unproject(x, y).reshape(-1, 3)
    v = np.einsum("nij,nj->ni", camera.projection_jacobian(w), cross(w, np.asarray(omega_rad_s, dtype=float)))
    return v[:, 0], v[:, 1]


def displace_direction(camera, x, y, dw_cam, jacobian: bool = True):
    """Image positions after adding ``dw_cam`` (n, 3) to the unit line of sight ``w``.

    Returns ``(x', y', P(w + dw))`` so that a parameter entering linearly as ``dw = p * a`` has
    the exact Jacobian ``P(w + dw) a``.
    """
    w = camera.unproject(x, y).reshape(-1, 3) + np.asarray(dw_cam, dtype=float).reshape(-1, 3)
    x2, y2 = project(camera, w)
    return x2, y2, (camera.projection_jacobian(w) if jacobian else None)


def to_camera(attitude, v_icrs) -> np.ndarray:
    """ICRS vectors (n, 3) to the camera frame with camera->ICRS ``attitude``: ``R^T v``."""
    v = np.array(v_icrs, dtype=float).reshape(-1, 3)  # copy: scipy rejects read-only inputs
    return attitude.inv().apply(v).reshape(-1, 3)
