"""Windowed centroider: gyro-predicted readout windows around guide stars (liu2013 sec 2.1, eqs 8-10)."""
from __future__ import annotations

from dataclasses import replace
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from rollingstar.estimators.centroiders.base import Centroider
from rollingstar.estimators.centroiders.cog import CogCentroider, CogParams
from rollingstar.estimators.centroiders.covariance import effective_gain, isotropic_sigma
from rollingstar.estimators.centroiders.edge import with_edge_covariance
from rollingstar.estimators.centroiders.window_cog import (
    centroid_windows,
    cut_windows,
    median_rows,
    robust_sigma_rows,
)
from rollingstar.estimators.centroiders.window_gyro import FastGyroIntegrator
from rollingstar.estimators.centroiders.window_kernel import (
    any_coincident,
    any_near_edge,
    centroid_windows_kernel,
    predict_step,
    track_windows,
    truncated_normal_std,
    window_covariance,
    workspace,
)
from rollingstar.estimators.data import FrameData, SensorContext, StarTable
from rollingstar.sensors.conventions import S_PER_NS


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
        default=True, description="Centroid all windows in one pass (see kernel); False: one cog call per "
        "window (the original implementation, kept as the reference for tests and the side-by-side timing).")
    kernel: Literal["compiled", "numpy"] = Field(
        default="compiled", description="With batch: 'compiled' reads the windows in place with the numba kernel "
        "(window_kernel); 'numpy': the vectorised numpy pass over the stacked windows (window_cog: the reference the "
        "compiled kernel is timed and checked against; needs background='window').")
    background: Literal["tracked", "window"] | None = Field(
        default=None, description="'tracked': each window's background and noise are measured once (its median and "
        "robust sigma, at the first windowed frame after an acquisition) and then followed by a running mean over "
        "background_frames frames of its background pixels (outside the spots, within 3 sigma); 'window': each "
        "window's own median and robust sigma every frame (the cog definition per window). None: 'tracked' with the "
        "compiled kernel, 'window' with kernel='numpy' or batch=False (the only one they implement).")
    background_frames: float = Field(
        default=100.0, ge=1.0, description="Time constant (frames) of the tracked background and noise (an "
        "exponential running mean; 100 frames = 1 s at 100 Hz).")


class WindowedCentroider(Centroider):
    """Centroids only inside small windows predicted from the gyro (liu2013 sec 2.1).

    Frame 0, or any frame where a guide star is lost: full-frame detection with the ``cog`` core
    (:class:`~rollingstar.estimators.centroiders.cog.CogCentroider`, same ``cog`` params); the brightest
    ``n_guide_stars`` spots become the guide stars and are the output.

    Other frames, for every guide star (batched):

    1. prediction, eq (10): ``(x, y)_k = (x, y)_{k-1} + J (x, y)_{k-1} dtheta`` with ``J`` liu2013
       eq (8) derived for our camera convention (:func:`~rollingstar.estimators.filters.gyro_kf.star_motion_jacobian`)
       and ``dtheta`` the gyro angle increment from the previous centroid's time to this frame's
       (:class:`~rollingstar.sensors.gyro.GyroIntegrator`; with ``exposure_mean`` the increment of
       the exposure-window means, see there). For a rolling shutter the new row time uses the
       predicted row. Compiled, with steps 3-4, in one call per frame
       (:func:`~rollingstar.estimators.centroiders.window_kernel.track_windows`; the gyro history is
       :class:`~rollingstar.estimators.centroiders.window_gyro.FastGyroIntegrator`, the same model compiled).
    2. predicted 1-sigma error per axis (:meth:`predict`): the previous centroid's ``sigma_px``,
       the gyro angle random walk ``F N sqrt(dt)`` and the second-order term ``F |dtheta|^2``
       (neglected by eq 8), added in quadrature.
    3. a ``window_px`` square centred on the rounded prediction, shifted to lie on the detector,
       is centroided with the ``cog`` definition, all windows in one compiled pass that reads them
       in place (:func:`~rollingstar.estimators.centroiders.window_kernel.centroid_windows_at`; ``kernel:
       numpy``: the vectorised numpy pass :func:`~rollingstar.estimators.centroiders.window_cog.centroid_windows`,
       same spots); the spot nearest the prediction is kept. A window without a spot, or two stars
       claiming one spot, means the star is lost: the frame falls back to full-frame detection.
    4. background ``b_k`` and noise ``s_k`` of window ``k`` (``background``): ``window`` takes the
       window's median and robust sigma every frame (``cog`` per window). ``tracked`` (default)
       takes them once, at the first windowed frame after an acquisition, and then follows them
       with an exponential running mean over ``background_frames`` frames of the window's
       background pixels (outside the grown spots, ``|I - b_k| < 3 s_k``):
       ``b_k += a mean(d)``, ``s_k^2 = (1 - a) s_k^2 + a var(d) / 0.98658^2`` (``a`` = 1 /
       ``background_frames``; 0.98658: the std of a unit normal truncated to +-3). Physics: the
       background (sky, dark current, bias) and the pixel noise drift over seconds to minutes
       (temperature, the slow sweep of the boresight across sky gradients), not from one 10 ms
       frame to the next; re-estimating them per frame from 4096 pixels only adds noise (the
       median of one window has a standard error of ~0.02 s and is biased upwards by the star's
       own pixels, ~0.02 s for a 5 x 5 px spot in 64 x 64 px), while the running mean averages
       ~100 frames and excludes the spot. It also removes two sorts per window and frame, most
       of the cost (``benchmarks/windowed_speed.py``).

    Output spots are catalogue-agnostic (``catalog_id = -1``: identification stays with the
    identifier stage; the centroider role contract), in guide-star order; ``x, y``, ``flux``,
    ``sigma_px``, ``cov_*`` etc. are the window CoG's in full-frame pixel coordinates (the
    covariance as ``cog``'s, :mod:`rollingstar.estimators.centroiders.covariance`), times from the
    sensor timing of the full-frame row. A window keeps one spot per guide star, so a smear the
    threshold broke into pieces is not recognised there (``cog`` does it on the full frames;
    estimators/centroiders/fragments.py). ``last_mode`` is ``"full"`` or ``"window"`` (diagnostics).
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
        compiled = p.batch and p.kernel == "compiled"
        if not compiled and p.background == "tracked":
            raise ValueError("windowed: background='tracked' needs the compiled kernel (batch=True, kernel='compiled'); "
                             "kernel='numpy' and batch=False implement background='window' only")
        self._tracked = compiled and p.background != "window"
        if p.batch and p.cog.background != "median":
            raise ValueError("windowed: with batch=True cog.background must be 'median' (each window uses its own "
                             "median background); set batch=False to run the cog core per window")
        if p.batch and getattr(p.cog, "max_sharpness", None) is not None:
            raise ValueError("windowed: cog.max_sharpness is not implemented for batched windows; set batch=False")
        bit_depth = getattr(context, "bit_depth", None)
        wcam = replace(cam, width=self._ww, height=self._wh, cx=None, cy=None)
        # the per-window reference (batch=False); a window's border is not the detector's edge, which
        # is handled in full-frame coordinates (_edge_cut) as on the batched paths
        self._win = CogCentroider(**(p.cog.model_dump() | {"edge_sigma": False}))
        self._win.setup(SensorContext(camera=wcam, timing=context.timing, catalog=None, bit_depth=bit_depth,
                                      gain_e_per_adu=getattr(context, "gain_e_per_adu", None)))
        self._cov_gain = effective_gain(p.cog.gain_e_per_adu, context)
        self._saturation = (float(p.cog.saturation_adu) if p.cog.saturation_adu is not None
                            else float(2 ** int(bit_depth) - 1) if bit_depth else None)  # None: the image dtype's max
        self._gyro = FastGyroIntegrator(p.gyro_bias_rad_s, default_period_s=float(context.timing.frame_period_ns) * S_PER_NS)
        self._tracks: StarTable | None = None
        self._bg: np.ndarray | None = None  # tracked background / noise per guide star (ADU)
        self._noise: np.ndarray | None = None
        self._n_frames = 0
        self._exposure_ns = int(context.timing.exposure_ns)
        self._line_delay_ns = int(context.timing.effective_line_delay_ns)
        self._geometry = (float(cam.cx), float(cam.cy), float(cam.focal_px), int(cam.height), int(cam.width),
                          self._wh, self._ww)
        c = p.cog
        self._kernel_args = (float(c.threshold_sigma), int(c.min_pixels), -1 if c.max_pixels is None else int(c.max_pixels),
                             c.connectivity == 8, int(c.grow_px))
        clip = min(3.0, float(c.threshold_sigma))  # background pixels: |I - b| < clip s (below threshold)
        self._track_args = (self._line_delay_ns, self._exposure_ns, *self._geometry)
        self._kernel_args2 = (bool(c.reject_border), 0.0 if c.gain_e_per_adu is None else float(c.gain_e_per_adu),
                              self._cov_gain or 0.0, 1.0 / p.background_frames if self._tracked else 0.0, float(c.noise_floor_adu),
                              clip, truncated_normal_std(clip), *workspace(self._wh * self._ww))
        self.last_mode = ""

    # ------------------------------------------------------------------ prediction
    def predict(self, t0_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predicted ``(x, y, sigma_px)`` of the guide stars in the frame starting at ``t0_ns``
        (uses the gyro samples added so far)."""
        x, y, _, _, dtheta, dt = self._predict_windows(t0_ns)
        f = self.context.camera.focal_px
        prev = np.where(np.isfinite(self._tracks.sigma_px), self._tracks.sigma_px, 0.0)
        sigma = np.sqrt(prev**2 + (f * self.params.gyro_arw_rad_sqrt_s) ** 2 * dt
                        + (f * np.sum(dtheta**2, axis=1)) ** 2)
        return x, y, sigma

    def _predict_windows(self, t0_ns: int):
        """Eq (10), compiled (:func:`~rollingstar.estimators.centroiders.window_kernel.predict_step`): predicted
        ``px, py``, window origins ``r0, c0``, gyro increments ``dtheta`` (n, 3), their spans (s)."""
        tr = self._tracks
        g = self._gyro
        t_prev = tr.row_time_ns if self.params.exposure_mean else tr.t_ns
        px, py, r0, c0, dtheta, t_new = predict_step(tr.x, tr.y, t_prev, g.tau, g.psi, g.theta, g.rate,
                                                     g.origin_ns or 0, *self._timing_args(t0_ns), *self._geometry)
        return px, py, r0, c0, dtheta, np.abs(t_new - t_prev) * S_PER_NS

    def _timing_args(self, t0_ns: int) -> tuple:
        return self.params.exposure_mean, int(t0_ns), self._line_delay_ns, self._exposure_ns

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
        self._bg = self._noise = None
        self.last_mode = "full"
        return out.evolve(stars=stars)  # with cog's flags (edge_truncated_stars:N counts its detections)

    def process(self, frame: FrameData) -> FrameData:
        self._gyro.add(frame.gyro)
        if frame.image is None:
            raise ValueError(f"frame {frame.index}: no image; the 'windowed' centroider needs image-level recordings")
        if self._tracks is None:
            return self._full_frame(frame)
        image = np.asarray(frame.image)
        if image.shape != self._full._shape:
            raise ValueError(f"frame {frame.index}: image shape {image.shape} differs from the camera's {self._full._shape}")
        self._n_frames += 1
        if self._n_frames % 256 == 0:
            self._gyro.trim(frame.t0_ns)  # bounded gyro history (keep_s); the increments span one frame
        p = self.params
        if image.dtype == bool:
            image = image.astype(np.uint8)
        if self._tracked and self._bg is not None:
            # the default: prediction, windows, background update and checks in one compiled call
            tr = self._tracks
            g = self._gyro
            bg, noise = self._bg.copy(), self._noise.copy()  # as the kernel uses them (it updates them in place)
            status, vals, npix, saturated, times = track_windows(
                image, image.dtype.kind in "iu", tr.x, tr.y, tr.row_time_ns if p.exposure_mean else tr.t_ns, g.tau,
                g.psi, g.theta, g.rate, g.origin_ns or 0, p.exposure_mean, int(frame.t0_ns), *self._track_args,
                self._bg, self._noise, *self._kernel_args, self._saturation_of(image), *self._kernel_args2)
            if status:
                return self._full_frame(frame)  # a star lost, or two on one spot: re-acquire
            return self._table(frame, *self._kernel_columns(vals, saturated, image, bg, noise), npix, saturated, times)
        px, py, r0, c0, _, _ = self._predict_windows(frame.t0_ns)
        if not (np.isfinite(px.sum()) and np.isfinite(py.sum())):
            return self._full_frame(frame)
        c = p.cog
        if not p.batch:
            return self._windows_loop(frame, image, px, py, r0, c0)
        if p.kernel == "numpy":  # the previous path: stacked windows, vectorised numpy
            spots = centroid_windows(cut_windows(image, r0, c0, self._wh, self._ww), px - c0, py - r0,
                                     threshold_sigma=c.threshold_sigma, min_pixels=c.min_pixels, max_pixels=c.max_pixels,
                                     connectivity=c.connectivity, grow_px=c.grow_px, noise_floor_adu=c.noise_floor_adu,
                                     saturation_adu=self._saturation_of(image), reject_border=c.reject_border,
                                     gain_e_per_adu=c.gain_e_per_adu, cov_gain_e_per_adu=self._cov_gain)
            found = spots.found
            cols = (spots.x + c0, spots.y + r0, spots.flux, spots.peak, spots.snr, spots.cov,
                    spots.npix.astype(np.int64), spots.saturated)
        else:  # compiled kernel with each window's own background (background='window', or the first windowed frame)
            self._bg, self._noise = self._window_background(image, r0, c0)
            found, vals, npix, saturated, _ = centroid_windows_kernel(
                image, image.dtype.kind in "iu", r0, c0, self._wh, self._ww, px, py, self._bg, self._noise,
                *self._kernel_args, self._saturation_of(image), *self._kernel_args2)
            cols = (*self._kernel_columns(vals, saturated, image, self._bg, self._noise), npix, saturated)
        if not found.all():
            return self._full_frame(frame)
        if found.size > 1 and any_coincident(cols[0], cols[1], 1e-6):
            return self._full_frame(frame)  # two guide stars took the same spot: re-acquire
        return self._table(frame, *cols)

    def _kernel_columns(self, vals: np.ndarray, saturated: np.ndarray, image: np.ndarray, bg: np.ndarray,
                        noise: np.ndarray) -> tuple:
        """The kernel's ``x, y, flux, peak, snr`` and the spots' position covariance (3, n) from its
        moments (``bg``, ``noise``: each window's, as the kernel used them)."""
        cov = window_covariance(vals, saturated, bg, noise, float(self.params.cog.threshold_sigma), self._cov_gain,
                                self._saturation_of(image))
        return vals[0], vals[1], vals[2], vals[3], vals[4], cov

    def _table(self, frame: FrameData, x, y, flux, peak, snr, cov, npix, saturated, times=None) -> FrameData:
        """The guide stars' spots as the frame's stars (they become the tracks); ``cov`` (3, n) their
        position covariance; ``times``: their (mid-exposure, row start) from the compiled path, else
        from the sensor timing."""
        if times is None:
            timing = self.context.timing
            times = timing.row_mid_exposure_ns(frame.t0_ns, y), timing.row_start_ns(frame.t0_ns, y)
        cov, cut = self._edge_cut(x, y, flux, peak, cov)
        n = x.size
        unknown = np.full(5 * n, np.nan)  # vx, vy, ref_icrs: one allocation, contiguous views
        # the table directly (StarTable.build's checks and broadcasts cost more than the kernel here)
        stars = StarTable(x=x, y=y, t_ns=times[0], row_time_ns=times[1], flux=flux, peak=peak, npix=npix,
                          saturated=saturated, snr=snr, sigma_px=isotropic_sigma(cov), cov_xx=cov[0], cov_xy=cov[1],
                          cov_yy=cov[2], vx=unknown[:n], vy=unknown[n:2 * n],
                          catalog_id=np.full(n, -1, dtype=np.int64), ref_icrs=unknown[2 * n:].reshape(n, 3))
        self._tracks = stars
        self.last_mode = "window"
        return self._edge_flag(frame.evolve(stars=stars), cut)

    def _edge_cut(self, x, y, flux, peak, cov) -> tuple[np.ndarray, np.ndarray | None]:
        """``cov`` (rows ``xx, xy, yy``) with the CoG bias of stars cut by the detector edge added
        (edge.py, as ``cog`` does on full frames) and the mask of those stars (None: none near the
        edge, the usual case, decided by one compiled call). A window does not say which spots
        reach the outermost rows/columns, so the model alone decides (an upper estimate for a spot
        that stops short)."""
        H, W = self._full._shape
        if not self.params.cog.edge_sigma or not any_near_edge(x, y, flux, peak, W, H):
            return cov, None
        return with_edge_covariance(cov, x, y, flux, peak, (H, W))

    @staticmethod
    def _edge_flag(frame: FrameData, cut: np.ndarray | None) -> FrameData:
        n = 0 if cut is None else int(cut.sum())
        return frame.flagged(f"edge_truncated_stars:{n}") if n else frame

    def _window_background(self, image: np.ndarray, r0: np.ndarray, c0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each window's median and robust sigma (floored): the ``cog`` definition per window."""
        stack = cut_windows(image, r0, c0, self._wh, self._ww).astype(float).reshape(r0.size, -1)
        bg = median_rows(stack)
        noise = np.maximum(robust_sigma_rows(stack - bg[:, None], np.zeros(r0.size)), self.params.cog.noise_floor_adu)
        return bg, noise


    def _accept(self, frame: FrameData, stars: StarTable) -> FrameData:
        if stars.n > 1 and any_coincident(stars.x, stars.y, 1e-6):
            return self._full_frame(frame)  # two guide stars took the same spot: re-acquire
        cov, cut = self._edge_cut(stars.x, stars.y, stars.flux, stars.peak,
                                  np.stack([stars.cov_xx, stars.cov_xy, stars.cov_yy]))
        if cut is not None:
            stars = stars.with_columns(sigma_px=isotropic_sigma(cov), cov_xx=cov[0], cov_xy=cov[1], cov_yy=cov[2])
        self._tracks = stars
        self.last_mode = "window"
        return self._edge_flag(frame.evolve(stars=stars), cut)

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
        cat = StarTable.concat(*pick)
        x, y = cat.x + c0, cat.y + r0
        timing = self.context.timing
        return self._accept(frame, cat.with_columns(x=x, y=y, t_ns=timing.row_mid_exposure_ns(frame.t0_ns, y),
                                                    row_time_ns=timing.row_start_ns(frame.t0_ns, y)))
