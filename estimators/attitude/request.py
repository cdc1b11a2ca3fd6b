"""High-update-rate REQUEST attitude solver for rolling-shutter frames (He et al. 2021b, Algorithm 1).

The seed (``he2021b_high_update_rate_request.txt``) fuses Davenport's K matrix, propagated with the
angular rate, with the stars exposed since the previous update, corrected to the current group's
reference row; one attitude per group of stars, several per frame. Equation numbers below are the
seed's. Two printing errors of the seed are corrected here:

- eqs (5)-(6) add ``(y - k) v dt`` to the position; moving a star seen at row ``y`` (time
  ``t_y``) to the reference row ``k`` (time ``t_k``) needs ``x + v (t_k - t_y) = x - (y - k) v dt``,
  which is the sign of Algorithm 1 line 7 (used here);
- eq (25) drops the index on ``v`` (``w_i^T v_i`` is meant).
"""
from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import ConfigDict, Field
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.base import AttitudeSolver
from rollingstar.estimators.attitude.robust import RobustParams, apply_robust
from rollingstar.estimators.attitude.star_covariance import (
    anisotropic_covariance,
    direction_covariance,
    isotropic_sigma_px,
)
from rollingstar.estimators.data import AttitudeEstimate, FrameData, default_sigma_px, frame_camera
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.so3 import skew

__all__ = ["RequestSolver", "RequestParams", "davenport_k", "transition_matrix", "propagate_k", "dominant_quaternion"]


class RequestParams(RobustParams):  # robust: the shared outlier gate (robust.py)
    model_config = ConfigDict(extra="forbid")

    group_size: Annotated[int, Field(ge=1)] | Literal["frame"] = Field(
        default="frame", description="Stars per attitude update (the seed's 1, 3, 5); 'frame' (default): one update per frame.")
    rate_source: Literal["truth", "gyro", "estimate", "fixed"] = Field(
        default="fixed", description="Angular rate for K propagation and star correction: 'truth' (simulated "
        "recordings only; oracle), 'gyro' (frame.gyro samples), 'estimate' (frame.rate from a rate stage), "
        "'fixed' (rate_deg_s).")
    rate_deg_s: tuple[float, float, float] = Field(
        default=(0.0, 0.0, 0.0), description="Camera-frame rate for rate_source 'fixed' (deg/s); default: inertial hold.")
    forgetting: float = Field(
        default=1.0, ge=0.0, le=1.0, description="Fading-memory factor rho per update (Bar-Itzhack 1996): "
        "b2 = rho b1 + db, K2 = rho b1/b2 K(t2|t1) + dK/b2. 1 = the seed's eqs (30)-(31) exactly (no forgetting); "
        "0 = no memory (each group alone).")
    sigma_px: float | None = Field(
        default=None, gt=0, description="1-sigma centroid error (px) for stars whose sigma_px is NaN; None: the "
        "sensor context's centroid_sigma_px, else 0.05 px.")
    use_star_sigma: bool = Field(default=True, description="Weight by each star's own sigma_px when finite.")
    star_covariance: bool = Field(
        default=True, description="Stars with anisotropic 2 x 2 position covariances (cov_xx, cov_xy, cov_yy): K "
        "takes their isotropic equivalents and the reported covariance is the scalar-weighted estimate's actual "
        "one under the 2 x 2 noise (sandwich); False: the scalar sigma_px alone.")
    rate_sigma_deg_s: float = Field(
        default=0.0, ge=0.0, description="1-sigma rate error (deg/s) inflating the sigma of a star corrected over "
        "|dt|: sigma^2 + (f_px * rate_sigma * |dt|)^2.")
    use_star_velocity: bool = Field(default=True, description="Use the stars' vx/vy (px/s) when finite, else the "
                                    "image velocity from the rate and the camera model.")
    min_stars: int = Field(default=2, ge=2, description="Stars fused since the start before an update is reported valid.")
    degenerate_tol: float = Field(default=1e-10, gt=0, description="Smallest eigenvalue of the accumulated information "
                                  "matrix relative to its trace below which the attitude is unobservable.")


# ----------------------------------------------------------------------------------- the maths
def davenport_k(obs_cam, ref_icrs, weights) -> tuple[np.ndarray, np.ndarray]:
    """Unnormalised ``(Delta K, Delta b)`` of star groups, eqs (24)-(29), batched over groups.

    ``obs_cam`` (G, N, 3) corrected camera vectors ``w_i``, ``ref_icrs`` (G, N, 3) catalogue vectors
    ``v_i``, ``weights`` (G, N) ``a_i`` (0 for padding). ``dB = sum a w v^T`` (26),
    ``dS = dB + dB^T`` (27), ``dsigma = sum a w^T v = tr dB`` (25, index restored),
    ``dz = sum a w x v`` (28), ``dK = [[dS - dsigma I, dz], [dz^T, dsigma]]`` (29); ``db = sum a`` (24).
    Normalised by ``b`` this is eqs (18)-(23). The dominant eigenvector of K is the scalar-last
    quaternion of the camera-to-ICRS rotation (see :mod:`rollingstar.estimators.attitude.wahba`).
    """
    w = np.asarray(obs_cam, dtype=float)
    v = np.asarray(ref_icrs, dtype=float)
    a = np.asarray(weights, dtype=float)
    B = np.einsum("gn,gni,gnj->gij", a, w, v)
    sigma = np.trace(B, axis1=-2, axis2=-1)
    z = np.einsum("gn,gni->gi", a, np.cross(w, v))
    K = np.zeros(B.shape[:-2] + (4, 4))
    K[..., :3, :3] = B + np.swapaxes(B, -1, -2) - sigma[..., None, None] * np.eye(3)
    K[..., :3, 3] = z
    K[..., 3, :3] = z
    K[..., 3, 3] = sigma
    return K, a.sum(axis=-1)


def transition_matrix(theta) -> np.ndarray:
    """Quaternion transition matrix ``Phi`` of eqs (12)-(13) for rotation vectors ``theta = omega (t2 - t1)``.

    ``Phi = cos(|theta|/2) I4 + [[-[psi x], psi], [-psi^T, 0]]``, ``psi = sin(|theta|/2) theta/|theta|``
    (eq 13's ``sin(.)/|omega| omega``). On scalar-last camera-to-ICRS quaternions it is exactly
    ``R(t2) = R(t1) Exp(theta)`` (body-frame rate, project convention), i.e. eq (11). (..., 4, 4).
    """
    th = np.asarray(theta, dtype=float)
    ang = np.linalg.norm(th, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(ang > 1e-12, np.sin(ang / 2) / np.where(ang > 0, ang, 1.0), 0.5)
    psi = scale[..., None] * th
    Phi = np.cos(ang / 2)[..., None, None] * np.eye(4)
    Phi[..., :3, :3] -= skew(psi)
    Phi[..., :3, 3] += psi
    Phi[..., 3, :3] -= psi
    return Phi


def propagate_k(K, theta) -> np.ndarray:
    """``K(t2|t1) = Phi K(t1|t1) Phi^T`` (eq 16) for rotation vectors ``theta = omega (t2 - t1)``."""
    Phi = transition_matrix(theta)
    return Phi @ np.asarray(K, dtype=float) @ np.swapaxes(Phi, -1, -2)


def dominant_quaternion(K) -> tuple[np.ndarray, np.ndarray]:
    """Eq (32): unit eigenvector of the largest eigenvalue of K (scalar-last, ``w >= 0``), and the gap
    ``lambda_1 - lambda_2`` (0 when the attitude is unobservable). Batched over leading axes."""
    vals, vecs = np.linalg.eigh(np.asarray(K, dtype=float))
    q = vecs[..., :, -1]
    q = np.where(q[..., 3:4] < 0, -q, q)
    return q, vals[..., -1] - vals[..., -2]


# ----------------------------------------------------------------------------------- the plugin
class RequestSolver(AttitudeSolver):
    """REQUEST with rolling-shutter star correction: several attitudes per frame (he2021b Algorithm 1).

    Per frame, the identified stars (finite position and reference) are sorted by the time their
    position refers to (``t_ns``) and cut into consecutive groups of ``group_size`` (the last group
    of a frame may be smaller; ``"frame"``: one group). For each group ``j`` with reference star =
    its last star (the seed's "row of the 5th star"), reference time ``t_j`` = that star's ``t_ns``:

    1. propagate: ``K(t_j|t_{j-1}) = Phi K Phi^T`` with ``Phi`` from the rate over
       ``[t_{j-1}, t_j]`` (eqs 9-16; Algorithm 1 lines 3-5);
    2. correct every star of the group to ``t_j``: ``x_C = x - (t_i - t_j) v_x`` (Algorithm 1 line 7,
       eqs 5-6 with the sign fixed), ``v = (vx, vy)`` from the table when finite and
       ``use_star_velocity``, else the image velocity of the star from the rate and the camera model,
       ``v = J(w) (-omega x w)`` (``J`` the pinhole projection Jacobian, ``dw/dt = -omega x w``);
    3. build ``Delta K(t_j)`` from the corrected vectors, weights ``a_i = 1/sigma_i^2`` (rad^-2,
       ``sigma_i = sigma_px / f_px``, inflated by ``rate_sigma_deg_s * |t_i - t_j|``) (eqs 24-29);
    4. fuse: ``b_j = rho b_{j-1} + Delta b``, ``K(t_j|t_j) = rho b_{j-1}/b_j K(t_j|t_{j-1}) +
       Delta K / b_j`` (eqs 30-31; ``rho = forgetting``, 1 gives the seed's equations);
    5. attitude = dominant eigenvector of ``K(t_j|t_j)`` (eq 32), timestamped ``t_j``.

    Rate over an interval: ``fixed``: ``rate_deg_s``; ``estimate``: the frame's valid
    ``frame.rate`` (else the last valid one, flag ``"rate_held"``); ``gyro``: the gyro samples
    received so far, linearly interpolated at the interval's middle (held beyond the newest sample);
    ``truth``: the exact relative truth rotation (slerp of ``frame.truth``; the plugin sets
    ``needs_truth`` so the runner passes it). Without a rate the group's estimate is invalid.

    ``covariance_rad2``: inverse of the information matrix ``sum a_i (I - w_i w_i^T)`` propagated
    and faded like K (Shuster's QUEST covariance of all fused stars; exact for ``rho = 1`` and an
    exact rate, approximate otherwise). ``n_stars``: the stars of the group (new in this update).

    Stars with 2 x 2 position covariances (``star_covariance``; a frame with one that is not
    isotropic): Davenport's K holds one scalar weight per star, so K takes each star's isotropic
    equivalent ``a_i = f^2 / (trace(C_i) / 2)`` (the attitude is the scalar-weighted REQUEST
    solution, not the 2 x 2 optimum; refining it would need every fused star, which K summarises
    away). Its covariance is then reported honestly for that estimator under the 2 x 2 noise: the
    sandwich ``J^-1 M J^-1`` with ``J`` as above and ``M = sum a_i^2 H_i^T Sigma_i H_i``
    (``H_i = E_i^T [w_i x]``, ``Sigma_i`` the star's tangent-plane covariance,
    :mod:`rollingstar.estimators.attitude.star_covariance`, plus the ``rate_sigma_deg_s`` term),
    propagated like ``J`` and faded by ``rho^2``. With isotropic noise and ``rho = 1``, ``M = J``.
    Stars are unprojected with the frame's camera (:func:`~rollingstar.estimators.data.frame_camera`).
    Invalid (reason given, never invented): no stars, no rate, fewer than ``min_stars`` fused, or
    the fused stars do not fix all three axes (e.g. one star); flag ``"attitude_invalid"``.
    """

    name = "request"
    Params = RequestParams

    @property
    def needs_truth(self) -> bool:
        """The runner passes ``frame.truth`` only to stages that need it (oracle ``rate_source``)."""
        return self.params.rate_source == "truth"

    @property
    def needs(self) -> frozenset[str]:
        """Identified stars; with ``rate_source: estimate`` also a rate stage's ``frame.rate``."""
        return AttitudeSolver.needs | ({"rate"} if self.params.rate_source == "estimate" else set())

    def setup(self, context) -> None:
        super().setup(context)
        p = self.params
        self._sigma_px = default_sigma_px(p.sigma_px, context)
        self._K = np.zeros((4, 4))
        self._J = np.zeros((3, 3))
        self._M = np.zeros((3, 3))  # sum a^2 H^T Sigma H of the fused stars (sandwich covariance)
        self._sandwich = False  # the fused state holds a star of anisotropic covariance
        self._b = 0.0
        self._n_fused = 0
        self._t_last: int | None = None
        self._rate_held: np.ndarray | None = None
        self._gyro_t = np.zeros(0, dtype=np.int64)
        self._gyro_w = np.zeros((0, 3))
        self._truth_t = np.zeros(0, dtype=np.int64)
        self._truth_q = np.zeros((0, 4))
        self._fixed = np.radians(np.asarray(p.rate_deg_s, dtype=float))

    # ------------------------------------------------------------------ rate over intervals
    def _prepare_rate(self, frame: FrameData) -> tuple[str | None, tuple[str, ...]]:
        """Take in this frame's rate information; returns (reason if unavailable, extra flags)."""
        src = self.params.rate_source
        if src == "fixed":
            return None, ()
        if src == "estimate":
            r = frame.rate
            if r is not None and r.valid and np.all(np.isfinite(r.omega_rad_s)):
                self._rate_held = np.asarray(r.omega_rad_s, dtype=float).copy()
                return None, ()
            if self._rate_held is not None:
                return None, ("rate_held",)
            return "no valid rate estimate (frame.rate) yet", ("rate_unavailable",)
        if src == "gyro":
            g = frame.gyro
            if g is not None and len(g.t_ns):
                self._gyro_t, self._gyro_w = _merge_window(  # the last 2 s are plenty
                    self._gyro_t, self._gyro_w, g.t_ns, g.omega_rad_s, 2_000_000_000, unique=False)
            if self._gyro_t.size == 0:
                return "no gyro samples yet", ("rate_unavailable",)
            return None, ()
        # truth
        tr = frame.truth
        if tr is not None and len(tr.t_ns):
            self._truth_t, self._truth_q = _merge_window(
                self._truth_t, self._truth_q, tr.t_ns, tr.q_xyzw, 500_000_000, unique=True)
        if self._truth_t.size < 2:
            return "rate_source 'truth' but the frame carries no truth (simulated recordings only)", ("rate_unavailable",)
        return None, ()

    def _increments(self, t_a: np.ndarray, t_b: np.ndarray) -> np.ndarray:
        """Body rotation vectors ``theta`` with ``R(t_b) = R(t_a) Exp(theta)`` (n, 3); NaN if unknown."""
        t_a = np.asarray(t_a, dtype=np.int64)
        t_b = np.asarray(t_b, dtype=np.int64)
        dt = (t_b - t_a).astype(float) * S_PER_NS
        src = self.params.rate_source
        if src == "fixed":
            return dt[:, None] * self._fixed
        if src == "estimate":
            return dt[:, None] * self._rate_held
        if src == "gyro":
            base = self._gyro_t[0]
            mid = ((t_a - base) + (t_b - base)).astype(float) * 0.5e-9
            ref = (self._gyro_t - base).astype(float) * S_PER_NS
            w = np.stack([np.interp(mid, ref, self._gyro_w[:, k]) for k in range(3)], axis=-1)
            return dt[:, None] * w
        # truth: exact relative rotation from the slerped truth attitudes
        out = np.full((t_a.size, 3), np.nan)
        lo, hi = self._truth_t[0], self._truth_t[-1]
        ok = (t_a >= lo) & (t_a <= hi) & (t_b >= lo) & (t_b <= hi)
        if ok.any():
            out[ok] = (self._truth_at(t_a[ok]).inv() * self._truth_at(t_b[ok])).as_rotvec()
        return out

    def _truth_at(self, t: np.ndarray) -> Rotation:
        """Truth attitude at covered times: slerp between the two bracketing samples."""
        T, Q = self._truth_t, self._truth_q
        i = np.clip(np.searchsorted(T, t, side="right") - 1, 0, T.size - 2)
        frac = (t - T[i]).astype(float) / (T[i + 1] - T[i]).astype(float)
        R0 = Rotation.from_quat(Q[i])
        step = (R0.inv() * Rotation.from_quat(Q[i + 1])).as_rotvec()
        return R0 * Rotation.from_rotvec(frac[:, None] * step)

    # ------------------------------------------------------------------ per frame
    def process(self, frame: FrameData) -> FrameData:
        p = self.params
        cam = frame_camera(frame, self.context)
        frame = apply_robust(frame, cam, p, self._sigma_px, p.use_star_sigma, p.star_covariance)
        sel, flags, invalid = self._usable_stars(frame)
        if invalid is not None:
            return self._append(frame, [invalid], flags + ("attitude_invalid",))
        starts, ends, group_of, width = _groups(sel.n, p.group_size)
        t_ref = sel.t_ns[ends - 1].astype(np.int64)  # eq (5) k: the group's last star's row

        reason, rate_flags = self._prepare_rate(frame)
        flags += rate_flags
        if reason is not None:
            ests = [AttitudeEstimate.invalid(int(t), int(m), reason) for t, m in zip(t_ref, ends - starts)]
            return self._append(frame, ests, flags + ("attitude_invalid",))

        w_c, a, good_star, theta_i, cov_dir = self._corrected_stars(sel, t_ref[group_of], cam)
        dK, db, dJ, dM, m_good = _group_information(w_c, sel.ref_icrs, a, good_star, starts, group_of, width, cov_dir)
        Ks, Js, Ms, valid, reasons = self._fuse(t_ref, theta_i, group_of, dK, db, dJ, dM, m_good)
        ests = _estimates(Ks, Js, Ms, valid, reasons, t_ref, ends - starts)
        if not valid.all():
            flags += ("attitude_invalid",)
        return self._append(frame, ests, flags)

    def _usable_stars(self, frame: FrameData):
        """The identified stars with finite position and reference, sorted by time; returns
        ``(stars, flags, None)``, or ``(None, flags, invalid estimate)`` when there are none."""
        t_frame = int(self.context.timing.frame_reference_ns(frame.t0_ns))
        stars = frame.stars
        if stars is None or stars.n == 0 or not stars.identified.any():
            n = 0 if stars is None else int(stars.identified.sum())
            return None, (), AttitudeEstimate.invalid(t_frame, n, "no identified stars")
        sel = stars.take(stars.identified)
        finite = np.isfinite(sel.x) & np.isfinite(sel.y) & np.isfinite(sel.ref_icrs).all(axis=1)
        flags: tuple[str, ...] = ()
        if not finite.all():
            flags += (f"non_finite_star:{int((~finite).sum())}",)
            sel = sel.take(finite)
        if sel.n == 0:
            return None, flags, AttitudeEstimate.invalid(t_frame, 0, "no identified star with finite position and reference")
        return sel.take(np.argsort(sel.t_ns, kind="stable")), flags, None

    def _corrected_stars(self, sel, t_k: np.ndarray, cam):
        """Camera vectors of the stars moved to their group's reference time ``t_k`` (eqs 5-6,
        Algorithm 1 line 7), their weights ``a_i = 1 / sigma_rad^2``, which of them are finite,
        the rotation vectors ``theta_i`` over ``[t_i, t_k]`` (NaN where the rate is unknown), and
        the stars' tangent-plane covariances (basis, covariance rad^2) when they carry anisotropic
        2 x 2 ones (else None)."""
        p = self.params
        t_i = sel.t_ns.astype(np.int64)
        dt = (t_i - t_k).astype(float) * S_PER_NS  # t_i - t_ref <= 0
        w_raw = cam.unproject(sel.x, sel.y)
        theta_i = self._increments(t_i, t_k)  # R(t_k) = R(t_i) Exp(theta_i)
        span = -dt  # t_ref - t_i >= 0, the interval theta_i covers
        omega_i = np.where(span[:, None] > 0, theta_i / np.where(span == 0, 1.0, span)[:, None], 0.0)
        vel = np.einsum("nij,nj->ni", cam.projection_jacobian(w_raw), -np.cross(omega_i, w_raw))  # px/s
        if p.use_star_velocity:
            own = np.column_stack([sel.vx, sel.vy])
            has = np.isfinite(own).all(axis=1)
            vel[has] = own[has]
        xc = sel.x - dt * vel[:, 0]
        yc = sel.y - dt * vel[:, 1]
        w_c = cam.unproject(xc, yc)

        focal = float(cam.focal_px)
        cov_px = anisotropic_covariance(sel, self._sigma_px, p.use_star_sigma, p.star_covariance)
        cov_dir = None
        if cov_px is None:
            sigma_px = np.full(sel.n, self._sigma_px)
            if p.use_star_sigma:
                sigma_px = np.where(np.isfinite(sel.sigma_px) & (sel.sigma_px > 0), sel.sigma_px, sigma_px)
        else:
            sigma_px = isotropic_sigma_px(cov_px)
            d = direction_covariance(cam, xc, yc, cov_px)
            rate_var = (np.radians(p.rate_sigma_deg_s) * dt) ** 2  # rad^2, isotropic
            cov_dir = (d.basis, d.cov + rate_var[:, None, None] * np.eye(2))
        sig2 = sigma_px**2 + (focal * np.radians(p.rate_sigma_deg_s) * dt) ** 2
        a = focal**2 / sig2
        return w_c, a, np.isfinite(w_c).all(axis=1), theta_i, cov_dir

    def _fuse(self, t_ref, theta_i, group_of, dK, db, dJ, dM, m_good):
        """Propagate and fuse the groups one after the other (eqs 9-16, 30-31), carrying the state
        ``K, J, b`` (and the sandwich's ``M``) and the fused star count across frames; returns per
        group the fused ``K``, information ``J``, ``M`` (None where the state never held a star of
        anisotropic covariance: the covariance is then ``J^-1``), whether its attitude is valid, and
        the reason where it is not. ``dM`` None: the frame's stars are isotropic (``dM = dJ``)."""
        p = self.params
        G = t_ref.size
        t_prev = np.concatenate([[t_ref[0] if self._t_last is None else self._t_last], t_ref[:-1]])
        theta = self._increments(t_prev, t_ref)
        Phi = transition_matrix(np.nan_to_num(theta))
        C = Rotation.from_rotvec(np.nan_to_num(theta)).as_matrix().transpose(0, 2, 1)  # w' = C w
        rho = p.forgetting
        Ks = np.zeros((G, 4, 4))
        Js = np.zeros((G, 3, 3))
        Ms: list[np.ndarray | None] = [None] * G
        valid = np.zeros(G, dtype=bool)
        reasons = [""] * G
        K, J, M, b, nf = self._K, self._J, self._M, self._b, self._n_fused
        sandwich = self._sandwich or dM is not None
        for j in range(G):
            if not np.isfinite(theta[j]).all() or not np.isfinite(theta_i[group_of == j]).all():
                # no rate over the interval: nothing can be propagated; restart from this group
                K, J, M, b, nf = np.zeros((4, 4)), np.zeros((3, 3)), np.zeros((3, 3)), 0.0, 0
                sandwich = dM is not None
                reasons[j] = "no angular rate over the update interval"
                continue
            if b > 0:
                K = Phi[j] @ K @ Phi[j].T  # eq (16)
                J = C[j] @ J @ C[j].T
                M = C[j] @ M @ C[j].T
            b_new = rho * b + db[j]  # eq (30)
            if b_new > 0:
                K = (rho * b / b_new) * K + dK[j] / b_new  # eq (31)
            J = rho * J + dJ[j]
            M = rho**2 * M + (dJ[j] if dM is None else dM[j])
            b = b_new
            nf += int(m_good[j])
            Ks[j], Js[j], Ms[j] = K, J, (M if sandwich else None)
            if nf < p.min_stars:
                reasons[j] = f"fewer than {p.min_stars} stars fused ({nf})"
                continue
            ev = np.linalg.eigvalsh(J)
            if not (ev[0] > p.degenerate_tol * max(ev.sum(), np.finfo(float).tiny)):
                reasons[j] = "fused stars do not fix all three axes (collinear or a single star)"
                continue
            valid[j] = True
        self._K, self._J, self._M, self._b, self._n_fused, self._sandwich = K, J, M, b, nf, sandwich
        self._t_last = int(t_ref[-1])
        return Ks, Js, Ms, valid, reasons

    @staticmethod
    def _append(frame: FrameData, ests: list[AttitudeEstimate], flags: tuple[str, ...]) -> FrameData:
        return frame.evolve(attitudes=frame.attitudes + tuple(ests), flags=frame.flags + flags)


def _groups(n: int, group_size) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Consecutive groups of ``group_size`` of ``n`` time-sorted stars (``"frame"``: one group):
    each group's first index, its end (exclusive), the group of every star and the group size."""
    g = n if group_size == "frame" else int(group_size)
    starts = np.arange(0, n, g)
    ends = np.minimum(starts + g, n)
    return starts, ends, np.repeat(np.arange(starts.size), ends - starts), g


def _group_information(w_c, ref_icrs, a, good_star, starts, group_of, g: int, cov_dir=None):
    """Per group ``Delta K``, ``Delta b`` (eqs 24-29), the information ``sum a_i (I - w_i w_i^T)``,
    the sandwich term ``sum a_i^2 H_i^T Sigma_i H_i`` (None without ``cov_dir``, the stars' tangent
    bases and covariances) and the number of finite stars, vectorised with a padded (G, g, 3) layout
    (g: the group size)."""
    G, n = starts.size, group_of.size
    slot = np.arange(n) - starts[group_of]
    W = np.zeros((G, g, 3))
    V = np.zeros((G, g, 3))
    A = np.zeros((G, g))
    W[group_of, slot] = np.where(good_star[:, None], w_c, 0.0)
    V[group_of, slot] = ref_icrs
    A[group_of, slot] = np.where(good_star, a, 0.0)
    dK, db = davenport_k(W, V, A)
    dJ = np.einsum("gn,ij->gij", A, np.eye(3)) - np.einsum("gn,gni,gnj->gij", A, W, W)
    dM = None
    if cov_dir is not None:
        basis, cov = cov_dir
        H = np.swapaxes(basis, -1, -2) @ skew(np.where(good_star[:, None], w_c, 0.0))  # (n, 2, 3)
        per_star = np.where(good_star, a, 0.0)[:, None, None] ** 2 * (np.swapaxes(H, -1, -2) @ cov @ H)
        dM = np.zeros((G, 3, 3))
        np.add.at(dM, group_of, per_star)
    m_good = np.bincount(group_of, weights=good_star.astype(float), minlength=G).astype(int)
    return dK, db, dJ, dM, m_good


def _estimates(Ks, Js, Ms, valid, reasons, t_ref, n_stars) -> list[AttitudeEstimate]:
    """One estimate per group: the dominant eigenvector of its fused K (eq 32, batched over the
    frame's updates) with the inverse information as covariance (the sandwich ``J^-1 M J^-1`` where
    ``M`` is given), or invalid with its reason."""
    q, _ = dominant_quaternion(Ks)
    ests = []
    for j in range(len(t_ref)):
        m = int(n_stars[j])
        if valid[j]:
            cov = np.linalg.inv(Js[j])
            if Ms[j] is not None:
                cov = cov @ Ms[j] @ cov
            ests.append(AttitudeEstimate(t_ns=int(t_ref[j]), q_xyzw=q[j].copy(), n_stars=m, valid=True,
                                         covariance_rad2=0.5 * (cov + cov.T)))
        else:
            ests.append(AttitudeEstimate.invalid(int(t_ref[j]), m, reasons[j]))
    return ests


def _merge_window(t_old, v_old, t_new, v_new, window_ns: int, unique: bool):
    """Append timed samples, sort by time, keep the last ``window_ns`` (and one sample per time if ``unique``)."""
    t = np.concatenate([t_old, np.asarray(t_new, dtype=np.int64)])
    v = np.concatenate([v_old, np.asarray(v_new, dtype=float)])
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    keep = t >= t[-1] - window_ns
    if unique:
        keep &= np.concatenate([[True], np.diff(t) > 0])
    return t[keep], v[keep]
