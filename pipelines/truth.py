"""Truth carried in a log, evaluable at any time, and the true image position of a star then."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


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
        return (np.asarray(t_ns, dtype=np.int64) - self.t_ns[0]).astype(float) * 1e-9

    def covers(self, t_ns) -> np.ndarray:
        t = np.asarray(t_ns, dtype=np.int64)
        return (t >= self.t_ns[0]) & (t <= self.t_ns[-1])

    def attitude(self, t_ns) -> Rotation:
        """Truth at ``t_ns`` (must be covered: check with :meth:`covers`)."""
        return self._slerp(self._rel(t_ns))

    def angular_velocity(self, t_ns) -> np.ndarray:
        s = self._rel(t_ns)
        ref = self._rel(self.t_ns)
        return np.stack([np.interp(s, ref, self.omega[:, i], left=np.nan, right=np.nan) for i in range(3)], axis=-1)


def true_positions(camera, effects, attitude: Rotation, unit_icrs: np.ndarray, t_ns: np.ndarray):
    """Where catalogue directions image at ``t_ns`` (one attitude per star), effects included."""
    w = attitude.inv().apply(unit_icrs)
    x, y, _ = camera.project(w)
    for effect in effects:
        x, y = effect.apply(x, y, t_ns, camera)
    return x, y


def attitude_crb_rad2(camera, w_cam: np.ndarray, sigma_px: float) -> np.ndarray:
    """Cramér–Rao bound on the camera-frame attitude error for one frame's stars (3x3, rad^2).

    Pixel noise is Gaussian, isotropic, ``sigma_px`` per axis. For a small error rotation
    ``R_est = R Exp(d)`` a star's camera vector becomes ``w + [w]x d`` so its pixel Jacobian is
    ``J = P(w) [w]x`` (P: projection Jacobian) and the Fisher information is
    ``F = sum J^T J / sigma^2``; the bound is ``F^-1`` (pseudo-inverse when singular).
    """
    w = np.asarray(w_cam, dtype=float)
    skew = np.zeros(w.shape[:-1] + (3, 3))
    skew[..., 0, 1], skew[..., 0, 2] = -w[..., 2], w[..., 1]
    skew[..., 1, 0], skew[..., 1, 2] = w[..., 2], -w[..., 0]
    skew[..., 2, 0], skew[..., 2, 1] = -w[..., 1], w[..., 0]
    jac = camera.projection_jacobian(w) @ skew
    fisher = np.einsum("nki,nkj->ij", jac, jac) / sigma_px**2
    return np.linalg.pinv(fisher)
