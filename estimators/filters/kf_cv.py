"""Per-star constant-velocity Kalman filter of he2021a section 2.1 (eqs 5-11), batched over stars.

State per star (eq 7): ``X = [x, vx, y, vy]`` in px and px/s. Model (eqs 8-10), with the step
``dt`` between two measurements of the star::

    X(k) = F X(k-1) + G W(k),   F = [[1, dt, 0, 0], [0, 1, 0, 0], [0, 0, 1, dt], [0, 0, 0, 1]]
    Z(k) = H X(k) + V(k),       H = [[1, 0, 0, 0], [0, 0, 1, 0]]

The noise input matrix ``G`` is printed in the seed with a missing row (known typo of eq 8); the
random-acceleration model it describes is the 4 x 2 matrix

    G = [[dt^2/2, 0], [dt, 0], [0, dt^2/2], [0, dt]],

so the process noise covariance is ``Q_k = q G G^T`` with ``q`` the variance of the random
acceleration ``W`` (px^2/s^4; the seed's "Q = 1e-4" read in these units). ``V`` has covariance
``r I`` (``r`` the seed's "R", read as a centroid variance in px^2: R = 0.05 px^2 is a 0.224 px
1-sigma centroid noise per axis).

Initialisation (eq 6): a track's first measurement is stored; at its second, ``x, y`` = the second
measurement and ``vx, vy`` = frame difference / ``dt``. The seed gives no initial covariance; we use
the exact covariance of that differencing initialiser per axis, ``[[r, r/dt], [r/dt, 2 r/dt^2]]``.

2 x 2 measurement noise: a star that carries its own position covariance ``C`` (``cov_xx, cov_xy,
cov_yy``) that is not isotropic (a smeared spot: long along the smear) is filtered with ``V ~ C``
instead of ``r I`` (``star_covariance``; the x and y axes are then coupled), and its initialiser's
covariance is the exact one of the difference of two measurements of covariances ``C_prev``,
``C``: position ``C``, position-velocity ``C / dt``, velocity ``(C + C_prev) / dt^2``. The other
stars keep the seed's ``r I``. The filters are per star, so the choice of one star never changes
another's estimate.

Recursion (eq 11): predict ``X = F X``, ``P = F P F^T + Q``; update with gain
``K = P H^T (H P H^T + r I)^-1``. The covariance update uses the Joseph form
``(I - K H) P (I - K H)^T + K r K^T`` (equal to eq 11's ``(I - K H) P`` for the optimal gain,
numerically symmetric, and what filterpy computes, so both backends agree to rounding).

``dt``: the seed's eq (5) frame interval ``t_f = t_e + N dt_line`` is the interval between frame
timestamps. A rolling-shutter star's consecutive measurements are, however, ``t_f + (y_k - y_{k-1})
dt_line`` apart (its row moves); with ``t_f`` the velocity comes out scaled by ``1/(1 - vy dt_line)``
(1 % at 3 deg/s on the he2021a sensor, i.e. ~2 px/s). Default ``dt_source="star_time"`` uses each
star's own measurement-time difference (``t_ns``, exact); ``"frame_start"`` uses the difference of
the frames' ``t0`` (= eq 5 for a recording with the eq-5 period), as in the seed.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from rollingstar.estimators.attitude.star_covariance import is_isotropic
from rollingstar.estimators.data import FrameData, StarTable
from rollingstar.estimators.filters.base import StarMotionFilter
from rollingstar.estimators.filters.kf_cv_kernel import (
    kf_cv_batch_kernel,
    kf_cv_step_cov_kernel,
    kf_cv_step_kernel,
)
from rollingstar.sensors.conventions import S_PER_NS

H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
_EYE4 = np.eye(4)


# ------------------------------------------------- batched maths (numpy reference; the filter runs kf_cv_kernel)
def cv_transition(dt) -> tuple[np.ndarray, np.ndarray]:
    """``F`` (n, 4, 4) and the random-acceleration input ``G`` (n, 4, 2) of eq (8) for steps ``dt`` (n,) s."""
    dt = np.asarray(dt, dtype=float).reshape(-1)
    n = dt.shape[0]
    F = np.broadcast_to(_EYE4, (n, 4, 4)).copy()
    F[:, 0, 1] = dt
    F[:, 2, 3] = dt
    G = np.zeros((n, 4, 2))
    G[:, 0, 0] = G[:, 2, 1] = 0.5 * dt**2
    G[:, 1, 0] = G[:, 3, 1] = dt
    return F, G


def cv_process_noise(dt, q: float) -> np.ndarray:
    """Eq (8) (corrected): ``Q = q G G^T`` (n, 4, 4) for steps ``dt`` (n,) s and acceleration variance ``q``."""
    _, G = cv_transition(dt)
    return q * np.einsum("nik,njk->nij", G, G)


def kf_cv_init(z_prev: np.ndarray, z: np.ndarray, dt, r: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq (6) initialisation from two measurements ``(n, 2)`` ``dt`` (n,) s apart: state (n, 4), covariance (n, 4, 4)."""
    z_prev = np.asarray(z_prev, dtype=float).reshape(-1, 2)
    z = np.asarray(z, dtype=float).reshape(-1, 2)
    dt = np.broadcast_to(np.asarray(dt, dtype=float), (z.shape[0],))
    v = (z - z_prev) / dt[:, None]
    X = np.column_stack([z[:, 0], v[:, 0], z[:, 1], v[:, 1]])
    P = np.zeros((z.shape[0], 4, 4))
    for a in (0, 2):  # x block then y block (two fixed indices, not a loop over stars)
        P[:, a, a] = r
        P[:, a, a + 1] = P[:, a + 1, a] = r / dt
        P[:, a + 1, a + 1] = 2.0 * r / dt**2
    return X, P


def kf_cv_init_cov(z_prev: np.ndarray, z: np.ndarray, dt, R_prev: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`kf_cv_init` with 2 x 2 measurement covariances ``R_prev``, ``R`` (n, 2, 2) px^2 of the two
    measurements: position covariance ``R``, position-velocity ``R / dt``, velocity ``(R + R_prev) / dt^2``."""
    X, _ = kf_cv_init(z_prev, z, dt, 1.0)
    dt = np.broadcast_to(np.asarray(dt, dtype=float), (X.shape[0],))
    P = np.zeros((X.shape[0], 4, 4))
    for a, pa in enumerate((0, 2)):  # state index of axis a's position (pa) and velocity (pa + 1)
        for b, pb in enumerate((0, 2)):
            P[:, pa, pb] = R[:, a, b]
            P[:, pa, pb + 1] = P[:, pb + 1, pa] = R[:, a, b] / dt
            P[:, pa + 1, pb + 1] = (R[:, a, b] + R_prev[:, a, b]) / dt**2
    return X, P


def kf_cv_predict(X: np.ndarray, P: np.ndarray, dt, q: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq (11) prediction for all stars at once: ``X = F X``, ``P = F P F^T + Q``.

    ``F = I + dt (e_0 e_1^T + e_2 e_3^T)`` is applied as row/column updates instead of 4 x 4
    products (same arithmetic, ~5x less overhead for the few tracks of a frame; ``rollingstar bench perf --only kf``).
    """
    X = np.asarray(X, dtype=float)
    dt = np.broadcast_to(np.asarray(dt, dtype=float).reshape(-1), (X.shape[0],))
    Xp = X.copy()
    Xp[:, 0] += dt * X[:, 1]
    Xp[:, 2] += dt * X[:, 3]
    FP = np.array(P, dtype=float)  # F P: row 0 += dt row 1, row 2 += dt row 3
    FP[:, 0, :] += dt[:, None] * FP[:, 1, :]
    FP[:, 2, :] += dt[:, None] * FP[:, 3, :]
    Pp = FP  # (F P) F^T: column 0 += dt column 1, column 2 += dt column 3
    Pp[:, :, 0] += dt[:, None] * Pp[:, :, 1]
    Pp[:, :, 2] += dt[:, None] * Pp[:, :, 3]
    # Q = q G G^T (eq 8, corrected): per axis [[dt^4/4, dt^3/2], [dt^3/2, dt^2]] q
    q11, q12, q22 = q * dt**4 / 4.0, q * dt**3 / 2.0, q * dt**2
    for a in (0, 2):  # x block then y block
        Pp[:, a, a] += q11
        Pp[:, a, a + 1] += q12
        Pp[:, a + 1, a] += q12
        Pp[:, a + 1, a + 1] += q22
    return Xp, Pp


def kf_cv_update(X: np.ndarray, P: np.ndarray, z: np.ndarray, r) -> tuple[np.ndarray, np.ndarray]:
    """Eq (11) update for all stars at once (Joseph-form covariance, see the module docstring).

    ``r``: the measurement variance per axis (px^2), or (n, 2, 2) each star's measurement
    covariance (then the general form ``S = H P H^T + R``, ``+ K R K^T``).

    ``H`` selects state components 0 and 2, so ``P H^T``, ``H P`` and ``H P H^T`` are slices, and
    the Joseph form ``(I - K H) P (I - K H)^T + r K K^T`` is evaluated as ``A = P - K (H P)``,
    ``A - (A H^T) K^T + r K K^T`` (the same expression multiplied out; no 4 x 4 ``I - K H``).
    The 2 x 2 innovation covariance is inverted in closed form (``np.linalg.inv``'s per-call
    overhead is most of an update for the few tracks of a frame; ``rollingstar bench perf --only kf``).
    """
    X = np.asarray(X, dtype=float)
    P = np.asarray(P, dtype=float)
    n = X.shape[0]
    if np.ndim(r) == 3:
        S = P[:, ::2, ::2] + r
        K = np.swapaxes(np.linalg.solve(S, P[:, ::2, :]), 1, 2)  # P H^T S^-1 (S symmetric)
        Xu = X + (K @ (np.asarray(z, dtype=float).reshape(n, 2) - X[:, ::2])[:, :, None])[:, :, 0]
        IKH = np.eye(4) - K @ H
        return Xu, IKH @ P @ np.swapaxes(IKH, 1, 2) + K @ r @ np.swapaxes(K, 1, 2)
    PHt = P[:, :, ::2]  # P H^T (n, 4, 2)
    HP = P[:, ::2, :]  # H P (n, 2, 4)
    a, b, c, d = HP[:, 0, 0] + r, HP[:, 0, 2], HP[:, 1, 0], HP[:, 1, 2] + r  # S = H P H^T + r I
    det = a * d - b * c
    S_inv = np.empty((n, 2, 2))
    S_inv[:, 0, 0], S_inv[:, 0, 1], S_inv[:, 1, 0], S_inv[:, 1, 1] = d / det, -b / det, -c / det, a / det
    K = PHt @ S_inv  # (n, 4, 2)
    y = np.asarray(z, dtype=float).reshape(n, 2) - X[:, ::2]
    Xu = X + (K @ y[:, :, None])[:, :, 0]
    A = P - K @ HP  # (I - K H) P
    Kt = np.swapaxes(K, 1, 2)
    Pu = A - A[:, :, ::2] @ Kt + r * (K @ Kt)  # (I - K H) P (I - K H)^T + K r K^T
    return Xu, Pu


def kf_cv_batch(z: np.ndarray, dt, q: float = 1e-4, r: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Filter ``n`` complete tracks of ``T`` frames at once (benchmarks, tests).

    ``z`` (T, n, 2) measured ``(x, y)`` px; ``dt`` seconds between frame ``t-1`` and ``t``: a scalar,
    (T,) or (T, n) (entry 0 unused). Returns states (T, n, 4) ``[x, vx, y, vy]`` and covariances
    (T, n, 4, 4): frame 0 holds the raw measurement with NaN velocity and NaN covariance, frame 1
    the eq (6) initialisation, later frames eq (11).
    """
    z = np.asarray(z, dtype=float)
    T, n, _ = z.shape
    dts = np.broadcast_to(np.asarray(dt, dtype=float).reshape((-1, 1) if np.ndim(dt) == 1 else np.shape(dt)), (T, n))
    states = np.full((T, n, 4), np.nan)
    covs = np.full((T, n, 4, 4), np.nan)
    states[0, :, 0], states[0, :, 2] = z[0, :, 0], z[0, :, 1]
    if T < 2:
        return states, covs
    states[1], covs[1] = kf_cv_init(z[0], z[1], dts[1], r)
    # the recursion over time is sequential: compiled loop (kf_cv_kernel explains why)
    kf_cv_batch_kernel(np.ascontiguousarray(z), np.ascontiguousarray(dts), float(q), float(r), states, covs)
    return states, covs


def steady_state_covariance(dt: float, q: float, r: float) -> tuple[np.ndarray, np.ndarray]:
    """Discrete algebraic Riccati solution of the model: (prior, posterior) 4 x 4 covariances."""
    from scipy.linalg import solve_discrete_are

    F, _ = cv_transition([dt])
    Q = cv_process_noise([dt], q)[0]
    prior = solve_discrete_are(F[0].T, H.T, Q, r * np.eye(2))
    S = H @ prior @ H.T + r * np.eye(2)
    post = prior - prior @ H.T @ np.linalg.solve(S, H @ prior)
    return prior, post


# ------------------------------------------------------------------------ plugin
class KfCvParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    backend: Literal["batched", "filterpy"] = Field(
        default="batched", description="'batched': numpy over all tracks; 'filterpy': one filterpy KalmanFilter per track (reference).")
    q: float = Field(default=1e-4, ge=0, description="Random-acceleration variance (px^2/s^4), the seed's Q (eq 8).")
    r: float = Field(default=0.05, gt=0, description="Centroid measurement-noise variance per axis (px^2), the seed's R (eq 9).")
    dt_source: Literal["star_time", "frame_start"] = Field(
        default="star_time", description="Step between measurements: each star's t_ns difference (exact) or the frames' t0 difference (eq 5).")
    star_covariance: bool = Field(
        default=True, description="Filter a star that carries a 2 x 2 position covariance that is not isotropic "
        "(cov_xx, cov_xy, cov_yy) with it as measurement noise; False (and every other star): r I.")


class KfCvFilter(StarMotionFilter):
    """he2021a constant-velocity Kalman filter per identified star (eqs 5-11; see the module docstring).

    Tracks are keyed by ``catalog_id``: created when an identified star appears, retired as soon as
    a frame does not contain it (a re-appearing star starts a new track). Unidentified stars
    (``catalog_id < 0``) and stars of a duplicated id pass through unchanged.

    Output per star (a new :class:`StarTable`, same rows and order):

    - first sighting: position unchanged, ``vx = vy = NaN`` (no velocity can be estimated yet);
    - second: eq (6) initialisation, position = measurement, velocity = difference / dt;
    - later: eq (11) filtered ``x, y, vx, vy``.

    ``sigma_px`` = ``sqrt((P_xx + P_yy) / 2)`` and ``cov_xx, cov_xy, cov_yy`` the position block of the
    filtered state's covariance (unchanged on first sighting); ``t_ns`` unchanged: the filtered state refers to the time of the star's current measurement.
    Frames get flag ``"kf_cv_nonpositive_dt:<n>"`` when ``n`` tracks saw a step <= 0 (restarted).
    """

    name = "kf-cv"
    Params = KfCvParams

    def setup(self, context) -> None:
        super().setup(context)
        self._ids = np.zeros(0, dtype=np.int64)  # sorted track ids
        self._X = np.zeros((0, 4))
        self._P = np.zeros((0, 4, 4))
        self._t = np.zeros(0, dtype=np.int64)  # time of the last measurement (ns)
        self._stage = np.zeros(0, dtype=np.int8)  # 1: one measurement stored, 2: filtering
        self._R = np.zeros((0, 2, 2))  # measurement covariance of each track's last measurement (px^2)
        self._own = np.zeros(0, dtype=bool)  # that measurement had its own 2 x 2 covariance
        self._kf: dict[int, object] = {}  # filterpy backend: catalog_id -> KalmanFilter

    def process(self, frame: FrameData) -> FrameData:
        stars = frame.stars
        if stars is None or stars.n == 0:
            self.setup_empty()
            return frame.evolve()
        p = self.params
        ids = stars.catalog_id
        uniq, counts = np.unique(ids[ids >= 0], return_counts=True)
        dup = np.isin(ids, uniq[counts > 1])
        use = (ids >= 0) & ~dup & np.isfinite(stars.x) & np.isfinite(stars.y)
        rows = np.flatnonzero(use)
        sid = ids[rows]
        z = np.column_stack([stars.x[rows], stars.y[rows]])
        t = stars.t_ns[rows] if p.dt_source == "star_time" else np.full(rows.size, frame.t0_ns, dtype=np.int64)
        R, own = self._measurement_noise(stars.take(rows))

        # match to existing tracks (sorted ids), retire the absent ones
        pos = np.searchsorted(self._ids, sid)
        pos_c = np.minimum(pos, max(self._ids.size - 1, 0))
        known = (self._ids.size > 0) & (self._ids[pos_c] == sid) if self._ids.size else np.zeros(sid.size, bool)
        old = np.where(known, pos_c, -1)
        X = np.full((sid.size, 4), np.nan)
        P = np.full((sid.size, 4, 4), np.nan)
        stage = np.ones(sid.size, dtype=np.int8)
        X[:, 0], X[:, 2] = z[:, 0], z[:, 1]
        dt = np.full(sid.size, np.nan)
        k = old >= 0
        dt[k] = (t[k] - self._t[old[k]]).astype(float) * S_PER_NS
        bad_dt = k & ~(dt > 0)
        k &= ~bad_dt
        init = k & (self._stage[np.where(k, old, 0)] == 1) if sid.size and self._stage.size else np.zeros(sid.size, bool)
        step = k & ~init
        if init.any():
            X[init], P[init] = self._initialise(old[init], z[init], dt[init], R[init], own[init])
            stage[init] = 2
        if step.any():
            X[step], P[step] = self._steps(old[step], sid[step], z[step], dt[step], R[step], own[step])
            stage[step] = 2
        if p.backend == "filterpy":
            self._filterpy_sync(sid, X, P, stage)

        order = np.argsort(sid, kind="stable")
        self._ids, self._X, self._P, self._t, self._stage = sid[order], X[order], P[order], t[order], stage[order]
        self._R, self._own = R[order], own[order]
        flags = frame.flags + ((f"kf_cv_nonpositive_dt:{int(bad_dt.sum())}",) if bad_dt.any() else ())
        return frame.evolve(stars=_filtered_table(stars, rows, X, P, stage == 2, own), flags=flags)

    def _measurement_noise(self, sel: StarTable) -> tuple[np.ndarray, np.ndarray]:
        """Each star's measurement covariance (n, 2, 2) px^2 and which stars use their own 2 x 2 one
        (``star_covariance``: a valid covariance that is not isotropic; the fallbacks of
        :meth:`StarTable.position_covariance` are isotropic); the others get ``r I``."""
        R = np.broadcast_to(self.params.r * np.eye(2), (sel.n, 2, 2)).copy()
        own = np.zeros(sel.n, dtype=bool)
        if self.params.star_covariance and sel.n:
            cov = sel.position_covariance(np.sqrt(self.params.r), use_star_sigma=True)
            own = ~is_isotropic(cov)
            R[own] = cov[own]
        return R, own

    def _initialise(self, old, z, dt, R, own) -> tuple[np.ndarray, np.ndarray]:
        """Eq (6) for tracks at their second measurement (the 2 x 2 form where either measurement has its own)."""
        zp = np.column_stack([self._X[old, 0], self._X[old, 2]])
        X, P = kf_cv_init(zp, z, dt, self.params.r)
        full = own | self._own[old]
        if full.any():
            X[full], P[full] = kf_cv_init_cov(zp[full], z[full], dt[full], self._R[old[full]], R[full])
        return X, P

    def _steps(self, old, sid, z, dt, R, own) -> tuple[np.ndarray, np.ndarray]:
        """Eq (11) predict + update of the tracks past their initialisation."""
        p = self.params
        if p.backend == "filterpy":
            return self._filterpy_steps(sid, dt, z, R)
        n = old.size
        X, P = np.empty((n, 4)), np.empty((n, 4, 4))
        kf_cv_step_kernel(self._X[old], self._P[old], z, dt, float(p.q), float(p.r), X, P)
        if own.any():
            Xo, Po = np.empty((int(own.sum()), 4)), np.empty((int(own.sum()), 4, 4))
            kf_cv_step_cov_kernel(self._X[old[own]], self._P[old[own]], np.ascontiguousarray(z[own]), dt[own],
                                  float(p.q), np.ascontiguousarray(R[own]), Xo, Po)
            X[own], P[own] = Xo, Po
        return X, P

    def setup_empty(self) -> None:
        """Retire every track (a frame without stars)."""
        self.setup(self.context)

    # filterpy reference backend: one KalmanFilter per track, stepped in a loop over tracks
    def _filterpy_steps(self, ids, dt, z, R):
        from filterpy.kalman import KalmanFilter

        X = np.zeros((ids.size, 4))
        P = np.zeros((ids.size, 4, 4))
        for i, (cid, h, zi) in enumerate(zip(ids, dt, z)):
            kf: KalmanFilter = self._kf[int(cid)]
            F, _ = cv_transition([h])
            kf.F = F[0]
            kf.Q = cv_process_noise([h], self.params.q)[0]
            kf.predict()
            kf.update(zi.reshape(2, 1), R=R[i])
            X[i], P[i] = kf.x.reshape(4), kf.P
        return X, P

    def _filterpy_sync(self, ids, X, P, stage) -> None:
        from filterpy.kalman import KalmanFilter

        kept = {}
        for cid, x, cov, s in zip(ids, X, P, stage):
            cid = int(cid)
            kf = self._kf.get(cid)
            if kf is None or s == 1:
                kf = KalmanFilter(dim_x=4, dim_z=2)
                kf.H = H.copy()
                kf.R = self.params.r * np.eye(2)
            if s == 2:
                kf.x = x.reshape(4, 1).copy()
                kf.P = cov.copy()
            kept[cid] = kf
        self._kf = kept


def _filtered_table(stars: StarTable, rows, X, P, filtered, own) -> StarTable:
    """``stars`` with the filtered positions, velocities and sigmas of ``rows`` (``filtered``: past
    the first sighting; the others get NaN velocities); stars filtered with their own 2 x 2
    covariance (``own``) also get the filtered one, the position block of ``P``."""
    out_x, out_y = stars.x.copy(), stars.y.copy()
    vx, vy = stars.vx.copy(), stars.vy.copy()
    sigma = stars.sigma_px.copy()
    cov = {k: getattr(stars, k).copy() for k in ("cov_xx", "cov_xy", "cov_yy")}
    r_f = rows[filtered]
    out_x[r_f], out_y[r_f] = X[filtered, 0], X[filtered, 2]
    vx[r_f], vy[r_f] = X[filtered, 1], X[filtered, 3]
    sigma[r_f] = np.sqrt(0.5 * (P[filtered, 0, 0] + P[filtered, 2, 2]))
    c = filtered & own
    for key, (i, j) in zip(cov, ((0, 0), (0, 2), (2, 2))):
        cov[key][rows[c]] = P[c, i, j]
    r1 = rows[~filtered]
    vx[r1] = vy[r1] = np.nan
    return stars.with_columns(x=out_x, y=out_y, vx=vx, vy=vy, sigma_px=sigma, **cov)
