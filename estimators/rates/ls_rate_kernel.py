"""Compiled per-pair loops of the ``ls-rate`` solver (numba): residuals and Jacobian, pixel sensitivity.

The same equations as the numpy reference functions in :mod:`rollingstar.estimators.rates.ls_rate`
(eq 1 by :func:`rollingstar.sensors.so3.rotate_at_rate`, ``pair_residuals`` eq 2, ``pair_jacobian`` eq 3, ``pixel_sensitivity``);
the tests check the kernels against them. Why compiled code: a frame has 10-25 stars, 45-300 pairs,
so a vectorised numpy evaluation is bound by the fixed cost of its ~40 array operations (~45 us
measured), not by arithmetic; the loop below does the same work in a few microseconds, and the
solver evaluates 3 times per frame (benchmarks/rate_solvers.py).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def residual_jacobian_kernel(w, dt, i, j, cat, omega, out):  # pragma: no cover (compiled)
    """Fill ``out`` (m, 4) with ``[r_ij, d r_ij / d omega]`` at ``omega`` (3,) for unit ``w`` (n, 3),
    ``dt`` (n,) s, pairs ``i, j`` (m,) and catalogue angles ``cat`` (m,).

    Eq 1 by Rodrigues with ``t = |omega| dt``: ``a = w - s1 (w x omega) + s2 (w x omega) x omega``,
    ``s1 = sin(t) / |omega|``, ``s2 = (1 - cos t) / |omega|^2 = 2 sin^2(t/2) / |omega|^2``. Eq 2:
    ``atan2(|a_i x a_j|, a_i . a_j) - cat``. Eq 3 with ``n = a_i x a_j / |a_i x a_j|``,
    ``p = n x omega``, ``q = p x omega``: ``(dt_j - dt_i) n + (s2_j - s2_i) p + (s3_j - s3_i) q``
    where ``s2 = c1 dt^2`` and ``s3 = c2 dt^3 = (dt - s1) / |omega|^2`` (series
    ``dt^3 (1/6 - t^2/120 + t^4/5040)`` below ``|t| = 0.01``, exact to rounding) are the left
    Jacobian's coefficients (``left_jacobian``) times powers of ``dt``.
    """
    n = w.shape[0]
    m = i.shape[0]
    ox, oy, oz = omega[0], omega[1], omega[2]
    th2 = ox * ox + oy * oy + oz * oz
    th = math.sqrt(th2)
    a = np.empty((n, 3))
    c = np.empty((n, 3))
    for s in range(n):
        d = dt[s]
        wx, wy, wz = w[s, 0], w[s, 1], w[s, 2]
        c[s, 0] = d
        if th2 == 0.0:
            a[s, 0], a[s, 1], a[s, 2] = wx, wy, wz
            c[s, 1] = 0.0
            c[s, 2] = 0.0
            continue
        t = th * d
        s1 = math.sin(t) / th
        h = math.sin(0.5 * t)
        s2 = 2.0 * h * h / th2
        if abs(t) < 0.01:
            t2 = t * t
            s3 = d * d * d * (1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0)
        else:
            s3 = (d - s1) / th2
        ux, uy, uz = wy * oz - wz * oy, wz * ox - wx * oz, wx * oy - wy * ox  # w x omega
        vx, vy, vz = uy * oz - uz * oy, uz * ox - ux * oz, ux * oy - uy * ox  # (w x omega) x omega
        a[s, 0] = wx - s1 * ux + s2 * vx
        a[s, 1] = wy - s1 * uy + s2 * vy
        a[s, 2] = wz - s1 * uz + s2 * vz
        c[s, 1] = s2
        c[s, 2] = s3
    for k in range(m):
        p, q = i[k], j[k]
        ax, ay, az = a[p, 0], a[p, 1], a[p, 2]
        bx, by, bz = a[q, 0], a[q, 1], a[q, 2]
        cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        sn = math.sqrt(cx * cx + cy * cy + cz * cz)
        out[k, 0] = math.atan2(sn, ax * bx + ay * by + az * bz) - cat[k]
        nx, ny, nz = cx / sn, cy / sn, cz / sn
        px, py, pz = ny * oz - nz * oy, nz * ox - nx * oz, nx * oy - ny * ox  # n x omega
        qx, qy, qz = py * oz - pz * oy, pz * ox - px * oz, px * oy - py * ox  # p x omega
        d0 = c[q, 0] - c[p, 0]
        d1 = c[q, 1] - c[p, 1]
        d2 = c[q, 2] - c[p, 2]
        out[k, 1] = d0 * nx + d1 * px + d2 * qx
        out[k, 2] = d0 * ny + d1 * py + d2 * qy
        out[k, 3] = d0 * nz + d1 * pz + d2 * qz


@njit(cache=True, nogil=True, error_model="numpy")
def pair_setup_kernel(w, ref, inv_W, i, j, G, cat):  # pragma: no cover (compiled)
    """Fill ``G`` (m, 2n, zeroed) with ``pixel_sensitivity`` (``d theta_ij / d(x_i, y_i) = (t_ij,x,
    t_ij,y) / |W_i|``, ``t_ij`` the unit tangent at ``w_i`` towards ``w_j``; ``inv_W = 1 / |W|``) and
    ``cat`` (m,) with the catalogue angles ``atan2(|r_i x r_j|, dot(r_i, r_j))`` of unit ``ref`` (n, 3)."""
    for k in range(i.shape[0]):
        p, q = i[k], j[k]
        ax, ay, az = ref[p, 0], ref[p, 1], ref[p, 2]
        bx, by, bz = ref[q, 0], ref[q, 1], ref[q, 2]
        cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        cat[k] = math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)
        ax, ay, az = w[p, 0], w[p, 1], w[p, 2]
        bx, by, bz = w[q, 0], w[q, 1], w[q, 2]
        cos = ax * bx + ay * by + az * bz
        tx, ty, tz = bx - cos * ax, by - cos * ay, bz - cos * az  # towards w_j at w_i
        inv_sin = 1.0 / math.sqrt(tx * tx + ty * ty + tz * tz)  # |w_j - cos w_i| = |w_i - cos w_j|
        G[k, 2 * p] = tx * inv_W[p] * inv_sin
        G[k, 2 * p + 1] = ty * inv_W[p] * inv_sin
        G[k, 2 * q] = (ax - cos * bx) * inv_W[q] * inv_sin
        G[k, 2 * q + 1] = (ay - cos * by) * inv_W[q] * inv_sin
