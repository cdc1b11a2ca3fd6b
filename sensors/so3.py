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
from numba import njit


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


def _rows(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple]:
    """``a`` and ``b`` (..., 3) broadcast against each other as (m, 3) rows, and the broadcast shape."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.shape[-1:] != (3,) or b.shape[-1:] != (3,):
        raise ValueError(f"expected vectors (..., 3), got shapes {a.shape} and {b.shape}")
    if a.shape == b.shape and a.ndim == 2:
        return a, b, a.shape
    shape = np.broadcast_shapes(a.shape, b.shape)
    return (np.broadcast_to(a, shape).reshape(-1, 3), np.broadcast_to(b, shape).reshape(-1, 3), shape)


def rotate_by_rotvec(rotvec: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``Exp(rotvec) v`` for broadcastable (..., 3) arrays (module docstring; series below 1e-8 rad)."""
    r, w, shape = _rows(rotvec, v)
    return rotate_rows(r, w).reshape(shape)


@njit(cache=True, nogil=True)
def rotate_rows(rotvec, v):  # pragma: no cover - compiled
    """:func:`rotate_by_rotvec` row by row on (m, 3) arrays, callable from other compiled code.
    Compiled: the trackers and the diagnosis rotate a few tens of stars per call, where a dozen
    numpy calls' overhead was several times the arithmetic."""
    out = np.empty(v.shape)
    for i in range(v.shape[0]):
        p0, p1, p2 = rotvec[i, 0], rotvec[i, 1], rotvec[i, 2]
        th = np.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
        if th < 1e-8:
            a, b = 1.0 - th * th / 6.0, 0.5 - th * th / 24.0
        else:
            a, b = np.sin(th) / th, (1.0 - np.cos(th)) / (th * th)
        v0, v1, v2 = v[i, 0], v[i, 1], v[i, 2]
        k0, k1, k2 = p1 * v2 - p2 * v1, p2 * v0 - p0 * v2, p0 * v1 - p1 * v0
        out[i, 0] = v0 + a * k0 + b * (p1 * k2 - p2 * k1)
        out[i, 1] = v1 + a * k1 + b * (p2 * k0 - p0 * k2)
        out[i, 2] = v2 + a * k2 + b * (p0 * k1 - p1 * k0)
    return out


def rotate_at_rate(omega, w: np.ndarray, dt_s: np.ndarray) -> np.ndarray:
    """``Exp(omega dt_i) w_i`` for ``omega`` (3,), ``w`` (n, 3), ``dt_s`` (n,) (module docstring)."""
    omega = np.asarray(omega, dtype=float)
    if not omega.any():
        return w
    w, dt_s = np.asarray(w, dtype=float), np.asarray(dt_s, dtype=float)
    n = np.broadcast_shapes(w.shape[:1], dt_s.shape)  # numpy's broadcasting of the rows and the times
    if w.shape[1:] != (3,) or len(n) != 1:
        raise ValueError(f"rotate_at_rate: expected w (n, 3) and dt_s (n,), got {w.shape} and {dt_s.shape}")
    return _rotate_at_rate(omega, np.broadcast_to(w, n + (3,)), np.broadcast_to(dt_s, n))


@njit(cache=True, nogil=True)
def _rotate_at_rate(omega, w, dt_s):  # pragma: no cover - compiled
    """:func:`rotate_at_rate` star by star (compiled for the reason of :func:`rotate_rows`)."""
    norm = np.sqrt(omega[0] * omega[0] + omega[1] * omega[1] + omega[2] * omega[2])
    if norm == 0.0:  # a rate whose square underflows: no rotation
        return w.copy()
    k0, k1, k2 = omega[0] / norm, omega[1] / norm, omega[2] / norm
    out = np.empty(w.shape)
    for i in range(w.shape[0]):
        t = norm * dt_s[i]
        c, s = np.cos(t), np.sin(t)
        v0, v1, v2 = w[i, 0], w[i, 1], w[i, 2]
        kv = (v0 * k0 + v1 * k1 + v2 * k2) * (1.0 - c)
        out[i, 0] = v0 * c + (k1 * v2 - k2 * v1) * s + k0 * kv
        out[i, 1] = v1 * c + (k2 * v0 - k0 * v2) * s + k1 * kv
        out[i, 2] = v2 * c + (k0 * v1 - k1 * v0) * s + k2 * kv
    return out


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
    per-call overhead, for callers that need the matrix (the identification check, the tracker's
    refit, the start of ``rs-bundle``'s fit; :func:`quat_from_matrix` gives its quaternion
    without ``Rotation.from_matrix``'s overhead). ``rollingstar bench perf --only chain`` measures
    the chain these run in."""
    ref, body = np.asarray(ref, dtype=float), np.asarray(body, dtype=float)
    if ref.ndim != 2 or ref.shape[1:] != (3,) or body.shape != ref.shape:
        raise ValueError(f"wahba: expected ref and body (n, 3) alike, got {ref.shape} and {body.shape}")
    w = np.ones(len(ref)) if weights is None else np.broadcast_to(np.asarray(weights, dtype=float), (len(ref),))
    u, _, vt = np.linalg.svd(_wahba_B(ref, body, w))
    d = np.sign(np.linalg.det(u @ vt))
    return (u * np.array([1.0, 1.0, d])) @ vt


@njit(cache=True, nogil=True)
def _wahba_B(ref, body, weights):  # pragma: no cover - compiled
    """``B = sum w_i ref_i body_i^T`` (compiled: the trackers and the identification check form it
    on every frame; the 3 x 3 SVD stays numpy's)."""
    B = np.zeros((3, 3))
    for i in range(ref.shape[0]):
        for a in range(3):
            for b in range(3):
                B[a, b] += weights[i] * ref[i, a] * body[i, b]
    return B


@njit(cache=True, nogil=True)
def quat_from_matrix(m):  # pragma: no cover - compiled
    """The unit quaternion (x, y, z, w) of the rotation matrix ``m`` (3, 3), by the largest of the
    four diagonal combinations (Shepperd 1978; the sign is not normalised). Written by hand because
    ``scipy.spatial.transform.Rotation.from_matrix`` costs more per call for one matrix than
    the whole position fit it would start."""
    t = m[0, 0] + m[1, 1] + m[2, 2]
    q = np.empty(4)
    if t >= m[0, 0] and t >= m[1, 1] and t >= m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + t)
        q[0], q[1], q[2], q[3] = (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q[0], q[1], q[2], q[3] = 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s
    elif m[1, 1] >= m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q[0], q[1], q[2], q[3] = (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q[0], q[1], q[2], q[3] = (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s
    return q / np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])


@njit(cache=True, nogil=True)
def quat_to_matrix(q):  # pragma: no cover - compiled
    """Rotation matrix of the unit quaternion ``q`` (x, y, z, w)."""
    x, y, z, w = q[0], q[1], q[2], q[3]
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@njit(cache=True, nogil=True)
def quat_times_exp(q, delta):  # pragma: no cover - compiled
    """``q Exp(delta)`` (scalar-last quaternions; the rotation ``R Exp(delta)``), renormalised: the
    product of :func:`quat_multiply` written for one quaternion in compiled code (the bundle's
    position fit and pixel step update their attitude with it)."""
    th = np.sqrt(delta[0] ** 2 + delta[1] ** 2 + delta[2] ** 2)
    s = 0.5 - th * th / 48.0 if th < 1e-6 else np.sin(0.5 * th) / th
    px, py, pz, pw = q[0], q[1], q[2], q[3]
    qx, qy, qz, qw = s * delta[0], s * delta[1], s * delta[2], np.cos(0.5 * th)
    out = np.array([pw * qx + px * qw + py * qz - pz * qy, pw * qy - px * qz + py * qw + pz * qx,
                    pw * qz + px * qy - py * qx + pz * qw, pw * qw - px * qx - py * qy - pz * qz])
    return out / np.sqrt(np.sum(out * out))
