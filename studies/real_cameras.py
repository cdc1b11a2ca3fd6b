"""Cameras the pipeline was not tuned on, end to end as a user runs them.

    rollingstar figures real-cameras [--quick] [--json] [--seed S]
    python -m rollingstar.studies.real_cameras --site /tmp/before/site [--quick] [--json]

Every set goes through the user's path: a folder of image files and a ``recording.yaml`` sidecar,
``rollingstar import images`` (:func:`rollingstar.logs.importers.import_images`, what the command
calls), ``rollingstar run configs/pipelines/real_images.yaml``, then the output log is read. With
``--site`` the two commands run instead as subprocesses of another installation of rollingstar
(``PYTHONPATH=<site> python -m rollingstar ...``, its own shipped ``real_images`` pipeline), with the
sidecar keys that installation does not know (``observation_time``, ``catalog``) left out: the
numbers of an earlier version on the same files.

Sets:

- ``tetra3``: the eight tetra3 images (``ROLLINGSTAR_REAL_DATA``/tetra3, sidecar
  ``configs/cameras/tetra3_recording.yaml``). No independent attitude exists for them (no
  astrometric solution is published; the mount angles in the file names are not calibrated): the
  table gives the residual of the identified stars instead, and the angle to the peer's pointing.
- ``creusot``: every PNG under ``ROLLINGSTAR_REAL_DATA``/creusot, one recording per folder, the camera
  from the folder's ``log.json`` (``focal_px_from_fov``, principal point at the centre); pointing
  error = angle between our image-centre direction and astrometry.net's pointing centre (log.json).
- rendered sets (:data:`RENDERED`), made with our image simulator in geometries the pipeline was not
  tuned on, written as image files with a sidecar and a truth CSV: a 50 deg lens with strong barrel
  distortion (8-bit), a 6 deg field rendered to Hp 9 (12-bit in 16-bit PNGs), a colour sensor (an
  RGGB mosaic demosaiced to an RGB PNG that the importer converts to luminance), JPEG at quality 75.
  Frames come in sessions: the camera is re-pointed between sessions (a random direction and roll),
  static within one. Pointing error = angle between our boresight and the truth's, the truth read
  from the output log (the importer carries the truth CSV into the recording, ``run`` into its output).

The peer: tetra3rs ``SolverDatabase.solve_from_centroids`` at its defaults (``match_radius``,
``match_threshold``, ``match_max_error``, ``pattern_checking_stars``, no field-error filter) except
its 5 s wall-clock timeout (off, so that the outcome does not depend on the machine; its default work
bound ``max_patterns_checked`` still ends a search), on the same ``cog`` centroids the pipeline's
first stage finds (its parameters read from the pipeline file), with the sidecar's nominal field
(``fov_estimate_deg``). Its database: tetra3rs' own star selection (``star_max_magnitude`` None) from
Hipparcos-2 to Hp 9 at the set's epoch, single scale at the nominal field (tetra3rs' default when no
``min_fov_deg`` is given). Its pointing is the direction of the image centre it reports (ra, dec).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from PIL import Image
from scipy.ndimage import convolve
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from rollingstar.config import CONFIGS, read_yaml
from rollingstar.errors import UserError
from rollingstar.estimators.data import FrameData, SensorContext
from rollingstar.estimators.identifiers.camera_fit import RadialCamera
from rollingstar.estimators.identifiers.tetra3_database import solver_database
from rollingstar.logs.importers import import_images
from rollingstar.logs.importers.common import WarningLog
from rollingstar.logs.importers.corr import focal_px_from_fov, read_log_json
from rollingstar.logs.reader import LogReader
from rollingstar.logs.records import stars_to_arrays
from rollingstar.logs.replay import image_from_raw
from rollingstar.logs.topics import TOPIC_EST_ATTITUDE, TOPIC_EST_FRAME, TOPIC_EST_STARS, TOPIC_IMAGE
from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.registry import get_plugin_class
from rollingstar.pipelines.runner import run_pipeline
from rollingstar.pipelines.simulate import build_simulator
from rollingstar.progress import progress_bar
from rollingstar.sensors.build import initial_attitude
from rollingstar.sensors.catalog import StarCatalog
from rollingstar.sensors.conventions import RAD_TO_ARCSEC, quat_from_fields, radec_to_unit
from rollingstar.sensors.scenario import (
    AttitudeConfig,
    CatalogConfig,
    EffectConfig,
    ImageConfig,
    MotionConfig,
    ScenarioConfig,
    SensorConfig,
    ShutterConfig,
)
from rollingstar.studies.real_data import CREUSOT_EPOCH, TETRA3_EPOCH

ROOT = Path(__file__).resolve().parents[1]
PIPELINE = CONFIGS / "pipelines" / "real_images.yaml"
TETRA3_SIDECAR = CONFIGS / "cameras" / "tetra3_recording.yaml"
RENDER_EPOCH = 2025.0
RENDER_OBSERVATION = "2024-12-31T18:00:00Z"  # Julian epoch 2025.0
PEER_CATALOG_HP = 9.0
LEGACY_KEYS = ("observation_time", "catalog")
SESSION_GAP_NS = 600 * 10**9
FRAME_SPACING_NS = 10**9


@dataclass(frozen=True)
class RenderedSpec:
    """A camera rendered with our simulator: geometry, photometry and the file format written.

    ``focal_error`` is the relative error of the focal length the sidecar states (a published
    value, not a calibration); ``output``: ``png16`` (the ADC's counts in 16-bit PNGs), ``png8``,
    ``rgb`` (RGGB mosaic, bilinear demosaic, 8-bit RGB PNG), ``jpeg`` (8-bit greyscale, quality 75).
    """

    name: str
    description: str
    width: int
    height: int
    hfov_deg: float
    pixel_um: float
    render_hp: float  # faintest star rendered
    limit_hp: float  # magnitude whose peak pixel is 5 sigma of the background noise (sets the photometry)
    exposure_ms: float
    image: dict
    output: str
    k1: float = 0.0
    focal_error: float = 0.005

    @property
    def focal_px(self) -> float:
        return float((self.width / 2.0) / np.tan(np.radians(self.hfov_deg) / 2.0))

    def image_config(self) -> ImageConfig:
        """The detector of ``image`` with the star signal that puts a ``limit_hp`` star's peak pixel at
        5 sigma of the background noise: ``sigma_e = sqrt((background + dark) T + read^2)``, peak
        fraction of a centred Gaussian PSF ``1 / (2 pi s^2)``."""
        base = ImageConfig(**self.image)
        t = self.exposure_ms * 1e-3
        sigma_e = np.sqrt((base.background_e_per_px_s + base.dark_e_per_px_s) * t + base.read_noise_e**2)
        peak = 1.0 / (2.0 * np.pi * base.psf_sigma_px**2)
        photons = 5.0 * sigma_e / (peak * t * 10.0 ** (-0.4 * self.limit_hp))
        return base.model_copy(update={"photons_per_s_mag0": float(photons)})


RENDERED = (
    RenderedSpec("wide_barrel_50deg", "1920x1080, 50 deg, k1 -0.2 barrel, 8-bit PNG", 1920, 1080, 50.0, 1.55, 7.0, 6.0,
                 200.0, dict(psf_sigma_px=1.2, background_e_per_px_s=2000.0, read_noise_e=3.0, gain_e_per_adu=8.0,
                             bias_adu=8.0, bit_depth=8, full_well_e=10000.0), "png8", k1=-0.2),
    RenderedSpec("narrow_faint_6deg", "1280x1024, 6 deg, stars to Hp 9, 12-bit in 16-bit PNG", 1280, 1024, 6.0, 5.3, 9.0,
                 8.5, 500.0, dict(psf_sigma_px=1.3, background_e_per_px_s=400.0, read_noise_e=4.0, gain_e_per_adu=8.0,
                                  bias_adu=100.0, bit_depth=12, full_well_e=30000.0), "png16"),
    RenderedSpec("colour_30deg", "1600x1200, 30 deg, k1 -0.05, RGGB demosaiced to RGB PNG", 1600, 1200, 30.0, 3.45, 7.5,
                 6.5, 300.0, dict(psf_sigma_px=1.1, background_e_per_px_s=1500.0, read_noise_e=3.0, gain_e_per_adu=0.8,
                                  bias_adu=64.0, bit_depth=12, full_well_e=15000.0), "rgb", k1=-0.05),
    RenderedSpec("jpeg_16deg", "1456x1088, 16 deg, 8-bit JPEG quality 75", 1456, 1088, 16.0, 3.45, 8.0, 7.0,
                 300.0, dict(psf_sigma_px=1.3, background_e_per_px_s=1500.0, read_noise_e=3.0, gain_e_per_adu=8.0,
                             bias_adu=10.0, bit_depth=8, full_well_e=10000.0), "jpeg"),
)
BAYER_RESPONSE = {"R": 0.55, "G": 1.0, "B": 0.75}  # relative channel response to a star's light
JPEG_QUALITY = 75
BRIGHT_MARGIN_MAG = 0.5
WRONG_ARCSEC = 3600.0
"""A valid attitude whose pointing is off its reference by more than 1 deg is a misidentification, not a
lens-model or reference error (those stay under 400 arcsec on every set here)."""


@dataclass
class CameraSet:
    """One recording to import: image folder, sidecar, and what its frames are compared with."""

    group: str  # the set's name in the table
    name: str  # the recording's name (a folder for creusot)
    folder: Path
    sidecar: Path
    width: int
    height: int
    nominal_focal_px: float
    epoch_year: float
    centre_radec_deg: tuple[float, float] | None = None  # astrometry.net's centre (creusot)
    has_truth: bool = False
    true_camera: RadialCamera | None = None  # the camera the frames were rendered with
    limit_hp: float | None = None  # rendered: magnitude at 5 sigma peak (RenderedSpec.limit_hp)
    note: str = ""


@dataclass
class Runner:
    """The user's two commands, in this process (``site`` None) or as ``python -m rollingstar`` of another
    installation (``PYTHONPATH=site``, run from ``cwd`` outside the repository)."""

    site: Path | None = None
    python: str = sys.executable
    cwd: Path = field(default_factory=lambda: Path(tempfile.gettempdir()))

    @property
    def legacy(self) -> bool:
        return self.site is not None

    def pipeline_file(self) -> Path:
        return PIPELINE if self.site is None else Path(self.site) / "rollingstar" / "configs" / "pipelines" / "real_images.yaml"

    def import_and_run(self, cs: CameraSet, rec: Path, out: Path) -> None:
        if self.site is None:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                import_images(cs.folder, rec, sidecar=cs.sidecar)
                run_pipeline(rec, load_pipeline(PIPELINE), out, show_progress=False)
            return
        env = {**os.environ, "PYTHONPATH": str(self.site)}
        for args in (["import", "images", str(cs.folder), "--sidecar", str(cs.sidecar), "-o", str(rec), "-q"],
                     ["run", "real_images", str(rec), "-o", str(out), "-q"]):
            done = subprocess.run([self.python, "-m", "rollingstar", *args], cwd=self.cwd, env=env,
                                  capture_output=True, text=True)
            if done.returncode != 0:
                raise UserError(f"{' '.join(args[:2])} of {cs.name} failed ({done.returncode}): {done.stderr.strip()[-400:]}")


def real_data_dir() -> Path:
    """``ROLLINGSTAR_REAL_DATA``, default ``../shared/data/real`` relative to the repository."""
    return Path(os.environ.get("ROLLINGSTAR_REAL_DATA", ROOT.parent / "shared" / "data" / "real"))


def write_sidecar(path: Path, data: dict, legacy: bool) -> Path:
    """``data`` as a recording.yaml at ``path``; ``legacy`` drops the keys older importers reject."""
    if legacy:
        data = {k: v for k, v in data.items() if k not in LEGACY_KEYS}
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


# ------------------------------------------------------------------------------------------ real sets
def tetra3_set(base: Path, work: Path, legacy: bool) -> CameraSet:
    """The tetra3 folder with the shipped sidecar (a copy without the new keys for ``legacy``)."""
    data = read_yaml(TETRA3_SIDECAR)
    data["camera_file"] = str((TETRA3_SIDECAR.parent / data["camera_file"]).resolve())
    sidecar = TETRA3_SIDECAR if not legacy else write_sidecar(work / "tetra3_recording.yaml", data, legacy)
    cam = read_yaml(Path(data["camera_file"]))
    focal = cam["focal_length_mm"] * 1e3 / cam["pixel_size_um"]
    return CameraSet("tetra3", "tetra3", base / "tetra3", sidecar, cam["width_px"], cam["height_px"], focal, TETRA3_EPOCH)


def creusot_sets(base: Path, work: Path, legacy: bool) -> list[CameraSet]:
    """One recording per creusot folder holding PNGs, its camera from the folder's log.json."""
    root = base / "creusot"
    sets = []
    for folder in sorted({p.parent for p in root.rglob("*.png")}):
        found = sorted(folder.glob("*.json"))
        if len(found) != 1:
            raise UserError(f"{folder}: expected one log.json beside the PNGs, found {len(found)}")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            meta = read_log_json(found[0], WarningLog())
        w, h = meta.image_size.x, meta.image_size.y
        focal = focal_px_from_fov(meta.fov_deg, w, h)
        name = str(folder.relative_to(root))
        data = {"camera": {"name": name, "width_px": w, "height_px": h, "focal_length_mm": float(focal) * 1e-3,
                           "pixel_size_um": 1.0}, "files": "*.png", "timestamps": {"frame_rate_hz": 1.0},
                "catalog": {"epoch_year": CREUSOT_EPOCH}}
        sidecar = write_sidecar(work / (name.replace("/", "__") + ".yaml"), data, legacy)
        sets.append(CameraSet("creusot", name, folder, sidecar, w, h, focal, CREUSOT_EPOCH,
                              (meta.center.ra_degrees, meta.center.dec_degrees)))
    return sets


# -------------------------------------------------------------------------------------- rendered sets
def session_scenario(spec: RenderedSpec, attitude: AttitudeConfig, frames: int, seed: int) -> ScenarioConfig:
    """A static global-shutter image-level scenario of ``spec`` pointed at ``attitude``."""
    effects = [EffectConfig(kind="radial_distortion", params={"k1": spec.k1})] if spec.k1 else []
    return ScenarioConfig(
        name=spec.name, level="image",
        sensor=SensorConfig(focal_length_mm=spec.focal_px * spec.pixel_um * 1e-3, pixel_size_um=spec.pixel_um,
                            width_px=spec.width, height_px=spec.height),
        shutter=ShutterConfig(mode="global", exposure_ms=spec.exposure_ms, frame_period_ms=FRAME_SPACING_NS * 1e-6),
        catalog=CatalogConfig(magnitude_limit=spec.render_hp, epoch_year=RENDER_EPOCH),
        motion=MotionConfig(initial_attitude=attitude), image=spec.image_config(), effects=effects,
        frames=frames, seed=seed)


def random_attitude(rng: np.random.Generator) -> AttitudeConfig:
    """A direction uniform on the sphere and a uniform roll."""
    v = rng.normal(size=3)
    v /= np.linalg.norm(v)
    return AttitudeConfig(ra_deg=float(np.degrees(np.arctan2(v[1], v[0])) % 360.0),
                          dec_deg=float(np.degrees(np.arcsin(v[2]))), roll_deg=float(rng.uniform(0.0, 360.0)))


def demosaic_rgb(image: np.ndarray) -> np.ndarray:
    """An RGGB mosaic of ``image`` (each pixel keeps its colour's share, :data:`BAYER_RESPONSE`),
    demosaiced bilinearly: (H, W, 3) float."""
    h, w = image.shape
    masks = {c: np.zeros((h, w), dtype=bool) for c in "RGB"}
    masks["R"][0::2, 0::2] = True
    masks["G"][0::2, 1::2] = True
    masks["G"][1::2, 0::2] = True
    masks["B"][1::2, 1::2] = True
    k_rb = np.array([[0.25, 0.5, 0.25], [0.5, 1.0, 0.5], [0.25, 0.5, 0.25]])
    k_g = np.array([[0.0, 0.25, 0.0], [0.25, 1.0, 0.25], [0.0, 0.25, 0.0]])
    img = image.astype(float)
    return np.stack([convolve(np.where(masks[c], img * BAYER_RESPONSE[c], 0.0), k_g if c == "G" else k_rb,
                              mode="mirror") for c in "RGB"], axis=-1)


#: zlib level of the PNGs written (lossless at any level; 1 writes 5-10x faster than the default 6).
PNG_COMPRESS_LEVEL = 1


def save_image(spec: RenderedSpec, image: np.ndarray, path: Path) -> Path:
    """Write one rendered frame in ``spec.output``'s format; returns the file written."""
    bits = spec.image["bit_depth"]
    if spec.output == "png16":
        Image.fromarray(image.astype(np.uint16)).save(path.with_suffix(".png"), compress_level=PNG_COMPRESS_LEVEL)
        return path.with_suffix(".png")
    if spec.output == "rgb":
        rgb = np.clip(np.rint(demosaic_rgb(image) * (255.0 / (2**bits - 1))), 0, 255).astype(np.uint8)
        Image.fromarray(rgb, mode="RGB").save(path.with_suffix(".png"), compress_level=PNG_COMPRESS_LEVEL)
        return path.with_suffix(".png")
    grey = Image.fromarray(np.clip(image, 0, 255).astype(np.uint8), mode="L")
    if spec.output == "jpeg":
        grey.save(path.with_suffix(".jpg"), quality=JPEG_QUALITY)
        return path.with_suffix(".jpg")
    grey.save(path.with_suffix(".png"), compress_level=PNG_COMPRESS_LEVEL)
    return path.with_suffix(".png")


def render_set(spec: RenderedSpec, folder: Path, sessions: int, frames_per_session: int, seed: int,
               legacy: bool) -> CameraSet:
    """Render ``sessions`` x ``frames_per_session`` frames of ``spec`` into ``folder`` with a sidecar and a truth CSV."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([seed, sum(map(ord, spec.name))])
    t0, truth_rows, k = [], [], 0
    for s in range(sessions):
        cfg = session_scenario(spec, random_attitude(rng), frames_per_session, seed * 1000 + s)
        q = initial_attitude(cfg).as_quat()
        for frame in build_simulator(cfg).frames(frames_per_session):
            t = s * SESSION_GAP_NS + frame.index * FRAME_SPACING_NS
            save_image(spec, frame.image, folder / f"frame_{k:03d}")
            t0.append(t)
            truth_rows += [[t, *q], [t + int(spec.exposure_ms * 1e6), *q]]
            k += 1
    with open(folder / "truth.csv", "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(["t_ns", "qx", "qy", "qz", "qw"])
        out.writerows([[int(r[0]), *(f"{v:.15f}" for v in r[1:])] for r in truth_rows])
    published = spec.focal_px * (1.0 + spec.focal_error)
    camera = {"name": spec.name, "description": spec.description, "width_px": spec.width, "height_px": spec.height,
              "focal_length_mm": round(float(published * spec.pixel_um * 1e-3), 4), "pixel_size_um": spec.pixel_um,
              "shutter": {"mode": "global", "exposure_ms": spec.exposure_ms}}
    if spec.output == "png16":
        camera["bit_depth"] = spec.image["bit_depth"]
    data = {"camera": camera, "timestamps": {"t0_ns": t0}, "truth_csv": "truth.csv",
            "observation_time": RENDER_OBSERVATION}
    sidecar = write_sidecar(folder / "recording.yaml", data, legacy)
    true_camera = RadialCamera(spec.focal_px, (spec.width - 1) / 2.0, (spec.height - 1) / 2.0, spec.k1)
    return CameraSet(spec.name, spec.name, folder, sidecar, spec.width, spec.height, published, RENDER_EPOCH,
                     has_truth=True, true_camera=true_camera, limit_hp=spec.limit_hp, note=spec.description)


# ------------------------------------------------------------------------------------------ evaluation
def read_output(out: Path) -> list[dict]:
    """Per frame of a run's output: index, t0, flags, detections, our attitude (valid or None), its
    time, and the identified stars (pixel positions and catalogue directions)."""
    reader = LogReader(out)
    frames: dict[int, dict] = {}
    for m in reader.messages([TOPIC_EST_FRAME, TOPIC_EST_ATTITUDE, TOPIC_EST_STARS]):
        d = m.data
        row = frames.setdefault(int(d["frame"]), {"frame": int(d["frame"]), "attitude": None, "t_ns": None})
        if m.topic == TOPIC_EST_FRAME:
            row.update(t0_ns=int(d["t0_ns"]), flags=list(d["flags"]), n_detected=int(d["n_detected"]),
                       n_identified=int(d["n_identified"]), camera=d.get("camera"))
        elif m.topic == TOPIC_EST_ATTITUDE and d.get("valid") and d.get("q") is not None:
            row.update(attitude=Rotation.from_quat(quat_from_fields(d["q"])), t_ns=int(d["t_ns"]))
        elif m.topic == TOPIC_EST_STARS:
            a = stars_to_arrays(m.record)
            ok = np.asarray(a["catalog_id"]) >= 0
            row["stars"] = (np.asarray(a["x"])[ok], np.asarray(a["y"])[ok], np.asarray(a["ref_icrs"])[ok])
    truth = reader.truth_attitude()
    for row in frames.values():
        row["truth"] = _truth_at(truth, row["t_ns"] if row["t_ns"] is not None else row.get("t0_ns"))
    return [frames[k] for k in sorted(frames)]


def _truth_at(truth: dict, t_ns: int | None) -> Rotation | None:
    """The truth attitude of the last sample at or before ``t_ns`` (static frames), None without truth."""
    if t_ns is None or truth["t_ns"].size == 0:
        return None
    i = int(np.searchsorted(truth["t_ns"], t_ns, side="right")) - 1
    return Rotation.from_quat(truth["q_xyzw"][max(i, 0)])


def angle_arcsec(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two unit vectors, arcsec."""
    return float(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0)) * RAD_TO_ARCSEC)


def residual_rms_px(stars, attitude: Rotation, width: int, height: int, focal_px: float, fit_k1: bool) -> float:
    """RMS (px) of the identified stars against ``attitude``: the catalogue directions projected through a
    pinhole at the detector centre whose focal length (and k1 when ``fit_k1``) is least-squares fitted with the
    attitude held (x = cx - f w_x / w_z, he2021b eq 2; radial k1 r^2 as sensors/effects/radial_distortion.py)."""
    x, y, ref = stars
    if x.size < 3:
        return float("nan")
    w = attitude.inv().apply(ref)
    u, v = -w[:, 0] / w[:, 2], -w[:, 1] / w[:, 2]
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0

    def resid(p):
        s = 1.0 + (p[1] if fit_k1 else 0.0) * (u * u + v * v)
        return np.concatenate([cx + p[0] * u * s - x, cy + p[0] * v * s - y])

    sol = least_squares(resid, [focal_px, 0.0])
    r = sol.fun.reshape(2, -1)
    return float(np.sqrt(np.mean(np.sum(r**2, axis=0))))


def cog_stage(pipeline_file: Path):
    """The centroider stage (first stage) of the pipeline file, for the peer's centroids."""
    stage = load_pipeline(pipeline_file).stages[0]
    return get_plugin_class(stage.kind)(**stage.params)


def peer_solutions(cs: CameraSet, rec: Path, pipeline_file: Path) -> list[dict]:
    """tetra3rs at its defaults (module docstring) on the pipeline's centroids of every frame of ``rec``."""
    reader = LogReader(rec)
    context = SensorContext.from_scenario(reader.scenario())
    cog = cog_stage(pipeline_file)
    cog.setup(context)
    fov = float(np.degrees(2.0 * np.arctan(cs.width / 2.0 / cs.nominal_focal_px)))
    db = solver_database(StarCatalog.from_hipparcos(cs.epoch_year, PEER_CATALOG_HP), fov, fov)
    out = []
    for k, m in enumerate(reader.messages(TOPIC_IMAGE)):
        stars = cog.process(FrameData(index=k, t0_ns=m.log_time_ns, image=image_from_raw(m))).stars
        order = np.argsort(-np.nan_to_num(stars.flux), kind="stable")
        cents = np.column_stack([stars.x[order] - (cs.width - 1) / 2.0, stars.y[order] - (cs.height - 1) / 2.0,
                                 np.nan_to_num(stars.flux[order])])
        res = db.solve_from_centroids(cents, fov_estimate_deg=fov, image_width=cs.width, image_height=cs.height,
                                      solve_timeout_ms=None) if len(cents) >= 4 else None
        ok = bool(res)
        out.append({"solved": ok, "centre": radec_to_unit(np.radians(res.ra_deg), np.radians(res.dec_deg)) if ok else None,
                    "matches": int(res.num_matches) if ok else 0, "detections": int(stars.n)})
    return out


def centre_direction(row: dict, width: int, height: int) -> np.ndarray:
    """Camera-frame direction of the image centre pixel: through the camera the run fitted on the frame
    (its status record's ``camera``), else the boresight (the declared principal point is the centre)."""
    cam = row.get("camera")
    if not cam:
        return np.array([0.0, 0.0, 1.0])
    model = RadialCamera(**{k: float(cam[k]) for k in ("focal_px", "cx", "cy", "k1", "k2")})
    return model.unproject(np.array([(width - 1) / 2.0]), np.array([(height - 1) / 2.0]))[0]


def centroid_error_px(cs: CameraSet, row: dict) -> float | None:
    """RMS (px) of the identified detections against their true positions (rendered sets: the catalogue
    direction through the true attitude and the camera rendered with), None without a truth."""
    stars = row.get("stars")
    if cs.true_camera is None or row.get("truth") is None or stars is None or stars[0].size == 0:
        return None
    x, y, _ = cs.true_camera.project(row["truth"].inv().apply(stars[2]))
    return float(np.sqrt(np.mean((x - stars[0]) ** 2 + (y - stars[1]) ** 2)))


def bright_stars_in_field(cs: CameraSet, row: dict, margin_mag: float = BRIGHT_MARGIN_MAG) -> int | None:
    """Rendered sets: catalogue stars on the detector at the true attitude at least ``margin_mag`` brighter
    than the 5-sigma limit (peak pixel >= 5 x 10^(0.4 margin) sigma), None without a truth."""
    if cs.true_camera is None or row.get("truth") is None:
        return None
    cat = StarCatalog.from_hipparcos(cs.epoch_year, cs.limit_hp - margin_mag)
    idx = np.asarray(cat.cone(row["truth"].apply([0.0, 0.0, 1.0]), np.radians(90.0)), dtype=np.intp)
    x, y, front = cs.true_camera.project(row["truth"].inv().apply(cat.unit_icrs[idx]))
    inside = front & (x >= 0) & (x <= cs.width - 1) & (y >= 0) & (y <= cs.height - 1)
    return int(np.count_nonzero(inside))


def reference_direction(cs: CameraSet, row: dict) -> np.ndarray | None:
    """The independent direction of the image centre: the truth's boresight, astrometry.net's centre, or None."""
    if cs.centre_radec_deg is not None:
        return radec_to_unit(*np.radians(cs.centre_radec_deg))
    if row.get("truth") is not None:
        return row["truth"].apply([0.0, 0.0, 1.0])
    return None


def frame_rows(cs: CameraSet, ours: list[dict], peer: list[dict]) -> list[dict]:
    """One row per frame: ours (valid, pointing error, residual) and the peer's (solved, pointing error)."""
    wide = np.degrees(2.0 * np.arctan(cs.width / 2.0 / cs.nominal_focal_px)) > 20.0
    rows = []
    for row, p in zip(ours, peer, strict=True):
        ref = reference_direction(cs, row)
        att = row["attitude"]
        ours_dir = None if att is None else att.apply(centre_direction(row, cs.width, cs.height))
        r = {"set": cs.group, "recording": cs.name, "frame": row["frame"], "flags": row.get("flags", []),
             "detected": row.get("n_detected", 0), "identified": row.get("n_identified", 0),
             "valid": att is not None, "peer_solved": p["solved"], "peer_matches": p["matches"],
             "pointing_arcsec": None, "peer_pointing_arcsec": None, "ours_vs_peer_arcsec": None, "residual_px": None,
             "centroid_error_px": None, "ifov_arcsec": float(RAD_TO_ARCSEC / cs.nominal_focal_px),
             "bright_in_field": bright_stars_in_field(cs, row)}
        if att is not None:
            r["residual_px"] = residual_rms_px(row.get("stars", (np.zeros(0),) * 3), att, cs.width, cs.height,
                                               cs.nominal_focal_px, wide)
            if ref is not None:
                r["pointing_arcsec"] = angle_arcsec(ours_dir, ref)
            r["centroid_error_px"] = centroid_error_px(cs, row)
        if p["solved"]:
            if ref is not None:
                r["peer_pointing_arcsec"] = angle_arcsec(p["centre"], ref)
            if ours_dir is not None:
                r["ours_vs_peer_arcsec"] = angle_arcsec(p["centre"], ours_dir)
        rows.append(r)
    return rows


def _stats(values) -> dict:
    v = np.array([x for x in values if x is not None], dtype=float)
    return {"median": float(np.median(v)) if v.size else None, "max": float(v.max()) if v.size else None}


def summarise(name: str, rows: list[dict], reference: str) -> dict:
    """Per set: frames, identified fraction, pointing error median/max, the peer's, the frames it solves we do not."""
    n = len(rows)
    valid = sum(r["valid"] for r in rows)
    peer = sum(r["peer_solved"] for r in rows)
    missed = [f"{r['recording']}#{r['frame']}" for r in rows if r["peer_solved"] and not r["valid"]]
    wrong = sum(r["pointing_arcsec"] is not None and r["pointing_arcsec"] > WRONG_ARCSEC for r in rows)
    return {"set": name, "frames": n, "identified": valid, "identified_fraction": valid / n if n else None, "wrong": wrong,
            "reference": reference, "pointing_arcsec": _stats(r["pointing_arcsec"] for r in rows),
            "residual_px": _stats(r["residual_px"] for r in rows),
            "peer_solved": peer, "peer_pointing_arcsec": _stats(r["peer_pointing_arcsec"] for r in rows),
            "ours_vs_peer_arcsec": _stats(r["ours_vs_peer_arcsec"] for r in rows),
            "peer_solved_we_missed": missed}


REFERENCES = {"tetra3": "none independent (residual RMS and agreement with the peer instead)",
              "creusot": "astrometry.net pointing centre (log.json)"}


def evaluate_set(cs: CameraSet, runner: Runner, work: Path) -> list[dict]:
    """Import and run ``cs`` as a user does, then compare the output's frames with the reference and the peer."""
    stem = cs.name.replace("/", "__")
    rec, out = work / f"{stem}.mcap", work / f"{stem}.out.mcap"
    runner.import_and_run(cs, rec, out)
    return frame_rows(cs, read_output(out), peer_solutions(cs, rec, runner.pipeline_file()))


# ----------------------------------------------------------------------------------------------- run
SESSIONS = {False: (3, 4), True: (2, 2)}  # (sessions, frames per session): full, quick


def prepare_sets(work: Path, quick: bool, seed: int, legacy: bool, names=None,
                 base: Path | None = None) -> tuple[list[CameraSet], dict]:
    """The sets to run (``names`` None: all) and the reasons of those skipped."""
    base = real_data_dir() if base is None else Path(base)
    sets, skipped = [], {}
    for group, make in (("tetra3", lambda: [tetra3_set(base, work, legacy)]),
                        ("creusot", lambda: creusot_sets(base, work, legacy))):
        if names is not None and group not in names:
            continue
        if not (base / group).is_dir():
            skipped[group] = f"real data not found at {base / group} (set ROLLINGSTAR_REAL_DATA)"
            continue
        sets += make()
    sessions, per = SESSIONS[quick]
    for spec in RENDERED:
        if names is None or spec.name in names:
            sets.append(render_set(spec, work / spec.name, sessions, per, seed, legacy))
    return sets, skipped


def run_real_cameras(quick: bool = False, seed: int = 1, site: str | Path | None = None, names=None,
                     base: Path | None = None, show_progress: bool = False) -> dict:
    """Every set end to end (module docstring): per-set summary and per-frame rows.

    ``site``: run the user's commands from that installation (``PYTHONPATH``) instead of this one.
    ``names``: only these sets (``tetra3``, ``creusot``, the names in :data:`RENDERED`).
    """
    runner = Runner(site=None if site is None else Path(site))
    with tempfile.TemporaryDirectory(prefix="rollingstar_real_cameras_") as tmp:
        work = Path(tmp)
        sets, skipped = prepare_sets(work, quick, seed, runner.legacy, names, base)
        rows: list[dict] = []
        with progress_bar("real cameras", len(sets), show_progress) as advance:
            for cs in sets:
                rows += evaluate_set(cs, runner, work)
                advance()
    groups = list(dict.fromkeys(cs.group for cs in sets))
    summary = [summarise(g, [r for r in rows if r["set"] == g], REFERENCES.get(g, "truth (rendered)"))
               for g in groups]
    return {"quick": quick, "seed": seed, "site": None if site is None else str(site),
            "pipeline": str(runner.pipeline_file()), "sets": summary, "skipped": skipped, "frames": rows}


def _fmt(stats: dict, key: str = "median") -> str:
    v = stats.get(key)
    return "-" if v is None else f"{v:.1f}"


def real_cameras_markdown(result: dict, command: str) -> str:
    """The per-set table of :func:`run_real_cameras`."""
    lines = [f"Measured by `{command}`" + (f" (installation: {result['site']})" if result["site"] else "") + ".", "",
             "| set | frames | identified (wrong: > 1 deg off) | pointing err median / max (arcsec) "
             "| residual RMS median / max (px) "
             "| peer solved | peer pointing median / max (arcsec) | ours - peer median / max (arcsec) "
             "| peer-solved frames we miss | reference |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for s in result["sets"]:
        lines.append(f"| {s['set']} | {s['frames']} | {s['identified']} ({s['identified_fraction']:.0%}; {s['wrong']}) "
                     f"| {_fmt(s['pointing_arcsec'])} / {_fmt(s['pointing_arcsec'], 'max')} "
                     f"| {_fmt(s['residual_px'])} / {_fmt(s['residual_px'], 'max')} | {s['peer_solved']} "
                     f"| {_fmt(s['peer_pointing_arcsec'])} / {_fmt(s['peer_pointing_arcsec'], 'max')} "
                     f"| {_fmt(s['ours_vs_peer_arcsec'])} / {_fmt(s['ours_vs_peer_arcsec'], 'max')} "
                     f"| {', '.join(s['peer_solved_we_missed']) or 'none'} | {s['reference']} |")
    lines += [f"- {name}: skipped: {why}" for name, why in result["skipped"].items()]
    return "\n".join(lines)


def real_cameras_figures(quick: bool = False, as_json: bool = False, seed: int = 1, site: str | Path | None = None,
                         names=None) -> dict:
    """``rollingstar figures real-cameras [--quick] [--json]``: the table (or the JSON) on stdout."""
    command = "rollingstar figures real-cameras" + (" --quick" if quick else "") + f" --seed {seed}"
    result = run_real_cameras(quick=quick, seed=seed, site=site, names=names, show_progress=not as_json)
    if as_json:
        print(json.dumps(result, indent=1, default=str))
    else:
        print(real_cameras_markdown(result, command))
    return result


def main(argv=None) -> None:
    """``python -m rollingstar.studies.real_cameras [--site DIR] [--quick] [--json] [--seed S] [--set NAME ...]``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--site", help="run `import images` and `run` from this installation (PYTHONPATH)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--set", action="append", dest="names", help="only this set (repeatable)")
    args = ap.parse_args(argv)
    real_cameras_figures(args.quick, args.json, args.seed, args.site, args.names)


if __name__ == "__main__":
    main()
