"""Gyro-driven Kalman filter of star-spot positions (liu2013 eqs 8-17), batched over stars.

The gyro history is :class:`rollingstar.sensors.gyro.GyroIntegrator` (the attitude-angle increment
between two times, and between two exposure-window means); :func:`star_motion_jacobian` is liu2013
eq (8) derived for *our* camera convention (the ``windowed`` centroider applies the same equation).

Derivation of eq (8) for our convention (``docs/conventions.md``): with ``u = x - cx``,
``v = y - cy`` (px) and ``F`` the focal length in px, the camera-frame direction of a pixel is
``w ~ [-u, -v, F]``. The body rotates as ``R(t + dt) = R(t) Exp(omega dt)``, so a fixed star's
camera-frame direction ``w = R^T v_icrs`` moves as ``dw = -omega x w dt = w x omega dt``. With
``u = -F w_x / w_z``, ``v = -F w_y / w_z`` this gives, for a small rotation-vector increment
``dtheta = (dtheta_x, dtheta_y, dtheta_z)`` (camera frame, rad)::

    du = -(u v / F) dtheta_x + (F + u^2 / F) dtheta_y + v dtheta_z
    dv = -(F + v^2 / F) dtheta_x + (u v / F) dtheta_y - u dtheta_z

This is liu2013 eq (8) term by term with ``(m, n, f) = (u, v, F)`` and the paper's pitch, roll and
yaw angles ``(theta, psi, phi) = (dtheta_y, dtheta_x, dtheta_z)``. Eq (9) multiplies the Jacobian by
the *attitude angles* at ``k - 1``; the image displacement between frames needs the angle
*increment* over the frame interval (what a rate-integrating gyro measures), which we use.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from rollingstar.estimators.attitude.star_covariance import is_isotropic
from rollingstar.estimators.data import FrameData, frame_camera
from rollingstar.estimators.filters.base import StarMotionFilter
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.gyro import GyroIntegrator


def star_motion_jacobian(x, y, camera) -> np.ndarray:
    """d(x, y)/d(theta_x, theta_y, theta_z), shape (n, 2, 3): liu2013 eq (8) in our convention.

    See the module docstring for the derivation; ``theta`` is a small body-frame rotation vector.
    """
    f = float(camera.focal_px)
    u = np.asarray(x, dtype=float) - camera.cx
    v = np.asarray(y, dtype=float) - camera.cy
    uv = u * v / f
    row_x = np.stack([-uv, f + u * u / f, v], axis=-1)
    row_y = np.stack([-(f + v * v / f), uv, -u], axis=-1)
    return np.stack([row_x, row_y], axis=-2)


class GyroKfParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    gyro_bias_rad_s: tuple[float, float, float] = Field(
        default=(0.0, 0.0, 0.0), description="Known (calibrated) gyro bias subtracted from the samples, rad/s (camera frame).")
    gyro_arw_rad_sqrt_s: float = Field(
        default=0.0, ge=0, description="Gyro angle random walk N (rad/sqrt(s)); gives Q = J diag(N^2 dt) J^T.")
    process_sigma_px: float = Field(
        default=0.005, ge=0, description="Extra process noise per axis per frame period (px): prediction model error.")
    measurement_sigma_px: float | None = Field(
        default=None, gt=0, description="Measurement noise per axis (px); None: the spot's sigma_px (else the context's, else 0.1).")
    model_sigma_px: float = Field(
        default=0.0, ge=0, description="Added in quadrature to the spot's sigma_px (unmodelled noise, e.g. aberrations).")
    reference: Literal["exposure_mean", "instant"] = Field(
        default="exposure_mean",
        description="'exposure_mean': a spot is the mean position over its row's exposure (what a CoG measures of a "
                    "smeared spot); 'instant': the position at the spot's t_ns.")
    gate_sigma: float = Field(default=6.0, gt=0, description="Innovation gate (Mahalanobis sigmas): beyond it the track restarts.")
    max_gap_s: float = Field(default=1.0, gt=0, description="A track not updated for longer restarts.")
    star_covariance: bool = Field(
        default=True, description="Measurement noise of a spot that carries a 2 x 2 position covariance that is not "
        "isotropic (cov_xx, cov_xy, cov_yy): that covariance (+ model_sigma_px^2 I); False: its sigma_px.")


class GyroKalmanFilter(StarMotionFilter):
    """Per-star Kalman filter of the spot position with the gyro-driven prediction (liu2013 eqs 11-17).

    Tracks are keyed by ``catalog_id`` (unidentified spots pass through unchanged). For the stars
    of a frame with a track (all arrays batched over stars, no per-star loop):

    - gyro angle increment ``dtheta`` between the track's last time and the spot's time
      (:class:`GyroIntegrator`; ``reference='exposure_mean'`` uses the increment of the mean angle
      over the two exposure windows, which is what moves the CoG of a smeared spot);
    - prediction, eq (13): ``x- = x^(k-1) + J(x^(k-1)) dtheta`` with ``J`` eq (8) in our convention
      (:func:`star_motion_jacobian`) evaluated at the previous *estimate*;
    - eq (14): ``P- = P + Q`` with ``Q = J diag(N^2 |dt|) J^T + q^2 (|dt| / frame period) I``
      (the gyro's angle random walk mapped to pixels, plus a model-error term; the paper gives no Q);
    - eq (15): ``K = P- (P- + R)^-1`` (the paper writes the matrix inverse as a fraction),
      ``R = sigma^2 I`` (``measurement_sigma_px``, else the spot's ``sigma_px`` with
      ``model_sigma_px`` added in quadrature); a spot that carries a 2 x 2 position covariance ``C``
      that is not isotropic (``star_covariance``, and no ``measurement_sigma_px``) gets
      ``R = C + model_sigma_px^2 I`` (a smeared spot: long along the smear);
    - eq (16): ``x = x- + K (z - x-)``;
    - eq (17), Joseph form: ``P = (I - K) P- (I - K)^T + K R K^T`` (symmetric PSD by construction).

    New tracks (and tracks whose innovation exceeds ``gate_sigma`` or that were not updated within
    ``max_gap_s``) start at the measurement with ``P = R``. Output: ``x, y`` the filtered position,
    ``sigma_px = sqrt(trace(P) / 2)`` (and for the spots measured with their own 2 x 2 covariance
    ``cov_xx, cov_xy, cov_yy`` = ``P``; the others keep theirs, their ``P`` differs from isotropic only
    by the gyro term), ``vx, vy = J omega`` the image velocity from the held gyro rate at ``t_ns``
    (px/s). ``t_ns`` and ``row_time_ns`` are unchanged. ``J`` uses the frame's camera
    (:func:`~rollingstar.estimators.data.frame_camera`).
    """

    name = "gyro-kf"
    Params = GyroKfParams

    def setup(self, context) -> None:
        super().setup(context)
        timing = context.timing
        self._period_s = float(timing.frame_period_ns) * S_PER_NS
        self._exposure_ns = int(timing.exposure_ns)
        self._gyro = GyroIntegrator(self.params.gyro_bias_rad_s, default_period_s=self._period_s,
                                    keep_s=self.params.max_gap_s + 4 * self._period_s)
        self._ids = np.zeros(0, dtype=np.int64)  # sorted track keys
        self._x = np.zeros((0, 2))
        self._P = np.zeros((0, 2, 2))
        self._t = np.zeros(0, dtype=np.int64)  # reference instant (t_ns) of the estimate
        self._row = np.zeros(0, dtype=np.int64)  # exposure start of the estimate's row

    def _measurement_noise(self, stars) -> tuple[np.ndarray, np.ndarray]:
        """Each spot's measurement covariance (n, 2, 2) px^2, and which spots use their own 2 x 2 one."""
        p = self.params
        own = np.zeros(stars.n, dtype=bool)
        if p.measurement_sigma_px is not None:
            sig = np.full(stars.n, p.measurement_sigma_px)
        else:
            fallback = getattr(self.context, "centroid_sigma_px", None) or 0.1
            s = np.where(np.isfinite(stars.sigma_px) & (stars.sigma_px > 0), stars.sigma_px, fallback)
            sig = np.hypot(s, p.model_sigma_px)
        R = (sig**2)[:, None, None] * np.eye(2)
        if p.measurement_sigma_px is None and p.star_covariance and stars.n:
            cov = stars.position_covariance(fallback)
            own = ~is_isotropic(cov)  # the fallbacks are isotropic: these are the spots' own
            R[own] = cov[own] + p.model_sigma_px**2 * np.eye(2)
        return R, own

    def process(self, frame: FrameData) -> FrameData:
        self._gyro.add(frame.gyro)
        stars = frame.stars
        if stars is None or stars.n == 0:
            return frame.evolve()
        p = self.params
        cam = frame_camera(frame, self.context)
        sel = np.flatnonzero(stars.catalog_id >= 0)
        ids = stars.catalog_id[sel]
        z = np.column_stack([stars.x[sel], stars.y[sel]])
        t_now = stars.t_ns[sel]
        row_now = stars.row_time_ns[sel]
        R, own = self._measurement_noise(stars)
        R, own = R[sel], own[sel]

        pos = np.searchsorted(self._ids, ids)
        pos_c = np.minimum(pos, max(self._ids.size - 1, 0))
        exists = (self._ids[pos_c] == ids) if self._ids.size else np.zeros(ids.size, dtype=bool)
        has = exists.copy()
        has[exists] &= np.abs(t_now[exists] - self._t[pos_c[exists]]) * S_PER_NS <= p.max_gap_s
        k = pos_c[has]

        x_new = z.copy()
        P_new = R.copy()
        if k.size:
            if p.reference == "exposure_mean":
                dtheta = self._gyro.increment(self._row[k], row_now[has], self._exposure_ns)
            else:
                dtheta = self._gyro.increment(self._t[k], t_now[has])
            dt = np.abs(t_now[has] - self._t[k]) * S_PER_NS
            xo = self._x[k]
            J = star_motion_jacobian(xo[:, 0], xo[:, 1], cam)  # eq (8) at the previous estimate
            x_pred = xo + np.einsum("nij,nj->ni", J, dtheta)  # eq (13)
            Q = (p.gyro_arw_rad_sqrt_s**2) * dt[:, None, None] * np.einsum("nij,nkj->nik", J, J)
            Q = Q + (p.process_sigma_px**2 * dt / self._period_s)[:, None, None] * np.eye(2)
            P_pred = self._P[k] + Q  # eq (14)
            Rk = R[has]
            S = P_pred + Rk
            K = np.linalg.solve(S, P_pred.transpose(0, 2, 1)).transpose(0, 2, 1)  # eq (15): P- S^-1 (S symmetric)
            innov = z[has] - x_pred
            m2 = np.einsum("ni,ni->n", innov, np.linalg.solve(S, innov[..., None])[..., 0])
            x_upd = x_pred + np.einsum("nij,nj->ni", K, innov)  # eq (16)
            IK = np.eye(2) - K
            P_upd = IK @ P_pred @ IK.transpose(0, 2, 1) + K @ Rk @ K.transpose(0, 2, 1)  # eq (17), Joseph form
            P_upd = 0.5 * (P_upd + P_upd.transpose(0, 2, 1))
            ok = m2 <= p.gate_sigma**2
            idx = np.flatnonzero(has)
            x_new[idx[ok]] = x_upd[ok]
            P_new[idx[ok]] = P_upd[ok]

        # store tracks (replace / insert, keys kept sorted)
        keep = np.ones(self._ids.size, dtype=bool)
        keep[pos_c[exists]] = False
        all_ids = np.concatenate([self._ids[keep], ids])
        order = np.argsort(all_ids, kind="stable")
        self._ids = all_ids[order]
        self._x = np.concatenate([self._x[keep], x_new])[order]
        self._P = np.concatenate([self._P[keep], P_new])[order]
        self._t = np.concatenate([self._t[keep], t_now])[order]
        self._row = np.concatenate([self._row[keep], row_now])[order]
        if t_now.size:
            self._gyro.trim(int(t_now.min()))

        J_now = star_motion_jacobian(x_new[:, 0], x_new[:, 1], cam)
        vel = np.einsum("nij,nj->ni", J_now, self._gyro.rate_at(t_now))
        x = stars.x.copy()
        y = stars.y.copy()
        sigma = stars.sigma_px.copy()
        vx = stars.vx.copy()
        vy = stars.vy.copy()
        x[sel], y[sel] = x_new[:, 0], x_new[:, 1]
        sigma[sel] = np.sqrt(0.5 * np.trace(P_new, axis1=1, axis2=2))
        vx[sel], vy[sel] = vel[:, 0], vel[:, 1]
        cov = {k: getattr(stars, k).copy() for k in ("cov_xx", "cov_xy", "cov_yy")}
        for key, (i, j) in zip(cov, ((0, 0), (0, 1), (1, 1))):
            cov[key][sel[own]] = P_new[own, i, j]
        return frame.evolve(stars=stars.with_columns(x=x, y=y, sigma_px=sigma, vx=vx, vy=vy, **cov))

    def covariance(self, catalog_id: int) -> np.ndarray:
        """The current 2x2 covariance (px^2) of a track (for tests and diagnostics)."""
        i = int(np.searchsorted(self._ids, catalog_id))
        if i >= self._ids.size or self._ids[i] != catalog_id:
            raise KeyError(catalog_id)
        return self._P[i].copy()
