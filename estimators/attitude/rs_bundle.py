"""Rolling-shutter bundle adjustment of one frame: one attitude and one body rate shared by every star.

A rolling-shutter frame images each star at its own time ``t_i`` (the mid-exposure of its own
row). With a constant body rate ``omega`` over the frame the attitude at that time is
``R(t_i) = R Exp(omega dt_i)``, ``dt_i = t_i - t_ref``, ``R`` the attitude at the reference time
``t_ref`` (the frame's middle row, mid-exposure), so star ``i`` with catalogue direction ``r_i``
images at ``proj(w_i)``, ``w_i = R(t_i)^T r_i``. The stage fits ``R`` and ``omega`` together, in
two steps:

1. **Positions** (:func:`rollingstar.estimators.attitude.frame_fit.fit_positions`): Gauss-Newton on the stars' measured positions, each
   weighted by its own 2 x 2 covariance in the tangent plane of its direction (the maximum-likelihood
   fit for Gaussian centroid errors; :mod:`rollingstar.estimators.attitude.star_covariance`). A
   perturbation ``(delta, eps)`` of the attitude and the rate moves ``w_i`` by
   ``[w_i]x (delta + eps dt_i)``, the linearisation :func:`rollingstar.pipelines.truth.rate_crb_rad2`
   states; the residuals are evaluated exactly, so the fixed point does not depend on it.
2. **Pixels** (:mod:`rollingstar.estimators.attitude.pixel_bundle`, ``pixels: true`` on an
   image-level recording): the same two unknowns fitted to the pixels of every star's window, the
   star drawn by the rolling-shutter smear model (:mod:`rollingstar.sensors.streak_model`) from its
   predicted position and image velocity, with its flux and local background as per-star
   nuisances. This is the maximum-likelihood estimate from the image itself, the estimator the
   pixel-level Cramér–Rao bound (:mod:`rollingstar.sensors.pixel_crb`) describes.

The initial rate is the frame's rate estimate when an earlier stage made one, else zero; from zero
the position step converges at the rates a frame allows (the stars' times spread over one readout).
With fewer than ``min_rate_stars`` identified stars the rate is not observable from one frame: the
frame's rate (or zero) is held fixed and only the attitude is fitted.

Outputs: an :class:`AttitudeEstimate` at ``t_ref`` with the attitude block of the inverse
information, and ``frame.rate`` (a :class:`RateEstimate` at ``t_ref`` with the rate block).
"""
from __future__ import annotations

import numpy as np
from pydantic import ConfigDict, Field
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.base import AttitudeSolver
from rollingstar.estimators.attitude.frame_fit import fit_positions, star_times, velocity_rate
from rollingstar.estimators.attitude.pixel_bundle import measure_psf, refine_on_pixels
from rollingstar.estimators.attitude.robust import RobustParams, apply_robust
from rollingstar.estimators.attitude.star_covariance import direction_covariance
from rollingstar.estimators.data import AttitudeEstimate, FrameData, RateEstimate, default_sigma_px, frame_camera
from rollingstar.sensors.so3 import rotate_at_rate, wahba

DEFAULT_PSF_SIGMA_PX = 1.0  # the pixel model's PSF sigma on frames before one is measured
MAX_PSF_REMEASURES = 2  # measurements after a misfit frame (a camera whose PSF the model cannot draw misfits on)
HUBER_K = 3.0  # Huber threshold (Mahalanobis sigmas) of the position step that starts the pixel step


class RsBundleParams(RobustParams):
    model_config = ConfigDict(extra="forbid")

    sigma_px: float | None = Field(
        default=None, gt=0, description="1-sigma centroid error (px) of stars without their own covariance; "
        "None: the sensor context's centroid_sigma_px, else 0.05 px.")
    iterations: int = Field(default=2, ge=1, le=20, description="Gauss-Newton iterations of the position step.")
    min_rate_stars: int = Field(default=4, ge=3, description="Fewest identified stars at distinct times for which "
                                "the rate is fitted; below it the frame's rate (or zero) is held.")
    pixels: bool = Field(default=True, description="Refine attitude and rate on the image's pixels (image-level "
                         "recordings) with the rolling-shutter smear model; False: positions only.")
    pixel_iterations: int = Field(default=8, ge=1, le=30, description="Most Gauss-Newton iterations of the pixel "
                                  "step (it stops earlier once a step, or the one predicted after it, is a small "
                                  "fraction of every parameter's sigma).")
    psf_sigma_px: float | None = Field(default=None, gt=0, description="Gaussian PSF sigma of the pixel model "
                                       "(px); None: measured from the first frame's stars, and again (twice at "
                                       "most) after a frame whose stars the model does not explain.")
    window_sigmas: float = Field(default=3.0, gt=1, description="Half width of each star's pixel window beyond "
                                 "its streak, in PSF sigmas.")


class RsBundleSolver(AttitudeSolver):
    """Attitude and body rate of a rolling-shutter frame fitted together (module docstring)."""

    name = "rs-bundle"
    Params = RsBundleParams
    provides = frozenset({"attitude", "rate"})

    def setup(self, context) -> None:
        super().setup(context)
        self._sigma_px = default_sigma_px(self.params.sigma_px, context)
        self._psf_sigma_px = self.params.psf_sigma_px  # None until measured
        self._psf_remeasures = 0

    def process(self, frame: FrameData) -> FrameData:
        p = self.params
        camera = frame_camera(frame, self.context)
        frame = apply_robust(frame, camera, p, self._sigma_px, True, True)
        t_ref = int(self.context.timing.frame_reference_ns(frame.t0_ns))
        stars = frame.stars.take(frame.stars.identified) if frame.stars is not None else None
        if stars is not None:
            finite = np.isfinite(stars.x) & np.isfinite(stars.y) & np.isfinite(stars.ref_icrs).all(axis=1)
            stars = stars.take(finite)
        n = 0 if stars is None else stars.n
        if n < 2:
            return self._invalid(frame, t_ref, n, f"fewer than 2 identified stars with finite positions ({n})")
        omega0 = self._initial_rate(frame, camera, stars)
        dt = star_times(stars, t_ref)
        fit_rate = n >= p.min_rate_stars and np.ptp(dt) > 0
        ref = stars.ref_icrs / np.linalg.norm(stars.ref_icrs, axis=1, keepdims=True)
        d = direction_covariance(camera, stars.x, stars.y, stars.position_covariance(self._sigma_px))
        body0 = rotate_at_rate(omega0, d.body, dt)
        R0 = wahba(ref, body0)  # the start: Wahba's problem on the directions at the start rate
        huber = HUBER_K if p.pixels and frame.image is not None else None  # a robust start for the pixel step
        R, omega, info = fit_positions(R0, omega0, ref, dt, d, p.iterations + (2 if huber else 0), fit_rate, huber)
        flags = frame.flags
        if p.pixels and frame.image is not None:
            R, omega, info, flags, used = self._refine_on_pixels(frame, camera, stars, R, omega, info, fit_rate, t_ref)
            frame = frame.evolve(psf_sigma_px=used)  # the stated or measured width this frame used; None: the default
        return self._estimates(frame.evolve(flags=flags), t_ref, n, R, omega, info, fit_rate)

    def _initial_rate(self, frame: FrameData, camera, stars) -> np.ndarray:
        if frame.rate is not None and frame.rate.valid and np.all(np.isfinite(frame.rate.omega_rad_s)):
            return np.asarray(frame.rate.omega_rad_s, dtype=float)
        from_velocities = velocity_rate(camera, stars)
        return np.zeros(3) if from_velocities is None else from_velocities

    def _refine_on_pixels(self, frame, camera, stars, R, omega, info, fit_rate, t_ref):
        if self._psf_sigma_px is None:
            self._psf_sigma_px = measure_psf(frame, self.context, camera, stars, R, omega, t_ref,
                                             self.params.window_sigmas)
        # too few stars to measure the width on: the default for this frame, measured on the next
        used = self._psf_sigma_px
        R, omega, info, flags = refine_on_pixels(frame, self.context, camera, stars, R, omega, info, fit_rate, t_ref,
                                                 self.params, DEFAULT_PSF_SIGMA_PX if used is None else used)
        misfit = any(f.startswith("pixel_step_skipped:model_misfit") for f in flags)
        if self.params.psf_sigma_px is None and misfit and self._psf_remeasures < MAX_PSF_REMEASURES:
            self._psf_sigma_px = None  # measured again on the next frame
            self._psf_remeasures += 1
        return R, omega, info, flags, used

    @property
    def psf_sigma_px(self) -> float | None:
        """The PSF sigma (px) the pixel step works with: the parameter, or the one measured."""
        return self._psf_sigma_px

    def _estimates(self, frame: FrameData, t_ref: int, n: int, R: Rotation, omega, info, fit_rate: bool) -> FrameData:
        try:
            cov = np.linalg.inv(info)
        except np.linalg.LinAlgError:
            return self._invalid(frame, t_ref, n, "degenerate geometry: attitude and rate not observable")
        cov = 0.5 * (cov + cov.T)
        est = AttitudeEstimate(t_ns=t_ref, q_xyzw=R.as_quat(canonical=True), n_stars=n, valid=True,
                               covariance_rad2=cov[:3, :3])
        if not fit_rate:
            return frame.evolve(attitudes=frame.attitudes + (est,))
        rate = RateEstimate(t_ns=t_ref, omega_rad_s=np.asarray(omega, dtype=float), covariance=cov[3:, 3:])
        return frame.evolve(attitudes=frame.attitudes + (est,), rate=rate)

    @staticmethod
    def _invalid(frame: FrameData, t_ns: int, n: int, reason: str) -> FrameData:
        est = AttitudeEstimate.invalid(t_ns, n, reason)
        return frame.evolve(attitudes=frame.attitudes + (est,), flags=frame.flags + ("attitude_invalid",))
