"""QUEST attitude solver plugin (Shuster & Oh 1981): one attitude per frame from identified stars."""
from __future__ import annotations

import numpy as np
from pydantic import ConfigDict, Field

from rollingstar.estimators.attitude.base import AttitudeSolver
from rollingstar.estimators.attitude.robust import RobustParams, apply_robust
from rollingstar.estimators.attitude.star_covariance import (
    anisotropic_covariance,
    direction_covariance,
    isotropic_sigma_px,
)
from rollingstar.estimators.attitude.wahba import quest, quest_covariance, refine_attitude
from rollingstar.estimators.data import AttitudeEstimate, FrameData, default_sigma_px, frame_camera


class QuestParams(RobustParams):
    model_config = ConfigDict(extra="forbid")

    sigma_px: float | None = Field(
        default=None, gt=0,
        description="1-sigma centroid error (px) for stars whose sigma_px column is NaN; "
        "None: the sensor context's centroid_sigma_px, else 0.05 px.",
    )
    use_star_sigma: bool = Field(default=True, description="Weight by each star's own sigma_px when finite.")
    star_covariance: bool = Field(
        default=True, description="When a star of the frame carries a 2 x 2 position covariance (cov_xx, cov_xy, "
        "cov_yy) that is not isotropic, refine the QUEST attitude by Gauss-Newton with every star's 2 x 2 "
        "tangent-plane information; False: the scalar sigma_px weighting alone.")
    refine_iterations: int = Field(default=2, ge=1, le=10,
                                   description="Gauss-Newton iterations of the 2 x 2 refinement (star_covariance).")
    degenerate_tol: float = Field(default=1e-10, gt=0, description="Collinearity threshold (see wahba.quest).")


class QuestSolver(AttitudeSolver):
    """Single-frame QUEST solution of Wahba's problem (Shuster & Oh 1981), see :func:`wahba.quest`.

    Uses the identified stars (``catalog_id >= 0``) of ``frame.stars``: observations
    ``b_i = camera.unproject(x_i, y_i)`` (he2021b eq 2, the frame's camera:
    :func:`~rollingstar.estimators.data.frame_camera`), references ``r_i = ref_icrs``, weights
    ``a_i = 1 / sigma_i^2`` with ``sigma_i = sigma_px_i / focal_px`` rad (the pixel's angular size at
    the principal point; off-axis foreshortening neglected).

    2 x 2 position covariances (``star_covariance``): QUEST takes one scalar weight per star. When a
    star of the frame carries a covariance that is not isotropic, QUEST runs with the isotropic
    equivalents ``sigma_i = sqrt(trace(C_i) / 2) / focal_px`` and its attitude is refined by
    Gauss-Newton (:func:`wahba.refine_attitude`, ``refine_iterations``) with every star's exact
    tangent-plane information ``(E^T J C J^T E)^-1``
    (:mod:`rollingstar.estimators.attitude.star_covariance`); the covariance is then
    ``(sum H_i^T W_i H_i)^-1``. A frame whose stars are all isotropic is solved by QUEST alone.

    Appends one :class:`AttitudeEstimate` with

    - ``q_xyzw``: camera-to-ICRS;
    - ``t_ns``: the weighted mean of the stars' ``t_ns`` (weights ``a_i``), rounded to the ns. For a
      rolling-shutter frame whose stars refer to different times (uncorrected centroids), the
      least-squares attitude is, to first order in the rate, the attitude at that mean time; after a
      correction that moves every star to one time it is that time;
    - ``covariance_rad2``: Shuster's measurement-model covariance ``(sum a_i (I - b_i b_i^T))^-1``
      in the camera frame (with the 2 x 2 refinement: ``(sum H_i^T W_i H_i)^-1``).

    Fewer than two identified stars, non-finite positions/references or collinear stars give an
    invalid estimate with the reason (the frame also gets flag ``"attitude_invalid"``; the runner
    adds ``"too_few_stars"`` where that is the cause).
    """

    name = "quest"
    Params = QuestParams

    def setup(self, context) -> None:
        super().setup(context)
        self._sigma_px = default_sigma_px(self.params.sigma_px, context)

    def process(self, frame: FrameData) -> FrameData:
        p = self.params
        camera = frame_camera(frame, self.context)
        frame = apply_robust(frame, camera, p, self._sigma_px, p.use_star_sigma, p.star_covariance)
        stars = frame.stars
        t_frame = int(self.context.timing.frame_reference_ns(frame.t0_ns))
        if stars is None or stars.n == 0:
            return self._invalid(frame, t_frame, 0, "no stars")
        sel = stars.take(stars.identified)
        n = sel.n
        t_ref = _weighted_mean_ns(sel.t_ns, np.ones(n)) if n else t_frame
        if n < 2:
            return self._invalid(frame, t_ref, n, f"fewer than 2 identified stars ({n})")
        finite = np.isfinite(sel.x) & np.isfinite(sel.y) & np.isfinite(sel.ref_icrs).all(axis=1)
        if not finite.all():
            return self._invalid(frame, t_ref, n, f"non-finite position or reference for {int((~finite).sum())} of {n} identified stars")
        cov_px = anisotropic_covariance(sel, self._sigma_px, p.use_star_sigma, p.star_covariance)
        if cov_px is None:
            sigma_px = np.full(n, self._sigma_px)
            if p.use_star_sigma:
                own = sel.sigma_px
                good = np.isfinite(own) & (own > 0)
                sigma_px = np.where(good, own, sigma_px)
        else:
            sigma_px = isotropic_sigma_px(cov_px)
        a = (float(camera.focal_px) / sigma_px) ** 2  # 1 / sigma_rad^2
        obs = camera.unproject(sel.x, sel.y)
        res = quest(sel.ref_icrs[None], obs[None], a[None], degenerate_tol=p.degenerate_tol)
        t_ref = _weighted_mean_ns(sel.t_ns, a)
        if not res.valid[0]:
            return self._invalid(frame, t_ref, n, "degenerate geometry: identified stars collinear")
        if cov_px is None:
            q, cov = res.q_xyzw[0], quest_covariance(obs[None], a[None])[0]
        else:
            d = direction_covariance(camera, sel.x, sel.y, cov_px)
            ref = sel.ref_icrs / np.linalg.norm(sel.ref_icrs, axis=1, keepdims=True)
            q, cov = refine_attitude(res.q_xyzw[0], ref, d.body, d.basis, d.info, p.refine_iterations)
        est = AttitudeEstimate(t_ns=t_ref, q_xyzw=q, n_stars=n, valid=True, covariance_rad2=cov)
        return frame.evolve(attitudes=frame.attitudes + (est,))

    @staticmethod
    def _invalid(frame: FrameData, t_ns: int, n: int, reason: str, flag: str = "attitude_invalid") -> FrameData:
        est = AttitudeEstimate.invalid(t_ns, n, reason)
        return frame.evolve(attitudes=frame.attitudes + (est,), flags=frame.flags + (flag,))


def _weighted_mean_ns(t_ns: np.ndarray, weights: np.ndarray) -> int:
    """Weighted mean of integer-ns times without float overflow: ``t_min + round(mean(t - t_min))``."""
    t = np.asarray(t_ns, dtype=np.int64)
    base = int(t.min())
    offsets = (t - base).astype(float)
    return base + int(np.rint(np.sum(weights * offsets) / np.sum(weights)))
