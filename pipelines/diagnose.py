"""``rollingstar diagnose``: locate a simulation/recording mismatch, name it, model it, show the fit improve.

The command around the diagnosis algorithm (:mod:`rollingstar.estimators.diagnosis.algorithm`; see
docs/diagnosis.md for the method). Here: load the scenario (``--sim``, or the one the recording
declares) and the pipeline; run the pipeline on the recording (identified stars, a first attitude
per frame; lost in space when the recording declares no attitude or tracking loses lock); flatten its output
into :class:`~rollingstar.estimators.diagnosis.observations.Observations`; read the recording's gyro
samples. The algorithm then locates, names, models and verifies; this module writes what it found:
the JSON object (``--json``), the report directory (``index.html``, PNGs, ``result.json``,
``scenario_updated.yaml``) and the console summary.
"""
from __future__ import annotations

import math
import tempfile
import warnings
from pathlib import Path

import numpy as np
from rich.table import Table
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from rollingstar.config import parse_yaml, to_yaml, validate
from rollingstar.errors import UserError
from rollingstar.estimators.diagnosis import algorithm
from rollingstar.estimators.diagnosis.algorithm import Diagnosis
from rollingstar.estimators.diagnosis.gyro_channel import GyroData
from rollingstar.estimators.diagnosis.inputs import DiagnoseOptions
from rollingstar.estimators.diagnosis.locating import MIN_STARS_PER_FRAME
from rollingstar.estimators.diagnosis.observations import (
    Observations,
    frame_reference_times,
    rates_from_attitudes,
)
from rollingstar.estimators.diagnosis.report import write_report
from rollingstar.logs.errors import LogFormatError
from rollingstar.logs.reader import LogReader
from rollingstar.logs.records import stars_to_arrays
from rollingstar.logs.topics import TOPIC_EST_ATTITUDE, TOPIC_EST_STARS, TOPIC_TRUTH_ATTITUDE
from rollingstar.outputs import PartialOutputWarning, safe_output
from rollingstar.pipelines.config import PipelineConfig, load_pipeline
from rollingstar.pipelines.runner import run_pipeline
from rollingstar.pipelines.truth import TruthTrajectory
from rollingstar.progress import progress_bar
from rollingstar.sensors import build
from rollingstar.sensors.scenario import ScenarioConfig, load_scenario
from rollingstar.sensors.timing import DetectorTiming

__all__ = ["DiagnoseOptions", "diagnose_recording", "run_diagnose", "print_summary"]

MAX_REFERENCE_ARCSEC = 648_000.0  # 180 deg: a reference no better than this carries no attitude
# a reference further than this from the stars' attitude (median) is no reference of this camera
# (as `rollingstar evaluate` reads a truth that far from the estimates)
REFERENCE_MISMATCH_DEG = 1.0

# The identifier starts from the recording's declared initial attitude when it has one (tracking,
# verified against the false-match bound on every frame) and by a pattern search when it has none
# or tracking loses the stars. Tracking gate 30 px: the second frame is predicted without a rate
# (the tracker extrapolates from two estimates), and 2 deg/s over a 130 ms frame period moves
# stars ~20 px on a 4380 px focal length; the refine pass (2 px) then drops mismatches.
DEFAULT_PIPELINE_YAML = """
name: diagnose-default
stages:
  - {kind: cog, params: {threshold_sigma: 5.0}}
  - {kind: lost-in-space, params: {start_from_prior: true, tracking: {gate_px: 30.0}}}
  - {kind: none}
  - {kind: quest}
"""
DEFAULT_PIPELINE_SOURCE = "<diagnose default pipeline>"
SAME_STAR_RAD = 1e-3  # a catalogue id names the recorded star only if their directions agree this well


# ---------------------------------------------------------------------------------------- loading
def recording_scenario(recording: Path) -> ScenarioConfig:
    return LogReader(recording).scenario("pass --sim SCENARIO.yaml")


def default_pipeline() -> PipelineConfig:
    return validate(PipelineConfig, parse_yaml(DEFAULT_PIPELINE_YAML, DEFAULT_PIPELINE_SOURCE), DEFAULT_PIPELINE_SOURCE)


def run_and_read(recording: Path, pipeline: PipelineConfig, source: str, show_progress: bool):
    """Run ``pipeline`` on the recording; per frame the identified stars and the first valid attitude.

    Both are keyed by the frame's place in the run (0, 1, ... in time order), not by its ``frame``
    field, which a recording may repeat (a counter that wraps or restarts): an attitude belongs to
    the latest frame of its number that started before it (else the first of its number). Each star table keeps the recording's
    number as ``"frame"``."""
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        # the run's output is scratch, removed with its folder: a failed run keeps no partial worth naming
        warnings.simplefilter("ignore", PartialOutputWarning)
        out = Path(tmp) / "diagnose_run.mcap"
        summary = run_pipeline(recording, pipeline, out, pipeline_source=source, show_progress=show_progress)
        reader = LogReader(out)
        stars = {k: (m.record.t0_ns, {**stars_to_arrays(m.record), "t0_ns": m.record.t0_ns, "frame": m.record.frame})
                 for k, m in enumerate(reader.messages([TOPIC_EST_STARS]))}
        places: dict[int, list[tuple[int, int]]] = {}  # frame number -> (t0, place) in time order
        for k, (t0, s) in stars.items():
            places.setdefault(s["frame"], []).append((t0, k))
        att = {}
        for m in reader.messages([TOPIC_EST_ATTITUDE]):
            d = m.data
            same = places.get(int(d["frame"]), [])
            started = [k for t0, k in same if t0 <= int(d["t_ns"])] or [k for _, k in same[:1]]
            if d.get("valid") and d.get("q") is not None and started and started[-1] not in att:
                q = d["q"]
                att[started[-1]] = np.array([q["x"], q["y"], q["z"], q["w"]], dtype=float)
    if not att and summary.outcomes is not None:  # what became of the frames says why, as `run` says it
        raise UserError(f"{recording}: no frame has a valid attitude to diagnose from; the pipeline {pipeline.name} "
                        f"gave {summary.outcomes.sentence()}" + "".join(f" {h}" for h in summary.outcomes.hints()))
    return stars, att


def identify_stars(recording: Path, pipeline: PipelineConfig | None, source: str, show_progress: bool):
    """Run the given pipeline, or the default one (tracking from the declared attitude when there is
    one, lost in space otherwise and whenever tracking loses the stars).

    Returns the pipeline that ran, its identified stars and its attitudes (:func:`run_and_read`).
    """
    chosen = pipeline or default_pipeline()
    stars, att = run_and_read(recording, chosen, source, show_progress)
    return chosen, stars, att


def build_observations(stars: dict, att: dict, scenario: ScenarioConfig, catalog) -> tuple[Observations, Rotation]:
    """Flatten the identified stars of frames with a valid attitude into :class:`Observations`.

    Returns the observations and every kept frame's first attitude.
    """
    timing = build.build_timing(scenario)
    f_index, f_t0, f_q, f_exp, cols = _frame_columns(stars, att, timing)
    if not f_index:
        raise UserError("no frame has a valid attitude and at least "
                        f"{MIN_STARS_PER_FRAME} identified stars: nothing to diagnose (check the pipeline and the sensor model)")
    cat_ids = np.concatenate(cols["cat"])
    u_all = np.concatenate(cols["u"])
    mag, pm = _catalog_magnitudes(catalog, cat_ids, u_all)
    flux = np.concatenate(cols["flux"])
    with np.errstate(divide="ignore", invalid="ignore"):
        mag = np.where(np.isfinite(mag), mag, -2.5 * np.log10(flux))  # instrumental magnitude when uncatalogued
    sigma, source = _sigma_and_source(np.concatenate(cols["sigma"]), scenario)
    cov, source = _position_covariance(np.concatenate(cols["cov"]), sigma, source)
    t0 = np.asarray(f_t0, dtype=np.int64)
    expo = np.asarray(f_exp, dtype=np.int64)
    # one exposure (rounding aside): the scenario's timing holds; mixed: carried per frame
    mixed = np.ptp(expo) > 1000 if expo.size else False
    expo = expo if mixed else None
    obs = Observations(
        frame=np.concatenate(cols["frame"]).astype(np.int64), x=np.concatenate(cols["x"]), y=np.concatenate(cols["y"]),
        sigma=sigma, t_ns=np.concatenate(cols["t_ns"]).astype(np.int64), u_icrs=u_all,
        magnitude=np.asarray(mag, dtype=float), catalog_id=cat_ids, flux=flux, frame_index=np.asarray(f_index),
        t0_ns=t0, t_ref_ns=frame_reference_times(t0, timing, expo), sigma_source=source,
        pm_rad_yr=pm, exposure_ns=expo, cov=cov)
    return obs, Rotation.from_quat(np.asarray(f_q))


def _frame_columns(stars: dict, att: dict, timing: DetectorTiming):
    """Per kept frame its number, start time, attitude and exposure; per star the columns of every kept frame.

    A frame is kept when it has an attitude and at least ``MIN_STARS_PER_FRAME`` identified stars
    with finite positions and catalogue directions.
    """
    frames = sorted((k for k in stars if k in att), key=lambda k: stars[k][0])  # in time order
    cols = {k: [] for k in ("frame", "x", "y", "sigma", "t_ns", "u", "cat", "flux", "cov")}
    f_index, f_t0, f_q, f_exp = [], [], [], []
    for k in frames:
        t0, c = stars[k]
        cat = c.get("catalog_id", np.full(len(c["x"]), -1))
        ref = c.get("ref_icrs", np.full((len(c["x"]), 3), np.nan))
        ok = (cat >= 0) & np.all(np.isfinite(ref), axis=1) & np.isfinite(c["x"]) & np.isfinite(c["y"])
        if ok.sum() < MIN_STARS_PER_FRAME:
            continue
        j = len(f_index)
        f_index.append(int(c.get("frame", k)))  # the recording's number, for the report
        f_t0.append(t0)
        f_q.append(att[k])
        # the exposure each frame was taken with: a star's t_ns (mid-exposure of its row) minus its
        # row_time_ns (exposure start of its row) is half of it; absent -> the scenario's
        rt = c.get("row_time_ns")
        f_exp.append(int(np.median(2 * (c["t_ns"][ok] - rt[ok]))) if rt is not None and np.all(np.isfinite(rt[ok]))
                     else int(timing.exposure_ns))
        n = int(ok.sum())
        cols["frame"].append(np.full(n, j))
        cols["x"].append(c["x"][ok])
        cols["y"].append(c["y"][ok])
        cols["sigma"].append(c.get("sigma_px", np.full(len(c["x"]), np.nan))[ok])
        cols["cov"].append(np.column_stack([c.get(k, np.full(len(c["x"]), np.nan))[ok] for k in ("cov_xx", "cov_xy", "cov_yy")]))
        cols["t_ns"].append(c["t_ns"][ok])
        cols["u"].append(ref[ok])
        cols["cat"].append(cat[ok])
        cols["flux"].append(c.get("flux", np.full(len(c["x"]), np.nan))[ok])
    return f_index, f_t0, f_q, f_exp, cols


def _catalog_magnitudes(catalog, cat_ids: np.ndarray, u_all: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Catalogue magnitude of every star the catalogue knows (NaN otherwise), and the proper motions
    when every star is a catalogue star with a known proper motion (else None)."""
    idx = catalog.index_of(cat_ids) if catalog is not None else np.full(cat_ids.size, -1)
    if catalog is not None:
        # the ids must name the same star (imported data may use another catalogue's ids): same direction
        same = np.einsum("ij,ij->i", catalog.unit_icrs[np.maximum(idx, 0)], u_all) > np.cos(SAME_STAR_RAD)
        idx = np.where(same, idx, -1)
    mag = np.where(idx >= 0, catalog.magnitude[np.maximum(idx, 0)] if catalog is not None else np.nan, np.nan)
    pm = None
    if catalog is not None and getattr(catalog, "pm_rad_yr", None) is not None and np.all(idx >= 0):
        pm = catalog.pm_rad_yr[idx]
    return mag, pm


def _sigma_and_source(sigma: np.ndarray, scenario: ScenarioConfig) -> tuple[np.ndarray, str]:
    """Per-star centroid sigma: the recording's, the scenario's where missing, else NaN ("estimated")."""
    source = "recording: each star's sigma_px"
    bad = ~(np.isfinite(sigma) & (sigma > 0))
    if bad.any():
        s = scenario.noise.centroid_sigma_px if scenario.level == "centroid" else 0.0
        if s > 0:
            sigma = np.where(bad, s, sigma)
            source = "scenario noise.centroid_sigma_px" if bad.all() else "recording, scenario where missing"
        else:
            sigma = np.where(bad, np.nan, sigma)
            source = "estimated"
    return sigma, source


def _position_covariance(cov3: np.ndarray, sigma: np.ndarray, source: str) -> tuple[np.ndarray | None, str]:
    """The stars' 2 x 2 position covariances (n, 2, 2) px^2 from the recorded ``cov_xx, cov_xy, cov_yy``
    rows ``cov3`` (n, 3), when some star carries one that is not isotropic and every star has a known
    sigma (stars without a valid one get ``sigma^2 I``); else None (the diagnosis then whitens by sigma)."""
    xx, xy, yy = cov3.T
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(cov3).all(axis=1) & (xx > 0) & (yy > 0) & (xx * yy - xy * xy > 0)
    if not (valid & ((xy != 0) | (xx != yy))).any() or not np.all(np.isfinite(sigma)):
        return None, source
    cov = sigma[:, None, None] ** 2 * np.eye(2)
    cov[valid] = np.stack([np.stack([xx, xy], -1), np.stack([xy, yy], -1)], -2)[valid]
    return cov, source + "; 2 x 2 position covariances (cov_xx, cov_xy, cov_yy)"


def read_reference(recording: Path, obs: Observations, stars_attitude: Rotation | None = None,
                   mount_free: bool = False) -> tuple[Rotation, np.ndarray]:
    """The recording's ``/truth/attitude`` at every frame's reference time, and the frames its
    samples cover; exit 2 (UserError) when the recording carries none, or when it misses the
    attitude the stars give (``stars_attitude``, per frame) by more than ``REFERENCE_MISMATCH_DEG``
    (median; after the best constant rotation when the mount is free): no accuracy a user would
    state covers that, and the message names the convention that reading it would fit, when one does."""
    samples = LogReader(recording).truth_attitude()
    if samples["t_ns"].size < 2:
        raise UserError(f"{recording}: --reference-attitude-arcsec needs a reference attitude in the recording "
                        f"(/truth/attitude, at least two samples); it has {samples['t_ns'].size}")
    truth = TruthTrajectory(**samples)
    covered = truth.covers(obs.t_ref_ns)
    if stars_attitude is not None and covered.any():
        _check_reference(recording, truth, obs.t_ref_ns[covered], stars_attitude[covered], mount_free)
    return truth.attitude(np.where(covered, obs.t_ref_ns, truth.t_ns[0])), covered


def _reference_miss_deg(truth: TruthTrajectory, t_ns: np.ndarray, stars: Rotation, mount_free: bool) -> float:
    d = truth.attitude(t_ns).inv() * stars
    if mount_free:
        d = d.mean().inv() * d
    return float(np.degrees(np.median(d.magnitude())))


def _check_reference(recording: Path, truth: TruthTrajectory, t_ns: np.ndarray, stars: Rotation, mount_free: bool):
    miss = _reference_miss_deg(truth, t_ns, stars, mount_free)
    if miss <= REFERENCE_MISMATCH_DEG:
        return
    for reading, other in truth.other_readings().items():
        if _reference_miss_deg(other, t_ns, stars, mount_free) <= REFERENCE_MISMATCH_DEG:
            raise UserError(f"{recording}: /truth/attitude misses the attitude the stars give by {miss:.3g} deg (median) "
                            f"but agrees with it when read {reading}: the recording's reference follows another "
                            "convention than docs/conventions.md (camera-to-ICRS, our camera frame, named quaternion "
                            "fields); write it in ours to use it as a reference")
    raise UserError(f"{recording}: /truth/attitude misses the attitude the stars give by {miss:.3g} deg (median"
                    + (", after the best constant rotation" if mount_free else "") + "), and no other convention "
                    "explains it: it is not a reference of any stated accuracy for this camera (another camera, "
                    "another clock?)" + ("" if mount_free else "; a reference on another mount takes "
                                         "--reference-mount-free"))


def read_gyro(recording: Path, scenario: ScenarioConfig) -> GyroData | None:
    """The recording's gyro samples (``/gyro``) as :class:`GyroData`, None without any.

    The angle random walk comes from the scenario's gyro model (0 when it declares none: the
    increment noise is then the attitude error of the image fit alone)."""
    gyro = LogReader(recording).gyro()
    if gyro["t_ns"].size == 0:
        return None
    t, w = gyro["t_ns"], gyro["omega_rad_s"]
    order = np.argsort(t, kind="stable")
    t, w = t[order], w[order]
    keep = np.concatenate([[True], np.diff(t) > 0])  # a sample published twice at a frame boundary
    arw = np.deg2rad(scenario.gyro.arw_deg_sqrt_h) / 60.0 if scenario.gyro.enabled else 0.0  # deg/sqrt(h) -> rad/sqrt(s)
    return GyroData(t[keep], w[keep], float(arw))


# Readings of a gyro written elsewhere (docs/conventions.md: rad/s about the camera axes): the
# matrix that maps the rates as written to ours
GYRO_READINGS = {
    "in deg/s (rad/s expected)": np.deg2rad(1.0) * np.eye(3),
    "about the OpenCV camera axes (x and y reversed)": np.diag([-1.0, -1.0, 1.0]),
    "in deg/s about the OpenCV camera axes": np.deg2rad(1.0) * np.diag([-1.0, -1.0, 1.0]),
}
GYRO_MISS = 0.5  # median |star rate - gyro rate| / median |star rate| beyond which another reading is tried
GYRO_READING_FITS = 0.1  # and below which that reading is taken to be the one the recording used
MIN_STAR_RATE = np.deg2rad(0.01)  # rad/s: a slower camera shows no rate to compare a gyro with


def check_gyro(recording: Path, gyro: GyroData | None, obs: Observations, attitudes: Rotation) -> None:
    """Refuse a gyro that cannot be this camera's as written: no sample within the frames' times
    (times in another unit or clock), or rates that miss those the frames' attitudes show by
    more than ``GYRO_MISS`` of them while a reading of :data:`GYRO_READINGS` fits them within
    ``GYRO_READING_FITS`` (a large bias or scale error fits none and is left to the diagnosis)."""
    if gyro is None or gyro.m == 0:
        return
    t = obs.t_ref_ns
    inside = (t >= gyro.t_ns[0]) & (t <= gyro.t_ns[-1])
    if not inside.any():
        raise UserError(f"{recording}: /gyro: its {gyro.m} samples span t = {gyro.t_ns[0]} to {gyro.t_ns[-1]} ns and "
                        f"the frames t = {t.min()} to {t.max()} ns: no frame falls within the gyro's samples (gyro "
                        "times in another unit or on another clock? both are nanoseconds on one clock, docs/log-format.md)")
    if obs.n_frames < 3 or inside.sum() < 3:
        return
    stars = rates_from_attitudes(attitudes, t)[2][inside]
    scale = float(np.median(np.linalg.norm(stars, axis=1)))
    if scale < MIN_STAR_RATE:
        return
    written = np.stack([np.interp(t[inside], gyro.t_ns, gyro.omega[:, i]) for i in range(3)], axis=-1)

    def miss(m: np.ndarray) -> float:
        return float(np.median(np.linalg.norm(stars - written @ m.T, axis=1))) / scale

    base = miss(np.eye(3))
    if base <= GYRO_MISS:
        return
    for reading, m in GYRO_READINGS.items():
        if miss(m) <= GYRO_READING_FITS:
            raise UserError(f"{recording}: /gyro rates miss those the frames' attitudes show by {base:.3g} of them "
                            f"(median) but agree within {miss(m):.2g} when read {reading}: the recording's gyro follows "
                            "another convention than docs/conventions.md (rad/s about the camera axes); write it in "
                            "ours to use it")


# ------------------------------------------------------------------------------------ the command
def diagnose_recording(recording: str | Path, scenario: ScenarioConfig | None = None,
                       pipeline: PipelineConfig | None = None, options: DiagnoseOptions = DiagnoseOptions(),
                       pipeline_source: str = DEFAULT_PIPELINE_SOURCE, sim_source: str | None = None,
                       exclude_effects=()) -> tuple[dict, Diagnosis]:
    """Diagnose ``recording`` against ``scenario`` (default: the model its metadata declares).

    Returns the JSON-able report (:func:`~rollingstar.estimators.diagnosis.algorithm.as_json`) and
    the :class:`~rollingstar.estimators.diagnosis.algorithm.Diagnosis` it was made from (the
    observations, predictions and step results the report's plots need). The pipeline runs with
    single-threaded BLAS like the algorithm (see :func:`~rollingstar.estimators.diagnosis.algorithm.diagnose`).
    """
    recording = Path(recording)
    if not recording.exists():
        raise UserError(f"{recording}: recording not found")
    s = options.reference_sigma_arcsec
    if s is not None and not (math.isfinite(s) and 0.0 <= s <= MAX_REFERENCE_ARCSEC):
        raise UserError(f"--reference-attitude-arcsec {s}: expected the reference's accuracy per axis in arcsec, a "
                        f"finite number from 0 to {MAX_REFERENCE_ARCSEC:g} (180 deg)")
    if options.reference_mount_free and options.reference_sigma_arcsec is None:
        raise UserError(f"{recording}: --reference-mount-free fits the misalignment of a reference attitude; "
                        "state the reference's accuracy with --reference-attitude-arcsec S to use one")
    if scenario is None:
        scenario = recording_scenario(recording)
        sim_source = sim_source or f"{recording} (metadata 'scenario')"
    with threadpool_limits(limits=1, user_api="blas"):
        try:
            catalog = build.build_catalog(scenario, build.build_camera(scenario))
        except UserError:
            catalog = None
        pipeline, stars, att = identify_stars(recording, pipeline, pipeline_source, options.show_progress)
        try:
            obs, att0 = build_observations(stars, att, scenario, catalog)
        except UserError as exc:
            raise UserError(f"{recording}: {exc} (pipeline {pipeline.name})") from None
        reference = (read_reference(recording, obs, att0, options.reference_mount_free)
                     if options.reference_sigma_arcsec is not None else None)
        with progress_bar("diagnose", len(algorithm.PHASES), options.show_progress) as advance:
            gyro = read_gyro(recording, scenario)
            check_gyro(recording, gyro, obs, att0)
            d = algorithm.diagnose(obs, att0, scenario, gyro, options, exclude_effects,
                                   reference, on_phase=lambda name: advance(), carries_reference=_carries_truth(recording))
    result = algorithm.as_json(d, recording=str(recording), sim=sim_source or scenario.name, pipeline=pipeline.name)
    _refuse_non_finite(result, recording)
    return result, d


def _refuse_non_finite(result: dict, recording: Path) -> None:
    """No verdict on statistics that are not numbers: a model that cannot place the stars (times in
    another unit, a sensor model far from the camera) gives NaN residuals, and "no mismatch" on them
    would be a verdict on nothing."""
    keys = ("train_rms_before_px", "train_rms_after_px", "train_chi2_dof_before", "train_chi2_dof_after",
            "heldout_rms_before_px", "heldout_rms_after_px")
    bad = {k: result.get(k) for k in keys if result.get(k) is not None and not math.isfinite(result[k])}
    if bad:
        listing = ", ".join(f"{k} = {v}" for k, v in bad.items())
        raise UserError(f"{recording}: the model given cannot place this recording's stars ({listing}), so no "
                        "verdict is given; check the frame and star times (nanoseconds), the sensor model and the "
                        "catalogue directions")


def _carries_truth(recording: Path) -> bool:
    """Whether the recording has ``/truth/attitude`` messages a reference could be read from (a
    damaged one, which the run skipped with a warning, does not stop the diagnosis here: the
    option that reads them says what is wrong)."""
    reader = LogReader(recording)
    if TOPIC_TRUTH_ATTITUDE not in reader.topics():  # the channel table: no pass over the messages
        return False
    try:
        return next(reader.messages(TOPIC_TRUTH_ATTITUDE), None) is not None
    except LogFormatError:
        return True


def run_diagnose(recording: Path, sim: Path | None, pipeline: Path | None, out_dir: Path | None,
                 options: DiagnoseOptions = DiagnoseOptions()) -> dict:
    """The CLI entry: load configs, diagnose, write the report folder; returns the JSON object.

    The report folder is written through :func:`rollingstar.outputs.safe_output` (an earlier report
    stays until the new one is complete; an output folder inside or equal to an input is refused)."""
    scenario = load_scenario(sim) if sim is not None else None
    pipe = load_pipeline(pipeline) if pipeline is not None else None
    result, d = diagnose_recording(recording, scenario, pipe, options,
                                   pipeline_source=str(pipeline) if pipeline else DEFAULT_PIPELINE_SOURCE,
                                   sim_source=str(sim) if sim else None)
    if out_dir is not None:
        inputs = [p for p in (recording, sim, pipeline) if p is not None]
        with safe_output(out_dir, inputs, directory=True) as folder:
            (folder / "scenario_updated.yaml").write_text(to_yaml(d.updated_scenario()))
            result["scenario_updated"] = str(out_dir / "scenario_updated.yaml")
            write_report(result, d, folder)
    return result


def print_summary(result: dict, console) -> None:
    """Human-readable summary of a diagnosis on the terminal (rich)."""
    def f(v):
        return "n/a" if v is None else f"{v:.4g}"

    loc = result["located"]
    console.print(result["summary"], highlight=False, markup=False)
    console.print()
    console.print(f"[bold]verdict:[/] {result['verdict']}", highlight=False)
    corrected = bool((result["unexplained_systematic"].get("description") or {}).get("correction"))
    where = "none" if loc["strongest_covariate"] is None else f"{loc['strongest_covariate']} / {loc['strongest_channel']}"
    console.print(f"located{' (the empirical correction in the model)' if corrected else ''}: chi2/dof {f(loc['chi2_dof'])} "
                  f"(z {f(loc['z'])}), strongest covariate {where} (z {f(loc['strongest_z'])})", highlight=False)
    if result["effects"]:
        t = Table(title="effects")
        for col in ("effect", "parameter", "value", "sigma", "unit", "delta BIC", "inclusion", "confidence"):
            t.add_column(col)
        for e in result["effects"]:
            for pn, p in e["params"].items():
                t.add_row(e["name"], pn, f(p["value"]), f(p["sigma"]), p["unit"], f(e["delta_bic"]),
                          f(e["inclusion_probability"]), e["confidence"])
        console.print(t)
    for a in result["ambiguous"]:
        console.print(f"ambiguous: {' / '.join(a['candidates'])} -> {a['separating_experiment']}", highlight=False)
    t = Table(title="residual RMS per axis (px)")
    for col in ("data", "before", "after"):
        t.add_column(col)
    t.add_row("training", f(result["train_rms_before_px"]), f(result["train_rms_after_px"]))
    t.add_row("held-out", f(result["heldout_rms_before_px"]), f(result["heldout_rms_after_px"]))
    console.print(t)
    rs = result.get("resimulation")
    if rs:
        console.print("re-simulation, recording vs re-simulated residuals (KS p): "
                      f"before {f(rs['before']['ks_p_value'])}, after {f(rs['after']['ks_p_value'])}", highlight=False)
    if result.get("scenario_updated"):
        console.print(f"wrote {Path(result['scenario_updated']).parent}/index.html and scenario_updated.yaml", highlight=False)
