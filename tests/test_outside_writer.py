"""Recordings written from the documents alone solve to the truth they carry.

The writer in this file is an outsider: it uses the plain ``mcap`` package, ``json``, ``yaml``,
numpy, scipy's ``Rotation`` and Pillow, and no rollingstar writer, record or helper. It follows
docs/log-format.md and docs/conventions.md literally: the pinhole projection, the frame and row
times, the centroid noise, the attitude quaternions and body rates are the code below, written
from those two pages. Only the star directions come from rollingstar's Hipparcos-2 catalogue
(reference data, the same the recording's scenario names). ``rollingstar run`` and ``rollingstar
evaluate`` (the command line, in a subprocess) must then find the attitude at the noise floor the
writer injected, on every camera axis. A disagreement between the documents and the code shows
as a 180 deg error about the boresight, a mirrored field that tracking cannot identify, or an
error of (rotation rate) x (time offset) on a moving camera.

- Centroid level: rolling shutter, a 0.4 deg/s rotation, ``/camera/centroids`` frames,
  ``/truth/attitude`` and ``/gyro`` written with ``mcap.writer.Writer``; pipelines ``ls_rate``
  (each frame's rate from its stars' row times, every star moved to one time, QUEST) and
  ``he2021b_mekf`` (gyro propagation, every star at its own row time).
- Image level: global shutter, PNG frames from a Gaussian renderer, the attitude built in the
  OpenCV camera frame and converted with the relation conventions.md states, a truth CSV, a
  ``recording.yaml`` sidecar, ``rollingstar import images``, pipeline ``baseline``.

``pytest -s tests/test_outside_writer.py`` prints the attitude error per axis next to its floor.
"""
from __future__ import annotations

import json
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.writer import CompressionType, Writer
from PIL import Image
from scipy.spatial.transform import Rotation
from scipy.special import erf

from rollingstar.sensors.catalog import StarCatalog

ROOT = Path(__file__).resolve().parents[1]
ARCSEC_PER_RAD = 180.0 / np.pi * 3600.0
POINTING = {"ra_deg": 83.8, "dec_deg": -5.4, "roll_deg": 30.0}  # Orion: 15-25 stars to Hp 6 in 10 deg
CATALOG = {"source": "hipparcos", "magnitude_limit": 6.0, "epoch_year": 2025.0}


# --- the outside writer's own geometry, from docs/conventions.md -----------------------------------

def radec_unit(ra_deg, dec_deg) -> np.ndarray:
    """Catalogue direction: ``[cos a cos d, sin a cos d, sin d]``."""
    a, d = np.radians(ra_deg), np.radians(dec_deg)
    return np.array([np.cos(a) * np.cos(d), np.sin(a) * np.cos(d), np.sin(d)])


def rot_z(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def pointing_attitude(ra_deg: float, dec_deg: float, roll_deg: float) -> np.ndarray:
    """Camera-to-ICRS matrix (columns: the camera axes in ICRS) for a boresight and roll.

    conventions.md: +z is the boresight; at roll 0 the camera's -y axis points to celestial north;
    roll turns the camera about +z: ``R = R(ra, dec, 0) Rz(roll)``.
    """
    z = radec_unit(ra_deg, dec_deg)
    north = np.array([0.0, 0.0, 1.0]) - z[2] * z
    y = -north / np.linalg.norm(north)
    x = np.cross(y, z)
    return np.column_stack([x, y, z]) @ rot_z(np.radians(roll_deg))


def exp_so3(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: the rotation matrix of a rotation vector."""
    angle = float(np.linalg.norm(rotvec))
    if angle == 0.0:
        return np.eye(3)
    k = np.asarray(rotvec) / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


class Camera:
    """conventions.md's pixel direction ``w ~ [-(x - cx) p, -(y - cy) p, f]`` and its inverse;
    the principal point defaults to the detector centre ``((W - 1) / 2, (H - 1) / 2)``."""

    def __init__(self, sensor: dict):
        self.f = sensor["focal_length_mm"] * 1e3 / sensor["pixel_size_um"]  # px
        self.width, self.height = sensor["width_px"], sensor["height_px"]
        self.cx, self.cy = sensor.get("principal_point_px") or ((self.width - 1) / 2.0, (self.height - 1) / 2.0)

    def direction(self, x, y) -> np.ndarray:
        w = np.column_stack([-(np.asarray(x) - self.cx), -(np.asarray(y) - self.cy), np.full(np.size(x), self.f)])
        return w / np.linalg.norm(w, axis=1, keepdims=True)

    def project(self, w_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w = np.atleast_2d(w_cam)
        return self.cx - self.f * w[:, 0] / w[:, 2], self.cy - self.f * w[:, 1] / w[:, 2]

    def on_detector(self, x, y, margin: float) -> np.ndarray:
        return (x > margin - 0.5) & (y > margin - 0.5) & (x < self.width - 0.5 - margin) & (y < self.height - 0.5 - margin)


def body_rate_motion(start: np.ndarray, omega_rad_s: np.ndarray, t_start_ns: int):
    """``R(t) = R(t_start) Exp(omega (t - t_start))``: a constant body rate (camera frame)."""
    def attitude(t_ns: int) -> np.ndarray:
        return start @ exp_so3(omega_rad_s * (t_ns - t_start_ns) / 1e9)
    return attitude


def field_stars(attitude: np.ndarray, cam: Camera, min_gap_px: float = 30.0):
    """Catalogue stars in the field at ``attitude``, without close pairs: (ids, unit_icrs, magnitude)."""
    cat = StarCatalog.from_hipparcos(epoch_year=CATALOG["epoch_year"], magnitude_limit=CATALOG["magnitude_limit"])
    w = cat.unit_icrs @ attitude  # rows: R^T u
    front = w[:, 2] > 0.95
    x, y = cam.project(w[front])
    near = np.flatnonzero(front)[cam.on_detector(x, y, -200.0)]
    px = np.column_stack(cam.project(w[near]))
    gap = np.linalg.norm(px[:, None] - px[None], axis=-1) + np.eye(len(near)) * 1e9
    keep = near[gap.min(axis=1) > min_gap_px]
    return cat.ids[keep], cat.unit_icrs[keep], cat.magnitude[keep]


def attitude_floor_arcsec(frames: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """RMS over frames of the single-frame attitude error bound per camera axis (arcsec).

    ``frames``: per frame the stars' camera-frame unit directions (n, 3) and the standard deviation
    (rad) with which each is measured in the two directions across it. Information
    ``sum (I - w w^T) / sigma^2``; the bound is the square root of its inverse's diagonal.
    """
    var = [np.diag(np.linalg.inv(sum((np.eye(3) - np.outer(w, w)) / s**2 for w, s in zip(ws, sig))))
           for ws, sig in frames]
    return np.sqrt(np.mean(var, axis=0)) * ARCSEC_PER_RAD


# --- the outside writer's MCAP, from docs/log-format.md --------------------------------------------

def start_log(f, kind: str, scenario: dict) -> Writer:
    w = Writer(f, chunk_size=256 * 1024, compression=CompressionType.ZSTD)
    w.start(profile="rollingstar", library="outside-writer test")
    w.add_metadata("rollingstar", {"format_version": "1.0", "software_version": "outside-writer test",
                                   "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                                   "kind": kind})
    w.add_metadata("scenario", {"yaml": yaml.safe_dump(scenario, sort_keys=False)})
    return w


def json_channel(w: Writer, topic: str, schema: str) -> int:
    return w.register_channel(topic, "json", w.register_schema(schema, "jsonschema", b"{}"))


def add_json(w: Writer, channel: int, log_time: int, record: dict) -> None:
    w.add_message(channel, log_time=log_time, publish_time=log_time, data=json.dumps(record).encode())


def truth_record(attitude, omega_rad_s: np.ndarray, times_ns: list[int]) -> dict:
    q = Rotation.from_matrix(np.array([attitude(t) for t in times_ns])).as_quat()  # scalar last
    return {"t_ns": times_ns, "qx": q[:, 0].tolist(), "qy": q[:, 1].tolist(), "qz": q[:, 2].tolist(),
            "qw": q[:, 3].tolist(), "wx": [float(omega_rad_s[0])] * len(times_ns),
            "wy": [float(omega_rad_s[1])] * len(times_ns), "wz": [float(omega_rad_s[2])] * len(times_ns)}


# --- running the command line ---------------------------------------------------------------------

def cli(*args) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=ROOT, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def run_and_evaluate(pipeline: str, recording: Path) -> dict:
    out = recording.with_suffix(".out.mcap")
    cli("run", pipeline, recording, "-o", out, "--quiet")
    return json.loads(cli("evaluate", out, "--json").stdout)


def check_at_floor(label: str, metrics: dict, floor: np.ndarray, frames: int, stars: float,
                   single_frame: bool = True) -> None:
    """Every frame solved, the attitude error RMSE below 3 times the floor on each axis and, for a
    single-frame solver (which cannot beat the floor), above a third of it."""
    err = metrics["attitude_error_arcsec"]
    rmse = np.array([np.nan if err[f"{ax}_rmse"] is None else err[f"{ax}_rmse"] for ax in "xyz"])
    print(f"\n{label}: {frames} frames, {stars:.1f} stars per frame; attitude error RMSE x, y, z = "
          f"{np.array2string(rmse, precision=3)} arcsec, floor {np.array2string(floor, precision=3)} arcsec, "
          f"ratio {np.array2string(rmse / floor, precision=2)}")
    updates = frames if single_frame else metrics["attitude_updates"]  # a filter may update per star
    assert metrics["attitude_updates"] == updates >= frames and metrics["invalid_attitude_estimates"] == 0, metrics
    assert np.all(rmse < 3.0 * floor), (rmse, floor)
    if single_frame:
        assert np.all(rmse > floor / 3.0), (rmse, floor)  # the injected noise is there: not a trivial pass


# --- centroid level --------------------------------------------------------------------------------

ROLLING = {"focal_length_mm": 24.09, "pixel_size_um": 5.5, "width_px": 1024, "height_px": 1024}
ROLLING_SHUTTER = {"mode": "rolling", "exposure_ms": 50.0, "line_delay_us": 49.0, "frame_period_ms": 100.0}


GYRO_STEP_NS = 5_000_000  # 200 Hz
GYRO_NOISE_RAD_S = np.radians(0.01 / 60.0) * np.sqrt(1e9 / GYRO_STEP_NS)  # angle random walk 0.01 deg/sqrt(h)


def gyro_record(omega_rad_s: np.ndarray, times_ns: list[int], rng) -> dict:
    """A ``rollingstar.GyroSamples`` record: the body rate about the camera axes, white noise."""
    w = omega_rad_s + rng.normal(0.0, GYRO_NOISE_RAD_S, (len(times_ns), 3))
    return {"t_ns": times_ns, "x": w[:, 0].tolist(), "y": w[:, 1].tolist(), "z": w[:, 2].tolist()}


def camera_directions(attitude, t_ns: np.ndarray, unit_icrs: np.ndarray) -> np.ndarray:
    """``w_i = R(t_i)^T u_i``: each star's camera-frame direction at its own time."""
    return np.array([attitude(int(t)).T @ u for t, u in zip(t_ns, unit_icrs)])


def centroid_frame(k: int, t0: int, attitude, stars, cam: Camera, rng, sigma_px: float) -> tuple[dict, np.ndarray]:
    """One ``rollingstar.Stars`` record: every star where it is at the mid-exposure of its own row,
    plus Gaussian noise of ``sigma_px`` per axis; also the true camera-frame directions.

    The row a star lands on depends on when that row exposes: fixed-point passes of
    ``y = project(R(t(y))^T u)`` with ``t(y) = t0 + round(y line_delay) + exposure / 2``.
    """
    _, unit, mag = stars
    line_ns = round(ROLLING_SHUTTER["line_delay_us"] * 1e3)
    half_exposure_ns = round(ROLLING_SHUTTER["exposure_ms"] * 1e6) // 2
    y = np.full(len(unit), cam.cy)
    for _ in range(4):
        t = t0 + np.rint(y * line_ns).astype(np.int64) + half_exposure_ns
        w = camera_directions(attitude, t, unit)
        x, y = cam.project(w)
    seen = cam.on_detector(x, y, 5.0)
    n = int(seen.sum())
    true_directions = w[seen]
    x = x[seen] + rng.normal(0.0, sigma_px, n)
    y = y[seen] + rng.normal(0.0, sigma_px, n)
    row_start = t0 + np.rint(y * line_ns).astype(np.int64)  # the measured (fractional) row
    record = {"frame": k, "t0_ns": t0, "x": x.tolist(), "y": y.tolist(),
              "t_ns": (row_start + half_exposure_ns).tolist(), "row_time_ns": row_start.tolist(),
              "flux": (1e5 * 10 ** (-0.4 * mag[seen])).tolist(), "sigma_px": [sigma_px] * n}
    return record, true_directions


def write_centroid_recording(path: Path, frames: int, sigma_px: float, seed: int, edit=None) -> tuple[np.ndarray, float]:
    """The rolling-shutter recording; returns the attitude floor per axis (arcsec) and the mean
    number of stars per frame. ``edit(record, rng)``: changes each centroid record before it is
    written (a detector defect, a noise other than the stated one)."""
    rng = np.random.default_rng(seed)
    cam = Camera(ROLLING)
    omega = np.radians([0.25, -0.15, 0.25])  # deg/s about camera x, y, z
    t_first = 2_000_000_000
    period = round(ROLLING_SHUTTER["frame_period_ms"] * 1e6)
    attitude = body_rate_motion(pointing_attitude(**POINTING), omega, t_first)
    stars = field_stars(attitude(t_first + frames * period // 2), cam)
    scenario = {"name": "outside writer", "level": "centroid",
                "sensor": {**ROLLING, "principal_point_px": [cam.cx, cam.cy]}, "shutter": ROLLING_SHUTTER,
                "catalog": CATALOG, "motion": {"initial_attitude": POINTING},
                "noise": {"centroid_sigma_px": sigma_px}, "frames": frames}
    directions = []
    with open(path, "wb") as f:
        w = start_log(f, "import", scenario)
        centroids = json_channel(w, "/camera/centroids", "rollingstar.Stars")
        truth = json_channel(w, "/truth/attitude", "rollingstar.AttitudeSamples")
        gyro = json_channel(w, "/gyro", "rollingstar.GyroSamples")
        for k in range(frames):
            t0 = t_first + k * period
            # truth over the frame, logged at its first sample (t0): it belongs to frame k
            add_json(w, truth, t0, truth_record(attitude, omega, list(range(t0, t0 + period, 5_000_000))))
            # gyro samples since the previous frame, logged at the last one (t0): frame k's
            add_json(w, gyro, t0, gyro_record(omega, list(range(t0 - period + GYRO_STEP_NS, t0 + 1, GYRO_STEP_NS)), rng))
            record, w_cam = centroid_frame(k, t0, attitude, stars, cam, rng, sigma_px)
            add_json(w, centroids, t0, edit(record, rng) if edit else record)
            directions.append((w_cam, np.full(len(w_cam), sigma_px / cam.f)))
        w.finish()
    return attitude_floor_arcsec(directions), float(np.mean([len(d) for d, _ in directions]))


CENTROID_FRAMES = 30


@pytest.fixture(scope="module")
def centroid_recording(tmp_path_factory) -> tuple[Path, np.ndarray, float]:
    """30 frames, 0.1 px centroid noise: (recording, attitude floor per axis in arcsec, stars per frame)."""
    recording = tmp_path_factory.mktemp("outside") / "outside_centroids.mcap"
    return (recording, *write_centroid_recording(recording, CENTROID_FRAMES, sigma_px=0.1, seed=3))


def test_outside_centroid_recording_solves_at_the_noise_floor(centroid_recording):
    """Single-frame solutions: the rate from the stars' row times, every star moved to mid-frame, QUEST."""
    recording, floor, stars = centroid_recording
    metrics = run_and_evaluate("ls_rate", recording)
    check_at_floor("centroid-level outside recording (ls_rate)", metrics, floor, CENTROID_FRAMES, stars)


def test_outside_centroid_recording_with_its_gyro_filters_at_the_noise_floor(centroid_recording):
    """The MEKF propagates with the writer's ``/gyro`` (rates about the camera axes) and updates
    with every star at its own row time, one estimate per star."""
    recording, floor, stars = centroid_recording
    metrics = run_and_evaluate("he2021b_mekf", recording)
    check_at_floor("centroid-level outside recording with /gyro (he2021b_mekf)", metrics, floor, CENTROID_FRAMES,
                   stars, single_frame=False)


# --- image level -----------------------------------------------------------------------------------

IMAGER = {"name": "outside imager", "width_px": 1024, "height_px": 1024, "focal_length_mm": 24.09,
          "pixel_size_um": 5.5, "principal_point_px": [530.0, 490.0],
          "shutter": {"mode": "global", "exposure_ms": 100.0, "line_delay_us": 0.0}, "bit_depth": 16}
PSF_SIGMA_PX = 1.2
BACKGROUND_E = 100.0  # per pixel and frame, gain 1 e-/ADU
READ_NOISE_E = 5.0
BIAS_ADU = 200.0


def pixel_gaussian(x0: float, y0: float, flux: float, sigma: float, half: int = 7):
    """A circular Gaussian integrated over each pixel; pixel ``(i, j)`` covers ``[i - 0.5, i + 0.5]``
    in x (pixel centres at integers): (rows slice, columns slice, values)."""
    cx, cy = int(round(x0)), int(round(y0))
    xs, ys = np.arange(cx - half, cx + half + 1), np.arange(cy - half, cy + half + 1)

    def edges(c, v):
        e = erf((np.append(v - 0.5, v[-1] + 0.5) - c) / (np.sqrt(2.0) * sigma))
        return np.diff(e) / 2.0
    return slice(ys[0], ys[-1] + 1), slice(xs[0], xs[-1] + 1), flux * np.outer(edges(y0, ys), edges(x0, xs))


def opencv_project(w_cv: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """The OpenCV pinhole: ``x = cx + f X / Z``, ``y = cy + f Y / Z`` (column, row)."""
    return cam.cx + cam.f * w_cv[:, 0] / w_cv[:, 2], cam.cy + cam.f * w_cv[:, 1] / w_cv[:, 2]


def render_frame(t0: int, attitude_cv, stars, cam: Camera, rng, substeps: int = 16):
    """A 16-bit frame exposed from ``t0`` for the exposure: each star smeared along its path (the
    exposure split into ``substeps``), photon and read noise; also each star's mid-exposure
    pixel, its flux and whether it is fully on the detector."""
    _, unit, mag = stars
    exposure_ns = round(IMAGER["shutter"]["exposure_ms"] * 1e6)
    flux = 4e4 * 10 ** (-0.2 * (mag - 4.0))  # e-: a compressed magnitude law keeps Hp 0-6 within 16 bits
    signal = np.full((IMAGER["height_px"], IMAGER["width_px"]), BACKGROUND_E)
    for s in range(substeps):
        t = t0 + (2 * s + 1) * exposure_ns // (2 * substeps)
        x, y = opencv_project(unit @ attitude_cv(t), cam)
        for xi, yi, fi in zip(x, y, flux):
            if 10 < xi < IMAGER["width_px"] - 11 and 10 < yi < IMAGER["height_px"] - 11:
                rows, cols, values = pixel_gaussian(xi, yi, fi / substeps, PSF_SIGMA_PX)
                signal[rows, cols] += values
    electrons = rng.poisson(signal) + rng.normal(0.0, READ_NOISE_E, signal.shape)
    image = np.clip(np.rint(electrons + BIAS_ADU), 0, 65535).astype(np.uint16)
    xm, ym = opencv_project(unit @ attitude_cv(t0 + exposure_ns // 2), cam)
    inside = (xm > 12) & (ym > 12) & (xm < IMAGER["width_px"] - 13) & (ym < IMAGER["height_px"] - 13)
    return image, xm, ym, flux, inside


def centroid_bound_px(flux: float, x0: float, y0: float) -> float:
    """Cramér–Rao bound (px) on one coordinate of a star's position from its pixels' Poisson and
    read noise: ``1 / sqrt(sum (d mu / d x)^2 / var)``."""
    h = 1e-4
    _, _, plus = pixel_gaussian(x0 + h, y0, flux, PSF_SIGMA_PX)
    _, _, minus = pixel_gaussian(x0 - h, y0, flux, PSF_SIGMA_PX)
    _, _, mu = pixel_gaussian(x0, y0, flux, PSF_SIGMA_PX)
    return float(1.0 / np.sqrt(np.sum(((plus - minus) / (2 * h)) ** 2 / (mu + BACKGROUND_E + READ_NOISE_E**2))))


def write_truth_csv(path: Path, attitude_cv, omega_cv: np.ndarray, times_ns: list[int]) -> None:
    """The truth CSV of log-format.md from an OpenCV-frame attitude: ``q = q_opencv * (0, 0, 1, 0)``
    (scalar last) and body rates ``(-wx, -wy, wz)``, as conventions.md converts them."""
    q_cv = Rotation.from_matrix(np.array([attitude_cv(t) for t in times_ns]))
    q = (q_cv * Rotation.from_quat([0.0, 0.0, 1.0, 0.0])).as_quat()
    wx, wy, wz = -omega_cv[0], -omega_cv[1], omega_cv[2]
    rows = [f"{t},{a:.12f},{b:.12f},{c:.12f},{d:.12f},{wx:.9g},{wy:.9g},{wz:.9g}" for t, (a, b, c, d) in zip(times_ns, q)]
    path.write_text("t_ns,qx,qy,qz,qw,wx,wy,wz\n" + "\n".join(rows) + "\n")


def write_image_folder(folder: Path, meta: Path, frames: int, seed: int) -> tuple[np.ndarray, float]:
    """PNG frames in ``folder``, a truth CSV and a ``recording.yaml`` sidecar in ``meta``; returns
    the attitude floor per axis (arcsec) and the mean number of stars per frame.

    The motion is built in the OpenCV camera frame (+x towards increasing column, +y towards
    increasing row) and the stars rendered with the OpenCV pinhole; only the truth CSV is converted.
    """
    rng = np.random.default_rng(seed)
    cam = Camera(IMAGER)
    to_opencv = rot_z(np.pi)  # R_opencv = R Rz(180 deg)^-1, and Rz(180 deg)^-1 = Rz(180 deg)
    omega_cv = np.radians([-0.08, 0.12, 0.2])  # deg/s about the OpenCV camera axes
    t0s = [1_000_000_000 + k * 250_000_000 for k in range(frames)]
    attitude_cv = body_rate_motion(pointing_attitude(**POINTING) @ to_opencv, omega_cv, t0s[0])
    stars = field_stars(attitude_cv(t0s[frames // 2]) @ to_opencv, cam)
    floor_frames = []
    for k, t0 in enumerate(t0s):
        image, xm, ym, flux, inside = render_frame(t0, attitude_cv, stars, cam, rng)
        Image.fromarray(image).save(folder / f"frame_{k:03d}.png")
        sigma_px = [centroid_bound_px(fl, x, y) for fl, x, y in zip(flux[inside], xm[inside], ym[inside])]
        floor_frames.append((cam.direction(xm[inside], ym[inside]), np.array(sigma_px) / cam.f))
    write_truth_csv(meta / "truth.csv", attitude_cv, omega_cv, list(range(t0s[0] - 50_000_000, t0s[-1] + 300_000_000,
                                                                          10_000_000)))
    sidecar = {"camera": IMAGER, "files": "*.png", "timestamps": {"t0_ns": t0s}, "truth_csv": "truth.csv",
               "initial_attitude": POINTING}
    (meta / "recording.yaml").write_text(yaml.safe_dump(sidecar, sort_keys=False))
    return attitude_floor_arcsec(floor_frames), float(np.mean([len(w) for w, _ in floor_frames]))


def test_outside_image_folder_imports_and_solves_at_the_noise_floor(tmp_path):
    frames = 8
    folder, meta = tmp_path / "frames", tmp_path / "meta"
    folder.mkdir()
    meta.mkdir()
    floor, stars = write_image_folder(folder, meta, frames, seed=5)
    recording = tmp_path / "outside_images.mcap"
    cli("import", "images", folder, "--sidecar", meta / "recording.yaml", "-o", recording)
    metrics = run_and_evaluate("baseline", recording)
    check_at_floor("image-level outside recording (import images, baseline)", metrics, floor, frames, stars)

