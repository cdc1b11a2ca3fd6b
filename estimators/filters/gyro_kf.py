"""Gyro-driven Kalman filter of star-spot positions (liu2013 eqs 8-17), batched over stars.

Shared helpers (also used by the ``windowed`` centroider):

- :class:`GyroIntegrator`: the attitude-angle increment from gyro samples between two times
  (rate-integrating samples, zero-order hold) and the increment of its exposure-window mean.
- :func:`star_motion_jacobian`: liu2013 eq (8) derived for *our* camera convention.

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

from rollingstar.estimators.data import FrameData, GyroSamples
from rollingstar.estimators.filters.base import StarMotionFilter

NS = 1e-9


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


class GyroIntegrator:
    """Body-angle history from gyro samples, for increments between arbitrary times.

    Sample ``i`` at ``t_i`` holds the mean rate over ``(t_{i-1}, t_i]`` (a rate-integrating gyro,
    see :mod:`rollingstar.sensors.gyro`); the first sample's interval length is taken from the next spacing
    (or ``default_period_s``). Minus the known bias, the rates are held constant over their
    intervals (zero-order hold) and also extrapolated beyond the first/last sample, so the angle
    ``Theta(t) = int omega`` is piecewise linear and its integral ``Psi(t)`` piecewise quadratic;
    both are exact for the held rates. Angles are summed as rotation vectors (small-angle: the
    rotation over one frame is arcseconds here; the Jacobian is first order anyway).
    """

    def __init__(self, bias_rad_s=(0.0, 0.0, 0.0), default_period_s: float = 0.01, keep_s: float = 2.0):
        self.bias = np.asarray(bias_rad_s, dtype=float).reshape(3)
        self.default_period_s = float(default_period_s)
        self.keep_ns = int(keep_s / NS)
        self.origin_ns: int | None = None
        self.tau = np.zeros(0)  # knot times (s from origin), m + 1 of them
        self.rate = np.zeros((0, 3))  # m held rates, rate[j] on (tau[j], tau[j + 1]]
        self.theta = np.zeros((0, 3))  # Theta at the knots
        self.psi = np.zeros((0, 3))  # Psi at the knots

    def add(self, samples: GyroSamples) -> None:
        """Append samples (times must increase past the last one; older ones are ignored)."""
        t = np.asarray(samples.t_ns, dtype=np.int64)
        if t.size == 0:
            return
        w = np.asarray(samples.omega_rad_s, dtype=float).reshape(-1, 3) - self.bias
        if self.origin_ns is None:
            self.origin_ns = int(t[0])
        ts = (t - self.origin_ns) * NS
        if self.tau.size:
            keep = ts > self.tau[-1]
            ts, w = ts[keep], w[keep]
            if ts.size == 0:
                return
            knots = np.concatenate([[self.tau[-1]], ts])
        else:
            first = ts[1] - ts[0] if ts.size > 1 else self.default_period_s
            knots = np.concatenate([[ts[0] - first], ts])
            self.tau = knots[:1]
            self.theta = np.zeros((1, 3))
            self.psi = np.zeros((1, 3))
        dt = np.diff(knots)[:, None]
        d_theta = np.cumsum(w * dt, axis=0)
        theta = self.theta[-1] + np.vstack([np.zeros((1, 3)), d_theta])
        # Psi(t_j) - Psi(t_{j-1}) = Theta(t_{j-1}) dt + omega dt^2 / 2
        d_psi = np.cumsum(theta[:-1] * dt + 0.5 * w * dt * dt, axis=0)
        self.tau = np.concatenate([self.tau, knots[1:]])
        self.rate = np.vstack([self.rate, w])
        self.theta = np.vstack([self.theta, theta[1:]])
        self.psi = np.vstack([self.psi, self.psi[-1] + d_psi])

    def trim(self, before_ns: int) -> None:
        """Forget intervals ending before ``before_ns - keep_s`` (Theta/Psi stay consistent)."""
        if self.origin_ns is None or self.rate.shape[0] < 2:
            return
        cut = (before_ns - self.origin_ns - self.keep_ns) * NS
        j = int(np.searchsorted(self.tau, cut)) - 1
        j = min(max(j, 0), self.rate.shape[0] - 1)
        if j > 0:
            self.tau, self.theta, self.psi, self.rate = self.tau[j:], self.theta[j:], self.psi[j:], self.rate[j:]

    @property
    def empty(self) -> bool:
        return self.rate.shape[0] == 0

    def _locate(self, t_ns):
        ts = (np.asarray(t_ns, dtype=np.int64) - (self.origin_ns or 0)) * NS
        j = np.clip(np.searchsorted(self.tau, ts, side="left"), 1, self.rate.shape[0]) - 1
        return j, (ts - self.tau[j])[..., None]

    def angle(self, t_ns) -> np.ndarray:
        """``Theta(t)`` (..., 3) rad; zeros when no sample was ever added."""
        t = np.asarray(t_ns)
        if self.empty:
            return np.zeros(t.shape + (3,))
        j, h = self._locate(t)
        return self.theta[j] + self.rate[j] * h

    def integral(self, t_ns) -> np.ndarray:
        """``Psi(t) = int Theta`` (..., 3) rad s."""
        t = np.asarray(t_ns)
        if self.empty:
            return np.zeros(t.shape + (3,))
        j, h = self._locate(t)
        return self.psi[j] + self.theta[j] * h + 0.5 * self.rate[j] * h * h

    def rate_at(self, t_ns) -> np.ndarray:
        """Held gyro rate (bias removed) at ``t`` (..., 3) rad/s."""
        t = np.asarray(t_ns)
        if self.empty:
            return np.zeros(t.shape + (3,))
        j, _ = self._locate(t)
        return self.rate[j]

    def window_mean(self, start_ns, exposure_ns: int) -> np.ndarray:
        """Mean of ``Theta`` over ``[start, start + exposure]``: ``(Psi(b) - Psi(a)) / exposure``."""
        start = np.asarray(start_ns, dtype=np.int64)
        return (self.integral(start + np.int64(exposure_ns)) - self.integral(start)) / (exposure_ns * NS)

    def increment(self, t_from, t_to, exposure_ns: int | None = None) -> np.ndarray:
        """Body angle increment (..., 3) rad between two instants (``exposure_ns`` None), or between
        the means over two exposure windows starting at ``t_from`` / ``t_to`` (the quantity that
        moves a smeared spot's centre of gravity)."""
        if exposure_ns is None:
            return self.angle(t_to) - self.angle(t_from)
        # the two window means of window_mean, from one integral() call on the four instants
        a, b = np.broadcast_arrays(np.asarray(t_from, dtype=np.int64), np.asarray(t_to, dtype=np.int64))
        e = np.int64(exposure_ns)
        P = self.integral(np.stack([b + e, b, a + e, a]))
        return ((P[0] - P[1]) - (P[2] - P[3])) / (exposure_ns * NS)


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
      ``model_sigma_px`` added in quadrature);
    - eq (16): ``x = x- + K (z - x-)``;
    - eq (17), Joseph form: ``P = (I - K) P- (I - K)^T + K R K^T`` (symmetric PSD by construction).

    New tracks (and tracks whose innovation exceeds ``gate_sigma`` or that were not updated within
    ``max_gap_s``) start at the measurement with ``P = R``. Output: ``x, y`` the filtered position,
    ``sigma_px = sqrt(trace(P) / 2)``, ``vx, vy = J omega`` the image velocity from the held gyro
    rate at ``t_ns`` (px/s). ``t_ns`` and ``row_time_ns`` are unchanged.
    """

    name = "gyro-kf"
    Params = GyroKfParams

    def setup(self, context) -> None:
        super().setup(context)
        timing = context.timing
        self._period_s = float(timing.frame_period_ns) * NS
        self._exposure_ns = int(timing.exposure_ns)
        self._gyro = GyroIntegrator(self.params.gyro_bias_rad_s, default_period_s=self._period_s,
                                    keep_s=self.params.max_gap_s + 4 * self._period_s)
        self._ids = np.zeros(0, dtype=np.int64)  # sorted track keys
        self._x = np.zeros((0, 2))
        self._P = np.zeros((0, 2, 2))
        self._t = np.zeros(0, dtype=np.int64)  # reference instant (t_ns) of the estimate
        self._row = np.zeros(0, dtype=np.int64)  # exposure start of the estimate's row

    def _measurement_sigma(self, stars) -> np.ndarray:
        if self.params.measurement_sigma_px is not None:
            return np.full(stars.n, self.params.measurement_sigma_px)
        fallback = getattr(self.context, "centroid_sigma_px", None) or 0.1
        s = np.where(np.isfinite(stars.sigma_px) & (stars.sigma_px > 0), stars.sigma_px, fallback)
        return np.hypot(s, self.params.model_sigma_px)

    def process(self, frame: FrameData) -> FrameData:
        self._gyro.add(frame.gyro)
        stars = frame.stars
        if stars is None or stars.n == 0:
            return frame.evolve()
        p = self.params
        cam = self.context.camera
        sel = np.flatnonzero(stars.catalog_id >= 0)
        ids = stars.catalog_id[sel]
        z = np.column_stack([stars.x[sel], stars.y[sel]])
        t_now = stars.t_ns[sel]
        row_now = stars.row_time_ns[sel]
        sig = self._measurement_sigma(stars)[sel]
        R = (sig**2)[:, None, None] * np.eye(2)

        pos = np.searchsorted(self._ids, ids)
        pos_c = np.minimum(pos, max(self._ids.size - 1, 0))
        exists = (self._ids[pos_c] == ids) if self._ids.size else np.zeros(ids.size, dtype=bool)
        has = exists.copy()
        has[exists] &= np.abs(t_now[exists] - self._t[pos_c[exists]]) * NS <= p.max_gap_s
        k = pos_c[has]

        x_new = z.copy()
        P_new = R.copy()
        if k.size:
            if p.reference == "exposure_mean":
                dtheta = self._gyro.increment(self._row[k], row_now[has], self._exposure_ns)
            else:
                dtheta = self._gyro.increment(self._t[k], t_now[has])
            dt = np.abs(t_now[has] - self._t[k]) * NS
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
        return frame.evolve(stars=stars.with_columns(x=x, y=y, sigma_px=sigma, vx=vx, vy=vy))

    def covariance(self, catalog_id: int) -> np.ndarray:
        """The current 2x2 covariance (px^2) of a track (for tests and diagnostics)."""
        i = int(np.searchsorted(self._ids, catalog_id))
        if i >= self._ids.size or self._ids[i] != catalog_id:
            raise KeyError(catalog_id)
        return self._P[i].copy()
