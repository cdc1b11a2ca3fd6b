"""Compiled recursion of the he2021a constant-velocity Kalman filter (numba).

The same equations as the numpy reference functions :func:`rollingstar.estimators.filters.kf_cv.kf_cv_predict`
and :func:`~rollingstar.estimators.filters.kf_cv.kf_cv_update` (eq 11 with the corrected eq 8 process noise and
the Joseph-form covariance update); the tests check the kernels against them and against filterpy.

Why compiled code: a frame has 5-40 tracks of 4 states, so one vectorised numpy step is ~25 array
operations on (n, 4, 4) arrays whose cost is the fixed per-call overhead (~1 us each), not the
~300 flops per track. Measured by ``rollingstar bench perf --only kf`` (docs/performance.md): the
numpy step gave 9.95x filterpy on 20 stars x 5,000 frames, short of the target of >= 10x; this
loop removes the per-call overhead.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def _cv_predict(X, P, s, h, q, x, Pp):  # pragma: no cover (compiled)
    """The prediction of track ``s`` over ``h`` seconds into ``x`` (4,) and ``Pp`` (4, 4):
    ``x = F X[s]``, ``Pp = F P[s] F^T + Q`` (the kernels' shared first half)."""
    x[0] = X[s, 0] + h * X[s, 1]
    x[1] = X[s, 1]
    x[2] = X[s, 2] + h * X[s, 3]
    x[3] = X[s, 3]
    for j in range(4):  # F P: row 0 += h row 1, row 2 += h row 3
        Pp[0, j] = P[s, 0, j] + h * P[s, 1, j]
        Pp[1, j] = P[s, 1, j]
        Pp[2, j] = P[s, 2, j] + h * P[s, 3, j]
        Pp[3, j] = P[s, 3, j]
    for i in range(4):  # (F P) F^T: column 0 += h column 1, column 2 += h column 3
        Pp[i, 0] += h * Pp[i, 1]
        Pp[i, 2] += h * Pp[i, 3]
    q11, q12, q22 = q * h**4 / 4.0, q * h**3 / 2.0, q * h**2
    for a in (0, 2):
        Pp[a, a] += q11
        Pp[a, a + 1] += q12
        Pp[a + 1, a] += q12
        Pp[a + 1, a + 1] += q22


@njit(cache=True, nogil=True, error_model="numpy")
def _cv_gain_update(Pp, x, z, s, sa, sb, sc, sd, K, X_out, A):  # pragma: no cover (compiled)
    """Track ``s``'s update from the prediction ``x``, ``Pp`` and the innovation covariance
    ``S = [[sa, sb], [sc, sd]]``: the gain ``K = Pp H^T S^-1`` (2 x 2 inverted in closed form), the
    state ``X_out[s] = x + K (z[s] - H x)`` and ``A = Pp - K H Pp`` (the kernels' shared middle)."""
    det = sa * sd - sb * sc
    i00, i01, i10, i11 = sd / det, -sb / det, -sc / det, sa / det
    for i in range(4):
        K[i, 0] = Pp[i, 0] * i00 + Pp[i, 2] * i10
        K[i, 1] = Pp[i, 0] * i01 + Pp[i, 2] * i11
    y0, y1 = z[s, 0] - x[0], z[s, 1] - x[2]
    for i in range(4):
        X_out[s, i] = x[i] + K[i, 0] * y0 + K[i, 1] * y1
    for i in range(4):
        for j in range(4):
            A[i, j] = Pp[i, j] - (K[i, 0] * Pp[0, j] + K[i, 1] * Pp[2, j])


@njit(cache=True, nogil=True, error_model="numpy")
def kf_cv_step_kernel(X, P, z, dt, q, r, X_out, P_out):  # pragma: no cover (compiled)
    """Eq (11) predict + update of ``n`` tracks: state ``X`` (n, 4), covariance ``P`` (n, 4, 4),
    measurement ``z`` (n, 2) px, step ``dt`` (n,) s; results into ``X_out``, ``P_out`` (may alias).

    Predict: ``X = F X``, ``P = F P F^T + Q`` with ``F = I + dt (e0 e1^T + e2 e3^T)`` and
    ``Q = q G G^T`` (per axis ``q [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]``). Update with
    ``H = [e0, e2]^T``: ``S = H P H^T + r I`` (2 x 2, inverted in closed form),
    ``K = P H^T S^-1``, ``X += K (z - H X)``, ``A = P - K H P``,
    ``P = A - (A H^T) K^T + r K K^T`` (the Joseph form multiplied out).
    """
    n = X.shape[0]
    x = np.empty(4)
    Pp = np.empty((4, 4))
    K = np.empty((4, 2))
    A = np.empty((4, 4))
    for s in range(n):
        _cv_predict(X, P, s, dt[s], q, x, Pp)
        # ---- update
        _cv_gain_update(Pp, x, z, s, Pp[0, 0] + r, Pp[0, 2], Pp[2, 0], Pp[2, 2] + r, K, X_out, A)
        for i in range(4):
            for j in range(4):
                P_out[s, i, j] = (A[i, j] - (A[i, 0] * K[j, 0] + A[i, 2] * K[j, 1])
                                  + r * (K[i, 0] * K[j, 0] + K[i, 1] * K[j, 1]))


@njit(cache=True, nogil=True, error_model="numpy")
def kf_cv_batch_kernel(z, dts, q, r, states, covs):  # pragma: no cover (compiled)
    """Run :func:`kf_cv_step_kernel` over frames ``2..T-1`` of ``z`` (T, n, 2) with steps ``dts``
    (T, n), starting from ``states[1]``, ``covs[1]``; fills ``states[t]``, ``covs[t]`` in place."""
    for t in range(2, z.shape[0]):
        kf_cv_step_kernel(states[t - 1], covs[t - 1], z[t], dts[t], q, r, states[t], covs[t])


@njit(cache=True, nogil=True, error_model="numpy")
def kf_cv_step_cov_kernel(X, P, z, dt, q, R, X_out, P_out):  # pragma: no cover (compiled)
    """:func:`kf_cv_step_kernel` with a 2 x 2 measurement covariance per track, ``R`` (n, 2, 2) px^2
    (a smeared spot's centroid covariance, long along the smear): ``S = H P H^T + R_s`` and the
    Joseph term ``K R_s K^T``. A kernel of its own so that the tracks with the scalar ``r`` keep
    :func:`kf_cv_step_kernel`'s arithmetic exactly."""
    n = X.shape[0]
    x = np.empty(4)
    Pp = np.empty((4, 4))
    K = np.empty((4, 2))
    A = np.empty((4, 4))
    KR = np.empty((4, 2))
    for s in range(n):
        _cv_predict(X, P, s, dt[s], q, x, Pp)
        _cv_gain_update(Pp, x, z, s, Pp[0, 0] + R[s, 0, 0], Pp[0, 2] + R[s, 0, 1], Pp[2, 0] + R[s, 1, 0],
                        Pp[2, 2] + R[s, 1, 1], K, X_out, A)
        for i in range(4):
            KR[i, 0] = K[i, 0] * R[s, 0, 0] + K[i, 1] * R[s, 1, 0]
            KR[i, 1] = K[i, 0] * R[s, 0, 1] + K[i, 1] * R[s, 1, 1]
        for i in range(4):
            for j in range(4):
                P_out[s, i, j] = (A[i, j] - (A[i, 0] * K[j, 0] + A[i, 2] * K[j, 1])
                                  + (KR[i, 0] * K[j, 0] + KR[i, 1] * K[j, 1]))
