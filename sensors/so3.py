"""Rotation maths shared by the simulator and the estimators: cross products and rotations of vectors.

Vectors are the last axis of arrays of any shape (``(..., 3)``). A body turning at the constant
rate ``omega`` for ``dt`` rotates a vector ``w`` to ``Exp(omega dt) w`` (Rodrigues' formula); it
is written two ways here, equal to rounding (about 1e-17 on unit vectors):

- :func:`rotate_by_rotvec`: ``w + a (phi x w) + b phi x (phi x w)`` with the rotation vector
  ``phi = omega dt``, ``a = sin t / t``, ``b = (1 - cos t) / t^2``, ``t = |phi|`` (series near 0);
- :func:`rotate_at_rate`: ``w cos t + (k x w) sin t + k (k . w)(1 - cos t)`` with the unit axis
  ``k = omega / |omega|`` and ``t = |omega| dt``.

The rate-based estimators and the rate correction each use one of them, and their results depend
on which in the last bits.
"""
from __future__ import annotations

import numpy as np


def skew(v) -> np.ndarray:
    """Cross-product matrices ``[v]x`` (``[v]x u = v x u``), (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` over the last axis (broadcasting); written out because ``np.cross`` costs ~10x more
    on small arrays, and the solvers call this in their inner loops."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def rotate_by_rotvec(rotvec: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``Exp(rotvec) v`` for broadcastable (..., 3) arrays (module docstring; series below 1e-8 rad)."""
    th = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    small = th < 1e-8
    safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    rotvec, v = np.asarray(rotvec, dtype=float), np.asarray(v, dtype=float)
    kxv = cross(rotvec, v)
    return v + a * kxv + b * cross(rotvec, kxv)


def rotate_at_rate(omega, w: np.ndarray, dt_s: np.ndarray) -> np.ndarray:
    """``Exp(omega dt_i) w_i`` for ``omega`` (3,), ``w`` (n, 3), ``dt_s`` (n,) (module docstring)."""
    omega = np.asarray(omega, dtype=float)
    norm = float(np.sqrt(omega @ omega))
    if norm == 0.0:
        return w
    k = omega / norm
    t = norm * dt_s
    c, s = np.cos(t)[:, None], np.sin(t)[:, None]
    return w * c + cross(k[None, :], w) * s + np.outer(w @ k, k) * (1.0 - c)


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p q`` of scalar-last quaternions (..., 4): the rotation ``R(p) R(q)``.
    Written out because ``scipy.spatial.transform.Rotation`` composition of per-star arrays
    dominated the diagnosis's predictions in a profile (``rollingstar bench perf --only diagnose``
    measures the diagnosis that uses this)."""
    px, py, pz, pw = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qx, qy, qz, qw = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(np.broadcast_shapes(p.shape, q.shape))
    out[..., 0] = pw * qx + px * qw + py * qz - pz * qy
    out[..., 1] = pw * qy - px * qz + py * qw + pz * qx
    out[..., 2] = pw * qz + px * qy - py * qx + pz * qw
    out[..., 3] = pw * qw - px * qx - py * qy - pz * qz
    return out


def wahba(ref: np.ndarray, body: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The rotation matrix ``R`` minimising ``sum w_i |ref_i - R body_i|^2`` (Wahba's problem by
    SVD, Markley 1988): ``Rotation.align_vectors(ref, body, weights).as_matrix()`` without its
    per-call overhead (65 against 17 microseconds on 36 vectors), for callers that need only the
    matrix (the identification check, the tracker's refit; building a ``Rotation`` from it with
    ``Rotation.from_matrix`` costs what the SVD saves)."""
    B = (ref if weights is None else ref * np.asarray(weights, dtype=float)[:, None]).T @ body
    u, _, vt = np.linalg.svd(B)
    d = np.sign(np.linalg.det(u @ vt))
    return (u * np.array([1.0, 1.0, d])) @ vt
