"""Uniform image-velocity star field: the motion model he2021a's simulation assumes (its eq 19).

he2021a (section 3.1) converts the body rate to one image velocity for every star,
``V = omega * 3600 / IFOV`` (eq 19, IFOV in arcsec per pixel), and shifts each star of a
global-exposure star map by that velocity times its row's exposure delay. A real rotating
pinhole camera has a position-dependent image velocity and hence image *acceleration*
(``~2 v^2 r / f^2``), which the paper's constant-velocity filter does not model. To reproduce the
paper under its own assumption, :class:`UniformDriftSimulator` keeps the attitude fixed and
translates the whole image at ``V``: a star whose fixed-attitude pinhole position is ``p`` is at
``p + V (t - epoch)`` at time ``t``. Everything else follows the project's simulator
(:mod:`rollingstar.sensors.simulate`): the centroid row solves the rolling-shutter row equation
``y = Y(t0 + y ld + T/2)`` (here in closed form), ``t_ns`` is the mid-exposure of that row, the
centroid level adds Gaussian noise per axis and Poisson flux, the image level renders the exact
rolling-shutter smear with :func:`rollingstar.sensors.image_sim.render_star_electrons` and digitises with the
same detector chain. Noise streams are per frame (``default_rng([seed, k, stream])``).

This is a separate class rather than a scenario option because a uniform translation is not an
attitude motion (no rotation produces it) and needs its own truth (:meth:`true_xy`).

:func:`image_velocity_px_s` gives eq (19)'s ``V`` for a body rate: the image velocity of the
boresight under a rigid rotation at that rate (``omega / IFOV`` with IFOV = pixel / f at the
principal point; Table 1's 10 deg / 1024 px would give 34 % more -- the two Table 1 numbers are
inconsistent, we take the one consistent with f and the pixel pitch, so the drift and the real-sky
runs have the same speed at the image centre).

There is no rigid attitude that produces a uniform translation; :func:`drift_reference_vectors`
gives the directions that true positions at a chosen time unproject to (rotated to ICRS by the
fixed attitude): the reference the paper's QUEST experiment implies (an attitude solved from stars
all corrected to that time then equals the fixed attitude exactly).
"""
from __future__ import annotations

import numpy as np

from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.image_sim import (
    ImageModel,
    digitise,
    mean_electrons,
    render_star_electrons,
)
from rollingstar.sensors.motion import inertial_hold
from rollingstar.sensors.simulate import SimulatedFrame, TrueStars

DETECTOR_MARGIN_PX = 50.0  # stars farther than this outside the detector are not rendered
STREAM_CENTROID_X, STREAM_CENTROID_Y, STREAM_FLUX, STREAM_SHOT, STREAM_READ = range(5)


def image_velocity_px_s(camera, motion, t_ns: int = 0, h_ns: int = 500_000) -> np.ndarray:
    """Image velocity (px/s, (2,)) of the boresight direction under ``motion`` at ``t_ns`` (central difference)."""
    t = np.array([t_ns - h_ns, t_ns + h_ns], dtype=np.int64)
    u = motion.attitude(np.array([t_ns], dtype=np.int64))[0].apply([0.0, 0.0, 1.0])
    x, y, _ = camera.project(motion.attitude(t).inv().apply(np.stack([u, u])))
    return np.array([x[1] - x[0], y[1] - y[0]]) / (2 * h_ns * S_PER_NS)


class UniformDriftSimulator:
    """Frames of a fixed-attitude camera whose whole image drifts at ``velocity_px_s`` (he2021a eq 19).

    ``attitude``: the fixed camera-to-ICRS rotation (pinhole positions at ``epoch_ns``);
    ``level``: ``"centroid"`` or ``"image"``. Attributes used by callers: ``camera``, ``timing``,
    ``catalog``, ``motion`` (the fixed attitude, :func:`rollingstar.sensors.motion.inertial_hold`), ``level``,
    ``seed``, ``velocity_px_s``. Stars drift in from outside the initial field (candidates come
    from a cone wide enough for the whole drift up to the frame's end).
    """

    def __init__(self, camera, timing, catalog, attitude, velocity_px_s, centroid_sigma_px: float = 0.0,
                 image_model: ImageModel | None = None, level: str = "centroid", seed: int = 0, epoch_ns: int = 0):
        v = np.asarray(velocity_px_s, dtype=float).reshape(2)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"velocity_px_s must be finite, got {velocity_px_s!r}")
        if abs(v[1]) * timing.effective_line_delay_ns * S_PER_NS >= 1.0:
            raise ValueError(f"|vy| * line delay must be < 1 row (got vy = {v[1]} px/s)")
        if level not in ("centroid", "image"):
            raise ValueError(f"level must be 'centroid' or 'image', got {level!r}")
        if image_model is not None and image_model.hot_pixel_fraction > 0:
            raise ValueError("UniformDriftSimulator does not simulate hot pixels (image_model.hot_pixel_fraction must be 0)")
        if not (np.isfinite(centroid_sigma_px) and centroid_sigma_px >= 0):
            raise ValueError(f"centroid_sigma_px must be finite and >= 0, got {centroid_sigma_px!r}")
        self.camera, self.timing, self.catalog = camera, timing, catalog
        self.attitude = attitude
        self.motion = inertial_hold(attitude)
        self.velocity_px_s = v
        self.centroid_sigma_px = float(centroid_sigma_px)
        self.image_model = image_model if image_model is not None else ImageModel()
        self.level = level
        self.seed = int(seed)
        self.epoch_ns = int(epoch_ns)

    # ------------------------------------------------------------------ truth
    def true_xy(self, unit_icrs, t_ns) -> np.ndarray:
        """True image positions (m, 2) of directions ``unit_icrs`` (m, 3) at int ns times ``t_ns`` (m,)."""
        u = np.asarray(unit_icrs, dtype=float).reshape(-1, 3)
        x, y, _ = self.camera.project(self.attitude.inv().apply(u))
        dt = (np.asarray(t_ns, dtype=np.int64).reshape(-1) - self.epoch_ns) * S_PER_NS
        return np.column_stack([x + self.velocity_px_s[0] * dt, y + self.velocity_px_s[1] * dt])

    def _candidates(self, t0: int) -> np.ndarray:
        cam = self.camera
        t_end_s = max(self.timing.frame_end_ns(t0) - self.epoch_ns, 0) * S_PER_NS
        reach_px = np.hypot(cam.width, cam.height) / 2 + float(np.hypot(*self.velocity_px_s)) * t_end_s
        radius = float(np.arctan(reach_px / cam.focal_px)) + np.radians(0.5)
        return self.catalog.cone(self.attitude.apply([0.0, 0.0, 1.0]), min(radius, np.radians(80.0)))

    def _solve(self, t0: int):
        """Closed form of the row equation ``y = y_p + Vy (t0 + y ld + T/2 - epoch)`` for every candidate.

        ``y = (y_p + Vy (t0 + T/2 - epoch)) / (1 - Vy ld)`` (``y_p`` the fixed-attitude pinhole row),
        ``x = x_p + Vx (t0 + y ld + T/2 - epoch)``. Returns candidates within the margin and ``x, y``.
        """
        cand = self._candidates(t0)
        xp, yp, _ = self.camera.project(self.attitude.inv().apply(self.catalog.unit_icrs[cand]))
        vx, vy = self.velocity_px_s
        ld = self.timing.effective_line_delay_ns * S_PER_NS
        base = (t0 - self.epoch_ns + self.timing.exposure_ns / 2.0) * S_PER_NS
        y = (yp + vy * base) / (1.0 - vy * ld)
        x = xp + vx * (base + y * ld)
        near = self.camera.contains(x, y, margin_px=-DETECTOR_MARGIN_PX)
        return cand[near], x[near], y[near]

    # ------------------------------------------------------------------ frames
    def frame(self, k: int) -> SimulatedFrame:
        """Simulate frame ``k`` (deterministic in ``seed`` and ``k`` only)."""
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
            raise ValueError(f"frame index must be a non-negative integer, got {k!r}")
        k = int(k)
        t0 = int(self.timing.frame_start_ns(k))
        cand, x, y = self._solve(t0)
        on = self.camera.contains(x, y)
        cat = self.catalog
        idx = cand[on]
        truth = TrueStars(catalog_id=cat.ids[idx].copy(), unit_icrs=cat.unit_icrs[idx].copy(),
                          magnitude=cat.magnitude[idx].copy(), x=x[on], y=y[on],
                          row_time_ns=self.timing.row_start_ns(t0, y[on]), t_ns=self.timing.row_mid_exposure_ns(t0, y[on]))
        if self.level == "centroid":
            return SimulatedFrame(k, t0, truth, centroids=self._measure(truth, k, t0))
        return SimulatedFrame(k, t0, truth, image=self._image(cand, y, k, t0))

    def _rng(self, k: int, stream: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, k, stream])

    def _measure(self, truth: TrueStars, k: int, t0: int) -> dict[str, np.ndarray]:
        n, s = len(truth), self.centroid_sigma_px
        x = truth.x + (self._rng(k, STREAM_CENTROID_X).normal(0.0, s, n) if s > 0 else 0.0)
        y = truth.y + (self._rng(k, STREAM_CENTROID_Y).normal(0.0, s, n) if s > 0 else 0.0)
        flux = self._rng(k, STREAM_FLUX).poisson(self.image_model.star_electrons(truth.magnitude, self.timing.exposure_ns))
        order = np.argsort(y, kind="stable")
        x, y = x[order], y[order]
        return {"x": x, "y": y, "row_time_ns": self.timing.row_start_ns(t0, y),
                "t_ns": self.timing.row_mid_exposure_ns(t0, y), "flux": flux[order].astype(float)}

    def _image(self, cand, y_star, k: int, t0: int) -> np.ndarray:
        model = self.image_model
        unit = self.catalog.unit_icrs[cand]
        electrons = model.star_electrons(self.catalog.magnitude[cand], self.timing.exposure_ns)

        def positions(star, t_ns, *_rows):  # render_star_electrons' callback: stars ``star`` at times ``t_ns``
            xy = self.true_xy(unit[np.asarray(star)], t_ns)
            return xy[:, 0], xy[:, 1]

        star_e = render_star_electrons(positions, self.timing, (self.camera.height, self.camera.width), t0,
                                       unit, electrons, y_star, model.psf_sigma_px)
        mean = mean_electrons(star_e, model, self.timing.exposure_ns, None)
        return digitise(mean, model, self._rng(k, STREAM_SHOT), self._rng(k, STREAM_READ))


def drift_reference_vectors(camera, attitude, x_true, y_true) -> np.ndarray:
    """ICRS unit vectors whose fixed-attitude images are the true positions ``(x_true, y_true)`` (n, 3)."""
    return attitude.apply(camera.unproject(x_true, y_true))
