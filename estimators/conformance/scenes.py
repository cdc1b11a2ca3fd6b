"""Synthetic scenes for plugin tests: a small camera, a catalogue, rendered images and star tables.

Used by the conformance suite (``frames_for_role`` gives the standard input of each role, so a new
role only needs an entry in ``ROLE_INPUT``) and by the per-plugin tests.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import erf

from rollingstar.estimators.data import FrameData, SensorContext, StarTable
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.catalog import StarCatalog
from rollingstar.sensors.conventions import attitude_from_radec_roll, radec_to_unit
from rollingstar.sensors.timing import DetectorTiming

# What each role consumes: "image" (raw frames), "detections" (unidentified spots), "identified".
# A new role (or a third-party plugin of a new role) only needs an entry here.
ROLE_INPUT = {
    "centroider": "image",
    "identifier": "detections",
    "filter": "identified",
    "correction": "identified",
    "attitude": "identified",
    "rate": "identified",
}


@dataclass(frozen=True)
class Scene:
    context: SensorContext
    truth: Rotation  # camera-to-ICRS, static over the scene's frames
    catalog_index: np.ndarray  # catalogue indices of the stars imaged
    x: np.ndarray  # true pixel positions of those stars
    y: np.ndarray
    flux: np.ndarray  # ADU


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
    flux = 4000.0 * 10 ** (-0.4 * (mag[:n_field] - 4.0))
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
    timing = scene.context.timing
    x = scene.x + rng.normal(0, sigma_px, scene.x.shape)
    y = scene.y + rng.normal(0, sigma_px, scene.y.shape)
    return StarTable.build(x, y, t_ns=timing.row_mid_exposure_ns(t0_ns, y), row_time_ns=timing.row_start_ns(t0_ns, y),
                           flux=scene.flux, peak=scene.flux / 10, npix=np.full(x.shape, 9), snr=scene.flux / 50,
                           sigma_px=np.full(x.shape, sigma_px))


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
            if empty:
                table = table.take(np.zeros(table.n, dtype=bool))
            out.append(FrameData(index=k, t0_ns=int(t0), stars=table))
    return out
