"""Windowed centroider: gyro-predicted readout windows around guide stars (liu2013 sec 2.1, eqs 8-10)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from estimators.centroiders.base import Centroider
from estimators.centroiders.cog import CogCentroider, CogParams
from estimators.centroiders.window_cog import centroid_windows, cut_windows
from estimators.data import FrameData, SensorContext, StarTable
from estimators.filters.gyro_kf import GyroIntegrator, star_motion_jacobian

NS = 1e-9


class WindowedParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    window_px: int = Field(default=64, ge=8, description="Side of the square readout window around each predicted position (px).")
    n_guide_stars: int | None = Field(
        default=None, ge=1, description="Guide stars tracked (the brightest of a full-frame detection); None: all detected.")
    gyro_bias_rad_s: tuple[float, float, float] = Field(
        default=(0.0, 0.0, 0.0), description="Known (calibrated) gyro bias subtracted from the samples, rad/s.")
    gyro_arw_rad_sqrt_s: float = Field(default=0.0, ge=0, description="Gyro angle random walk (rad/sqrt(s)) for the predicted error.")
    exposure_mean: bool = Field(
        default=True, description="Predict the move of the exposure-mean position (the CoG of a smeared spot) instead of the instant one.")
    cog: CogParams = Field(default_factory=CogParams, description="Centre-of-gravity parameters, used in windows and full frames alike.")
    batch: bool = Field(
        default=True, description="Centroid all windows in one vectorised pass (window_cog); False: one cog call per "
        "window (the original implementation, kept as the reference for tests and the side-by-side timing).")


class WindowedCentroider(Centroider):
    """Centroids only inside small windows predicted from the gyro (liu2013 sec 2.1).

    Frame 0, or any frame where a guide star is lost: full-frame detection with the ``cog`` core
    (:class:`~estimators.centroiders.cog.CogCentroider`, same ``cog`` params); the brightest
    ``n_guide_stars`` spots become the guide stars and are the output.

    Other frames, for every guide star (batched):

    1. prediction, eq (10): ``(x, y)_k = (x, y)_{k-1} + J (x, y)_{k-1} dtheta`` with ``J`` liu2013
       eq (8) derived for our camera convention (:func:`~estimators.filters.gyro_kf.star_motion_jacobian`)
       and ``dtheta`` the gyro angle increment from the previous centroid's time to this frame's
       (:class:`~estimators.filters.gyro_kf.GyroIntegrator`; with ``exposure_mean`` the increment of
       the exposure-window means, see there). For a rolling shutter the new row time uses the
       predicted row.
    2. predicted 1-sigma error per axis (:meth:`predict`): the previous centroid's ``sigma_px``,
       the gyro angle random walk ``F N sqrt(dt)`` and the second-order term ``F |dtheta|^2``
       (neglected by eq 8), added in quadrature.
    3. a ``window_px`` square centred on the rounded prediction, shifted to lie on the detector,
       is centroided with the ``cog`` definition (background = the window's median, noise = its
       robust sigma), all windows stacked and centroided in one vectorised pass
       (:func:`~estimators.centroiders.window_cog.centroid_windows`); the spot nearest the
       prediction is kept. A window without a spot, or two stars claiming one spot, means the star
       is lost: the frame falls back to full-frame detection.

    Output spots are catalogue-agnostic (``catalog_id = -1``: identification stays with the
    identifier stage; the centroider role contract), in guide-star order; ``x, y``, ``flux``,
    ``sigma_px`` etc. are the window CoG's in full-frame pixel coordinates, times from the sensor
    timing of the full-frame row. ``last_mode`` is ``"full"`` or ``"window"`` (diagnostics).
    """

    name = "windowed"
    Params = WindowedParams

    def setup(self, context) -> None:
        super().setup(context)
        cam = context.camera
        p = self.params
        self._full = CogCentroider(**p.cog.model_dump())
        self._full.setup(context)
        self._wh = min(p.window_px, int(cam.height))
        self._ww = min(p.window_px, int(cam.width))
        if p.batch and p.cog.background != "median":
            raise ValueError("windowed: with batch=True cog.background must be 'median' (each window uses its own "
                             "median background); set batch=False to run the cog core per window")
        if p.batch and getattr(p.cog, "max_sharpness", None) is not None:
            raise ValueError("windowed: cog.max_sharpness is not implemented for batched windows; set batch=False")
        bit_depth = getattr(context, "bit_depth", None)
        wcam = replace(cam, width=self._ww, height=self._wh, cx=None, cy=None)
        self._win = CogCentroider(**p.cog.model_dump())  # the per-window reference (batch=False)
        self._win.setup(SensorContext(camera=wcam, timing=context.timing, catalog=None, bit_depth=bit_depth))
        self._saturation = (float(p.cog.saturation_adu) if p.cog.saturation_adu is not None
                            else float(2 ** int(bit_depth) - 1) if bit_depth else None)  # None: the image dtype's max
        self._gyro = GyroIntegrator(p.gyro_bias_rad_s, default_period_s=float(context.timing.frame_period_ns) * NS)
        self._tracks: StarTable | None = None
        self.last_mode = ""

    # ------------------------------------------------------------------ prediction
    def predict(self, t0_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predicted ``(x, y, sigma_px)`` of the guide stars in the frame starting at ``t0_ns``
        (uses the gyro samples added so far)."""
        tr = self._tracks
        timing = self.context.timing
        cam = self.context.camera
        J = star_motion_jacobian(tr.x, tr.y, cam)
        y_guess = tr.y
        for _ in range(2 if timing.effective_line_delay_ns else 1):  # rolling: the row time depends on the predicted row
            row_new = timing.row_start_ns(t0_ns, y_guess)
            if self.params.exposure_mean:
                dtheta = self._gyro.increment(tr.row_time_ns, row_new, int(timing.exposure_ns))
            else:
                dtheta = self._gyro.increment(tr.t_ns, timing.row_mid_exposure_ns(t0_ns, y_guess))
            d = np.einsum("nij,nj->ni", J, dtheta)  # eq (9)
            y_guess = tr.y + d[:, 1]
        dt = np.abs(row_new - tr.row_time_ns) * NS
        f = cam.focal_px
        prev = np.where(np.isfinite(tr.sigma_px), tr.sigma_px, 0.0)
        sigma = np.sqrt(prev**2 + (f * self.params.gyro_arw_rad_sqrt_s) ** 2 * dt
                        + (f * np.sum(dtheta**2, axis=1)) ** 2)
        return tr.x + d[:, 0], tr.y + d[:, 1], sigma  # eq (10)

    def _saturation_of(self, image: np.ndarray) -> float:
        if self._saturation is not None:
            return self._saturation
        return float(np.iinfo(image.dtype).max) if np.issubdtype(image.dtype, np.integer) else np.inf

    # ------------------------------------------------------------------ processing
    def _full_frame(self, frame: FrameData) -> FrameData:
        out = self._full.process(frame)
        stars = out.stars
        if self.params.n_guide_stars is not None:
            stars = stars.take(np.arange(min(self.params.n_guide_stars, stars.n)))
        self._tracks = stars if stars.n else None
        self.last_mode = "full"
        return frame.evolve(stars=stars)

    def process(self, frame: FrameData) -> FrameData:
        self._gyro.add(frame.gyro)
        if frame.image is None:
            raise ValueError(f"frame {frame.index}: no image; the 'windowed' centroider needs image-level recordings")
        if self._tracks is None:
            return self._full_frame(frame)
        image = np.asarray(frame.image)
        if image.shape != self._full._shape:
            raise ValueError(f"frame {frame.index}: image shape {image.shape} differs from the camera's {self._full._shape}")
        px, py, _ = self.predict(frame.t0_ns)
        H, W = image.shape
        finite = np.isfinite(px) & np.isfinite(py)
        if not finite.all():
            return self._full_frame(frame)
        c0 = np.clip(np.rint(px).astype(np.int64) - self._ww // 2, 0, W - self._ww)
        r0 = np.clip(np.rint(py).astype(np.int64) - self._wh // 2, 0, H - self._wh)
        # all windows in one vectorised pass (window_cog; was one cog call per window: 8x -> see
        # docs/reproductions/liu2013.md for the before/after timing)
        c = self.params.cog
        if not self.params.batch:
            return self._windows_loop(frame, image, px, py, r0, c0)
        spots = centroid_windows(cut_windows(image, r0, c0, self._wh, self._ww), px - c0, py - r0,
                                 threshold_sigma=c.threshold_sigma, min_pixels=c.min_pixels, max_pixels=c.max_pixels,
                                 connectivity=c.connectivity, grow_px=c.grow_px, noise_floor_adu=c.noise_floor_adu,
                                 saturation_adu=self._saturation_of(image), reject_border=c.reject_border,
                                 gain_e_per_adu=getattr(c, "gain_e_per_adu", None))
        if not spots.found.all():
            return self._full_frame(frame)
        x = spots.x + c0
        y = spots.y + r0
        timing = self.context.timing
        cat = StarTable.build(x, y, t_ns=timing.row_mid_exposure_ns(frame.t0_ns, y),
                              row_time_ns=timing.row_start_ns(frame.t0_ns, y), flux=spots.flux, peak=spots.peak,
                              npix=spots.npix, saturated=spots.saturated, snr=spots.snr, sigma_px=spots.sigma_px)
        return self._accept(frame, cat)

    def _accept(self, frame: FrameData, stars: StarTable) -> FrameData:
        n = stars.n
        x, y = stars.x, stars.y
        if n > 1 and np.min(np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :]) + np.eye(n) * 1e9) < 1e-6:
            return self._full_frame(frame)  # two guide stars took the same spot: re-acquire
        self._tracks = stars
        self.last_mode = "window"
        return frame.evolve(stars=stars)

    def _windows_loop(self, frame, image, px, py, r0, c0) -> FrameData:
        """The original per-window path: one ``cog`` call per window (reference for ``batch``)."""
        pick: list[StarTable] = []
        for i in range(px.size):
            sub = image[r0[i]:r0[i] + self._wh, c0[i]:c0[i] + self._ww]
            spots = self._win.process(FrameData(index=frame.index, t0_ns=frame.t0_ns, image=sub)).stars
            if spots.n == 0:
                return self._full_frame(frame)
            d2 = (spots.x + c0[i] - px[i]) ** 2 + (spots.y + r0[i] - py[i]) ** 2
            pick.append(spots.take([int(np.argmin(d2))]))
        cat = StarTable(**{f: np.concatenate([getattr(s, f) for s in pick]) for f in StarTable.__dataclass_fields__})
        x, y = cat.x + c0, cat.y + r0
        timing = self.context.timing
        return self._accept(frame, cat.with_columns(x=x, y=y, t_ns=timing.row_mid_exposure_ns(frame.t0_ns, y),
                                                    row_time_ns=timing.row_start_ns(frame.t0_ns, y)))
