"""Per-lens joint calibration from identified real sky images (docs/real-data.md).

One lens (one folder of images) has one focal length, radial distortion and principal point; each
image has its own attitude. :func:`calibrate_lens` fits them together
(:func:`rollingstar.estimators.identifiers.camera_fit.fit_camera`) to the stars each image's lost-in-space
identification matched, rejects matches whose residual exceeds ``clip`` robust standard
deviations (``1.4826 * median |r|``, at least ``min_clip_px``) and refits once. Uncertainties are
the fit's ``s^2 (J^T J)^-1`` (scatter-scaled). :func:`leave_one_out` gives, for every image, the
lens model fitted to the *other* images of its folder, so that the image can be identified and
verified with a calibration it did not take part in.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.estimators.identifiers.camera_fit import (
    INTRINSICS,
    CameraFit,
    RadialCamera,
    fit_camera,
)


@dataclass(frozen=True)
class ImageMatches:
    """The identified stars of one image: observed pixels, catalogue directions, starting attitude."""

    name: str
    x: np.ndarray
    y: np.ndarray
    ref_icrs: np.ndarray
    attitude: Rotation


def lens_folder(group: str, name: str) -> str:
    """The calibration unit of an image: ``tetra3`` or the creusot folder of one lens state
    (``16mm_checker_2``, ``16mm_checker_calib/distorted``, ...)."""
    if group != "creusot":
        return group
    parts = name.split("/")
    return "/".join(parts[:2]) if parts[0].endswith("_calib") else parts[0]


def calibrate_lens(images: list[ImageMatches], camera: RadialCamera, fit=INTRINSICS, clip: float = 5.0,
                   min_clip_px: float = 1.0) -> tuple[CameraFit, list[np.ndarray]]:
    """Joint fit over ``images`` (module docstring); returns the fit and each image's kept-star mask."""
    obs = [(m.x, m.y, m.ref_icrs) for m in images]
    att = [m.attitude for m in images]
    first = fit_camera(obs, att, camera, fit=fit)
    norms = [np.hypot(r[:, 0], r[:, 1]) for r in first.residuals]
    bound = max(min_clip_px, clip * 1.4826 * float(np.median(np.concatenate(norms))))
    keep = [nrm <= bound for nrm in norms]
    obs = [(x[k], y[k], r[k]) for (x, y, r), k in zip(obs, keep)]
    return fit_camera(obs, list(first.attitudes), first.camera, fit=fit), keep


def leave_one_out(images: list[ImageMatches], camera: RadialCamera, fit=INTRINSICS) -> list[CameraFit]:
    """For each image the lens calibration fitted to the others (needs at least three images)."""
    if len(images) < 3:
        raise ValueError(f"leave-one-out calibration needs at least 3 images, got {len(images)}")
    return [calibrate_lens(images[:i] + images[i + 1:], camera, fit=fit)[0] for i in range(len(images))]


def calibration_summary(fitted: CameraFit, keep: list[np.ndarray], images: list[ImageMatches], width: int) -> dict:
    """JSON-ready table row: values, 1-sigma, RMS, stars used/clipped, per-image RMS."""
    cam = fitted.camera
    return {
        "images": [m.name for m in images], "n_images": len(images), "n_stars": fitted.n_stars,
        "n_clipped": int(sum((~k).sum() for k in keep)),
        "values": fitted.values, "sigma": fitted.sigma, "rms_px": fitted.rms_px,
        "rms_per_image_px": fitted.rms_per_image().tolist(),
        "fov_deg": float(np.degrees(2 * np.arctan(width / 2 / cam.focal_px))),
        "edge_distortion_px": edge_distortion_px(cam, width),
    }


def edge_distortion_px(camera: RadialCamera, width: int) -> float:
    """Radial displacement (px) the fitted distortion causes at the middle of the detector's side
    edge (``r = W / 2`` from the principal point): ``f rho (k1 rho^2 + k2 rho^4)``, ``rho = W / (2 f)``."""
    rho = width / 2.0 / camera.focal_px
    return float(camera.focal_px * rho * (camera.k1 * rho**2 + camera.k2 * rho**4))
