"""Robust gates against false and misidentified stars, shared by every attitude solver.

A false star (a planet, a satellite, a hot pixel that got a catalogue id) or a misidentified star
adds an observation ``b_i`` whose reference ``r_i`` is wrong by degrees; the least-squares attitude
of Wahba's problem (``L(A) = 1/2 sum a_i |b_i - A r_i|^2``) has unbounded influence and is dragged
by it. Before a solver fuses a frame's identified stars, :func:`robust_gate` checks them against one
attitude per frame:

- ``ransac`` (Fischler & Bolles 1981, with the MSAC score of Torr & Zisserman 2000): every pair
  of identified stars (or ``max_hypotheses`` pairs drawn with a fixed seed) gives an attitude
  hypothesis (two-star QUEST, batched); each star's angular residual
  ``e_i = angle(b_i, A r_i)`` is compared with the threshold; the hypothesis with the most inliers
  (ties: smallest sum of truncated squared residuals) wins, the attitude is refitted on its inliers
  and stars beyond the threshold of the refit are *unidentified* (``catalog_id = -1``,
  ``ref_icrs = NaN``): every solver then ignores them. A consensus of fewer than three stars cannot
  tell a good pair from a bad one: the frame is left as it is and flagged ``robust_undecided``.
- ``huber`` (Huber 1964 M-estimator by iteratively reweighted least squares): starting from the
  all-star QUEST solution, each star's weight is multiplied by ``w_i = min(1, k / e_i)`` (``k`` the
  threshold) and the attitude refitted, 20 times; the star's ``sigma_px`` is inflated to
  ``sigma_i / sqrt(w_i)``, so a solver weighting by the stars' own sigma (``use_star_sigma``, the
  default) fuses it with a bounded influence.

Stars with 2 x 2 position covariances (a frame where one is not isotropic, see
:mod:`rollingstar.estimators.attitude.star_covariance`): the residual of star ``i`` is its
Mahalanobis distance scaled back to an angle, ``e_i = |W_i E_i^T (b_i - A r_i)| * s_i`` (``W_i`` the
whitening of its tangent-plane covariance, ``s_i = sqrt(trace / 2)`` of that covariance, its
isotropic-equivalent sigma), so the threshold keeps its meaning for a star of isotropic noise while a
residual along a smeared star's long axis counts less than one across it; Huber inflates the
star's whole covariance by ``1 / w_i``.

Stars refer to their own rows' times on a rolling-shutter frame; where a star carries its image
velocity (``vx``, ``vy``, px/s) it is moved to the frame's mean star time first (first order), so
the frame's motion does not count as residual. Without velocities the threshold must exceed the
image motion over a frame (``rate * frame period * focal_px``).
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from rollingstar.estimators.attitude.star_covariance import (
    DirectionCovariance,
    anisotropic_covariance,
    direction_covariance,
)
from rollingstar.estimators.attitude.wahba import quest
from rollingstar.estimators.data import FrameData, StarTable
from rollingstar.sensors.conventions import S_PER_NS

__all__ = ["RobustParams", "robust_gate", "apply_robust", "star_residuals_rad"]

HUBER_ITERATIONS = 20


class RobustParams(BaseModel):
    """Robust gate parameters, mixed into every attitude solver's Params."""

    model_config = ConfigDict(extra="forbid")

    robust: Literal["none", "ransac", "huber"] = Field(
        default="none", description="Outlier gate on the identified stars before solving: 'ransac' unidentifies "
        "stars beyond robust_threshold_px of the consensus attitude; 'huber' down-weights them (M-estimator).")
    robust_threshold_px: float = Field(
        default=3.0, gt=0, description="Gate threshold (px at the focal length): RANSAC inlier radius / Huber k.")
    robust_max_hypotheses: int = Field(
        default=300, ge=1, description="RANSAC: star pairs tried (all pairs when fewer; else drawn with seed 0).")


def star_residuals_rad(R_mats: np.ndarray, body: np.ndarray, ref: np.ndarray,
                       direction: DirectionCovariance | None = None) -> np.ndarray:
    """Angle (rad) between each observation ``b_i`` and the prediction ``R^T r_i``: (H, n) for (H, 3, 3)
    camera-to-ICRS. With ``direction`` (2 x 2 tangent-plane covariances of the ``b_i``): the
    Mahalanobis distance of the tangent-plane residual times the star's isotropic-equivalent sigma
    (module docstring)."""
    pred = np.einsum("hji,nj->hni", R_mats, ref)  # R^T r
    if direction is not None:
        e = np.einsum("nik,hni->hnk", direction.basis, pred - body[None])  # (H, n, 2)
        white = np.einsum("nkl,hnl->hnk", direction.whiten, e)
        scale = np.sqrt(0.5 * np.trace(direction.cov, axis1=1, axis2=2))
        return np.linalg.norm(white, axis=-1) * scale[None]
    chord = np.linalg.norm(pred - body[None], axis=-1)
    return 2.0 * np.arcsin(np.clip(chord / 2.0, 0.0, 1.0))


def _quat_to_mats(q_xyzw: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(q_xyzw).as_matrix()


def _pairs(n: int, max_hypotheses: int) -> np.ndarray:
    i, j = np.triu_indices(n, k=1)
    pairs = np.column_stack([i, j])
    if len(pairs) > max_hypotheses:  # fixed seed: a run is reproducible
        pick = np.random.default_rng(0).choice(len(pairs), size=max_hypotheses, replace=False)
        pairs = pairs[np.sort(pick)]
    return pairs


def _ransac(body, ref, a, thr, max_hypotheses: int, direction=None) -> tuple[np.ndarray, bool]:
    """Inlier mask of the identified stars and whether the consensus was decisive (>= 3 stars)."""
    n = body.shape[0]
    pairs = _pairs(n, max_hypotheses)
    res = quest(ref[pairs], body[pairs], a[pairs])
    ok = res.valid
    if not ok.any():
        return np.ones(n, dtype=bool), False
    mats = _quat_to_mats(res.q_xyzw[ok])
    e = star_residuals_rad(mats, body, ref, direction)  # (H, n)
    inl = e < thr
    count = inl.sum(axis=1)
    cost = np.minimum(e, thr) ** 2
    score = count - cost.sum(axis=1) / (thr ** 2 * (n + 1))  # MSAC tie-break within equal counts
    best = int(np.argmax(score))
    mask = inl[best]
    if mask.sum() < 3:
        return np.ones(n, dtype=bool), False
    refit = quest(ref[mask][None], body[mask][None], a[mask][None])
    if refit.valid[0]:
        e_ref = star_residuals_rad(_quat_to_mats(refit.q_xyzw[:1]), body, ref, direction)[0]
        if (e_ref < thr).sum() >= 3:
            mask = e_ref < thr
    return mask, True


def _huber(body, ref, a, thr, direction=None) -> np.ndarray:
    """Huber weights ``w_i = min(1, k / e_i)`` at the IRLS fixed point (1 for every star if the fit fails)."""
    w = np.ones(body.shape[0])
    for _ in range(HUBER_ITERATIONS):
        res = quest(ref[None], body[None], (a * w)[None])
        if not res.valid[0]:
            return np.ones(body.shape[0])
        e = star_residuals_rad(_quat_to_mats(res.q_xyzw[:1]), body, ref, direction)[0]
        w_new = np.minimum(1.0, thr / np.maximum(e, 1e-300))
        if np.allclose(w_new, w, rtol=1e-6, atol=1e-9):
            break
        w = w_new
    return w


def _gate_inputs(sel: StarTable, camera, default_sigma_px: float, use_star_sigma: bool, star_covariance: bool):
    """Camera and ICRS unit vectors of the selected stars (moved to their mean time when they carry
    image velocities), their isotropic sigma (px), and their pixel and direction covariances when
    the 2 x 2 weighting applies (else None, None)."""
    x, y = sel.x.astype(float), sel.y.astype(float)
    vx, vy = sel.vx, sel.vy
    moving = np.isfinite(vx) & np.isfinite(vy)
    if moving.any():  # to the mean star time, first order in the image velocity
        dt = (sel.t_ns - int(np.mean(sel.t_ns))).astype(float) * S_PER_NS
        x = np.where(moving, x - vx * dt, x)
        y = np.where(moving, y - vy * dt, y)
    body = camera.unproject(x, y).reshape(-1, 3)
    body = body / np.linalg.norm(body, axis=1, keepdims=True)
    ref = sel.ref_icrs / np.linalg.norm(sel.ref_icrs, axis=1, keepdims=True)
    cov_px = anisotropic_covariance(sel, default_sigma_px, use_star_sigma, star_covariance)
    if cov_px is not None:
        direction = direction_covariance(camera, x, y, cov_px)
        return direction.body, ref, np.sqrt(0.5 * (cov_px[:, 0, 0] + cov_px[:, 1, 1])), cov_px, direction
    sigma = np.full(sel.n, float(default_sigma_px))
    if use_star_sigma:
        sigma = np.where(np.isfinite(sel.sigma_px) & (sel.sigma_px > 0), sel.sigma_px, sigma)
    return body, ref, sigma, None, None


def robust_gate(stars: StarTable, camera, params: RobustParams, default_sigma_px: float,
                use_star_sigma: bool = True, star_covariance: bool = True) -> tuple[StarTable, tuple[str, ...]]:
    """The frame's stars with outliers unidentified (ransac) or down-weighted (huber), and flags.

    Only identified stars with finite position and reference take part; fewer than three leave the
    table unchanged (two stars always fit one attitude up to their separation).
    """
    if params.robust == "none" or stars is None or stars.n == 0:
        return stars, ()
    use = stars.identified & np.isfinite(stars.x) & np.isfinite(stars.y) & np.isfinite(stars.ref_icrs).all(axis=1)
    idx = np.flatnonzero(use)
    if idx.size < 3:
        return stars, ()
    body, ref, sigma, cov_px, direction = _gate_inputs(stars.take(idx), camera, default_sigma_px, use_star_sigma,
                                                       star_covariance)
    a = 1.0 / sigma ** 2
    thr = float(params.robust_threshold_px) / float(camera.focal_px)
    if params.robust == "ransac":
        mask, decided = _ransac(body, ref, a, thr, params.robust_max_hypotheses, direction)
        if not decided:
            return stars, ("robust_undecided",)
        out = idx[~mask]
        if out.size == 0:
            return stars, ()
        cid = stars.catalog_id.copy()
        refs = stars.ref_icrs.copy()
        cid[out] = -1
        refs[out] = np.nan
        return stars.with_columns(catalog_id=cid, ref_icrs=refs), (f"outliers_rejected:{out.size}",)
    w = _huber(body, ref, a, thr, direction)
    down = w < 1.0 - 1e-9
    if not down.any():
        return stars, ()
    flags = (f"outliers_downweighted:{int(down.sum())}",)
    sig_all = stars.sigma_px.astype(float).copy()
    sig_all[idx] = sigma / np.sqrt(w)
    if cov_px is None:
        return stars.with_columns(sigma_px=sig_all), flags
    cov = {k: getattr(stars, k).astype(float).copy() for k in ("cov_xx", "cov_xy", "cov_yy")}
    for k, (i, j) in zip(cov, ((0, 0), (0, 1), (1, 1))):
        cov[k][idx] = cov_px[:, i, j] / w
    return stars.with_columns(sigma_px=sig_all, **cov), flags


def apply_robust(frame: FrameData, camera, params: RobustParams, default_sigma_px: float,
                 use_star_sigma: bool = True, star_covariance: bool = True) -> FrameData:
    """:func:`robust_gate` on ``frame.stars``; the flags are added to the frame's."""
    if getattr(params, "robust", "none") == "none":
        return frame
    stars, flags = robust_gate(frame.stars, camera, params, default_sigma_px, use_star_sigma, star_covariance)
    if stars is frame.stars and not flags:
        return frame
    return frame.evolve(stars=stars, flags=frame.flags + flags)
