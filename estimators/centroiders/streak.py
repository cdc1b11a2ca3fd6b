"""Streak-aware centroider: matched-filter detection along the expected motion, then a
maximum-likelihood fit of the rolling-shutter streak model to each star's pixels."""
from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from rollingstar.estimators.centroiders.base import Centroider
from rollingstar.estimators.centroiders.cog import (
    CogCentroider,
    _interp_matrix,
    _subsample_step,
    _tile_medians,
    median,
    robust_sigma,
)
from rollingstar.estimators.centroiders.covariance import effective_gain, isotropic_sigma
from rollingstar.estimators.centroiders.edge import with_edge_covariance
from rollingstar.estimators.centroiders.psf_width import measure_psf_sigma
from rollingstar.estimators.centroiders.streak_kernel import levenberg_marquardt, star_pixels, window_moments
from rollingstar.estimators.centroiders.window_kernel import centroid_windows_at
from rollingstar.estimators.data import FrameData, StarTable, frame_camera
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.effects.geometry import image_velocity, rotation_jacobian
from rollingstar.sensors.so3 import rotate_at_rate
from rollingstar.sensors.streak_model import effective_sigma, streak_mu

SLOW_STREAK_PX = 1.0  # an expected streak shorter than this starts its fit at rest
# the sky that entered through an edge is searched once it has moved in this far since the edge's
# last search: a new star is found within 8 px of the edge, where a tracked frame's 24 px window
# still holds it (a slow drift is searched every few frames instead of every frame)
NEW_SKY_PX = 8.0
LONG_STREAK_PX = 16.0  # streaks at least this long are detected on 4 x 4 bins, shorter ones on 2 x 2
MARGIN_SIGMAS = 3.0  # PSF widths around the expected streak in a fit window (besides half a detection bin)
FIT_TOLERANCE_PX = 1e-3  # the fit stops when no star's position step exceeds this,
STEP_SIGMAS = 0.1  # or none of its position and velocity steps exceeds this fraction of its sigma
CONVERGED_DAMPING = 0.1  # ... at a damping this low (the step within ~10 % of the Gauss-Newton step)
RIDGE = 1e-12  # added to the damped normal matrix: a star without usable pixels takes zero steps
FROZEN_VELOCITY_ITERATIONS = 2  # first iterations of the fit with the velocity held at its guess
MIN_STARS_FOR_RATE = 3  # stars needed to fit the body rate kept for the next frame
SIGN_MATCH_PX = 5.0  # a star moved from the previous frame lands this close to one of this frame's
# pixels of a tracked frame's noise and background-level sample: the level's standard error is
# then 1.25 sigma / 64 (a full search's, from cog's 16384, is half that)
TRACKED_SAMPLE_PX = 4096
ROUND_WINDOW_PX = 24  # window of a round spot's CoG in a tracked frame (a saturated bright star's spot fits)
SAME_SPOT_PX = 1.0  # spots closer than this are one
MAX_KERNELS = 256  # matched filters kept (by streak length in whole pixels and bin)
DEFAULT_PSF_SIGMA_PX = 1.0  # the model's PSF sigma until a later stage measures the camera's
PSF_CHANGE = 0.05  # a measured PSF sigma this far (relative) from the one in use replaces it
# A fit with an expected velocity must come within this fraction of it plus VELOCITY_SLACK_PX of
# streak length over the exposure (a fit across two collinear streaks, or onto a neighbour, is much
# longer or turned; a PSF 30 % wider than the model's passes for a 3 px smear)
VELOCITY_TOLERANCE = 0.2
SEPARABLE_RANK_TOLERANCE = 1e-3  # singular values of a matched filter below this fraction are left out
VELOCITY_SLACK_PX = 4.0


class StreakParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    threshold_sigma: float = Field(default=5.0, gt=0, description="Detection threshold of the matched filter, in "
                                   "sigmas of its output noise.")
    min_snr: float = Field(default=5.0, ge=0, description="Smallest fitted flux over its standard deviation kept.")
    psf_sigma_px: float | None = Field(default=None, gt=0, description="Gaussian PSF sigma of the model (px); "
                                       "None: measured from the stars of the first full search (1 px before), and taken from a "
                                       "later stage that measures it (rs-bundle does) when it differs by more than 5 %.")
    background: Literal["median", "tiles", "map"] = Field(
        default="median", description="Background model, as the cog centroider's: one global median, bilinear tile "
        "medians, or tile medians median-filtered over map_filter_tiles tiles.")
    tile_px: int = Field(default=64, ge=4, description="Tile size (px) for background='tiles' or 'map'.")
    map_filter_tiles: int = Field(default=3, ge=1, description="Median-filter width (tiles) of background='map'.")
    gain_e_per_adu: float | None = Field(default=None, gt=0, description="Conversion gain (e-/ADU) of the stars' "
                                         "shot noise; None: the sensor context's (none when unknown).")
    saturation_adu: float | None = Field(default=None, description="Saturation level (ADU); None: 2**bit_depth - 1 "
                                         "from the context, else the image dtype's maximum.")
    use_gyro: bool = Field(default=True, description="Take the expected motion from the frame's gyro samples "
                           "when it has any.")
    search_directions: int = Field(default=8, ge=1, description="Directions (over 180 deg) of the cold-start search.")
    search_lengths_px: tuple[float, ...] = Field(default=(6.0, 12.0, 24.0, 40.0), description="Streak lengths (px) "
                                                 "of the cold-start search, besides a motionless star.")
    detect_tile_px: int = Field(default=256, ge=32, description="Tiles (px) of one matched filter each when the "
                                "expected motion is known (the velocity at the tile's centre).")
    max_iterations: int = Field(default=15, ge=1, description="Levenberg-Marquardt iterations of the fit.")
    velocity_prior_px_s: float = Field(default=5000.0, gt=0, description="Sigma (px/s) of a weak zero-mean prior on "
                                       "each star's velocity: keeps the fit of a motionless star on a global "
                                       "shutter well posed.")
    edge_velocity_sigma_px_s: float = Field(
        default=20.0, gt=0, description="Sigma (px/s) of the prior on the velocity of a streak the detector edge cuts, "
        "centred on the expected velocity (gyro or previous frame): the visible part alone cannot tell the streak's "
        "length from its position.")
    noise_floor_adu: float = Field(default=float(1.0 / np.sqrt(12.0)), gt=0,
                                   description="Smallest noise sigma used (ADU): the quantisation noise of integer pixels.")
    track_windows: bool = Field(default=True, description="Once a frame's stars and the body rate are known, fit "
                                "the next frame's stars in windows around their positions moved by the rate, and "
                                "search only the sky that entered the detector since (a full-frame search again when "
                                "fewer than redetect_fraction of the last full search's stars remain).")
    redetect_fraction: float = Field(default=0.75, gt=0, le=1, description="Fraction of the last full-frame "
                                     "search's stars below which a tracked frame is searched over the full frame.")
    track_margin_px: float = Field(default=1.0, gt=0, description="Prediction error (px) a tracked star's window "
                                   "allows besides the streak and 3 PSF widths.")
    full_search_frames: int = Field(default=16, ge=0, description="A tracked frame is searched in full after this "
                                    "many tracked frames (a star the last full search missed, e.g. one of two "
                                    "collinear streaks it took as a blend, is found again). 0: only when stars "
                                    "are lost.")
    coast_frames: int = Field(default=2, ge=0, description="Frames a tracked star missing from its window is still "
                              "looked for (a faint star that dipped below min_snr).")
    cog_below_px: float = Field(default=0.0, ge=0, description="When the expected motion is known and no star's "
                                "streak is expected longer than this (px over one exposure), centroid the frame with "
                                "the cog centroider (same background model) instead: faster, and as good for "
                                "round spots. 0: never.")


class _Background(NamedTuple):
    """The frame's background (ADU): one level, or tile medians interpolated bilinearly (``map``:
    median-filtered over the tile grid first), as the ``cog`` centroider's."""

    tiles: np.ndarray  # (ny, nx) tile medians; (1, 1) for one global level
    centres_y: np.ndarray
    centres_x: np.ndarray

    @classmethod
    def of(cls, raw: np.ndarray, p: "StreakParams", sub: np.ndarray) -> "_Background":
        if p.background == "median":
            return cls(np.array([[float(np.median(sub))]]), np.zeros(1), np.zeros(1))
        tiles = _tile_medians(raw, p.tile_px)
        if p.background == "map" and p.map_filter_tiles > 1:
            tiles = ndimage.median_filter(tiles, size=p.map_filter_tiles, mode="nearest")
        H, W = raw.shape
        centres_y = np.minimum(np.arange(tiles.shape[0]) * p.tile_px + (p.tile_px - 1) / 2.0, H - 1)
        centres_x = np.minimum(np.arange(tiles.shape[1]) * p.tile_px + (p.tile_px - 1) / 2.0, W - 1)
        return cls(tiles, centres_y, centres_x)

    def grid(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(len(rows), len(cols)) background on the grid of 1-D ``rows`` x ``cols``."""
        rows, cols = np.asarray(rows, dtype=float).ravel(), np.asarray(cols, dtype=float).ravel()
        return _interp_matrix(rows, self.centres_y) @ self.tiles @ _interp_matrix(cols, self.centres_x).T

    def at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Background at the points ``(rows, cols)`` (any broadcastable shapes)."""
        rows, cols = np.broadcast_arrays(np.asarray(rows, dtype=float), np.asarray(cols, dtype=float))
        wy = _interp_matrix(rows.ravel(), self.centres_y)
        wx = _interp_matrix(cols.ravel(), self.centres_x)
        return np.einsum("ni,ij,nj->n", wy, self.tiles, wx).reshape(rows.shape)


class _Frame(NamedTuple):
    """What the fit of one frame needs: the image, its background at any pixel, noise and units."""

    raw: np.ndarray
    background: "_Background"
    noise: float
    saturation: float
    inv_gain: float


class _Candidates(NamedTuple):
    """Detected stars: centre (px), velocity guess (px/s), whether its sign is known, window size."""

    x: np.ndarray
    y: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    signed: np.ndarray
    nrows: np.ndarray
    ncols: np.ndarray


class _Kernel(NamedTuple):
    """A matched filter: the full 2-D kernel and its separable terms ``(column, row)`` (the SVD's
    terms above ``SEPARABLE_RANK_TOLERANCE`` of the largest); a motionless star's or a streak along
    a detector axis is one term, then two 1-D passes cost far less than the 2-D correlation."""

    full: np.ndarray
    terms: tuple

    @classmethod
    def of(cls, kern: np.ndarray) -> "_Kernel":
        u, sv, vt = np.linalg.svd(kern)
        keep = sv > SEPARABLE_RANK_TOLERANCE * sv[0]
        terms = tuple(((u[:, i] * sv[i]).astype(np.float32), vt[i].astype(np.float32)) for i in np.flatnonzero(keep))
        if len(terms) * sum(kern.shape) >= kern.size:
            terms = ()
        return cls(kern.astype(np.float32), terms)

    def correlate(self, img: np.ndarray) -> np.ndarray:
        """``img`` correlated with the kernel, zero outside (float32)."""
        if not self.terms:
            return ndimage.correlate(img, self.full, mode="constant")
        out = None
        for col, row in self.terms:
            part = ndimage.correlate1d(ndimage.correlate1d(img, col, axis=0, mode="constant"), row, axis=1,
                                       mode="constant")
            out = part if out is None else out + part
        return out


class StreakCentroider(Centroider):
    """Detects stars by a matched filter along their expected motion and fits each with the
    rolling-shutter streak model (:mod:`rollingstar.sensors.streak_model`) by maximum likelihood.

    1. Background and noise as the ``cog`` centroider's (its functions): a global median, or tile
       medians interpolated bilinearly; the noise sigma ``s`` from a strided subsample.
    2. Expected motion: the body rate ``omega`` from the frame's gyro samples (their mean), else the
       rate fitted to the star velocities of the previous frame; image velocity ``P(w)(w x omega)``
       at each tile's centre. Detection on the background-subtracted image binned ``k x k`` (``k = 4``
       for streaks of ``LONG_STREAK_PX`` or more, else 2): correlation with the binned model streak of
       unit flux (the kernel), normalised so that its output is in sigmas of noise. On a cold start
       (no gyro, no previous frame) ``k = 4`` and the kernels are a motionless star and
       ``search_directions`` directions times ``search_lengths_px``; each bin keeps its best score.
       Each bin above ``threshold_sigma`` and not below its 8 neighbours is a candidate, with the
       velocity of its kernel (its sign unknown on a cold start).
    3. Fit: per candidate a window holding the expected streak and ``MARGIN_SIGMAS`` PSF widths;
       ``(x, y, vx, vy, F, b)`` by Levenberg-Marquardt on all windows at once (weighted least
       squares, pixel variance ``s^2 + (mu - b) / gain``, saturated pixels left out; the normal
       equations in :mod:`.streak_kernel`), started from the centroid of the window's pixels more than
       3 ``s`` above the background, the candidate's velocity, the background there and the
       window's sum above it; the first iterations hold the velocity. A velocity whose sign is unknown is fitted both ways
       and the lower chi-square wins (the rolling shutter stretches a streak moving down the rows
       and compresses one moving up).
    4. Output: ``x, y`` at the mid-exposure of the star's own row, ``row_time_ns`` and ``t_ns`` that
       row's exposure start and mid-exposure (as ``cog``), ``vx, vy``, ``flux`` (ADU), ``snr = F /
       sigma_F`` and ``cov_xx, cov_xy, cov_yy`` from the inverse of the Fisher information at the
       fit (velocity, flux and background marginalised; times the reduced chi-square when that is
       implausibly large for a right model: a PSF unlike the model's, a blend, a hot pixel),
       ``peak`` and ``npix`` the fitted star
       signal's maximum and its pixels above ``s``, ``saturated`` any of those saturated. Kept:
       ``snr >= min_snr``, inside the detector and its window, with an expected velocity within
       ``VELOCITY_TOLERANCE`` of it (plus ``VELOCITY_SLACK_PX`` over the exposure); one star per streak (the best
       ``snr``).
    5. State: the body rate a later stage estimated for the frame (taken by :meth:`update_prior`,
       which the runner calls after every frame), else the body rate fitted to the kept stars'
       velocities (robust least squares): the expected motion of the next frame when it has no gyro
       samples. With ``cog_below_px`` a frame whose expected streaks are all shorter is centroided
       by ``cog`` instead (a spot that moves less than a pixel is round); fewer than
       ``MIN_STARS_FOR_RATE`` stars clear it (cold search next frame), and a frame whose expected
       motion finds fewer than that is searched cold again. After a cold search the frame is
       detected and fitted once more with the rate its stars give (their velocities' signs made
       consistent with that field). The sign of motion along the columns is not in one frame's
       pixels (the rolling shutter stretches a streak of one sign as it would a slower streak of
       the other sign), so without a gyro the next frame settles it: the previous stars moved by
       ``+v dt`` must land on the new ones (:meth:`_resolve_sign`); until then the velocities'
       overall sign may be reversed (positions are not affected).
    6. Tracked frames (``track_windows``; once the stars of a full search and the rate, with its
       sign, are known): each star of the last frame is moved to this frame by the rate (its line
       of sight turned by ``Exp(-omega t)``, ``t`` the time between its two rows' mid-exposures)
       and fitted in a window around that place (step 3, the window ``track_margin_px`` wider);
       the sky that entered the detector since (a strip along each edge the sky moved in through,
       as deep as its shift plus a window's half size) is searched by the matched filter (step 2)
       and its stars fitted too; the fits go through :func:`_one_per_streak`. A star whose window
       kept none is looked for ``coast_frames`` more frames at its predicted place. The frame is
       searched in full instead when fewer than ``redetect_fraction`` of the last full search's
       stars are found (an unpredicted jump, a wrong rate), and after ``full_search_frames``
       tracked frames (a star the last full search missed is found again). ``last_mode`` says which
       (``tracked``, ``full``, ``cold`` or ``cog``). The sky's background map is the last full
       search's, shifted to the frame's level; the noise is measured every frame.
    """

    name = "streak"
    Params = StreakParams

    def setup(self, context) -> None:
        super().setup(context)
        cam = context.camera
        self._shape = (int(cam.height), int(cam.width))
        self._gain = effective_gain(self.params.gain_e_per_adu, context)
        timing = context.timing
        self._exposure = timing.exposure_ns * S_PER_NS
        self._ld = timing.effective_line_delay_ns * S_PER_NS
        self._set_psf(DEFAULT_PSF_SIGMA_PX if self.params.psf_sigma_px is None else self.params.psf_sigma_px)
        self._measures_psf = self.params.psf_sigma_px is None  # on the first full search that finds stars
        self._omega = None
        self._sign_known = False
        self._previous = None  # (t0_ns, tracks (n, 4) = x, y, vx, vy at their own rows' mid-exposure)
        self._misses = np.zeros(0, dtype=np.int64)
        self._searched_count = 0
        self._tracked_frames = 0
        self._inflow = {}
        self._background = None
        self._sample_grid = None  # (map, stride, the map on the tracked frames' sample grid)
        self._corner_jacobian = None  # (camera, rotation_jacobian at the corners and centre)
        self._edges = None  # (camera, edge segments, rotation_jacobian at their centres)
        self.last_mode = ""  # how the last frame was centroided: tracked, full, cold or cog (diagnostics)
        self._kernels = {}
        p = self.params
        self._cog = CogCentroider(threshold_sigma=p.threshold_sigma, background=p.background, tile_px=p.tile_px,
                                  map_filter_tiles=p.map_filter_tiles, gain_e_per_adu=p.gain_e_per_adu,
                                  saturation_adu=p.saturation_adu)
        self._cog.setup(context)

    def _longest_streak_px(self, camera, omega) -> float:
        """The longest streak ``|v| E`` expected at the detector's corners and centre (px)."""
        if self._corner_jacobian is None or self._corner_jacobian[0] is not camera:  # once per camera
            x = np.array([0.0, camera.width - 1.0, 0.0, camera.width - 1.0, 0.5 * (camera.width - 1.0)])
            y = np.array([0.0, 0.0, camera.height - 1.0, camera.height - 1.0, 0.5 * (camera.height - 1.0)])
            self._corner_jacobian = (camera, rotation_jacobian(camera, x, y))
        v = self._corner_jacobian[1] @ np.asarray(omega, dtype=float)
        return float(np.max(np.hypot(v[:, 0], v[:, 1]))) * self._exposure

    def _set_psf(self, psf_sigma_px: float) -> None:
        """The model's PSF sigma, and what follows from it: the matched filters are built again, and
        the next frame is searched in full (the stars tracked so far were found with the old filter,
        which misses faint stars of another width)."""
        self._psf = float(psf_sigma_px)
        self._se = effective_sigma(self._psf)
        self._kernels = {}
        self._search_due = True

    def update_prior(self, frame: FrameData) -> bool:
        """Take the frame's body-rate estimate, when a later stage made a valid one, as the expected
        motion of the next frame (it also settles the sign of motion along the columns); and the
        PSF sigma a later stage measured, when this one's is not set and it differs by more than
        ``PSF_CHANGE`` from the one in use."""
        measured = frame.psf_sigma_px
        if (self.params.psf_sigma_px is None and measured is not None and np.isfinite(measured)
                and abs(measured / self._psf - 1.0) > PSF_CHANGE):
            self._set_psf(measured)
        rate = frame.rate
        if rate is None or not rate.valid or not np.all(np.isfinite(rate.omega_rad_s)):
            return False
        self._omega = np.asarray(rate.omega_rad_s, dtype=float)
        self._sign_known = True
        return True

    def process(self, frame: FrameData) -> FrameData:
        camera = frame_camera(frame, self.context)
        gyro = self._gyro_rate(frame)
        omega = gyro if gyro is not None else self._omega
        self._sign_known |= gyro is not None
        if self._can_track(omega):
            tracked = self._track(frame, camera, omega)
            if tracked is not None:
                self.last_mode = "tracked"
                return tracked
        if omega is not None and self._longest_streak_px(camera, omega) < self.params.cog_below_px:
            self.last_mode = "cog"
            return self._cog_frame(frame, camera, omega)
        f = self._frame(frame)
        self.last_mode = "full"
        p, cov = self._stars(f, camera, omega) if omega is not None else (np.zeros((0, 6)), None)
        if omega is not None and self._measure_psf(f, p):
            p, cov = self._stars(f, camera, omega)
        if p.shape[0] < MIN_STARS_FOR_RATE:
            self.last_mode = "cold"
            p, cov = self._cold(f, camera)
        elif gyro is None and not self._sign_known:
            p, cov = self._resolve_sign(f, camera, frame.t0_ns, p, cov, omega)
        self._omega = self._fitted_rate(camera, p, signed=True)
        self._searched(frame.t0_ns, p[:, :4], f.background)
        return frame.evolve(stars=self._table(frame, f, p, cov))

    def _measure_psf(self, f: _Frame, p: np.ndarray) -> bool:
        """On the first full search that finds stars, when no width is stated: the PSF sigma measured
        from them (:func:`~rollingstar.estimators.centroiders.psf_width.measure_psf_sigma`) becomes
        the model's when it differs by more than ``PSF_CHANGE``; True then (the caller searches
        again: the matched filter of the wrong width misses faint stars)."""
        if not self._measures_psf or p.shape[0] < MIN_STARS_FOR_RATE:
            return False
        measured = measure_psf_sigma(f.raw, p, self._exposure, self._ld, f.saturation, f.noise**2, f.inv_gain)
        if measured is None:
            return False
        self._measures_psf = False
        if abs(measured / self._psf - 1.0) <= PSF_CHANGE:
            return False
        self._set_psf(measured)
        return True

    def _searched(self, t0_ns: int, tracks: np.ndarray, background) -> None:
        """State after a full-frame search: its stars ``(x, y, vx, vy)`` are the tracks, their count
        the reference a tracked frame is held to, and its background map the tracked frames'."""
        self._previous = (t0_ns, np.array(tracks, dtype=float))
        self._misses = np.zeros(len(tracks), dtype=np.int64)
        self._searched_count = len(tracks)
        self._tracked_frames = 0
        self._search_due = False
        self._inflow = {}  # (axis, edge) -> the sky's shift in through that edge since it was last searched (px)
        self._background = background

    def _cog_frame(self, frame: FrameData, camera, omega) -> FrameData:
        """The frame centroided by ``cog`` (round spots); its spots, with the expected velocity, are the tracks."""
        out = self._cog.process(frame)
        s = out.stars
        vx, vy = image_velocity(camera, s.x, s.y, omega)
        self._searched(frame.t0_ns, np.column_stack([s.x, s.y, vx, vy]), None)
        return out

    # ------------------------------------------------------------------ tracked frames
    def _can_track(self, omega) -> bool:
        p = self.params
        due = self._search_due or (p.full_search_frames and self._tracked_frames >= p.full_search_frames)
        return (p.track_windows and omega is not None and self._sign_known and self._previous is not None
                and self._previous[1].shape[0] >= MIN_STARS_FOR_RATE and not due)

    def _track(self, frame: FrameData, camera, omega):
        """A tracked frame (class docstring, step 6); None when fewer than ``redetect_fraction`` of the
        last full search's stars are found (the frame is then searched in full)."""
        t_prev, q = self._previous
        dt = (frame.t0_ns - t_prev) * S_PER_NS
        x, y = self._moved(camera, q[:, 0], q[:, 1], omega, dt)
        H, W = self._shape
        inside = np.isfinite(x) & np.isfinite(y) & (x > -0.5) & (x < W - 0.5) & (y > -0.5) & (y < H - 0.5)
        x, y, misses = x[inside], y[inside], self._misses[inside]
        f = self._tracked_frame(frame)
        nx, ny = self._new_sky(f, camera, omega, dt)
        if self._longest_streak_px(camera, omega) < self.params.cog_below_px:
            return self._track_round(frame, camera, omega, f, x, y, misses, nx, ny, dt)
        vx, vy = image_velocity(camera, np.concatenate([x, nx]), np.concatenate([y, ny]), omega)
        # the centre's uncertainty: a tracked star's prediction, a new-sky detection's half bin
        extra = np.concatenate([np.full(x.size, self.params.track_margin_px),
                                0.5 * np.where(np.hypot(vx, vy)[x.size:] * self._exposure >= LONG_STREAK_PX, 4, 2)])
        nrows, ncols = self._window_size(vx, vy, extra, multiple=2)
        # a star both tracked and found in the new sky is fitted twice, and one fit kept: a track
        # from a streak the edge cut may be off by more than its window allows
        cand = _Candidates(np.concatenate([x, nx]), np.concatenate([y, ny]), vx, vy, np.ones(vx.size, dtype=bool),
                           nrows, ncols)
        p, cov = _one_per_streak(*self._fit(f, cand), self._se, self._exposure)
        if p.shape[0] < max(MIN_STARS_FOR_RATE, self.params.redetect_fraction * self._searched_count):
            return None
        # tracked stars whose window kept no star coast for a few frames at their predicted place
        found = np.any((np.abs(p[None, :, 0] - x[:, None]) < 0.5 * ncols[: x.size, None])
                       & (np.abs(p[None, :, 1] - y[:, None]) < 0.5 * nrows[: x.size, None]), axis=1)
        coast = ~found & (misses < self.params.coast_frames)
        tracks = np.concatenate([p[:, :4], np.column_stack([x, y, vx[: x.size], vy[: x.size]])[coast]])
        self._previous = (frame.t0_ns, tracks)
        self._misses = np.concatenate([np.zeros(p.shape[0], dtype=np.int64), misses[coast] + 1])
        self._tracked_frames += 1
        self._omega = self._fitted_rate(camera, p, signed=True)
        return frame.evolve(stars=self._table(frame, f, p, cov))

    def _track_round(self, frame: FrameData, camera, omega, f: _Frame, x, y, misses, nx, ny, dt: float):
        """A tracked frame of round spots (every expected streak shorter than ``cog_below_px``): the
        ``cog`` definition and covariance model in a ``ROUND_WINDOW_PX`` window around each tracked
        star and each new-sky detection (compiled, read in place:
        :func:`~rollingstar.estimators.centroiders.window_kernel.centroid_windows_at`), as ``cog``
        would centroid the full frame; None when too few stars are found (as :meth:`_track`). The
        expected rate follows the stars' misses (:meth:`_rate_from_moves`)."""
        cp = self._cog.params
        H, W = self._shape
        h = min(ROUND_WINDOW_PX, H, W)
        px, py = np.concatenate([x, nx]), np.concatenate([y, ny])
        r0 = np.clip(np.rint(py - 0.5 * (h - 1)).astype(np.int64), 0, H - h)
        c0 = np.clip(np.rint(px - 0.5 * (h - 1)).astype(np.int64), 0, W - h)
        s, _ = centroid_windows_at(f.raw, r0, c0, h, h, px, py, f.background.at(py, px), np.full(px.size, f.noise),
                                   threshold_sigma=cp.threshold_sigma, min_pixels=cp.min_pixels,
                                   max_pixels=cp.max_pixels, connectivity=cp.connectivity, grow_px=cp.grow_px,
                                   saturation_adu=f.saturation, reject_border=cp.reject_border,
                                   gain_e_per_adu=cp.gain_e_per_adu, cov_gain_e_per_adu=self._gain)
        keep = np.flatnonzero(s.found & (s.flux > 0))
        keep = keep[_first_of_each(s.x[keep], s.y[keep])]  # a spot two windows found (tracked and new sky)
        if keep.size < max(MIN_STARS_FOR_RATE, self.params.redetect_fraction * self._searched_count):
            return None
        keep = keep[np.argsort(-s.flux[keep], kind="stable")]
        sx, sy, flux, cov = s.x[keep], s.y[keep], s.flux[keep], s.cov[:, keep]
        cut = np.zeros(keep.size, dtype=bool)
        if cp.edge_sigma:  # as cog: the spots that reach the outermost rows or columns (by their size)
            reach = np.sqrt(s.npix[keep] / np.pi) + cp.grow_px + 0.5
            border = (np.minimum(sx, W - 1 - sx) < reach) | (np.minimum(sy, H - 1 - sy) < reach)
            if border.any():
                cov, cut = with_edge_covariance(cov, sx, sy, flux, s.peak[keep], self._shape, only=border)
        timing = self.context.timing
        stars = StarTable.build(sx, sy, t_ns=timing.row_mid_exposure_ns(frame.t0_ns, sy),
                                row_time_ns=timing.row_start_ns(frame.t0_ns, sy), flux=flux, peak=s.peak[keep],
                                npix=s.npix[keep], saturated=s.saturated[keep], snr=s.snr[keep],
                                sigma_px=isotropic_sigma(cov), cov_xx=cov[0], cov_xy=cov[1], cov_yy=cov[2])
        d = np.hypot(sx[None, :] - x[:, None], sy[None, :] - y[:, None])
        nearest = d.argmin(axis=1) if sx.size else np.zeros(x.size, dtype=int)
        found = d[np.arange(x.size), nearest] < 0.5 * h if sx.size else np.zeros(x.size, dtype=bool)
        self._omega = self._rate_from_moves(camera, omega, x[found], y[found], sx[nearest[found]], sy[nearest[found]],
                                            dt)
        coast = ~found & (misses < self.params.coast_frames)
        tx, ty = np.concatenate([sx, x[coast]]), np.concatenate([sy, y[coast]])
        self._previous = (frame.t0_ns, np.column_stack([tx, ty, *image_velocity(camera, tx, ty, omega)]))
        self._misses = np.concatenate([np.zeros(sx.size, dtype=np.int64), misses[coast] + 1])
        self._tracked_frames += 1
        out = frame.evolve(stars=stars)
        return out.flagged(f"edge_truncated_stars:{int(cut.sum())}") if cut.any() else out

    def _rate_from_moves(self, camera, omega, x, y, fx, fy, dt: float):
        """``omega`` corrected by the tracked stars' misses: predicted at ``(x, y)`` with ``omega``,
        found at ``(fx, fy)`` after ``dt`` s, so ``found - predicted = J(x, y) d_omega dt`` (``J``
        the image velocity per unit rate; least squares, without misses beyond 3 robust sigmas).
        Round spots carry no velocity of their own: without a gyro or a later stage's rate this is
        how a tracked frame of them follows a changing rate."""
        if x.size < MIN_STARS_FOR_RATE or dt <= 0:
            return omega
        A = np.ascontiguousarray(rotation_jacobian(camera, x, y) * dt)
        return np.asarray(omega, dtype=float) + _robust_rate_step(A, np.column_stack([fx - x, fy - y]))

    def _moved(self, camera, x, y, omega, dt: float):
        """Where stars seen at ``(x, y)`` (their own rows' mid-exposure) are at this frame's: the line of
        sight turned by ``Exp(-omega t) w``, ``t = dt + (y' - y) ld`` the time between the two rows'
        mid-exposures (two fixed-point passes)."""
        w = camera.unproject(x, y).reshape(-1, 3)
        t = np.full(w.shape[0], dt)
        for _ in range(2):
            x2, y2, _ = camera.project(rotate_at_rate(omega, w, -t))
            t = dt + (np.nan_to_num(y2) - y) * self._ld
        return x2, y2

    def _tracked_frame(self, frame: FrameData) -> _Frame:
        """A tracked frame's fit inputs: the last full search's background map shifted to this frame's
        level and the noise, both from a strided sample of ``TRACKED_SAMPLE_PX`` pixels (the sky's
        background varies over the field slowly and over time by its level)."""
        if self._background is None:  # the last full search was cog's: this frame's map is the one tracked from now
            f = self._frame(frame)
            self._background = f.background
            return f
        raw = self._raw(frame)
        step = max(1, int(np.sqrt(raw.size / TRACKED_SAMPLE_PX)))
        sub = raw[::step, ::step].astype(float)
        resid = sub - self._background_on_sample(raw.shape, step)
        level = median(resid)
        noise = max(robust_sigma(resid - level), self.params.noise_floor_adu)
        background = self._background._replace(tiles=self._background.tiles + level)
        return _Frame(raw, background, noise, self._saturation(raw), 1.0 / self._gain if self._gain else 0.0)

    def _background_on_sample(self, shape: tuple[int, int], step: int) -> np.ndarray:
        """The last full search's background map on every ``step``-th row and column (computed once
        per map: the tracked frames all sample the same grid)."""
        cached = self._sample_grid
        if cached is None or cached[0] is not self._background or cached[1] != step:
            grid = self._background.grid(np.arange(0, shape[0], step), np.arange(0, shape[1], step))
            self._sample_grid = cached = (self._background, step, grid)
        return cached[2]

    def _new_sky(self, f: _Frame, camera, omega, dt: float):
        """Stars in the sky that entered the detector since an edge was last searched: the matched
        filter with the expected motion over a strip along each edge the sky moved in through, as
        deep as the sky's shift since (summed over frames until it exceeds ``NEW_SKY_PX``: a
        slow drift is searched every few frames) plus a fit window's half size (the largest along
        the edge), in ``detect_tile_px`` segments of one kernel each."""
        t = self.params.detect_tile_px
        xs, ys = [], []
        edges, jac = self._edge_segments(camera)
        v = jac @ np.asarray(omega, dtype=float)  # the image velocity of every edge segment
        cuts = np.cumsum([e[4].size for e in edges])[:-1]
        for (axis, size, across, edge, starts, _, _), vx, vy in zip(edges, np.split(v[:, 0], cuts), np.split(v[:, 1], cuts)):
            inward = (vx if axis == 1 else vy) * dt * (1.0 if edge == 0.0 else -1.0)
            reach = 0.5 * np.hypot(vx, vy) * self._exposure + MARGIN_SIGMAS * self._se + self.params.track_margin_px
            entered = self._inflow.get((axis, edge), 0.0) + max(float(np.max(inward)), 0.0)
            if entered <= NEW_SKY_PX:
                self._inflow[(axis, edge)] = entered
                continue
            self._inflow[(axis, edge)] = 0.0
            depth = int(np.ceil(entered + np.max(reach)))
            lo, hi = (0, min(depth, size)) if edge == 0.0 else (max(size - depth, 0), size)
            keys = [self._kernel_key(a, b, self._bin(a, b)) for a, b in zip(vx, vy)]
            for i, j in _runs(keys):  # neighbouring segments with one kernel searched as one
                a0, a1 = starts[i], min(starts[j - 1] + t, across)
                r0, r1, c0, c1 = (a0, a1, lo, hi) if axis == 1 else (lo, hi, a0, a1)
                x, y = self._tile_candidates(f, vx[i], vy[i], r0, r1, c0, c1)
                xs.append(x)
                ys.append(y)
        return (np.concatenate(xs), np.concatenate(ys)) if xs else (np.zeros(0), np.zeros(0))

    def _edge_segments(self, camera):
        """The detector's edges cut in ``detect_tile_px`` segments, as ``(axis, size, across, edge,
        segment starts, segment centres x, y)``, left and right edges (columns) then top and bottom
        (rows), and the rotation Jacobian at the segments' centres (n, 2, 3) (computed once per camera)."""
        if self._edges is not None and self._edges[0] is camera:
            return self._edges[1], self._edges[2]
        H, W = self._shape
        t = self.params.detect_tile_px
        edges = []
        for axis, size, across in ((1, W, H), (0, H, W)):
            starts = np.arange(0, across, t)
            centres = np.minimum(starts + t / 2.0, across - 1.0)
            for edge in (0.0, size - 1.0):
                px, py = (np.full(starts.size, edge), centres) if axis == 1 else (centres, np.full(starts.size, edge))
                edges.append((axis, size, across, edge, starts, px, py))
        jac = rotation_jacobian(camera, np.concatenate([e[5] for e in edges]), np.concatenate([e[6] for e in edges]))
        self._edges = (camera, edges, jac)
        return edges, jac

    def _bin(self, vx: float, vy: float) -> int:
        """Detection bin of a streak of velocity ``(vx, vy)``: 4 x 4 for long streaks, else 2 x 2."""
        return 4 if np.hypot(vx, vy) * self._exposure >= LONG_STREAK_PX else 2

    def _tile_candidates(self, f: _Frame, vx: float, vy: float, r0: int, r1: int, c0: int, c1: int):
        """Peaks above ``threshold_sigma`` of the matched filter for velocity ``(vx, vy)`` inside the
        tile ``[r0, r1) x [c0, c1)`` (pixel centres of their bins)."""
        k = self._bin(vx, vy)
        kern = self._kernel(vx, vy, k)
        hy, hx = k * (kern.full.shape[0] // 2 + 1), k * (kern.full.shape[1] // 2 + 1)
        H, W = self._shape
        top, left = max(r0 - hy, 0), max(c0 - hx, 0)
        img = self._binned(f, k, top, min(r1 + hy, H), left, min(c1 + hx, W))
        score = kern.correlate(img) * np.float32(1.0 / (k * f.noise))
        bi, bj = np.divmod(_peaks(score, self.params.threshold_sigma), score.shape[1])
        x, y = left + k * bj + (k - 1) / 2.0, top + k * bi + (k - 1) / 2.0
        inside = (x >= c0) & (x < c1) & (y >= r0) & (y < r1)
        return x[inside], y[inside]

    def _cold(self, f: _Frame, camera):
        """Cold search; then detection and fit again with the rate its stars give (whose overall
        sign the next frame settles)."""
        self._sign_known = False
        p, cov = self._stars(f, camera, None)
        if self._measure_psf(f, p):
            p, cov = self._stars(f, camera, None)
        omega = self._fitted_rate(camera, p, signed=False)
        if omega is not None:
            again = self._stars(f, camera, omega)
            if again[0].shape[0] >= MIN_STARS_FOR_RATE:
                return again
        return p, cov

    def _resolve_sign(self, f: _Frame, camera, t0_ns: int, p: np.ndarray, cov: np.ndarray, omega):
        """The sign of a streak's motion along the columns is not in one frame's pixels (the rolling
        shutter's stretch of one sign is a slower streak of the other). Between two frames it is:
        the previous frame's stars moved by ``+v dt`` land on this frame's stars, by ``-v dt`` not.
        When the reverse matches more stars, the frame is fitted again with the rate reversed."""
        if self._previous is None:
            return p, cov
        dt = (t0_ns - self._previous[0]) * S_PER_NS
        q = self._previous[1]
        if q.shape[0] < MIN_STARS_FOR_RATE or np.median(np.hypot(q[:, 2], q[:, 3])) * dt < SIGN_MATCH_PX:
            return p, cov  # too slow to tell (and too slow to matter)
        hits = []
        for sign in (1.0, -1.0):
            pred = q[:, :2] + sign * q[:, 2:4] * dt
            d = np.hypot(pred[:, None, 0] - p[None, :, 0], pred[:, None, 1] - p[None, :, 1])
            hits.append(int(np.sum(d.min(axis=1, initial=np.inf) < SIGN_MATCH_PX)))
        if max(hits) < MIN_STARS_FOR_RATE or hits[0] == hits[1]:
            return p, cov
        self._sign_known = True
        if hits[1] > hits[0]:
            again = self._stars(f, camera, -omega)
            if again[0].shape[0] >= MIN_STARS_FOR_RATE:
                return again
        return p, cov

    # ------------------------------------------------------------------ frame, background, motion
    def _raw(self, frame: FrameData) -> np.ndarray:
        if frame.image is None:
            raise ValueError(f"frame {frame.index}: no image; the 'streak' centroider needs image-level recordings")
        raw = np.asarray(frame.image)
        if raw.shape != self._shape:
            raise ValueError(f"frame {frame.index}: image shape {raw.shape} differs from the camera's {self._shape}")
        if raw.dtype == bool:
            raw = raw.astype(np.uint8)
        if not np.issubdtype(raw.dtype, np.integer) and not np.all(np.isfinite(raw)):
            raise ValueError(f"frame {frame.index}: image has non-finite pixels; cannot centroid")
        return raw

    def _frame(self, frame: FrameData) -> _Frame:
        raw = self._raw(frame)
        p = self.params
        step = _subsample_step(raw.shape)
        sub = raw[::step, ::step].astype(float)
        background = _Background.of(raw, p, sub)
        rows, cols = np.arange(0, raw.shape[0], step), np.arange(0, raw.shape[1], step)
        noise = max(robust_sigma(sub - background.grid(rows, cols)), p.noise_floor_adu)
        return _Frame(raw, background, noise, self._saturation(raw), 1.0 / self._gain if self._gain else 0.0)

    def _saturation(self, raw: np.ndarray) -> float:
        if self.params.saturation_adu is not None:
            return float(self.params.saturation_adu)
        bit_depth = getattr(self.context, "bit_depth", None)
        if bit_depth:
            return float(2 ** int(bit_depth) - 1)
        if np.issubdtype(raw.dtype, np.integer):
            return float(np.iinfo(raw.dtype).max)
        return np.inf

    def _gyro_rate(self, frame: FrameData):
        """Body rate (rad/s) of the frame's gyro samples (their mean), None without."""
        if self.params.use_gyro and frame.gyro is not None and len(frame.gyro.t_ns):
            return np.mean(np.asarray(frame.gyro.omega_rad_s, dtype=float).reshape(-1, 3), axis=0)
        return None

    def _fitted_rate(self, camera, p: np.ndarray, signed: bool):
        """Body rate fitted to the stars' velocities (two passes, the second without 3-sigma
        outliers). Velocities of unknown sign (``signed`` False) are first turned towards the
        best star's (the field of a turn across the boresight is nearly uniform), and after the
        first pass each takes the sign closer to the fitted field."""
        if p.shape[0] < MIN_STARS_FOR_RATE:
            return None
        jac = rotation_jacobian(camera, p[:, 0], p[:, 1])
        v = p[:, 2:4].copy()
        if not signed:
            v *= np.where(v @ v[np.argmax(p[:, 4])] < 0, -1.0, 1.0)[:, None]
        keep = np.ones(v.shape[0], dtype=bool)
        for _ in range(2):
            omega = np.linalg.lstsq(jac[keep].reshape(-1, 3), v[keep].reshape(-1), rcond=None)[0]
            field = jac @ omega
            if not signed:
                v *= np.where(np.sum(v * field, axis=1) < 0, -1.0, 1.0)[:, None]
            resid = np.hypot(*(field - v).T)
            keep = resid <= 3.0 * max(1.4826 * np.median(resid), 1.0)
        return omega

    # ------------------------------------------------------------------ detection
    def _stars(self, f: _Frame, camera, omega):
        """Detect and fit: fitted parameters (n, 6) and their covariances (n, 6, 6), one per streak."""
        cand = self._candidates(f, camera, omega)
        p, cov = self._fit(f, cand)
        return _one_per_streak(p, cov, self._se, self._exposure)

    def _candidates(self, f: _Frame, camera, omega) -> _Candidates:
        H, W = self._shape
        if omega is None:
            k = 4
            velocities = self._search_velocities()
            score, which = self._search(f, k, velocities)
        else:
            k, score, which, velocities = self._tracked(f, camera, omega)
        best = _peaks(score, self.params.threshold_sigma)
        bi, bj = np.divmod(best, score.shape[1])
        x, y = k * bj + (k - 1) / 2.0, k * bi + (k - 1) / 2.0
        if omega is None:
            vx, vy = velocities[which.ravel()[best]].T
        else:
            vx, vy = image_velocity(camera, x, y, omega)
            slow = np.hypot(vx, vy) * self._exposure < SLOW_STREAK_PX  # start at rest: no sign preferred
            vx, vy = np.where(slow, 0.0, vx), np.where(slow, 0.0, vy)
        nrows, ncols = self._window_size(vx, vy, k / 2.0)
        return _Candidates(x, y, vx, vy, np.full(x.size, omega is not None), nrows, ncols)

    def _window_size(self, vx, vy, extra_px, multiple: int = 4):
        """Rows and columns of the fit windows: the streak (rolling-shutter stretch included) plus
        ``MARGIN_SIGMAS`` PSF widths and ``extra_px`` (the uncertainty of the centre: half a
        detection bin, or a tracked star's prediction) each side, rounded up to a multiple of
        ``multiple`` (fewer distinct sizes: the fit runs once per size)."""
        margin = MARGIN_SIGMAS * self._se + extra_px
        along_y = np.abs(vy) * self._exposure / np.maximum(1.0 - np.abs(vy) * self._ld, 0.5)
        nrows = multiple * np.ceil((along_y + 2 * margin) / multiple)
        ncols = multiple * np.ceil((np.abs(vx) * self._exposure + 2 * margin) / multiple)
        return nrows.astype(int), ncols.astype(int)

    def _search_velocities(self) -> np.ndarray:
        p = self.params
        angles = np.arange(p.search_directions) * np.pi / p.search_directions
        lengths = np.asarray(p.search_lengths_px, dtype=float) / self._exposure
        v = [(0.0, 0.0)] + [(s * np.cos(a), s * np.sin(a)) for s in lengths for a in angles]
        return np.array(v)

    def _binned(self, f: _Frame, k: int, top: int = 0, bottom: int | None = None, left: int = 0,
                right: int | None = None) -> np.ndarray:
        """The image (or its part ``[top, bottom) x [left, right)``) minus its background, summed over
        ``k x k`` bins from its top-left corner (float32)."""
        H, W = self._shape
        bottom, right = H if bottom is None else bottom, W if right is None else right
        Hb, Wb = (bottom - top) // k, (right - left) // k
        raw = f.raw[top: top + Hb * k, left: left + Wb * k]
        rows = raw[0::k].astype(np.float32)
        for i in range(1, k):
            rows += raw[i::k]
        img = np.ascontiguousarray(rows[:, 0::k])
        for j in range(1, k):
            img += rows[:, j::k]
        centres_y = top + k * np.arange(Hb) + (k - 1) / 2.0
        centres_x = left + k * np.arange(Wb) + (k - 1) / 2.0
        img -= (k * k * f.background.grid(centres_y, centres_x)).astype(np.float32)
        return img

    def _kernel(self, vx: float, vy: float, k: int) -> _Kernel:
        """Unit-flux model streak binned ``k x k``, normalised to unit sum of squares (cached by the
        streak's length in whole pixels)."""
        key = self._kernel_key(vx, vy, k)
        if key not in self._kernels and len(self._kernels) >= MAX_KERNELS:  # a rate that keeps changing
            self._kernels.clear()
        if key not in self._kernels:
            vx, vy = key[0] / self._exposure, key[1] / self._exposure
            hx = int(np.ceil((abs(vx) * self._exposure / 2 + 3 * self._se) / k))
            hy = int(np.ceil((abs(vy) * self._exposure / 2 + 3 * self._se) / k))
            c = (hx * k + (k - 1) / 2.0, hy * k + (k - 1) / 2.0)
            mu = streak_mu([c[0], c[1], vx, vy, 1.0, 0.0], 0, 0, (2 * hy + 1) * k, (2 * hx + 1) * k,
                           self._psf, self._exposure, self._ld)[0]
            kern = mu.reshape(2 * hy + 1, k, 2 * hx + 1, k).sum(axis=(1, 3))
            self._kernels[key] = _Kernel.of(kern / np.sqrt(np.sum(kern**2)))
        return self._kernels[key]

    def _kernel_key(self, vx: float, vy: float, k: int) -> tuple[int, int, int]:
        """The streak's length along x and y in whole pixels, and the bin: velocities with one key share a kernel."""
        return int(round(vx * self._exposure)), int(round(vy * self._exposure)), k

    def _search(self, f: _Frame, k: int, velocities: np.ndarray):
        """Best matched-filter score (sigmas) over ``velocities`` per bin, and which velocity gave it."""
        img = self._binned(f, k)
        scale = np.float32(1.0 / (k * f.noise))
        best = np.full(img.shape, -np.inf, dtype=np.float32)
        which = np.zeros(img.shape, dtype=np.intp)
        for i, (vx, vy) in enumerate(velocities):
            s = self._kernel(vx, vy, k).correlate(img)
            s *= scale
            better = s > best
            best[better] = s[better]
            which[better] = i
        return best, which

    def _tracked(self, f: _Frame, camera, omega):
        """Matched filter with the expected motion: one kernel per ``detect_tile_px`` tile."""
        H, W = self._shape
        t = self.params.detect_tile_px
        ty, tx = np.meshgrid(np.arange(0, H, t) + min(t, H) / 2.0, np.arange(0, W, t) + min(t, W) / 2.0, indexing="ij")
        vx, vy = image_velocity(camera, tx.ravel(), ty.ravel(), omega)
        length = float(np.max(np.hypot(vx, vy))) * self._exposure
        k = 4 if length >= LONG_STREAK_PX else 2
        img = self._binned(f, k)
        score = np.empty(img.shape, dtype=np.float32)
        tb = t // k
        scale = np.float32(1.0 / (k * f.noise))
        for n, (i0, j0) in enumerate(zip(np.arange(0, img.shape[0], tb).repeat(tx.shape[1]),
                                         np.tile(np.arange(0, img.shape[1], tb), tx.shape[0]))):
            kern = self._kernel(vx[n], vy[n], k)
            hy, hx = kern.full.shape[0] // 2, kern.full.shape[1] // 2
            r0, c0 = max(i0 - hy, 0), max(j0 - hx, 0)
            part = kern.correlate(img[r0: i0 + tb + hy, c0: j0 + tb + hx])
            score[i0: i0 + tb, j0: j0 + tb] = part[i0 - r0: i0 - r0 + tb, j0 - c0: j0 - c0 + tb] * scale
        return k, score, None, None

    # ------------------------------------------------------------------ fit
    def _fit(self, f: _Frame, c: _Candidates):
        """Fit every candidate (grouped by window size); unknown signs are fitted both ways."""
        out_p, out_cov = [np.zeros((0, 6))], [np.zeros((0, 6, 6))]
        for nr, nc in set(zip(c.nrows.tolist(), c.ncols.tolist())):
            sel = np.flatnonzero((c.nrows == nr) & (c.ncols == nc))
            flip = sel[~c.signed[sel]]
            x = np.concatenate([c.x[sel], c.x[flip]])
            y = np.concatenate([c.y[sel], c.y[flip]])
            v = np.concatenate([np.column_stack([c.vx[sel], c.vy[sel]]), -np.column_stack([c.vx[flip], c.vy[flip]])])
            signed = np.concatenate([c.signed[sel], c.signed[flip]])
            p, cov, chi2, ok = self._fit_windows(f, x, y, v, signed, nr, nc)
            if flip.size:  # the better sign of each star fitted both ways
                other = np.full(sel.size, -1)
                other[np.searchsorted(sel, flip)] = sel.size + np.arange(flip.size)
                worse = (other >= 0) & (chi2[np.maximum(other, 0)] < chi2[: sel.size])
                pick = np.where(worse, other, np.arange(sel.size))
                p, cov, ok = p[pick], cov[pick], ok[pick]
            out_p.append(p[ok])
            out_cov.append(cov[ok])
        return np.concatenate(out_p), np.concatenate(out_cov)

    def _fit_windows(self, f: _Frame, x, y, v, signed, nrows: int, ncols: int):
        """Levenberg-Marquardt on windows of one size centred on ``(x, y)``: parameters, covariances,
        chi-squares and which fits are kept (module docstring of :class:`StreakCentroider`, step 4).
        The velocity's prior: weak and zero-mean, but centred on the expected velocity ``v`` with
        ``edge_velocity_sigma_px_s`` for a streak the detector edge cuts when ``v`` is ``signed``."""
        H, W = self._shape
        row0 = np.rint(y - (nrows - 1) / 2.0).astype(np.int64)
        col0 = np.rint(x - (ncols - 1) / 2.0).astype(np.int64)
        cut = signed & ((row0 < 0) | (row0 + nrows > H) | (col0 < 0) | (col0 + ncols > W))
        v_mean = np.where(cut[:, None], v, 0.0)
        v_weight = np.where(cut, self.params.edge_velocity_sigma_px_s, self.params.velocity_prior_px_s) ** -2.0
        b0 = f.background.at(y, x)
        start = window_moments(f.raw, row0, col0, nrows, ncols, b0, 3.0 * f.noise)
        p = np.column_stack([start[:, 1], start[:, 2], v, np.maximum(start[:, 0], 10.0 * f.noise), b0])
        args = (row0, col0, nrows, ncols, f.raw, f.saturation, f.noise**2, f.inv_gain, self._se, self._exposure,
                self._ld)
        p, hess, chi2, used = _levenberg_marquardt(p, args, self.params.max_iterations, v_mean, v_weight)
        with np.errstate(invalid="ignore", divide="ignore"):
            cov = np.linalg.pinv(hess, hermitian=True)  # a window without a usable pixel has no information
            cov *= _misfit_scale(chi2, used)[:, None, None]
            snr = p[:, 4] / np.sqrt(cov[:, 4, 4])
        ok = (np.all(np.isfinite(p), axis=1) & (cov[:, 0, 0] > 0) & (cov[:, 1, 1] > 0) & (snr >= self.params.min_snr)
              & (p[:, 0] >= col0) & (p[:, 0] <= col0 + ncols - 1) & (p[:, 1] >= row0) & (p[:, 1] <= row0 + nrows - 1)
              & (p[:, 0] > -0.5) & (p[:, 0] < W - 0.5) & (p[:, 1] > -0.5) & (p[:, 1] < H - 0.5)
              & (~signed | (np.hypot(*(p[:, 2:4] - v).T) <= VELOCITY_TOLERANCE * np.hypot(*v.T)
                             + VELOCITY_SLACK_PX / self._exposure)))
        return p, cov, chi2, ok

    # ------------------------------------------------------------------ output
    def _table(self, frame: FrameData, f: _Frame, p: np.ndarray, cov: np.ndarray) -> StarTable:
        if p.shape[0] == 0:
            return StarTable.empty()
        order = np.argsort(-p[:, 4], kind="stable")
        p, cov = p[order], cov[order]
        nrows, ncols = self._window_size(p[:, 2], p[:, 3], 0)
        nr, nc = int(nrows.max()), int(ncols.max())
        row0 = np.rint(p[:, 1] - (nr - 1) / 2.0).astype(np.int64)
        col0 = np.rint(p[:, 0] - (nc - 1) / 2.0).astype(np.int64)
        npix, peak, nsat = star_pixels(np.ascontiguousarray(p), row0, col0, nr, nc, f.raw, f.saturation, f.noise,
                                       self._se, self._exposure, self._ld)
        c = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]])
        timing = self.context.timing
        return StarTable.build(
            p[:, 0], p[:, 1], t_ns=timing.row_mid_exposure_ns(frame.t0_ns, p[:, 1]),
            row_time_ns=timing.row_start_ns(frame.t0_ns, p[:, 1]), flux=p[:, 4], peak=peak, npix=npix,
            saturated=nsat > 0, snr=p[:, 4] / np.sqrt(cov[:, 4, 4]), sigma_px=isotropic_sigma(c),
            cov_xx=c[0], cov_xy=c[1], cov_yy=c[2], vx=p[:, 2], vy=p[:, 3])


def _levenberg_marquardt(p: np.ndarray, args, iterations: int, v_mean: np.ndarray, v_weight: np.ndarray):
    """Damped Gauss-Newton of each star on its own window (compiled, star by star:
    :func:`rollingstar.estimators.centroiders.streak_kernel.levenberg_marquardt`); a step is kept when it lowers the star's
    chi-square, the Gaussian prior on its velocity (mean ``v_mean`` (n, 2), weight ``v_weight``
    (n,), the inverse variance) included. The first ``FROZEN_VELOCITY_ITERATIONS``
    hold the velocity at its guess (a bright star's first step at a poor flux guess would
    otherwise explain its wings by a smear). A star stops when a step moves its
    position by less than ``FIT_TOLERANCE_PX``, or its position and velocity by less than
    ``STEP_SIGMAS`` of their standard deviations (what further steps could move is noise's
    hundredth), at a damping of at most ``CONVERGED_DAMPING``
    (kept or not: at the minimum the chi-square cannot fall further than its rounding), or when
    its damping has grown a million-fold. Returns
    parameters, information matrices, chi-squares and the pixels they used at the solution."""
    p = np.ascontiguousarray(p, dtype=float)
    return levenberg_marquardt(p, *args, np.ascontiguousarray(v_mean, dtype=float),
                               np.ascontiguousarray(v_weight, dtype=float), iterations, FROZEN_VELOCITY_ITERATIONS,
                               FIT_TOLERANCE_PX, STEP_SIGMAS, CONVERGED_DAMPING, RIDGE)


def _misfit_scale(chi2: np.ndarray, used: np.ndarray) -> np.ndarray:
    """Covariance scale of each fit: its reduced chi-square when that is implausibly large for a
    right model (over ``1 + 3 sqrt(2 / dof)``: a PSF unlike the model's, a blended neighbour,
    a hot pixel), else 1."""
    dof = np.maximum(used - 6, 1)
    reduced = chi2 / dof
    return np.where(reduced > 1.0 + 3.0 * np.sqrt(2.0 / dof), reduced, 1.0)


@njit(cache=True, nogil=True)
def _robust_rate_step(A, r):  # pragma: no cover - compiled
    """``d_omega`` minimising ``sum |r_i - A_i d_omega|^2`` (``A`` (m, 2, 3), ``r`` (m, 2)) by least
    squares (minimum norm when the stars leave it undetermined, as ``numpy.linalg.lstsq``), then
    again without the stars that miss by more than 3 robust sigmas (at least 0.05 px). Compiled:
    two small least-squares problems per tracked frame, where numpy's calls cost more than the
    arithmetic."""
    m = A.shape[0]
    keep = np.ones(m, dtype=np.bool_)
    miss = np.zeros(m)
    d = np.zeros(3)
    for _ in range(2):
        kept = np.flatnonzero(keep)
        rows, rhs = np.zeros((2 * kept.size, 3)), np.zeros(2 * kept.size)
        for j in range(kept.size):
            for row in range(2):
                rows[2 * j + row] = A[kept[j], row]
                rhs[2 * j + row] = r[kept[j], row]
        d = np.linalg.lstsq(rows, rhs, rcond=2.220446049250313e-16 * max(rows.shape[0], 3))[0]
        for i in range(m):
            ex = r[i, 0] - (A[i, 0, 0] * d[0] + A[i, 0, 1] * d[1] + A[i, 0, 2] * d[2])
            ey = r[i, 1] - (A[i, 1, 0] * d[0] + A[i, 1, 1] * d[1] + A[i, 1, 2] * d[2])
            miss[i] = np.sqrt(ex * ex + ey * ey)
        keep = miss <= 3.0 * max(1.4826 * np.median(miss), 0.05)
    return d


def _first_of_each(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Mask of the spots not within ``SAME_SPOT_PX`` of an earlier one."""
    close = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :]) < SAME_SPOT_PX
    return ~np.any(np.tril(close, k=-1), axis=1)


def _runs(keys: list) -> list[tuple[int, int]]:
    """``(start, stop)`` of the runs of equal neighbouring ``keys``."""
    bounds = [0] + [i for i in range(1, len(keys)) if keys[i] != keys[i - 1]] + [len(keys)]
    return list(zip(bounds[:-1], bounds[1:]))


def _peaks(score: np.ndarray, threshold: float) -> np.ndarray:
    """Flat indices of the bins above ``threshold`` that are not below any of their 8 neighbours
    (the first of a plateau in raster order)."""
    Hb, Wb = score.shape
    flat = np.flatnonzero(score > threshold)
    if flat.size == 0:
        return flat
    padded = np.pad(score, 1, constant_values=-np.inf).ravel()
    r, c = np.divmod(flat, Wb)
    centre = (r + 1) * (Wb + 2) + c + 1
    value = padded[centre]
    peak = np.ones(flat.size, dtype=bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                other = padded[centre + dr * (Wb + 2) + dc]
                earlier = dr < 0 or (dr == 0 and dc < 0)
                peak &= (other < value) | ((other == value) & ~np.bool_(earlier))
    return flat[peak]


def _on_streak(p: np.ndarray, se: float, exposure: float) -> np.ndarray:
    """(n, n): whether star ``j``'s centre lies on star ``i``'s fitted streak (within its half
    length plus two PSF widths along it, two PSF widths across)."""
    speed = np.hypot(p[:, 2], p[:, 3])
    safe = np.where(speed > 0, speed, 1.0)
    ux, uy = np.where(speed > 0, p[:, 2] / safe, 1.0), np.where(speed > 0, p[:, 3] / safe, 0.0)
    dx = p[None, :, 0] - p[:, None, 0]
    dy = p[None, :, 1] - p[:, None, 1]
    along = np.abs(dx * ux[:, None] + dy * uy[:, None])
    across = np.abs(dy * ux[:, None] - dx * uy[:, None])
    return (across < 2.0 * se) & (along < (0.5 * speed * exposure + 2.0 * se)[:, None])


def _one_per_streak(p: np.ndarray, cov: np.ndarray, se: float, exposure: float):
    """One fit per star. A fit whose streak runs through the centres of two fits that are not one
    star (a window across the ends of two collinear streaks) is a blend and dropped; then a fit
    that lies on a better fit's streak, or whose own streak runs through a better fit's centre
    (a window that caught part of a brighter star), is dropped."""
    if p.shape[0] < 2:
        return p, cov
    snr = p[:, 4] / np.sqrt(cov[:, 4, 4])
    on = _on_streak(p, se, exposure)
    np.fill_diagonal(on, False)
    clash = on | on.T
    dropped = np.zeros(p.shape[0], dtype=bool)
    for i in np.flatnonzero(on.sum(axis=1) >= 2):
        inside = np.flatnonzero(on[i])
        apart = ~clash[np.ix_(inside, inside)]
        np.fill_diagonal(apart, False)
        dropped[i] = apart.any()
    for i in np.argsort(-snr, kind="stable"):
        if not dropped[i]:
            dropped |= clash[i] & ~dropped
    return p[~dropped], cov[~dropped]
