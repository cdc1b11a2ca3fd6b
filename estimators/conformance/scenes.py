"""Simulated scenes for the conformance checks and for plugin tests.

Two scenes share one small camera, one rolling-shutter timing and one synthetic catalogue:

- the *static* scene (:func:`make_scene`): a camera holding still, stars rendered with an exact
  Gaussian PSF (:func:`render`) or given as star tables (:func:`detections`, :func:`identified`);
- the *moving* scene (:func:`make_moving_scene`): the same sky seen by a camera turning at a
  constant body rate, simulated with :mod:`rollingstar.sensors` (rolling-shutter exact star rows,
  smeared images, a rate-integrating gyro), so that roles whose contract is about motion (filters
  fill velocities, corrections move stars to one time, rate estimators measure the rate) are
  checked on frames where it matters.

``frames_for_role`` and ``moving_frames_for_role`` give the standard input of each role; a new role
only needs an entry in ``ROLE_INPUT``. :func:`standard_scene` and :func:`moving_scene` build each
scene once per process.
"""
from __future__ import annotations

import copy
import functools
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import erf

from rollingstar.estimators.data import FrameData, GyroSamples, SensorContext, StarTable
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.catalog import StarCatalog
from rollingstar.sensors.conventions import attitude_from_radec_roll, radec_to_unit
from rollingstar.sensors.effects.geometry import image_velocity
from rollingstar.sensors.gyro import GyroModel, GyroRecord, simulate_gyro
from rollingstar.sensors.motion import AttitudeMotion, constant_rate
from rollingstar.sensors.simulate import ImageModel, StarTrackerSimulator, TrueStars
from rollingstar.sensors.timing import DetectorTiming

# What each role consumes: "image" (raw frames), "detections" (unidentified spots), "identified"
# (spots matched to the catalogue), "filtered" (identified, with the image velocity ``vx, vy`` a
# star-motion filter upstream gives). A new role (or a third-party plugin of a new role) only
# needs an entry here.
ROLE_INPUT = {
    "centroider": "image",
    "identifier": "detections",
    "filter": "identified",
    "correction": "filtered",
    "attitude": "identified",
    "rate": "identified",
}
STANDARD_SEED = 101  # the static scene every check uses
MOVING_RATE_DEG_S = (1.5, -1.0, 0.5)  # body rate of the moving scene: ~90 px/s on the detector
MOVING_FRAMES = 4
GYRO_RATE_HZ = 400.0


@dataclass(frozen=True)
class Scene:
    context: SensorContext
    truth: Rotation  # camera-to-ICRS, static over the scene's frames
    catalog_index: np.ndarray  # catalogue indices of the stars imaged
    x: np.ndarray  # true pixel positions of those stars
    y: np.ndarray
    flux: np.ndarray  # ADU

    def attitude(self, t_ns) -> Rotation:
        """The true camera-to-ICRS attitude at ``t_ns`` (the same at every time: the camera holds still)."""
        return self.truth


def small_camera() -> PinholeCamera:
    """320 x 256 px, 5.5 um pixels, 16 mm focal length: a 6.3 x 5.0 deg field."""
    return PinholeCamera(focal_length_m=0.016, pixel_size_m=5.5e-6, width=320, height=256)


def make_scene(seed: int = 0, n_field: int = 14, n_sky: int = 400, prior_error_arcsec: float = 20.0,
               min_sep_px: float = 25.0, edge_px: float = 8.0, initial_attitude: bool = True) -> Scene:
    """A static scene: ``n_field`` catalogue stars on the detector (at least ``min_sep_px`` apart and
    ``edge_px`` inside the edge) plus ``n_sky`` random stars elsewhere on the sky."""
    rng = np.random.default_rng(seed)
    cam = small_camera()
    timing = DetectorTiming(mode="rolling", exposure_ns=10_000_000, line_delay_ns=20_000, rows=cam.height)
    truth = attitude_from_radec_roll(rng.uniform(0, 360), rng.uniform(-60, 60), rng.uniform(-180, 180))
    xs, ys = [], []
    while len(xs) < n_field:  # rejection sampling of well-separated positions (test set-up only)
        px, py = rng.uniform(edge_px, cam.width - 1 - edge_px), rng.uniform(edge_px, cam.height - 1 - edge_px)
        if all(np.hypot(px - a, py - b) >= min_sep_px for a, b in zip(xs, ys)):
            xs.append(px)
            ys.append(py)
    x, y = np.array(xs), np.array(ys)
    field_icrs = truth.apply(cam.unproject(x, y))
    sky = radec_to_unit(rng.uniform(0, 2 * np.pi, n_sky), np.arcsin(rng.uniform(-1, 1, n_sky)))
    boresight = truth.apply([0.0, 0.0, 1.0])
    sky = sky[sky @ boresight < np.cos(cam.half_diagonal_rad + np.radians(2.0))]  # keep them off the field
    unit = np.vstack([field_icrs, sky])
    ids = rng.permutation(np.arange(1000, 1000 + 10 * unit.shape[0]))[: unit.shape[0]].astype(np.int64)
    mag = np.concatenate([rng.uniform(2.0, 5.5, n_field), rng.uniform(2.0, 6.5, sky.shape[0])])
    catalog = StarCatalog.synthetic(unit, magnitude=mag, ids=ids)
    prior = truth * Rotation.from_rotvec(rng.normal(size=3) * prior_error_arcsec / 206264.806)
    context = SensorContext(camera=cam, timing=timing, catalog=catalog,
                            initial_attitude=prior if initial_attitude else None,
                            centroid_sigma_px=0.05, bit_depth=12)
    flux = magnitude_flux(mag[:n_field])
    return Scene(context, truth, np.arange(n_field), x, y, flux)


def render(x, y, flux, shape, psf_sigma_px: float = 1.2, background: float = 100.0, noise_sigma: float = 5.0,
           rng=None, dtype=np.uint16, saturation: float | None = 4095.0) -> np.ndarray:
    """Image of Gaussian spots with exact pixel integration (erf), background and Gaussian noise.

    Pixel (c, r) covers [c - 0.5, c + 0.5] x [r - 0.5, r + 0.5]; its expected signal from a star at
    (x, y) is ``flux * dPhi_x * dPhi_y``. Computed as ``Ey^T diag(flux) Ex`` (vectorised over stars).
    """
    H, W = shape
    x = np.atleast_1d(np.asarray(x, dtype=float))
    y = np.atleast_1d(np.asarray(y, dtype=float))
    flux = np.broadcast_to(np.asarray(flux, dtype=float), x.shape)
    s = np.sqrt(2.0) * psf_sigma_px
    cols = np.arange(W + 1) - 0.5
    rows = np.arange(H + 1) - 0.5
    ex = np.diff(0.5 * erf((cols[None, :] - x[:, None]) / s), axis=1)  # (n, W)
    ey = np.diff(0.5 * erf((rows[None, :] - y[:, None]) / s), axis=1)  # (n, H)
    img = background + ey.T @ (flux[:, None] * ex)
    if rng is not None and noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, img.shape)
    if np.issubdtype(np.dtype(dtype), np.integer):
        hi = saturation if saturation is not None else np.iinfo(dtype).max
        img = np.clip(np.rint(img), 0, hi)
    return img.astype(dtype)


def frame_times(context: SensorContext, n_frames: int) -> np.ndarray:
    return np.asarray(context.timing.frame_start_ns(np.arange(n_frames)), dtype=np.int64)


def detections(scene: Scene, t0_ns: int, rng, sigma_px: float = 0.05) -> StarTable:
    """Unidentified spots at the true positions plus noise, with row times, as a centroider gives."""
    return _spots(scene.context.timing, t0_ns, scene.x, scene.y, scene.flux, rng, sigma_px)


def _spots(timing, t0_ns: int, x_true, y_true, flux, rng, sigma_px: float) -> StarTable:
    """Spots at ``x_true, y_true`` plus N(0, ``sigma_px``) noise (x drawn first), timed by their measured row."""
    x = x_true + rng.normal(0, sigma_px, x_true.shape)
    y = y_true + rng.normal(0, sigma_px, y_true.shape)
    return StarTable.build(x, y, t_ns=timing.row_mid_exposure_ns(t0_ns, y), row_time_ns=timing.row_start_ns(t0_ns, y),
                           flux=flux, peak=flux / 10, npix=np.full(x.shape, 9), snr=flux / 50,
                           sigma_px=np.full(x.shape, sigma_px))


def magnitude_flux(magnitude) -> np.ndarray:
    """The star tables' flux (ADU) of a star of ``magnitude``: 4000 ADU at magnitude 4."""
    return 4000.0 * 10 ** (-0.4 * (np.asarray(magnitude, dtype=float) - 4.0))


def identified(scene: Scene, t0_ns: int, rng, sigma_px: float = 0.05) -> StarTable:
    det = detections(scene, t0_ns, rng, sigma_px)
    cat = scene.context.catalog
    return det.with_columns(catalog_id=cat.ids[scene.catalog_index], ref_icrs=cat.unit_icrs[scene.catalog_index])


def frames_for_role(role: str, scene: Scene, n_frames: int = 3, empty: bool = False, seed: int = 1) -> list[FrameData]:
    """The standard input frames of ``role`` (``empty``: the same frames without any star)."""
    kind = ROLE_INPUT[role]
    rng = np.random.default_rng(seed)
    cam = scene.context.camera
    out = []
    for k, t0 in enumerate(frame_times(scene.context, n_frames)):
        if kind == "image":
            flux = scene.flux[:0] if empty else scene.flux
            x, y = (scene.x[:0], scene.y[:0]) if empty else (scene.x, scene.y)
            img = render(x, y, flux, (cam.height, cam.width), rng=rng)
            out.append(FrameData(index=k, t0_ns=int(t0), image=img))
        else:
            table = detections(scene, int(t0), rng) if kind == "detections" else identified(scene, int(t0), rng)
            if kind == "filtered":  # the camera holds still: every image velocity is zero
                table = table.with_columns(vx=np.zeros(table.n), vy=np.zeros(table.n))
            if empty:
                table = table.take(np.zeros(table.n, dtype=bool))
            out.append(FrameData(index=k, t0_ns=int(t0), stars=table))
    return out


# ------------------------------------------------------------------------------ the moving scene
@dataclass(frozen=True, eq=False)
class MovingScene:
    """The static scene's sensor and sky while the camera turns at the constant body rate
    ``omega_rad_s`` (camera frame), starting from the static scene's attitude at t = 0.

    ``stars``: the truth of each frame (:class:`~rollingstar.sensors.simulate.TrueStars`: the stars
    on the detector, at the mid-exposure of their own row); ``images``: the simulated (smeared,
    rolling-shutter) images; ``gyro``: a noise-free rate-integrating gyro covering every frame.
    """

    context: SensorContext
    motion: AttitudeMotion
    omega_rad_s: np.ndarray
    stars: tuple[TrueStars, ...]
    images: tuple[np.ndarray, ...]
    gyro: GyroRecord

    def attitude(self, t_ns) -> Rotation:
        """The true camera-to-ICRS attitude at ``t_ns``."""
        return self.motion.attitude(t_ns)

    def gyro_samples(self, t0_ns: int) -> GyroSamples:
        """The gyro samples a frame starting at ``t0_ns`` carries: those of the frame period before it."""
        sel = (self.gyro.t_ns > t0_ns - self.context.timing.frame_period_ns) & (self.gyro.t_ns <= t0_ns)
        return GyroSamples(self.gyro.t_ns[sel].copy(), self.gyro.omega_rad_s[sel].copy())


def make_moving_scene(scene: Scene, n_frames: int = MOVING_FRAMES, omega_deg_s=MOVING_RATE_DEG_S,
                      seed: int = 0) -> MovingScene:
    """``n_frames`` frames of ``scene``'s sky with the camera turning at ``omega_deg_s`` (body frame)."""
    ctx = scene.context
    omega = np.radians(np.asarray(omega_deg_s, dtype=float))
    motion = constant_rate(scene.truth, omega)
    sim = StarTrackerSimulator(ctx.camera, ctx.timing, ctx.catalog, motion, level="image",
                               image_model=ImageModel(psf_sigma_px=1.2), seed=seed)
    frames = list(sim.frames(n_frames))
    period = ctx.timing.frame_period_ns
    gyro = simulate_gyro(GyroModel(rate_hz=GYRO_RATE_HZ), motion, int(ctx.timing.frame_start_ns(0)) - period,
                         int(ctx.timing.frame_start_ns(n_frames)), seed)
    return MovingScene(ctx, motion, omega, tuple(f.truth for f in frames), tuple(f.image for f in frames), gyro)


def moving_table(scene: MovingScene, k: int, kind: str, rng, sigma_px: float = 0.05) -> StarTable:
    """Frame ``k``'s stars of ``kind`` ("detections", "identified" or "filtered"): the true positions
    plus noise, timed by their measured row; "filtered" adds the true image velocity."""
    truth = scene.stars[k]
    t0 = int(scene.context.timing.frame_start_ns(k))
    table = _spots(scene.context.timing, t0, truth.x, truth.y, magnitude_flux(truth.magnitude), rng, sigma_px)
    if kind == "detections":
        return table
    table = table.with_columns(catalog_id=truth.catalog_id, ref_icrs=truth.unit_icrs)
    if kind == "filtered":
        vx, vy = image_velocity(scene.context.camera, truth.x, truth.y, scene.omega_rad_s)
        table = table.with_columns(vx=vx, vy=vy)
    return table


def moving_frames_for_role(role: str, scene: MovingScene, seed: int = 1) -> list[FrameData]:
    """The standard input frames of ``role`` in the moving scene, each with its gyro samples."""
    kind = ROLE_INPUT[role]
    rng = np.random.default_rng(seed)
    out = []
    for k, image in enumerate(scene.images):
        t0 = int(scene.context.timing.frame_start_ns(k))
        frame = FrameData(index=k, t0_ns=t0, gyro=scene.gyro_samples(t0))
        if kind == "image":
            out.append(frame.evolve(image=image.copy()))
        else:
            out.append(frame.evolve(stars=moving_table(scene, k, kind, rng)))
    return out


# ------------------------------------------------------------------------------ built once per process
@functools.cache
def standard_scene() -> Scene:
    """The static scene of the conformance checks (``make_scene(seed=101)``)."""
    return make_scene(seed=STANDARD_SEED)


@functools.cache
def moving_scene() -> MovingScene:
    """The moving scene of the conformance checks (the static scene's sky, turning, with a gyro)."""
    return make_moving_scene(standard_scene())


@functools.cache
def _standard_frames(role: str, empty: bool) -> tuple[FrameData, ...]:
    return tuple(frames_for_role(role, standard_scene(), empty=empty))


@functools.cache
def _moving_frames(role: str) -> tuple[FrameData, ...]:
    return tuple(moving_frames_for_role(role, moving_scene()))


def standard_frames(role: str, empty: bool = False) -> list[FrameData]:
    """A fresh copy of ``role``'s standard input in the static scene (simulated once per process)."""
    return copy.deepcopy(list(_standard_frames(role, empty)))


def moving_frames(role: str) -> list[FrameData]:
    """A fresh copy of ``role``'s standard input in the moving scene (simulated once per process)."""
    return copy.deepcopy(list(_moving_frames(role)))
