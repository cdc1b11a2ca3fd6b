"""Star-tracker frame simulator: centroid level and image level, both rolling-shutter exact.

For frame ``k`` (timestamp ``t0 = timing.frame_start_ns(k)``, the start of exposure of row 0):

1. Candidate stars: ``catalog.cone`` around the boresight at the frame's reference time with
   radius ``half_diagonal + max|omega| * (frame end - t0) + margin`` (margin
   ``CONE_MARGIN_RAD + CONE_MARGIN_FRACTION * half_diagonal`` covers effects such as distortion),
   optionally cut at ``magnitude_limit``.
2. Truth: each star's centroid row solves ``y = Y(t0 + y ld + T/2)`` (see
   :mod:`rollingstar.sensors.centroid_sim`), ``x`` at the same time; stars with ``(x, y)`` on the detector are
   kept. ``row_time_ns = timing.row_start_ns(t0, y)``, ``t_ns = timing.row_mid_exposure_ns(t0, y)``.
3. Centroid level: measured ``x, y`` = truth + N(0, ``centroid_sigma_px``) each; measured
   ``row_time_ns`` / ``t_ns`` are those of the *measured* row (what a real pipeline timestamps);
   ``flux`` is Poisson(expected star electrons, :class:`ImageModel`); sorted by measured y.
4. Image level: exact smear rendering and detector chain of :mod:`rollingstar.sensors.image_sim`.

Randomness is per frame, ``np.random.default_rng([seed, k, stream])`` with one stream per noise
source, so ``frame(k)`` does not depend on which frames were simulated before. Hot-pixel
positions come from ``default_rng([seed, HOT_PIXEL_KEY, 0])`` and are the same in every frame.
"""
from __future__ import annotations

import functools
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from rollingstar.sensors.centroid_sim import (
    ObservationInfo,
    image_positions,
    solve_star_rows,
)
from rollingstar.sensors.conventions import NS_PER_S
from rollingstar.sensors.effects.base import Effect
from rollingstar.sensors.effects.chain import apply_gyro, ordered
from rollingstar.sensors.image_sim import (
    ImageModel,
    digitise,
    hot_pixel_mask,
    mean_electrons,
    render_star_electrons,
)

__all__ = ["ImageModel", "SimulatedFrame", "StarTrackerSimulator", "TrueStars"]

CONE_MARGIN_RAD = float(np.radians(0.5))
CONE_MARGIN_FRACTION = 0.1
HOT_PIXEL_KEY = 2**62  # frame indices never reach this: hot pixels get their own seed sequence

# noise streams of a frame
STREAM_CENTROID_X, STREAM_CENTROID_Y, STREAM_FLUX, STREAM_SHOT, STREAM_READ = range(5)
LEVELS = ("centroid", "image")


@dataclass(frozen=True, eq=False)
class TrueStars:
    """Truth of one frame for the n stars whose centroid lies on the detector.

    ``x, y``: noise-free affected image position at ``t_ns`` (px); ``row_time_ns``: exposure start
    of the star's fractional row; ``t_ns``: mid-exposure of that row (both int64).
    """

    catalog_id: np.ndarray
    unit_icrs: np.ndarray
    magnitude: np.ndarray
    x: np.ndarray
    y: np.ndarray
    row_time_ns: np.ndarray
    t_ns: np.ndarray

    def __len__(self) -> int:
        return int(self.catalog_id.shape[0])


@dataclass(frozen=True, eq=False)
class SimulatedFrame:
    """One simulated frame: truth plus measured centroids (centroid level) or an image (image level)."""

    index: int
    t0_ns: int
    truth: TrueStars
    centroids: dict[str, np.ndarray] | None = None
    image: np.ndarray | None = None


class StarTrackerSimulator:
    """Simulate frames of a star tracker looking at ``catalog`` while moving as ``motion``.

    ``effects`` (a sequence of :class:`rollingstar.sensors.effects.Effect`) are applied in canonical stage
    order (:func:`rollingstar.sensors.effects.chain.ordered`): time effects shift the instant each star is
    seen on the true motion, the others map the pinhole positions. ``zenith_icrs`` (3,) (ground
    tests) and ``covariates`` (name -> function of int64 ns) feed the effects' context.
    ``level`` is ``"centroid"`` or ``"image"``; ``image_model`` (default
    :class:`ImageModel()`) sets the photometry of both levels and the detector of the image level.
    """

    def __init__(self, camera, timing, catalog, motion, effects=(), centroid_sigma_px: float = 0.0,
                 image_model: ImageModel | None = None, level: str = "centroid", seed: int = 0,
                 magnitude_limit: float | None = None, zenith_icrs=None, covariates=None):
        if level not in LEVELS:
            raise ValueError(f"level must be one of {LEVELS}, got {level!r}")
        if timing.rows != camera.height:
            raise ValueError(f"timing.rows ({timing.rows}) must equal camera.height ({camera.height})")
        effects = tuple(effects)
        bad = [e for e in effects if not isinstance(e, Effect)]
        if bad:
            raise ValueError(f"effects must be Effect instances (see rollingstar.sensors.effects.build_effect), got {bad!r}")
        if level == "image":
            centroid_only = [e.name for e in effects if not e.image_level]
            if centroid_only:
                raise ValueError(f"effect(s) {', '.join(centroid_only)} are centroid-estimation biases: simulate them at "
                                 "level 'centroid' (an image-level simulation produces them through the centroider)")
        effects = ordered(effects)
        if not (np.isfinite(centroid_sigma_px) and centroid_sigma_px >= 0):
            raise ValueError(f"centroid_sigma_px must be finite and >= 0, got {centroid_sigma_px!r}")
        if image_model is not None and not isinstance(image_model, ImageModel):
            raise ValueError(f"image_model must be an ImageModel or None, got {type(image_model).__name__}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        if magnitude_limit is not None and np.isnan(magnitude_limit):
            raise ValueError("magnitude_limit must be a number or None, got NaN")
        self.camera = camera
        self.timing = timing
        self.catalog = catalog
        self.motion = motion
        self.effects = effects
        self.centroid_sigma_px = float(centroid_sigma_px)
        self.image_model = image_model if image_model is not None else ImageModel()
        self.level = level
        self.seed = int(seed)
        self.magnitude_limit = None if magnitude_limit is None else float(magnitude_limit)
        self.zenith_icrs = None if zenith_icrs is None else np.asarray(zenith_icrs, dtype=float).reshape(3)
        self.covariates = dict(covariates or {})

    # ------------------------------------------------------------------ public
    def frame(self, k: int) -> SimulatedFrame:
        """Simulate frame ``k`` (deterministic in ``seed`` and ``k`` only)."""
        k = self._check_index(k)
        t0 = int(self.timing.frame_start_ns(k))
        cand, x, y, info = self._solve(t0, k)
        keep = self.camera.contains(x, y)
        truth = self._truth(cand[keep], x[keep], y[keep], t0)
        if self.level == "centroid":
            return SimulatedFrame(k, t0, truth, centroids=self._measure(truth, k, t0))
        star_e = self._render(cand, y, t0, info)
        return SimulatedFrame(k, t0, truth, image=self._digitise(star_e, k))

    def frames(self, n: int, start: int = 0) -> Iterator[SimulatedFrame]:
        """Frames ``start, ..., start + n - 1``."""
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        self._check_index(start)
        return (self.frame(k) for k in range(start, start + n))

    def star_electrons(self, k: int) -> np.ndarray:
        """Noise-free star signal of frame ``k`` in electrons, float (H, W) (no background)."""
        k = self._check_index(k)
        t0 = int(self.timing.frame_start_ns(k))
        cand, _, y, info = self._solve(t0, k)
        return self._render(cand, y, t0, info)

    def expected_electrons(self, k: int) -> np.ndarray:
        """Mean electrons per pixel of frame ``k`` before noise: stars + background + dark + hot pixels."""
        return mean_electrons(self.star_electrons(k), self.image_model, self.timing.exposure_ns, self.hot_pixels)

    @functools.cached_property
    def hot_pixels(self) -> np.ndarray | None:
        """Fixed (H, W) boolean hot-pixel mask (None when ``hot_pixel_fraction`` is 0)."""
        if self.image_model.hot_pixel_fraction <= 0:
            return None
        rng = np.random.default_rng([self.seed, HOT_PIXEL_KEY, 0])
        return hot_pixel_mask((self.camera.height, self.camera.width), self.image_model.hot_pixel_fraction, rng)

    # ----------------------------------------------------------------- helpers
    def _check_index(self, k) -> int:
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
            raise ValueError(f"frame index must be a non-negative integer, got {k!r}")
        return int(k)

    def _rng(self, k: int, stream: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, k, stream])

    def apply_gyro(self, t_ns, omega_rad_s) -> np.ndarray:
        """Gyro samples (m, 3) after the gyro-channel effects (gyro_bias, gyro_scale, ...)."""
        return apply_gyro(self.effects, t_ns, omega_rad_s)

    def covariates_at(self, t_ns) -> dict[str, np.ndarray]:
        """The scenario's covariates (e.g. ``temperature_c``) at int64 ns times."""
        t = np.asarray(t_ns, dtype=np.int64)
        return {name: np.asarray(f(t), dtype=float) for name, f in self.covariates.items()}

    def _info(self, cand: np.ndarray, t0: int, k: int) -> ObservationInfo:
        """Per-star context of the candidates (only built when there are effects)."""
        cat = self.catalog
        mag = cat.magnitude[cand]
        pm = getattr(cat, "pm_rad_yr", None)
        return ObservationInfo(
            magnitude=mag, flux_e=self.image_model.star_electrons(mag, self.timing.exposure_ns),
            pm_rad_yr=None if pm is None else pm[cand], t0_ns=t0, frame=k, timing=self.timing,
            zenith_icrs=self.zenith_icrs, covariates=self.covariates, t_start_ns=int(self.timing.start_ns),
        )

    def _candidates(self, t0: int) -> np.ndarray:
        """Catalogue indices of stars that may be imaged during the frame."""
        timing = self.timing
        t_ref = timing.frame_reference_ns(t0)
        t_end = timing.frame_end_ns(t0)
        boresight = self.motion.attitude(np.array([t_ref], dtype=np.int64))[0].apply([0.0, 0.0, 1.0])
        rates = self.motion.angular_velocity(np.array([t0, t_ref, t_end], dtype=np.int64))
        sweep = float(np.max(np.linalg.norm(rates, axis=1))) * (t_end - t0) / NS_PER_S
        half = self.camera.half_diagonal_rad
        radius = half + sweep + CONE_MARGIN_RAD + CONE_MARGIN_FRACTION * half
        idx = self.catalog.cone(boresight, min(radius, np.pi))
        if self.magnitude_limit is not None:
            idx = idx[self.catalog.magnitude[idx] <= self.magnitude_limit]
        return idx

    def _solve(self, t0: int, k: int):
        cand = self._candidates(t0)
        info = self._info(cand, t0, k) if self.effects else None
        x, y, _ = solve_star_rows(self.camera, self.timing, self.motion, self.effects,
                                  self.catalog.unit_icrs[cand], t0, info=info)
        return cand, x, y, info

    def _truth(self, idx, x, y, t0: int) -> TrueStars:
        cat = self.catalog
        return TrueStars(
            catalog_id=cat.ids[idx].copy(),
            unit_icrs=cat.unit_icrs[idx].copy(),
            magnitude=cat.magnitude[idx].copy(),
            x=x,
            y=y,
            row_time_ns=self.timing.row_start_ns(t0, y),
            t_ns=self.timing.row_mid_exposure_ns(t0, y),
        )

    def _measure(self, truth: TrueStars, k: int, t0: int) -> dict[str, np.ndarray]:
        n = len(truth)
        sigma = self.centroid_sigma_px
        x = truth.x + (self._rng(k, STREAM_CENTROID_X).normal(0.0, sigma, n) if sigma > 0 else 0.0)
        y = truth.y + (self._rng(k, STREAM_CENTROID_Y).normal(0.0, sigma, n) if sigma > 0 else 0.0)
        expected = self.image_model.star_electrons(truth.magnitude, self.timing.exposure_ns)
        flux = self._rng(k, STREAM_FLUX).poisson(expected).astype(float)
        order = np.argsort(y, kind="stable")
        x, y, flux = x[order], y[order], flux[order]
        return {
            "x": x,
            "y": y,
            "row_time_ns": self.timing.row_start_ns(t0, y),
            "t_ns": self.timing.row_mid_exposure_ns(t0, y),
            "flux": flux,
        }

    def _render(self, cand, y_star, t0: int, info: ObservationInfo | None) -> np.ndarray:
        model = self.image_model
        finite = np.isfinite(y_star)
        idx = np.flatnonzero(finite)
        cand, y_star = cand[finite], y_star[finite]
        unit = self.catalog.unit_icrs[cand]
        electrons = model.star_electrons(self.catalog.magnitude[cand], self.timing.exposure_ns)

        def positions(star, t_ns, rows):  # star: indices into the rendered stars
            return image_positions(self.camera, self.motion, self.effects, unit[star], t_ns, rows=rows,
                                   info=info, index=None if info is None else idx[star])

        return render_star_electrons(positions, self.timing, (self.camera.height, self.camera.width), t0,
                                     unit, electrons, y_star, model.psf_sigma_px)

    def _digitise(self, star_e: np.ndarray, k: int) -> np.ndarray:
        mean = mean_electrons(star_e, self.image_model, self.timing.exposure_ns, self.hot_pixels)
        return digitise(mean, self.image_model, self._rng(k, STREAM_SHOT), self._rng(k, STREAM_READ))
