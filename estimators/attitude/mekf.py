"""Multiplicative extended Kalman filter (MEKF) of attitude and gyro bias, star by star.

Lefferts, Markley & Shuster, "Kalman filtering for spacecraft attitude estimation", J. Guidance
5(5):417-429, 1982; Markley & Crassidis, "Fundamentals of Spacecraft Attitude Determination and
Control", Springer 2014, sec. 6.4.4 (discrete propagation) and sec. 7.2 (MEKF). The on-board
baseline the smoother (``gtsam``) is compared with.

Hand-written with numpy rather than filterpy: filterpy's ``KalmanFilter``/``ExtendedKalmanFilter``
keep an additive state vector ``x += K y``; the MEKF's attitude lives on SO(3) and is reset
multiplicatively after every update (``R <- R Exp(dtheta)``, error state set back to zero), and its
transition matrix is rebuilt for every (irregular) star time, so filterpy would only contribute the
three lines of the Kalman gain and Joseph update while forcing a state layout it does not model.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import block_diag
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.base import AttitudeSolver
from rollingstar.estimators.attitude.motion_model import (
    MotionModelParams,
    motion_noise,
    resolve_mode,
)
from rollingstar.estimators.attitude.observations import (
    star_observations,
    tangent_basis,
)
from rollingstar.estimators.attitude.robust import apply_robust
from rollingstar.estimators.attitude.wahba import quest, quest_covariance, refine_attitude
from rollingstar.estimators.data import AttitudeEstimate, FrameData, RateEstimate, default_sigma_px, frame_camera
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.gyro import GyroIntegrator
from rollingstar.sensors.so3 import skew

__all__ = ["MekfFilter", "MekfParams", "propagation_matrices", "star_update"]


class MekfParams(MotionModelParams):
    pass


def propagation_matrices(theta: np.ndarray, dt: float, sigma_v: float, sigma_u: float) -> tuple[np.ndarray, np.ndarray]:
    """Error-state transition ``Phi`` and process noise ``Q`` (6x6) over ``dt`` seconds (may be < 0).

    Error state ``x = [dtheta, dbeta]`` with truth ``R_true = R Exp(dtheta)``, ``beta_true = beta +
    dbeta`` and kinematics ``R' = R Exp((u - beta) dt)``, i.e. ``dtheta' = -[w x] dtheta - dbeta - eta_v``,
    ``dbeta' = eta_u`` (Markley & Crassidis eqs 6.81-6.93, 7.37-7.41)::

        Phi = [[Exp(theta)^T, -dt I], [0, I]]        (theta = (u - beta) dt, the step's rotation;
                                                      -J_r(theta) dt ~ -dt I as |theta| << 1)
        Q   = [[sv^2 |dt| + su^2 |dt|^3 / 3, -su^2 dt |dt| / 2], [., su^2 |dt| I]]

    (Farrenkopf's discrete noise; the sign of the cross term follows the direction of time.)
    """
    Phi = np.eye(6)
    Phi[:3, :3] = Rotation.from_rotvec(theta).as_matrix().T
    Phi[:3, 3:] = -dt * np.eye(3)
    a = abs(dt)
    Q = np.zeros((6, 6))
    Q[:3, :3] = (sigma_v**2 * a + sigma_u**2 * a**3 / 3.0) * np.eye(3)
    Q[:3, 3:] = Q[3:, :3] = -0.5 * sigma_u**2 * dt * a * np.eye(3)
    Q[3:, 3:] = sigma_u**2 * a * np.eye(3)
    return Phi, Q


def star_update(R: Rotation, P: np.ndarray, body: np.ndarray, ref: np.ndarray, sigma_rad: np.ndarray,
                cov_rad2: np.ndarray | None = None):
    """One MEKF measurement update with the m stars of one state (Markley & Crassidis sec. 7.2.3).

    Predicted camera vector ``b^ = R^T r``; the truth ``R Exp(dtheta)`` sees ``b^ + [b^ x] dtheta``.
    Each star is measured in the plane perpendicular to its measured vector ``b`` (two components,
    basis ``E = tangent_basis(b)``, 1-sigma ``sigma`` each, the QUEST measurement model), so
    ``z = E^T (b - b^)``, ``H = [E^T [b^ x], 0]`` (2m x 6), ``R_z = diag(sigma^2)``; with ``cov_rad2``
    (m, 2, 2), each star's tangent-plane covariance in that basis
    (:mod:`rollingstar.estimators.attitude.star_covariance`), ``R_z`` is block diagonal with those
    blocks instead. Gain ``K = P H^T (H P H^T + R_z)^-1``, correction ``dx = K z``, Joseph-form
    covariance ``(I - K H) P (I - K H)^T + K R_z K^T``. Returns the error-state correction ``dx`` (6,),
    the updated covariance and the normalised innovation squared ``z^T S^-1 z``.
    """
    pred = R.inv().apply(ref)  # (m, 3)
    E = tangent_basis(body)  # (m, 3, 2)
    z = np.einsum("mik,mi->mk", E, body - pred).reshape(-1)
    H = np.zeros((z.size, 6))
    H[:, :3] = np.einsum("mik,mij->mkj", E, skew(pred)).reshape(-1, 3)
    if cov_rad2 is None:
        Rz = np.repeat(np.asarray(sigma_rad, dtype=float) ** 2, 2)
        S = H @ P @ H.T + np.diag(Rz)
    else:
        Rz = block_diag(*np.asarray(cov_rad2, dtype=float))
        S = H @ P @ H.T + Rz
    PHt = P @ H.T
    K = np.linalg.solve(S, PHt.T).T
    dx = K @ z
    IKH = np.eye(6) - K @ H
    P_new = IKH @ P @ IKH.T + ((K * Rz) @ K.T if cov_rad2 is None else K @ Rz @ K.T)
    nis = float(z @ np.linalg.solve(S, z))
    return dx, 0.5 * (P_new + P_new.T), nis


class MekfFilter(AttitudeSolver):
    """Multiplicative EKF (Lefferts-Markley-Shuster 1982): attitude error and gyro bias, every star
    at its own (row) time.

    State: the camera-to-ICRS attitude ``R`` (kept as a rotation; the filter estimates the small
    error ``dtheta``, ``R_true = R Exp(dtheta)``, and resets it after every update) and ``beta``, the
    gyro bias (``motion_model`` gyro) or minus the body rate (constant_rate), see
    :mod:`rollingstar.estimators.attitude.motion_model`. Per frame:

    1. gyro samples are added to a zero-order-hold integrator (:class:`GyroIntegrator`); the
       samples of a frame's rows arrive with the next frame, so a propagation beyond the newest
       sample holds it, and the filter adds the held sample's noise ``(N^2 / T_s) h^2`` over the
       held span ``h`` (``T_s`` the sample period) to ``Q``;
    2. the identified stars are sorted by time and grouped into states (:mod:`observations`;
       default one per star on a rolling-shutter frame); for each state in time order: propagate
       ``R <- R Exp((u - beta) dt)``, ``P <- Phi P Phi^T + Q`` (:func:`propagation_matrices`), then
       update with its stars (:func:`star_update`) and reset;
    3. one :class:`AttitudeEstimate` per state at the state's time, with the attitude block of
       ``P`` as ``covariance_rad2`` and (gyro model) ``beta`` as ``gyro_bias_rad_s``; when no
       earlier stage set ``frame.rate``, the rate ``u - beta`` at the last state with its covariance.

    Initialisation: QUEST (:func:`wahba.quest`) on the first frame with two non-collinear stars
    gives the attitude at the stars' weighted-mean time ``t_q`` (to first order in the rate) with
    Shuster's covariance (refined with the stars' 2 x 2 covariances when they carry anisotropic ones,
    :func:`wahba.refine_attitude`, as the ``quest`` solver does), and ``beta = 0`` with the prior
    sigma of the motion model. Stars are unprojected with the frame's camera
    (:func:`~rollingstar.estimators.data.frame_camera`). That frame's
    estimates are this solution propagated from ``t_q`` to each state (covariance
    ``Phi P0 Phi^T + Q``, which carries the rate uncertainty); its stars are not fused a second
    time. From the next frame on, every state is propagated and updated in time order (the
    sequential loop over states is inherent to a filter: each update depends on the last).
    Frames without identified stars give an invalid estimate with the reason; the filter keeps
    propagating from its last state at the next frame.
    """

    name = "mekf"
    Params = MekfParams
    provides = frozenset({"attitude", "rate"})

    def setup(self, context) -> None:
        super().setup(context)
        self._sigma_px = default_sigma_px(self.params.sigma_px, context)
        self._merge_ns = int(round(self.params.merge_us * 1e3))
        self._gyro = GyroIntegrator(keep_s=10.0)
        self._mode: str | None = None
        self._noise = None
        self._R: Rotation | None = None
        self._beta = np.zeros(3)
        self._P = np.zeros((6, 6))
        self._t: int | None = None
        self._held_ns = 0  # span already propagated past the newest gyro sample
        self._t_last_sample: int | None = None
        self.nis: list[float] = []  # normalised innovation squared of every update (consistency checks)

    # ---------------------------------------------------------------- propagation
    def _sample_period_s(self) -> float:
        tau = self._gyro.tau
        return float(np.median(np.diff(tau))) if tau.size > 1 else self._gyro.default_period_s

    def _propagate(self, t_ns: int) -> None:
        dt = (t_ns - self._t) * S_PER_NS
        if dt == 0.0:
            return
        n = self._noise
        if self._mode == "gyro":
            theta = self._gyro.increment(np.int64(self._t), np.int64(t_ns)) - self._beta * dt
        else:
            theta = -self._beta * dt
        Phi, Q = propagation_matrices(theta, dt, n.sigma_v, n.sigma_u)
        if self._mode == "gyro" and self._t_last_sample is not None:
            # Held gyro sample beyond the newest one: its white noise N / sqrt(T_s) acts over the
            # whole held span h, variance (N^2 / T_s) h^2; add the increase of that variance.
            h_old = self._held_ns if self._t > self._t_last_sample else 0
            h_new = h_old + max(0, t_ns - max(self._t_last_sample, self._t))
            extra = n.sigma_v**2 / self._sample_period_s() * ((h_new * S_PER_NS) ** 2 - (h_old * S_PER_NS) ** 2)
            Q[:3, :3] += max(extra, 0.0) * np.eye(3)
            self._held_ns = h_new
        self._R = self._R * Rotation.from_rotvec(theta)
        P = Phi @ self._P @ Phi.T + Q
        self._P = 0.5 * (P + P.T)
        self._t = int(t_ns)

    def _initialise(self, obs) -> str:
        a = 1.0 / obs.sigma_rad**2
        res = quest(obs.ref[None], obs.body[None], a[None])
        if not res.valid[0]:
            return "filter not initialised: the frame's stars do not fix all three axes (fewer than 2 or collinear)"
        q, cov = res.q_xyzw[0], quest_covariance(obs.body[None], a[None])[0]
        if obs.direction is not None:  # 2 x 2 star covariances: QUEST refined with them (as the quest solver)
            d = obs.direction
            q, cov = refine_attitude(q, obs.ref, d.body, d.basis, d.info)
        base = int(obs.t_ns[0])
        self._t = base + int(np.rint(np.sum(a * (obs.t_ns - base)) / np.sum(a)))
        self._R = Rotation.from_quat(q)
        self._beta = np.zeros(3)
        self._P = np.zeros((6, 6))
        self._P[:3, :3] = cov
        self._P[3:, 3:] = self._noise.beta_sigma**2 * np.eye(3)
        return ""

    def _initial_estimates(self, obs, counts) -> list[AttitudeEstimate]:
        """The initial QUEST solution propagated to each state of its own frame (no update)."""
        R0, P0, t0, h0 = self._R, self._P, self._t, self._held_ns
        ests = []
        for j, t in enumerate(obs.state_t_ns):
            self._R, self._P, self._t, self._held_ns = R0, P0, t0, h0
            self._propagate(int(t))
            ests.append(self._estimate(int(t), int(counts[j])))
        return ests

    def _estimate(self, t_ns: int, n: int) -> AttitudeEstimate:
        return AttitudeEstimate(t_ns=t_ns, q_xyzw=self._R.as_quat(canonical=True), n_stars=n,
                                covariance_rad2=self._P[:3, :3].copy(),
                                gyro_bias_rad_s=self._beta.copy() if self._mode == "gyro" else None)

    # ---------------------------------------------------------------- the plugin
    def process(self, frame: FrameData) -> FrameData:
        if frame.gyro.t_ns.size:
            self._gyro.add(frame.gyro)
            self._t_last_sample = int(self._gyro.origin_ns + round(self._gyro.tau[-1] / S_PER_NS))
            self._held_ns = 0
        p = self.params
        camera = frame_camera(frame, self.context)
        frame = apply_robust(frame, camera, p, self._sigma_px, p.use_star_sigma, p.star_covariance)
        obs, dropped = star_observations(frame.stars, camera, self._sigma_px, p.use_star_sigma, self._merge_ns,
                                         p.star_covariance)
        t_frame = int(self.context.timing.frame_reference_ns(frame.t0_ns))
        if obs.n == 0:
            why = "no identified stars" + (f" ({dropped} with non-finite position or reference)" if dropped else "")
            return self._invalid(frame, [t_frame], [0], why)
        if self._mode is None:
            self._mode = resolve_mode(self.params, not self._gyro.empty)
            self._noise = motion_noise(self.params, self._mode)
        counts = np.bincount(obs.state_of, minlength=obs.n_states)
        if self._mode == "gyro" and self._gyro.empty:
            return self._invalid(frame, obs.state_t_ns, counts, "motion_model gyro: no gyro samples received")
        if self._R is None:
            why = self._initialise(obs)
            if why:
                return self._invalid(frame, obs.state_t_ns, counts, why)
            ests = self._initial_estimates(obs, counts)
        else:
            ests = []
            for j, sl in enumerate(obs.state_slices()):  # sequential by nature (see class docstring)
                self._propagate(int(obs.state_t_ns[j]))
                cov = None if obs.direction is None else obs.direction.cov[sl]
                dx, self._P, nis = star_update(self._R, self._P, obs.body[sl], obs.ref[sl], obs.sigma_rad[sl], cov)
                self.nis.append(nis)
                self._R = self._R * Rotation.from_rotvec(dx[:3])
                self._beta = self._beta + dx[3:]
                ests.append(self._estimate(int(obs.state_t_ns[j]), int(counts[j])))
        out = frame.evolve(attitudes=frame.attitudes + tuple(ests))
        if out.rate is None:
            u = self._gyro.rate_at(np.int64(self._t)) if self._mode == "gyro" else np.zeros(3)
            out = out.evolve(rate=RateEstimate(t_ns=int(self._t), omega_rad_s=u - self._beta,
                                               covariance=self._P[3:, 3:].copy()))
        return out

    @staticmethod
    def _invalid(frame: FrameData, times, counts, reason: str) -> FrameData:
        ests = tuple(AttitudeEstimate.invalid(int(t), int(c), reason) for t, c in zip(times, counts))
        return frame.evolve(attitudes=frame.attitudes + ests, flags=frame.flags + ("attitude_invalid",))
