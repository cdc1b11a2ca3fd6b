"""Second residual channel: star-derived attitude increments against gyro-integrated increments.

Effects that leave no image-plane trace after the per-frame attitude refit (a gyro bias or scale
error, a camera clock offset, a centroid bias along the streak that is a rigid rotation of each
frame) still change the *attitude sequence* relative to an independent rate reference. With a
gyro logged alongside the frames, for every pair of consecutive frames ``(k, k+1)`` (both in the
training set)::

    S_k = R_k^T R_{k+1}                                    (star-derived increment, fitted attitudes)
    G_k = prod_j Exp(omega_j' dt_jk)                       (gyro increment over [t_ref,k, t_ref,k+1])
    e_k = log(G_k^T S_k)                                   (rad, body frame of frame k)

where ``omega_j'`` are the gyro samples corrected by the model's gyro effects (first order:
``omega' = omega - (g(omega) - omega)`` with ``g`` = :func:`rollingstar.sensors.effects.chain.apply_gyro`)
and ``dt_jk`` the overlap of sample ``j``'s interval ``(t_{j-1}, t_j]`` (interval-average rates,
:mod:`rollingstar.sensors.gyro`) with the window.

Noise. To first order ``e_k = delta_{k+1} - delta_k + n_k``: the attitude errors ``delta`` of the
image fit (covariance ``C_k``, the inverse of frame ``k``'s normal matrix with the recording's
sigmas) and the gyro's angle random walk ``n_k`` (``N^2 dt I``). Consecutive increments share a
frame, so the covariance of the stacked ``e`` is block tridiagonal (``C_k + C_{k+1} + Q_k`` on the
diagonal, ``-C_{k+1}`` between ``k`` and ``k+1``); it is whitened by its Cholesky factor.

Linear signatures (per unit parameter, for the selection): an image effect whose signature the
frame's attitude absorbs as the rotation ``a_k`` (the per-frame least-squares rotation of its
image Jacobian) moves ``e_k`` by ``a_{k+1} - a_k``; a gyro effect moves it by
``-int dg/dtheta dt`` over the window. A constant clock offset ``tau`` gives ``a_k = omega_k tau``:
visible where the rate changes (a rate reversal); a smear bias ``b T_k omega`` alternates with
alternating exposure times ``T_k``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.estimators.diagnosis.observations import frame_normal, solve_frames
from rollingstar.sensors.conventions import NS_PER_S
from rollingstar.sensors.effects.chain import gyro_effects
from rollingstar.sensors.so3 import quat_multiply


@dataclass(frozen=True, eq=False)
class GyroData:
    """Gyro samples of a recording: times (m,) int64 ns, rates (m, 3) rad/s (camera frame), the
    angle random walk ``arw_rad_sqrt_s`` of the declared gyro model (0 when not declared)."""

    t_ns: np.ndarray
    omega: np.ndarray
    arw_rad_sqrt_s: float = 0.0

    @property
    def m(self) -> int:
        return int(self.t_ns.shape[0])


def corrected(gyro: GyroData, effects) -> np.ndarray:
    """Gyro samples with the model's gyro effects removed, to first order."""
    eff = gyro_effects(tuple(effects))
    if not eff:
        return gyro.omega
    w = gyro.omega
    for e in eff:
        w = e.apply_gyro(gyro.t_ns, w)
    return 2.0 * gyro.omega - w


def overlaps(gyro: GyroData, t_ref_ns: np.ndarray) -> np.ndarray:
    """``dt_jk`` (s): overlap of sample ``j``'s interval ``(t_{j-1}, t_j]`` with window ``[t_k, t_{k+1}]``, (P, m)."""
    t = gyro.t_ns.astype(np.int64)
    prev = np.concatenate([[t[0] - (t[1] - t[0]) if t.size > 1 else t[0]], t[:-1]])
    lo = np.maximum(prev[None, :], t_ref_ns[:-1, None])
    hi = np.minimum(t[None, :], t_ref_ns[1:, None])
    return np.clip(hi - lo, 0, None).astype(float) / NS_PER_S


def covered(gyro: GyroData | None, t_ref_ns: np.ndarray) -> np.ndarray:
    """Pairs (k, k+1) whose whole window the gyro samples cover, (F-1,) bool."""
    if gyro is None or gyro.m < 2 or len(t_ref_ns) < 2:
        return np.zeros(max(len(t_ref_ns) - 1, 0), dtype=bool)
    dt = np.diff(t_ref_ns).astype(float) / NS_PER_S
    return np.abs(overlaps(gyro, t_ref_ns).sum(axis=1) - dt) < 1e-6


def gyro_increments(gyro: GyroData, t_ref_ns: np.ndarray, effects=()) -> Rotation:
    """``G_k`` for every consecutive pair (module doc), composed exactly sample by sample.

    The composition is sequential in time within a window; it runs over the sample position in the
    window (tens of steps), every pair at once, as quaternion products (padding with the identity).
    """
    w = corrected(gyro, effects)
    ov = overlaps(gyro, t_ref_ns)
    rows, cols = np.nonzero(ov > 0)  # row-major: each pair's samples in time order
    n_pairs = ov.shape[0]
    q = np.zeros((n_pairs, max(int(np.bincount(rows, minlength=n_pairs).max(initial=0)), 1), 4))
    q[..., 3] = 1.0
    if rows.size:
        first = np.searchsorted(rows, np.arange(n_pairs))
        q[rows, np.arange(rows.size) - first[rows]] = Rotation.from_rotvec(w[cols] * ov[rows, cols][:, None]).as_quat()
    out = q[:, 0]
    for s in range(1, q.shape[1]):
        out = quat_multiply(out, q[:, s])
    return Rotation.from_quat(out)


def increment_residual(attitude: Rotation, t_ref_ns: np.ndarray, gyro: GyroData, effects=()) -> np.ndarray:
    """``e_k = log(G_k^T S_k)`` (rad) of every consecutive pair, (F-1, 3)."""
    s = attitude[:-1].inv() * attitude[1:]
    g = gyro_increments(gyro, t_ref_ns, effects)
    return (g.inv() * s).as_rotvec()


def gyro_signature(effect, gyro: GyroData, t_ref_ns: np.ndarray) -> np.ndarray:
    """``d e_k / d theta`` of a gyro effect, ``-int dg/dtheta dt`` over each window, (F-1, 3, p)."""
    jac = effect.gyro_jacobian(gyro.t_ns, gyro.omega)  # (m, 3, p)
    return -np.einsum("km,mip->kip", overlaps(gyro, t_ref_ns), jac)


def attitude_covariances(frame: np.ndarray, n_frames: int, att_jac: np.ndarray, sigma: np.ndarray, mask,
                         cov: np.ndarray | None = None) -> np.ndarray:
    """``C_k``: inverse of each frame's attitude normal matrix over the stars in ``mask``, (F, 3, 3),
    with per-axis ``sigma`` or, given, the stars' 2 x 2 position covariances ``cov`` (n, 2, 2)."""
    if cov is None:
        wts = np.where(mask, 1.0 / sigma**2, 0.0)
    else:
        wts = np.where(np.asarray(mask, dtype=bool)[:, None, None], np.linalg.inv(cov), 0.0)
    a, _ = frame_normal(frame, n_frames, att_jac, wts, np.zeros((frame.size, 2, 1)))
    return np.linalg.pinv(a, hermitian=True)


def whitener(cov_att: np.ndarray, pairs: np.ndarray, t_ref_ns: np.ndarray, arw_rad_sqrt_s: float) -> np.ndarray:
    """``L^-1`` (3P, 3P) of the stacked increment covariance of the selected ``pairs`` (module doc)."""
    p = pairs.size
    dt = (t_ref_ns[pairs + 1] - t_ref_ns[pairs]).astype(float) / NS_PER_S
    cov = np.zeros((3 * p, 3 * p))
    for i, k in enumerate(pairs):  # block-tridiagonal assembly over pairs (tens)
        cov[3 * i:3 * i + 3, 3 * i:3 * i + 3] = cov_att[k] + cov_att[k + 1] + arw_rad_sqrt_s**2 * dt[i] * np.eye(3)
        if i + 1 < p and pairs[i + 1] == k + 1:
            cov[3 * i:3 * i + 3, 3 * i + 3:3 * i + 6] = -cov_att[k + 1]
            cov[3 * i + 3:3 * i + 6, 3 * i:3 * i + 3] = -cov_att[k + 1]
    cov += 1e-30 * np.eye(3 * p)
    return np.linalg.inv(np.linalg.cholesky(cov))


INCREMENT_CACHE = 8  # gyro integrations a channel remembers


@dataclass(frozen=True, eq=False)
class GyroChannel:
    """The channel of one recording: gyro data, the training pairs and their whitener."""

    gyro: GyroData
    pairs: np.ndarray  # first frame of each training pair
    w: np.ndarray  # (3P, 3P) whitener
    _increments: dict = field(default_factory=dict, repr=False)  # recent gyro integrations (:meth:`increments`)

    @property
    def rows(self) -> int:
        return int(3 * self.pairs.size)

    def increments(self, t_ref_ns: np.ndarray, effects=()) -> Rotation:
        """:func:`gyro_increments` under ``effects``, remembered for the last few gyro-effect values:
        fits evaluate the residual many times with the same gyro effects (most candidates act on
        the image only)."""
        key = (t_ref_ns.tobytes(), tuple((e.name, tuple(sorted(e._values.items()))) for e in gyro_effects(tuple(effects))))
        if key not in self._increments:
            if len(self._increments) >= INCREMENT_CACHE:
                self._increments.pop(next(iter(self._increments)))
            self._increments[key] = gyro_increments(self.gyro, t_ref_ns, effects)
        return self._increments[key]

    def residual(self, attitude: Rotation, t_ref_ns: np.ndarray, effects=(), increments: Rotation | None = None) -> np.ndarray:
        """Whitened increment residuals of the training pairs, (3P,); ``increments``: the gyro's
        integrated increments under ``effects`` (default: :meth:`increments`)."""
        g = self.increments(t_ref_ns, effects) if increments is None else increments
        e = (g.inv() * (attitude[:-1].inv() * attitude[1:])).as_rotvec()[self.pairs]
        return self.w @ e.reshape(-1)

    def whiten(self, sig: np.ndarray) -> np.ndarray:
        """Whitened signature rows (3P, p) from per-pair (F-1, 3, p) columns."""
        return self.w @ sig[self.pairs].reshape(self.rows, -1)

    def attitude_rows(self, n_frames: int) -> np.ndarray:
        """``d e / d delta`` (3P, 3F) whitened: ``+I`` for frame ``k+1``, ``-I`` for frame ``k``."""
        d = np.zeros((self.rows, 3 * n_frames))
        for i, k in enumerate(self.pairs):  # pairs (tens)
            d[3 * i:3 * i + 3, 3 * k:3 * k + 3] = -np.eye(3)
            d[3 * i:3 * i + 3, 3 * k + 3:3 * k + 6] = np.eye(3)
        return self.w @ d


def build_channel(gyro: GyroData | None, obs, pred, train_frames: np.ndarray, att_mask,
                  heldout: bool = False) -> GyroChannel | None:
    """The channel over consecutive training frames the gyro covers (``heldout``: over the pairs
    with at least one held-out frame instead); None without a gyro or without such pairs."""
    if gyro is None or obs.n_frames < 2:
        return None
    both = train_frames[:-1] & train_frames[1:]
    ok = covered(gyro, obs.t_ref_ns) & (~both if heldout else both)
    pairs = np.flatnonzero(ok)
    if pairs.size == 0:
        return None
    cov = attitude_covariances(obs.frame, obs.n_frames, pred.att_jac, obs.sigma, att_mask, obs.cov)
    return GyroChannel(gyro, pairs, whitener(cov, pairs, obs.t_ref_ns, gyro.arw_rad_sqrt_s))


def channel_rows(obs, pred) -> np.ndarray:
    """Whitened increment residuals of ``pred`` (its nuisance and effect chain); empty without a channel."""
    if obs.channel is None:
        return np.zeros(0)
    return obs.channel.residual(pred.nuisance.attitude, obs.t_ref_ns, pred.effects)


def absorbed_rotations(frame: np.ndarray, n_frames: int, att_jac_w: np.ndarray, cols_w: np.ndarray) -> np.ndarray:
    """Per-frame least-squares rotation (F, 3, m) fitted to whitened image columns (n, 2, m)."""
    a, b = frame_normal(frame, n_frames, att_jac_w, np.ones(frame.shape[0]), cols_w)
    return solve_frames(a, b)


def image_effect_signature(coef: np.ndarray) -> np.ndarray:
    """``a_{k+1} - a_k`` per pair, (F-1, 3, m), from per-frame absorbed rotations (F, 3, m)."""
    return coef[1:] - coef[:-1]
