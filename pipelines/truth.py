"""Truth carried in a log, evaluable at any time, and the true image position of a star then."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from rollingstar.sensors.conventions import S_PER_NS, attitude_from_opencv
from rollingstar.sensors.effects.chain import predict
from rollingstar.sensors.effects.context import context_from_attitude
from rollingstar.sensors.pixel_crb import FrameDetector, frame_crb
from rollingstar.sensors.so3 import skew


class TruthTrajectory:
    """Attitude and body rate from ``/truth/attitude`` samples, interpolated at any time.

    Attitude: spherical linear interpolation between samples (exact for constant rate between
    samples); body rate: linear interpolation. Times outside the samples give NaN.
    """

    def __init__(self, t_ns: np.ndarray, q_xyzw: np.ndarray, omega_rad_s: np.ndarray):
        order = np.argsort(t_ns, kind="stable")
        t = np.asarray(t_ns, dtype=np.int64)[order]
        keep = np.concatenate([[True], np.diff(t) > 0])
        self.t_ns = t[keep]
        self.q = np.asarray(q_xyzw, dtype=float)[order][keep]
        self.omega = np.asarray(omega_rad_s, dtype=float)[order][keep]
        if len(self.t_ns) < 2:
            raise ValueError("truth needs at least two attitude samples")
        self._slerp = Slerp(self._rel(self.t_ns), Rotation.from_quat(self.q))

    def _rel(self, t_ns) -> np.ndarray:
        return (np.asarray(t_ns, dtype=np.int64) - self.t_ns[0]).astype(float) * S_PER_NS

    def covers(self, t_ns) -> np.ndarray:
        t = np.asarray(t_ns, dtype=np.int64)
        return (t >= self.t_ns[0]) & (t <= self.t_ns[-1])

    def attitude(self, t_ns) -> Rotation:
        """Truth at ``t_ns`` (must be covered: check with :meth:`covers`)."""
        return self._slerp(self._rel(t_ns))

    def other_readings(self) -> dict[str, "TruthTrajectory"]:
        """The same samples read in the conventions a log written elsewhere may have used instead of
        ours (docs/conventions.md), each described in words: the inverse rotation (ICRS to
        camera), the OpenCV camera frame, both, and the quaternion's scalar written first."""
        R = Rotation.from_quat(self.q)
        readings = {
            "as the ICRS-to-camera rotation (the inverse of ours)": R.inv(),
            "in the OpenCV camera frame (+x towards increasing column, +y towards increasing row)": attitude_from_opencv(R),
            "as the ICRS-to-camera rotation in the OpenCV camera frame": attitude_from_opencv(R.inv()),
            "with the quaternion's scalar first (w, x, y, z written into the fields x, y, z, w)":
                Rotation.from_quat(np.roll(self.q, -1, axis=1)),
        }
        return {k: TruthTrajectory(self.t_ns, r.as_quat(), self.omega) for k, r in readings.items()}

    def angular_velocity(self, t_ns) -> np.ndarray:
        s = self._rel(t_ns)
        ref = self._rel(self.t_ns)
        return np.stack([np.interp(s, ref, self.omega[:, i], left=np.nan, right=np.nan) for i in range(3)], axis=-1)


def true_positions(camera, effects, attitude: Rotation, unit_icrs: np.ndarray, t_ns: np.ndarray,
                   omega_rad_s=None, **context):
    """Where catalogue directions image at ``t_ns`` (one attitude per star), effects included.

    The effects are applied by :func:`rollingstar.sensors.effects.chain.predict` on the context built from the
    attitude (:func:`rollingstar.sensors.effects.context.context_from_attitude`): pass the body rate
    ``omega_rad_s`` (n, 3) for time effects and any other context field they need in ``context``.
    """
    if not effects:
        x, y, _ = camera.project(attitude.inv().apply(np.array(unit_icrs, dtype=float)))
        return x, y
    ctx = context_from_attitude(camera, attitude, unit_icrs, t_ns, omega_rad_s, **context)
    return predict(effects, ctx)


def attitude_crb_rad2(camera, w_cam: np.ndarray, sigma_px: float) -> np.ndarray:
    """Cramér–Rao bound on the camera-frame attitude error for one frame's stars (3x3, rad^2).

    Pixel noise is Gaussian, isotropic, ``sigma_px`` per axis. For a small error rotation
    ``R_est = R Exp(d)`` a star's camera vector becomes ``w + [w]x d`` so its pixel Jacobian is
    ``J = P(w) [w]x`` (P: projection Jacobian) and the Fisher information is
    ``F = sum J^T J / sigma^2``; the bound is ``F^-1`` (pseudo-inverse when singular).
    """
    w = np.asarray(w_cam, dtype=float)
    jac = camera.projection_jacobian(w) @ skew(w)
    fisher = np.einsum("nki,nkj->ij", jac, jac) / sigma_px**2
    return np.linalg.pinv(fisher)


def rate_crb_rad2(camera, w_cam: np.ndarray, dt_s: np.ndarray, sigma_px, timing_sigma_s: float = 0.0,
                  omega_rad_s: np.ndarray | None = None) -> np.ndarray:
    """Single-frame Cramér–Rao bound on the body rate from one rolling-shutter frame's stars (3x3, (rad/s)^2).

    Star ``i`` is imaged at its own time ``t_i = t_ref + dt_i``; with constant rate over the frame
    its attitude is ``R_ref Exp(delta + omega dt_i)``, so a perturbation ``(delta, eps)`` of the
    reference attitude and the rate moves its camera vector by ``[w]x (delta + eps dt_i)``: pixel
    Jacobian ``J_i = P(w_i) [w_i]x [I, dt_i I]`` (2 x 6, P the projection Jacobian). Fisher
    information ``F = sum J_i^T S_i^-1 J_i`` with the pixel covariance
    ``S_i = sigma_i^2 I + timing_sigma^2 v_i v_i^T`` (a row-time error moves the star along its
    image velocity ``v_i = P(w_i) (w_i x omega)``; ``timing_sigma_s`` 0 = row times known exactly,
    as in the simulator). The attitude is a nuisance: the bound is the rate block of ``F^-1``
    (pseudo-inverse when singular, e.g. all stars at one time: no rate information). The row-time
    spread is what makes the rate observable at all; shifting every ``dt_i`` by a constant
    re-labels ``delta`` and leaves the rate block unchanged.
    """
    return joint_crb_rad2(camera, w_cam, dt_s, sigma_px, timing_sigma_s, omega_rad_s)[3:, 3:]


def joint_crb_rad2(camera, w_cam: np.ndarray, dt_s: np.ndarray, sigma_px, timing_sigma_s: float = 0.0,
                   omega_rad_s: np.ndarray | None = None) -> np.ndarray:
    """The joint single-frame bound of :func:`rate_crb_rad2` (6x6: attitude at ``dt = 0``, then the
    rate; rad^2, (rad/s)^2). Its attitude block is the bound on the attitude at the time ``dt = 0``
    when the rate is unknown too."""
    w = np.asarray(w_cam, dtype=float)
    dt = np.asarray(dt_s, dtype=float)
    n = w.shape[0]
    P = camera.projection_jacobian(w)  # (n, 2, 3)
    A = P @ skew(w)  # (n, 2, 3)
    jac = np.concatenate([A, A * dt[:, None, None]], axis=-1)  # (n, 2, 6)
    sig = np.broadcast_to(np.asarray(sigma_px, dtype=float), (n,))
    S = sig[:, None, None] ** 2 * np.eye(2)
    if timing_sigma_s > 0.0 and omega_rad_s is not None:
        v = np.einsum("nij,nj->ni", P, np.cross(w, np.asarray(omega_rad_s, dtype=float)))
        S = S + timing_sigma_s**2 * v[:, :, None] * v[:, None, :]
    fisher = np.einsum("nki,nkl,nlj->ij", jac, np.linalg.inv(S), jac)
    return np.linalg.pinv(fisher)


def pixel_frame_crb_rad2(camera, det: FrameDetector, truth: TruthTrajectory, t_ref_ns: int, t0_ns: int,
                         unit_icrs: np.ndarray, electrons: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-level Cramér–Rao bounds of one frame (row 0 starting at ``t0_ns``) on the attitude at
    ``t_ref_ns`` (3x3, rad^2) and the body rate (3x3, (rad/s)^2), both unknown, from the pixels of
    the stars ``unit_icrs`` (n, 3) with ``electrons`` (n,) each
    (:func:`rollingstar.sensors.pixel_crb.frame_crb`, linearised at the truth at ``t_ref_ns`` with
    the rate held constant over the frame). The stars are imaged through the camera alone: the
    scenario's effects move them by far less than they change the bound.
    """
    cov = frame_crb(camera, truth.attitude(t_ref_ns), truth.angular_velocity(t_ref_ns), unit_icrs, electrons,
                    (int(t0_ns) - int(t_ref_ns)) * S_PER_NS, det)
    return cov[:3, :3], cov[3:, 3:]
