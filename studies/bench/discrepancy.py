"""``rollingstar bench discrepancy``: can ``diagnose`` name physics concealed in a recording?

Each case is a recording simulated by :func:`rollingstar.pipelines.simulate.simulate_to_log` from a base
scenario (he2021b sensor: 24.09 mm, 1024 x 1024 px of 5.5 um, Hipparcos stars to Hp 6, centroid
noise 0.05 px) with a random motion design and zero, one or two effects switched on; the
diagnosing side is given only the base scenario. Designs: inertial hold, constant single-axis
rate, constant multi-axis rate, rate reversal (the rate flips sign at a frame boundary halfway),
each with the exposure drawn from two times (20 ms and 80 ms), and two exposure times (frames
alternate 20 and 80 ms, :func:`simulate_mixed`). The rate-reversal and two-exposure designs log a
gyro (``GYRO``): there the attitude-increment channel counts in detection limits and aliases and
the gyro effects are drawn too.

Effect magnitudes. For the drawn design, the *detection limit* of a parameter is the value whose
image signature, with the per-frame attitude projected out, reaches 5 sigma of the centroid noise
over the recording (:func:`rollingstar.sensors.effects.design.detection_limit` on the noise-free truth of
the same design). One parameter of the effect is set to ``m`` times its limit, ``m`` log-uniform
in [0.3, 30], random sign. An effect whose signature the attitude absorbs entirely (limit inf) is
recorded as invisible in that design. The *alias* of a case: every other library effect whose
projected signature space has a canonical correlation above 0.95 with the drawn effect's (whole
groups, as the diagnosis compares them); a case whose
effect has an alias is "not separable" by its design and counts as correctly named when the
diagnosis names the effect or reports the ambiguity that contains it.

Nuisance-mismatch nulls (:data:`NUISANCES`, run after the cases above with their own seeds):
recordings of the base design with no effect, whose centroids differ from the simulation only in
things that are not library physics (noise level, PSF shape, pixel response, row-quantised
shutter, catalogue positions within their errors). Any named effect is a false name; a stated
noise-model mismatch with its factor is allowed.

Out-of-library cases use perturbations defined only here (a detector stitching step and a
sinusoidal ripple of the column positions); they must come back as an unexplained systematic,
not as a confidently named library effect. At least 30 % of cases are nulls.

Scores by signal-to-noise bin (multiple of the detection limit): correct naming, wrong names,
misses, false discoveries on nulls, median relative parameter error and the coverage of the
reported 1-sigma and 2-sigma intervals, and the held-out RMS improvement.
"""
from __future__ import annotations

import contextlib
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import ClassVar

import numpy as np

from rollingstar.config import parse_yaml, to_yaml, validate
from rollingstar.errors import UserError
from rollingstar.estimators.diagnosis import gyro_channel as gc
from rollingstar.estimators.diagnosis.library import Candidate
from rollingstar.estimators.diagnosis.selection import canonical_correlation
from rollingstar.logs.reader import LogReader
from rollingstar.logs.topics import TOPIC_CENTROIDS, TOPIC_TRUTH_STARS
from rollingstar.logs.writer import LogWriter
from rollingstar.pipelines.diagnose import DiagnoseOptions, diagnose_recording
from rollingstar.pipelines.simulate import build_simulator, simulate_to_log
from rollingstar.progress import progress_bar
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.effects import EFFECTS, Effect, EffectParameter
from rollingstar.sensors.effects.base import (
    STAGE_DETECTOR,
    as_positions,
    stack_jacobian,
)
from rollingstar.sensors.effects.context import context_from_attitude
from rollingstar.sensors.effects.design import detection_limit, project_out
from rollingstar.sensors.effects.geometry import rotation_jacobian
from rollingstar.sensors.gyro import sample_times_ns
from rollingstar.sensors.scenario import ScenarioConfig

BASE_YAML = """
name: bench-discrepancy-base
level: centroid
sensor: {focal_length_mm: 24.09, pixel_size_um: 5.5, width_px: 1024, height_px: 1024}
shutter: {mode: rolling, exposure_ms: 50.0, line_delay_us: 49.0}
catalog: {source: hipparcos, magnitude_limit: 6.0, epoch_year: 2025.0}
motion:
  initial_attitude: {ra_deg: 83.8, dec_deg: -5.4, roll_deg: 0.0}
noise: {centroid_sigma_px: 0.05}
frames: 20
seed: 1
"""
DESIGNS = ("inertial_hold", "single_axis", "multi_axis", "rate_reversal", "two_exposures")
EXPOSURES_MS = (20.0, 80.0)
# two_exposures: frames alternate EXPOSURES_MS at one frame period (long enough for the longer)
MIXED_PERIOD_MS = 140.0
# designs logged with a gyro (the attitude-increment channel: gyro effects, clock offset, smear)
GYRO_DESIGNS = ("rate_reversal", "two_exposures")
GYRO = {"enabled": True, "rate_hz": 200.0, "arw_deg_sqrt_h": 0.02}
N_SIGMA = 5.0
MULT_RANGE = (0.3, 30.0)
SNR_BINS = ((0.3, 1.0), (1.0, 3.0), (3.0, 10.0), (10.0, 30.0))
ALIAS_CORR = 0.95
NULL_FRACTION = 0.34
OOL_FRACTION = 0.12
TWO_FRACTION = 0.15
# sky pointings (ra, dec) drawn per case so that star fields differ
POINTINGS = ((83.8, -5.4), (10.7, 41.3), (201.3, -11.2), (279.2, 38.8), (150.0, 2.0), (300.0, -30.0))


# ----------------------------------------------------------------------- out-of-library effects
RIPPLE_PERIOD_PX = 150.0
BASE_WIDTH_PX = 1024
class StitchStep(Effect):
    """Benchmark-only: the right half of the detector is a second die displaced by ``dy`` rows."""

    name: ClassVar[str] = "bench_stitch_step"
    stage: ClassVar[int] = STAGE_DETECTOR
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("dy", "px", 0.0, 0.05, (-50.0, 50.0), "row offset of the right half"),)
    explanation: ClassVar[str] = "benchmark-only out-of-library perturbation (not in rollingstar.sensors.effects)"

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        return x, y + self._values["dy"] * (x > ctx.camera.cx)

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        return stack_jacobian(np.stack([np.zeros_like(x), (x > ctx.camera.cx).astype(float)], axis=-1))


class ColumnRipple(Effect):
    """Benchmark-only: column positions ripple with a period of 150 px (a periodic detector defect)."""

    name: ClassVar[str] = "bench_column_ripple"
    stage: ClassVar[int] = STAGE_DETECTOR
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("amplitude", "px", 0.0, 0.05, (-50.0, 50.0), "ripple amplitude along x"),)
    explanation: ClassVar[str] = "benchmark-only out-of-library perturbation (not in rollingstar.sensors.effects)"

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        return x + self._values["amplitude"] * np.sin(2 * np.pi * y / RIPPLE_PERIOD_PX), y

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        return stack_jacobian(np.stack([np.sin(2 * np.pi * y / RIPPLE_PERIOD_PX), np.zeros_like(y)], axis=-1))


OUT_OF_LIBRARY = (StitchStep, ColumnRipple)


@contextlib.contextmanager
def registered(classes):
    """Register benchmark-only effects so that a scenario can switch them on; removed afterwards."""
    added = [c for c in classes if c.name not in EFFECTS]
    for c in added:
        EFFECTS[c.name] = c
    try:
        yield
    finally:
        for c in added:
            EFFECTS.pop(c.name, None)


# --------------------------------------------------------------------------------------- cases
@dataclass
class Case:
    index: int
    kind: str  # null | library | two | out_of_library
    design: str
    exposure_ms: float
    scenario: ScenarioConfig  # base (what the diagnosis gets)
    effects: list[dict]  # [{name, param, value, limit, multiple, alias}]


def base_scenario(frames: int) -> ScenarioConfig:
    data = parse_yaml(BASE_YAML, "<bench base>")
    data["frames"] = frames
    return validate(ScenarioConfig, data, "<bench base>")


def design_scenario(base: ScenarioConfig, design: str, exposure_ms: float, rng, frames: int, seed: int) -> ScenarioConfig:
    data = base.model_dump(mode="json")
    ra, dec = POINTINGS[rng.integers(len(POINTINGS))]
    data["motion"] = {"initial_attitude": {"ra_deg": float(ra), "dec_deg": float(dec), "roll_deg": float(rng.uniform(0, 360))}}
    data["shutter"]["exposure_ms"] = exposure_ms
    rate = float(rng.uniform(0.5, 2.0))
    if design == "single_axis":
        axis = np.zeros(3)
        axis[rng.integers(2)] = 1.0
        data["motion"]["rate_deg_s"] = (rate * axis).tolist()
    elif design == "multi_axis":
        v = rng.normal(size=3)
        v[2] *= 0.3
        data["motion"]["rate_deg_s"] = (rate * v / np.linalg.norm(v)).tolist()
    elif design == "two_exposures":  # a constant rate about a random cross-boresight axis, period fixed
        a = rng.uniform(0, 2 * np.pi)
        data["motion"]["rate_deg_s"] = [rate * float(np.cos(a)), rate * float(np.sin(a)), 0.0]
        data["shutter"]["frame_period_ms"] = MIXED_PERIOD_MS
    elif design == "rate_reversal":
        axis = np.zeros(3)
        axis[rng.integers(2)] = 1.0
        period_s = (exposure_ms * 1e-3 + base.sensor.height_px * base.shutter.line_delay_us * 1e-6)
        half = frames // 2
        data["motion"]["segments"] = [{"duration_s": half * period_s, "rate_deg_s": (rate * axis).tolist()},
                                      {"duration_s": (frames - half + 1) * period_s, "rate_deg_s": (-rate * axis).tolist()}]
    if design in GYRO_DESIGNS:
        data["gyro"] = dict(GYRO)
    data["seed"] = int(seed)
    data["name"] = f"bench-{design}"
    return validate(ScenarioConfig, data, "<bench design>")


def exposure_variant(cfg: ScenarioConfig, exposure_ms: float) -> ScenarioConfig:
    """The same scenario (motion, seed, frame period) with another exposure time."""
    data = cfg.model_dump(mode="json")
    data["shutter"]["exposure_ms"] = exposure_ms
    return validate(ScenarioConfig, data, "<bench exposure variant>")


def mixed_parts(cfg: ScenarioConfig) -> list[tuple[ScenarioConfig, np.ndarray]]:
    """A two-exposure design as (scenario, frames taken from it): even frames at the first exposure."""
    k = np.arange(cfg.frames)
    return [(exposure_variant(cfg, EXPOSURES_MS[0]), k[k % 2 == 0]), (exposure_variant(cfg, EXPOSURES_MS[1]), k[k % 2 == 1])]


def simulate_mixed(cfg: ScenarioConfig, output: Path) -> None:
    """One recording whose frames alternate two exposure times (:func:`mixed_parts`).

    The scenario language has a single exposure per recording, so each exposure is simulated as
    its own recording over the same motion and frame times (same seed, same frame period), and
    the frames are interleaved into one log: all of the first recording's messages except the
    odd frames' centroids and truth stars, which come from the second. Each star keeps the
    ``t_ns`` (mid-exposure of its row) and ``row_time_ns`` of its own exposure, so the recording
    states the exposure of every frame; its declared scenario is the first exposure's.
    """

    (cfg_a, _), (cfg_b, odd) = mixed_parts(cfg)
    pa, pb = output.with_suffix(".a.mcap"), output.with_suffix(".b.mcap")
    simulate_to_log(cfg_a, pa, show_progress=False)
    simulate_to_log(cfg_b, pb, show_progress=False)
    per_frame = (TOPIC_CENTROIDS, TOPIC_TRUTH_STARS)
    odd = set(int(k) for k in odd)
    from_b = {(m.topic, int(m.data["frame"])): m for m in LogReader(pb).messages(list(per_frame))
              if int(m.data["frame"]) in odd}
    with LogWriter(output, kind="simulation", metadata={"scenario": {"yaml": to_yaml(cfg_a)}}) as w:
        for m in LogReader(pa).messages():
            if m.topic in per_frame and int(m.data["frame"]) in odd:
                m = from_b[(m.topic, int(m.data["frame"]))]
            w.write_json(m.topic, m.data, m.log_time_ns)
    pa.unlink(missing_ok=True)
    pb.unlink(missing_ok=True)


# ----------------------------------------------------------------- nuisance-mismatch nulls
#: Differences between a recording and its simulation that are not library physics. Each is a null
#: of the library: the diagnosis must name no effect (it may state a noise-model mismatch with its
#: factor). Every nuisance recording states the scenario's noise (``sigma_px``) for its centroids.
NUISANCES = {
    "noise_1.5x": "centroid noise 1.5 x the stated, white",
    "noise_0.67x": "centroid noise 1 / 1.5 x the stated, white",
    "psf_shape": "elliptical PSF (axes 1.6 and 0.9 px, random orientation) measured by an efficient centroider: "
                 "anisotropic noise growing with magnitude (photon and background terms), median the stated",
    "pixel_response": "3 % rms pixel-to-pixel gain (PRNU, an uncorrected flat field) under a 0.8 px Gaussian PSF: "
                      "each star's centroid shifted by its pixels' gains, fixed on the detector, plus the stated noise",
    "row_quantised_shutter": "rows read out in blocks of 16 sharing one exposure time (the block's centre) instead of "
                             "each row its own: a sawtooth of image velocity x line delay x up to 8 rows, plus the stated noise",
    "catalogue_positions": "the sky's stars displaced from the catalogue by 1 arcsec per axis (another, older "
                           "catalogue's positions within its errors), plus the stated noise",
}
NUISANCE_DESIGNS = ("inertial_hold", "single_axis", "multi_axis", "rate_reversal")  # one recording each, no mixed exposures
PSF_AXES_PX = (1.6, 0.9)
PSF_BACKGROUND_SHARE = 0.3  # background share of the variance at the median star's brightness
PRNU_RMS = 0.03
PRNU_PSF_SIGMA_PX = 0.8
ROW_BLOCK = 16
CATALOGUE_ERROR_MAS = 1000.0


def nuisance_recording(cfg: ScenarioConfig, nuisance: str, output: Path, rng) -> float:
    """``cfg``'s recording (no effects) with the centroids rewritten by ``nuisance`` (:data:`NUISANCES`).

    The design is simulated without noise, each centroid is matched to its noise-free truth star,
    and the position is rebuilt as truth + the nuisance's shift + its noise. The log states the
    scenario's noise for every centroid, as a pipeline trusting the simulation would. Returns the
    nuisance's size against the stated noise: the RMS per axis of what it adds to the positions
    (its systematic shift and noise together) over the stated sigma; 1 is the stated noise alone.
    """
    clean = validate(ScenarioConfig, {**cfg.model_dump(mode="json"), "noise": {"centroid_sigma_px": 0.0}}, "<nuisance>")
    tmp = output.with_suffix(".clean.mcap")
    simulate_to_log(clean, tmp, show_progress=False)
    reader = LogReader(tmp)
    truth = {int(m.data["frame"]): m.data for m in reader.messages([TOPIC_TRUTH_STARS])}
    velocity = _truth_velocities(truth)
    sigma = cfg.noise.centroid_sigma_px
    camera = build_simulator(cfg).camera
    star_shift = {}  # per catalogue star: a fixed shift (catalogue positions) or a fixed PRNU map
    prnu = rng.normal(0.0, PRNU_RMS, (cfg.sensor.height_px + 16, cfg.sensor.width_px + 16))
    added = []
    with LogWriter(output, kind="simulation", metadata={"scenario": {"yaml": to_yaml(cfg)}}) as w:
        for m in reader.messages():
            if m.topic == TOPIC_CENTROIDS:
                m, shift = _rewrite(m, truth[int(m.data["frame"])], velocity, nuisance, sigma, camera, cfg, prnu, star_shift, rng)
                added.append(shift)
            w.write_json(m.topic, m.data, m.log_time_ns)
    tmp.unlink(missing_ok=True)
    return float(np.sqrt(np.mean(np.concatenate(added) ** 2)) / sigma)


def _truth_velocities(truth: dict) -> dict:
    """Image velocity (px/s) of every truth star in every frame, by finite differences of the same
    catalogue star's positions in the neighbouring frames: ``{(frame, catalog_id): (vx, vy)}``."""
    pos = {(k, int(c)): (x, y, t) for k, d in truth.items() for c, x, y, t in zip(d["catalog_id"], d["x"], d["y"], d["t_ns"])}
    out = {}
    for (k, c), (x, y, t) in pos.items():
        a, b = pos.get((k - 1, c), (x, y, t)), pos.get((k + 1, c), (x, y, t))
        dt = (b[2] - a[2]) * S_PER_NS
        out[(k, c)] = ((b[0] - a[0]) / dt, (b[1] - a[1]) / dt) if dt > 0 else (0.0, 0.0)
    return out


def _rewrite(m, truth: dict, velocity: dict, nuisance: str, sigma: float, camera, cfg, prnu, star_shift, rng):
    """One frame's centroid message with the nuisance applied (module data :data:`NUISANCES`)."""
    from scipy.spatial import cKDTree

    d = dict(m.data)
    tx, ty = np.asarray(truth["x"], float), np.asarray(truth["y"], float)
    ids = np.asarray(truth["catalog_id"], dtype=np.int64)
    x, y = np.asarray(d["x"], float), np.asarray(d["y"], float)
    _, j = cKDTree(np.c_[tx, ty]).query(np.c_[x, y])
    x, y, ids, mag = tx[j], ty[j], ids[j], np.asarray(truth["magnitude"], float)[j]
    n = x.size
    noise = rng.normal(0.0, sigma, (n, 2))
    if nuisance == "noise_1.5x":
        noise *= 1.5
    elif nuisance == "noise_0.67x":
        noise /= 1.5
    elif nuisance == "psf_shape":
        noise = _psf_shape_noise(mag, sigma, star_shift, rng)
    elif nuisance == "pixel_response":
        noise += _prnu_shift(x, y, prnu)
    elif nuisance == "row_quantised_shutter":
        v = np.array([velocity[(int(d["frame"]), int(c))] for c in ids]).reshape(-1, 2)
        block_centre = np.floor(y / ROW_BLOCK) * ROW_BLOCK + (ROW_BLOCK - 1) / 2.0
        noise += v * ((block_centre - y) * cfg.shutter.line_delay_us * 1e-6)[:, None]
    elif nuisance == "catalogue_positions":
        scale = camera.focal_px * np.deg2rad(CATALOGUE_ERROR_MAS / 3.6e6)
        noise += np.array([star_shift.setdefault(int(c), rng.normal(0.0, scale, 2)) for c in ids]).reshape(-1, 2)
    d["x"], d["y"] = (x + noise[:, 0]).tolist(), (y + noise[:, 1]).tolist()
    d["sigma_px"] = [float(sigma)] * n
    return replace(m, data=d), noise


def _psf_shape_noise(mag: np.ndarray, sigma: float, star_shift: dict, rng) -> np.ndarray:
    """Noise of an efficient centroider on an elliptical PSF (Gaussian approximation of its
    Cramér-Rao bound): covariance ``S / N (1 + b)`` with ``S`` the PSF's shape (unit determinant,
    axes :data:`PSF_AXES_PX`), ``N`` the photons (10^(-0.4 m)) and ``b`` the background term
    (grows as 1 / N); scaled so that a star of the recording's median magnitude has the covariance
    ``sigma^2 S`` (per-axis variances 1.78 and 0.56 sigma^2 along the PSF's axes, determinant sigma^4)."""
    if "shape" not in star_shift:
        a = rng.uniform(0.0, np.pi)
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        ax = np.array(PSF_AXES_PX) ** 2 / np.prod(PSF_AXES_PX)
        star_shift["shape"] = rot @ np.diag(ax) @ rot.T
        star_shift["m_ref"] = float(np.median(mag))
    inv_n = 10 ** (0.4 * (mag - star_shift["m_ref"]))
    var = sigma**2 * inv_n * (1 + PSF_BACKGROUND_SHARE * inv_n) / (1 + PSF_BACKGROUND_SHARE)
    chol = np.linalg.cholesky(star_shift["shape"])
    return np.sqrt(var)[:, None] * (rng.normal(size=(mag.size, 2)) @ chol.T)


def _prnu_shift(x: np.ndarray, y: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Centroid shift (n, 2) of a Gaussian spot (``PRNU_PSF_SIGMA_PX``) at (x, y) on pixels whose
    response is ``1 + gain`` (indexed [row + 8, column + 8]): the gain-weighted centre of light
    minus the unweighted one, over a 15 x 15 stamp."""
    off = np.arange(-7, 8)
    cols = np.floor(x)[:, None] + off  # (n, 15)
    rows = np.floor(y)[:, None] + off
    gx = np.exp(-0.5 * ((cols + 0.5 - x[:, None]) / PRNU_PSF_SIGMA_PX) ** 2)
    gy = np.exp(-0.5 * ((rows + 0.5 - y[:, None]) / PRNU_PSF_SIGMA_PX) ** 2)
    psf = gy[:, :, None] * gx[:, None, :]  # (n, row, col)
    r_idx = np.clip(rows.astype(int) + 8, 0, gain.shape[0] - 1)
    c_idx = np.clip(cols.astype(int) + 8, 0, gain.shape[1] - 1)
    g = gain[r_idx[:, :, None], c_idx[:, None, :]]
    lit = psf * (1 + g)
    cx = (lit * (cols + 0.5)[:, None, :]).sum((1, 2)) / lit.sum((1, 2)) - (psf * (cols + 0.5)[:, None, :]).sum((1, 2)) / psf.sum((1, 2))
    cy = (lit * (rows + 0.5)[:, :, None]).sum((1, 2)) / lit.sum((1, 2)) - (psf * (rows + 0.5)[:, :, None]).sum((1, 2)) / psf.sum((1, 2))
    return np.stack([cx, cy], axis=1)


@dataclass
class DesignContext:
    """Noise-free truth of a design: one EffectContext per exposure group (each with its timing)
    and their concatenation (frames, positions, attitudes) for the attitude projection; with a
    gyro, its noise-free samples, the frames' reference times and angle random walk."""

    parts: list
    whole: object
    gyro: object = None  # rollingstar.estimators.diagnosis.gyro_channel.GyroData (noise-free rates)
    t_ref_ns: np.ndarray | None = None  # (F,) per frame (frames numbered 0..F-1 in `whole.frame`)

    def jacobian(self, eff) -> np.ndarray:
        return np.concatenate([eff.jacobian(c.x, c.y, c) for c in self.parts])

    def design_matrix(self, eff, sigma: float) -> np.ndarray:
        """Whitened, attitude-projected image rows and, with a gyro, the whitened attitude-increment
        rows (:mod:`rollingstar.estimators.diagnosis.gyro_channel`) of ``eff``'s parameters, (N, p)."""

        for c in self.parts:
            c.check([eff])
        j = self.jacobian(eff) / sigma
        p = project_out(j, self.whole, "attitude")
        rows = [p[:, 0, :], p[:, 1, :]]
        if self.gyro is not None:
            frame = np.asarray(self.whole.frame)
            f = int(frame.max()) + 1
            aj = rotation_jacobian(self.whole.camera, self.whole.x, self.whole.y) / sigma
            inc = gc.image_effect_signature(gc.absorbed_rotations(frame, f, aj, j))
            if "gyro" in eff.channels:
                inc = inc + gc.gyro_signature(eff, self.gyro, self.t_ref_ns)
            cov = gc.attitude_covariances(frame, f, aj * sigma, np.full(frame.size, sigma), np.ones(frame.size, bool))
            pairs = np.arange(f - 1)
            chan = gc.GyroChannel(self.gyro, pairs, gc.whitener(cov, pairs, self.t_ref_ns, self.gyro.arw_rad_sqrt_s))
            rows.append(chan.whiten(inc))
        return np.concatenate(rows)


def _concat_contexts(parts):
    from dataclasses import fields
    from dataclasses import replace as dc_replace

    from scipy.spatial.transform import Rotation

    if len(parts) == 1:
        return parts[0]
    kw = {}
    for f in fields(parts[0]):
        vals = [getattr(c, f.name) for c in parts]
        if f.name in ("camera", "timing") or vals[0] is None:
            kw[f.name] = vals[0]
        elif f.name == "t_start_ns":
            kw[f.name] = min(vals)
        elif f.name == "covariates":
            kw[f.name] = {k: np.concatenate([v[k] for v in vals]) for k in vals[0]}
        elif f.name == "attitude":
            kw[f.name] = Rotation.concatenate(vals)
        else:
            kw[f.name] = np.concatenate([np.asarray(v) for v in vals])
    return dc_replace(parts[0], **kw)


def design_context(cfg: ScenarioConfig, design: str = "") -> DesignContext:
    """Noise-free truth of the design (for detection limits and aliases)."""
    if design == "two_exposures":
        parts = [_frame_context(c, keep) for c, keep in mixed_parts(cfg)]
        whole = _concat_contexts(parts)
    else:
        parts = [_frame_context(cfg)]
        whole = parts[0]
    gyro = t_ref = None
    if cfg.gyro.enabled:

        sim = build_simulator(cfg)
        timing = sim.timing
        t0 = timing.frame_start_ns(np.arange(cfg.frames))
        expo = np.full(cfg.frames, timing.exposure_ns, dtype=np.int64)
        if design == "two_exposures":
            for c, keep in mixed_parts(cfg):
                expo[keep] = int(round(c.shutter.exposure_ms * 1e6))
        t_ref = np.array([timing.frame_reference_ns(int(t)) for t in t0], dtype=np.int64) + (expo - timing.exposure_ns) // 2
        ts = sample_times_ns(cfg.gyro.rate_hz, int(t0[0]) - int(timing.frame_period_ns),
                             np.arange(int((cfg.frames + 2) * timing.frame_period_ns * S_PER_NS * cfg.gyro.rate_hz) + 2))
        w = sim.motion.angular_velocity(ts)
        gyro = gc.GyroData(ts, w, float(np.deg2rad(cfg.gyro.arw_deg_sqrt_h) / 60.0))
    return DesignContext(parts, whole, gyro, t_ref)


def _frame_context(cfg: ScenarioConfig, keep=None):
    sim = build_simulator(cfg)
    xs = []
    for f in sim.frames(cfg.frames):
        tr = f.truth
        if len(tr) == 0 or (keep is not None and f.index not in keep):
            continue
        xs.append((f.index, f.t0_ns, tr))
    t = np.concatenate([tr.t_ns for _, _, tr in xs])
    u = np.concatenate([tr.unit_icrs for _, _, tr in xs])
    frame = np.concatenate([np.full(len(tr), k) for k, _, tr in xs])
    t0 = np.concatenate([np.full(len(tr), t0) for _, t0, tr in xs])
    rows = np.concatenate([tr.y for _, _, tr in xs])
    mag = np.concatenate([tr.magnitude for _, _, tr in xs])
    att = sim.motion.attitude(t)
    omega = sim.motion.angular_velocity(t)
    ids = np.concatenate([tr.catalog_id for _, _, tr in xs])
    pm = None if getattr(sim.catalog, "pm_rad_yr", None) is None else sim.catalog.pm_rad_yr[sim.catalog.index_of(ids)]
    return context_from_attitude(sim.camera, att, u, t, omega, row=rows, t0_ns=t0, frame=frame, magnitude=mag,
                                 timing=sim.timing, t_start_ns=int(t0.min()), pm_rad_yr=pm)


def candidate_classes() -> dict[str, type[Effect]]:
    """Library effects the benchmark draws: image-plane ones whose context needs the recording meets."""

    out = {}
    for name, cls in sorted(EFFECTS.items()):
        if cls in OUT_OF_LIBRARY or cls.empirical:
            continue
        c = Candidate(cls)
        if cls().needs != c.needs or not ({"image", "time", "gyro"} & c.channels):
            continue
        if any(k not in ("omega_rad_s", "row", "t0_ns", "frame", "magnitude", "timing", "vx", "vy", "attitude", "unit_icrs",
                         "pm_rad_yr") for k in c.needs):
            continue
        out[name] = cls
    return out


def projected(cls, ctx: DesignContext) -> np.ndarray:
    return ctx.design_matrix(cls(), 1.0)


def design_detection_limit(eff, ctx: DesignContext, sigma: float, n_sigma: float = N_SIGMA) -> dict[str, float]:
    """:func:`rollingstar.sensors.effects.design.detection_limit` over the exposure groups and channels of a
    design: the value whose whitened signature (image rows with the attitude projected out, plus
    the gyro increment rows when the design has a gyro) reaches ``n_sigma``."""
    if len(ctx.parts) == 1 and ctx.gyro is None:
        return detection_limit(eff, ctx.whole, sigma, n_sigma, "attitude")
    norm = np.linalg.norm(ctx.design_matrix(eff, sigma), axis=0)
    with np.errstate(divide="ignore"):
        lim = np.where(norm > 1e-12, n_sigma / np.where(norm > 1e-12, norm, 1.0), np.inf)
    return {p.name: float(v) for p, v in zip(eff.parameters, lim)}


def aliases_in_design(name: str, param_index: int, ctx, classes: dict) -> list[str]:
    """Library effects whose projected signature space correlates above 0.95 with ``name``'s.

    Whole effect groups are compared (canonical correlation), as the diagnosis does: it fits and
    names groups, so two groups it cannot tell apart in this design are aliases here too.
    """
    a = projected(classes[name], ctx)
    a = a[:, np.linalg.norm(a, axis=0) > 1e-12]
    out = []
    for other, cls in classes.items():
        if other == name:
            continue
        try:
            b = projected(cls, ctx)
        except (ValueError, TypeError):  # cannot be evaluated on this design (e.g. missing context)
            continue
        b = b[:, np.linalg.norm(b, axis=0) > 1e-12]
        if canonical_correlation(a, b) > ALIAS_CORR:
            out.append(other)
    return out


def draw_effect(cls, ctx, sigma: float, rng) -> dict | None:
    """One parameter of ``cls`` at m x its detection limit (m log-uniform), random sign; None if invisible."""
    eff = cls()
    limits = design_detection_limit(eff, ctx, sigma)
    # a parameter can be drawn when 0.3x its limit is within its bounds (else the design cannot show it)
    finite = [i for i, p in enumerate(cls.parameters) if np.isfinite(limits[p.name]) and limits[p.name] > 0
              and MULT_RANGE[0] * limits[p.name] <= max(p.bounds[1] - p.default, p.default - p.bounds[0])]
    if not finite:
        return {"name": cls.name, "param": cls.parameters[0].name, "value": None, "limit": float("inf"), "multiple": None,
                "param_index": 0}
    j = int(rng.choice(finite))
    p = cls.parameters[j]
    m = float(np.exp(rng.uniform(np.log(MULT_RANGE[0]), np.log(MULT_RANGE[1]))))
    lim = limits[p.name]
    value = p.default + rng.choice([-1.0, 1.0]) * m * lim
    value = float(np.clip(value, p.bounds[0], p.bounds[1]))
    return {"name": cls.name, "param": p.name, "value": value, "limit": float(lim),
            "multiple": float(abs(value - p.default) / lim), "param_index": j}


def make_cases(n_cases: int, seed: int, frames: int) -> list[tuple[str, str, float, int]]:
    """Kinds and designs of the cases, deterministic in ``seed``: >= 30 % nulls, some out-of-library."""
    rng = np.random.default_rng([seed, 11])
    n_null = int(np.ceil(NULL_FRACTION * n_cases))
    n_ool = max(1, int(round(OOL_FRACTION * n_cases)))
    n_two = int(round(TWO_FRACTION * n_cases))
    n_lib = n_cases - n_null - n_ool - n_two
    kinds = ["null"] * n_null + ["out_of_library"] * n_ool + ["two"] * n_two + ["library"] * n_lib
    rng.shuffle(kinds)
    return [(k, DESIGNS[i % len(DESIGNS)], EXPOSURES_MS[(i // len(DESIGNS)) % 2], int(rng.integers(1, 2**31)))
            for i, k in enumerate(kinds)]


def run_case(i: int, kind: str, design: str, exposure_ms: float, case_seed: int, base: ScenarioConfig,
             frames: int, classes: dict, options: DiagnoseOptions, tmp: Path) -> dict:
    rng = np.random.default_rng(case_seed)
    if design == "two_exposures":
        exposure_ms = EXPOSURES_MS[0]  # the declared exposure; odd frames are taken at EXPOSURES_MS[1]
    cfg = design_scenario(base, design, exposure_ms, rng, frames, case_seed)
    sigma = cfg.noise.centroid_sigma_px
    drawn, excluded, invisible = [], [], []
    ctx = None
    if kind != "null":
        ctx = design_context(cfg, design)
        if kind == "out_of_library":
            d = draw_effect(OUT_OF_LIBRARY[rng.integers(len(OUT_OF_LIBRARY))], ctx, sigma, rng)
            d["multiple"] = d["multiple"]
            drawn.append(d)
        else:
            usable = {n for n, c in classes.items() if cfg.gyro.enabled or {"image", "time"} & set(c.channels)}
            names = list(rng.permutation(sorted(usable)))
            want = 2 if kind == "two" else 1
            while names and len(drawn) < want:
                name = names.pop()
                try:
                    d = draw_effect(classes[name], ctx, sigma, rng)
                except (ValueError, TypeError) as exc:  # an effect whose model fails on this design: skip, say so
                    excluded.append({"name": name, "reason": f"{type(exc).__name__}: {exc}"})
                    continue
                if d["value"] is None:  # invisible in this design (absorbed by the attitude): draw another
                    invisible.append(name)
                    continue
                d["aliases"] = aliases_in_design(d["name"], d["param_index"], ctx, classes)
                drawn.append(d)
    entries = [{"kind": d["name"], "params": {d["param"]: d["value"]}} for d in drawn if d["value"] is not None]
    rec = tmp / f"case{i}.mcap"
    # The out-of-library perturbations are registered only while this case runs (the recording's
    # metadata names them, and the runner validates that scenario); the diagnosis never sees them
    # as candidates (excluded by name) and is given the base scenario only.
    with registered(OUT_OF_LIBRARY):
        truth_cfg = validate(ScenarioConfig, {**cfg.model_dump(mode="json"), "effects": entries}, "<bench truth>")
        if design == "two_exposures":
            simulate_mixed(truth_cfg, rec)
        else:
            simulate_to_log(truth_cfg, rec, show_progress=False)
        t_start = time.perf_counter()
        try:
            result, _ = diagnose_recording(rec, cfg, None, options, sim_source="bench base scenario",
                                           exclude_effects=[c.name for c in OUT_OF_LIBRARY])
        except UserError as exc:  # the pipeline could not identify stars: reported, not hidden
            rec.unlink(missing_ok=True)
            return {"case": i, "kind": kind, "design": design, "exposure_ms": exposure_ms, "truth": drawn,
                    "outcome": "identification_failed", "error": str(exc), "named": [], "ambiguous": [],
                    "mismatch": None, "unexplained": None, "seconds": time.perf_counter() - t_start,
                    "multiple": min((d["multiple"] for d in drawn if d.get("multiple")), default=None),
                    "heldout_rms_before_px": None, "heldout_rms_after_px": None,
                    "excluded_effects": excluded, "invisible_in_design": invisible}
        seconds = time.perf_counter() - t_start
    rec.unlink(missing_ok=True)
    row = score_case(i, kind, design, exposure_ms, drawn, result, seconds)
    row["excluded_effects"] = excluded
    row["invisible_in_design"] = invisible
    return row


def make_nuisance_cases(seed: int, per_nuisance: int) -> list[tuple[str, str, float, int]]:
    """``per_nuisance`` recordings of every nuisance (:data:`NUISANCES`): (nuisance, design, exposure, seed)."""
    rng = np.random.default_rng([seed, 13])
    plan = []
    for k, name in enumerate(NUISANCES):
        for j in range(per_nuisance):
            i = k * per_nuisance + j
            plan.append((name, NUISANCE_DESIGNS[i % len(NUISANCE_DESIGNS)], EXPOSURES_MS[(i // len(NUISANCE_DESIGNS)) % 2],
                         int(rng.integers(1, 2**31))))
    return plan


def run_nuisance_case(i: int, nuisance: str, design: str, exposure_ms: float, case_seed: int, base: ScenarioConfig,
                      frames: int, options: DiagnoseOptions, tmp: Path) -> dict:
    """One nuisance-mismatch null: named effects are false names; a stated noise factor is allowed."""
    rng = np.random.default_rng(case_seed)
    cfg = design_scenario(base, design, exposure_ms, rng, frames, case_seed)
    rec = tmp / f"nuisance{i}.mcap"
    size = nuisance_recording(cfg, nuisance, rec, rng)
    start = time.perf_counter()
    try:
        result, _ = diagnose_recording(rec, cfg, None, options, sim_source="bench base scenario")
    except UserError as exc:
        rec.unlink(missing_ok=True)
        return {"case": i, "kind": "nuisance", "nuisance": nuisance, "design": design, "exposure_ms": exposure_ms,
                "outcome": "identification_failed", "error": str(exc), "named": [], "seconds": time.perf_counter() - start}
    seconds = time.perf_counter() - start
    rec.unlink(missing_ok=True)
    noise = result.get("noise_check") or {}
    named = [e["name"] for e in result["effects"]]
    return {"case": i, "kind": "nuisance", "nuisance": nuisance, "design": design, "exposure_ms": exposure_ms,
            "size_over_sigma": size, "named": named, "ambiguous": [a["candidates"] for a in result["ambiguous"]],
            "unexplained": result["unexplained_systematic"]["present"], "mismatch": result["mismatch"],
            "noise_factor": noise.get("factor"), "noise_factor_sigma": noise.get("factor_sigma"),
            "noise_factor_applied": noise.get("applied"), "seconds": seconds,
            "outcome": "false_name" if named else "correct"}


def score_case(i, kind, design, exposure_ms, drawn, result, seconds) -> dict:
    named = [e["name"] for e in result["effects"]]
    amb = [set(a["candidates"]) for a in result["ambiguous"]]
    row = {"case": i, "kind": kind, "design": design, "exposure_ms": exposure_ms, "truth": drawn, "named": named,
           "ambiguous": [sorted(a) for a in amb], "mismatch": result["mismatch"],
           "unexplained": result["unexplained_systematic"]["present"], "seconds": seconds,
           "heldout_rms_before_px": result["heldout_rms_before_px"], "heldout_rms_after_px": result["heldout_rms_after_px"]}
    if kind == "null":
        row["outcome"] = "false_discovery" if result["mismatch"] else "correct"
        return row
    if kind == "out_of_library":
        confident = [e["name"] for e in result["effects"] if e.get("confidence") == "confident"]
        row["multiple"] = drawn[0]["multiple"]
        row["outcome"] = ("unexplained" if row["unexplained"] else ("confident_wrong_name" if confident else "missed"))
        desc = result["unexplained_systematic"].get("description")
        row["description"] = None if desc is None else {k: desc.get(k) for k in ("shape", "axis", "coordinate", "position_px",
                                                                                "between_px", "period_px", "text")}
        row["located"] = located(drawn[0]["name"], desc)
        return row
    visible = [d for d in drawn if d["value"] is not None]
    row["multiple"] = min((d["multiple"] for d in visible), default=None)
    if not visible:
        row["outcome"] = "invisible_in_design"
        row["false_name"] = bool(named)
        return row
    truth = {d["name"] for d in visible}
    admissible = set(truth)
    separable = True
    for d in visible:
        admissible |= set(d.get("aliases", []))
        separable &= not d.get("aliases")
    row["separable"] = separable
    wrong = [n for n in named if n not in admissible]
    if separable:
        ok = set(named) == truth
    else:
        ok = all((d["name"] in named) or any(d["name"] in a for a in amb) or
                 (any(al in named for al in d.get("aliases", [])) and any(d["name"] in a for a in amb))
                 for d in visible) and not wrong
    row["wrong_names"] = wrong
    row["outcome"] = "correct" if ok else ("wrong_name" if wrong else "missed")
    errs = []
    for d in visible:
        e = next((e for e in result["effects"] if e["name"] == d["name"]), None)
        if e is None:
            continue
        p = e["params"][d["param"]]
        default = next(pp.default for pp in EFFECTS[d["name"]].parameters if pp.name == d["param"])
        truth_delta = d["value"] - default
        err = p["value"] - d["value"]
        errs.append({"effect": d["name"], "rel_error": abs(err) / abs(truth_delta) if truth_delta else None,
                     "pull": float(err / p["sigma"]) if p["sigma"] and np.isfinite(p["sigma"]) else None,
                     "within_1sigma": bool(abs(err) <= p["sigma"]), "within_2sigma": bool(abs(err) <= 2 * p["sigma"])})
    row["param_errors"] = errs
    return row


RIPPLE_PERIOD_TOLERANCE = 0.1  # a described ripple period within 10 % of the truth locates it


def located(name: str, desc: dict | None) -> bool:
    """Whether the description of an out-of-library case places its perturbation correctly: the
    stitch step as a step of y across the column the dies meet at (inside the reported gap between
    stars), the ripple as a ripple of x along the rows with its period within 10 %."""
    if desc is None:
        return False
    if name == StitchStep.name:
        lo, hi = desc["between_px"] if desc.get("between_px") else (np.inf, -np.inf)
        cx = (BASE_WIDTH_PX - 1) / 2.0
        return desc["shape"] == "step" and desc["axis"] == "y" and desc["coordinate"] == "column" and lo <= cx <= hi
    if name == ColumnRipple.name:
        return (desc["shape"] == "ripple" and desc["axis"] == "x" and desc["coordinate"] == "row"
                and abs(desc["period_px"] / RIPPLE_PERIOD_PX - 1.0) <= RIPPLE_PERIOD_TOLERANCE)
    return False


# ----------------------------------------------------------------------------------- aggregate
def snr_bin(m) -> str | None:
    if m is None:
        return None
    for lo, hi in SNR_BINS:
        if lo <= m < hi or (hi == SNR_BINS[-1][1] and m >= lo):
            return f"{lo:g}-{hi:g}x"
    return "<0.3x" if m < SNR_BINS[0][0] else None


def aggregate(rows: list[dict]) -> dict:
    def frac(a, b):
        return None if b == 0 else a / b

    lib = [r for r in rows if r["kind"] in ("library", "two") and r["outcome"] not in ("invisible_in_design", "identification_failed")]
    main = [r for r in rows if r["kind"] != "nuisance"]
    bins = {}
    for r in lib:
        b = snr_bin(r["multiple"])
        bins.setdefault(b, []).append(r)
    by_bin = []
    for lo, hi in SNR_BINS:
        key = f"{lo:g}-{hi:g}x"
        rs = bins.get(key, [])
        errs = [e for r in rs if r["outcome"] == "correct" for e in r.get("param_errors", []) if e["rel_error"] is not None]
        gain = [r["heldout_rms_before_px"] - r["heldout_rms_after_px"] for r in rs
                if r["heldout_rms_before_px"] is not None and r["heldout_rms_after_px"] is not None]
        by_bin.append({
            "bin": key, "cases": len(rs),
            "correct": frac(sum(r["outcome"] == "correct" for r in rs), len(rs)),
            "wrong_name": frac(sum(r["outcome"] == "wrong_name" for r in rs), len(rs)),
            "missed": frac(sum(r["outcome"] == "missed" for r in rs), len(rs)),
            "not_separable": sum(not r.get("separable", True) for r in rs),
            "median_param_error": float(np.median([e["rel_error"] for e in errs])) if errs else None,
            "coverage_1sigma": frac(sum(e["within_1sigma"] for e in errs), len(errs)),
            "coverage_2sigma": frac(sum(e["within_2sigma"] for e in errs), len(errs)),
            "median_heldout_gain_px": float(np.median(gain)) if gain else None,
        })
    above = [r for r in lib if r["multiple"] is not None and r["multiple"] >= 3.0]
    by_design = []
    for d in DESIGNS:
        rs = [r for r in lib if r["design"] == d]
        ab = [r for r in rs if r["multiple"] is not None and r["multiple"] >= 3.0]
        nl = [r for r in rows if r["kind"] == "null" and r["design"] == d]
        by_design.append({"design": d, "gyro": d in GYRO_DESIGNS, "cases": len(rs), "cases_above_3x": len(ab),
                          "correct_above_3x": frac(sum(r["outcome"] == "correct" for r in ab), len(ab)),
                          "nulls": len(nl), "false_discoveries": sum(r["outcome"] == "false_discovery" for r in nl),
                          "named_effects": sorted({d2["name"] for r in rs if r["outcome"] == "correct" for d2 in r["truth"]})})
    # the effects only the gyro / attitude-increment channel can show
    gyro_only = ("gyro_bias", "gyro_scale", "time_offset", "exposure_smear")
    by_gyro_effect = []
    for name in gyro_only:
        rs = [r for r in lib if any(d2["name"] == name and d2["value"] is not None for d2 in r["truth"])]
        ab = [r for r in rs if r["multiple"] is not None and r["multiple"] >= 3.0]
        by_gyro_effect.append({"effect": name, "cases": len(rs), "cases_above_3x": len(ab),
                               "correct_above_3x": frac(sum(r["outcome"] == "correct" for r in ab), len(ab)),
                               "designs": sorted({r["design"] for r in rs})})
    errs_all = [e for r in lib if r["outcome"] == "correct" for e in r.get("param_errors", []) if e["rel_error"] is not None]
    errs3 = [e for r in above if r["outcome"] == "correct" for e in r.get("param_errors", []) if e["rel_error"] is not None]
    nulls = [r for r in rows if r["kind"] == "null"]
    nuis = [r for r in rows if r["kind"] == "nuisance" and r["outcome"] != "identification_failed"]
    ool = [r for r in rows if r["kind"] == "out_of_library"]
    return {
        "cases": len(main),
        "nulls": len(nulls),
        "null_fraction": frac(len(nulls), len(main)),
        "nuisance_cases": len(nuis),
        "nuisance_false_name_rate": frac(sum(r["outcome"] == "false_name" for r in nuis), len(nuis)),
        "by_nuisance": nuisance_rows(nuis),
        "false_discovery_rate_nulls": frac(sum(r["outcome"] == "false_discovery" for r in nulls), len(nulls)),
        "correct_naming_above_3x": frac(sum(r["outcome"] == "correct" for r in above), len(above)),
        "cases_above_3x": len(above),
        "wrong_name_above_3x": frac(sum(r["outcome"] == "wrong_name" for r in above), len(above)),
        "median_param_error_above_3x": float(np.median([e["rel_error"] for e in errs3])) if errs3 else None,
        "coverage_1sigma_above_3x": frac(sum(e["within_1sigma"] for e in errs3), len(errs3)),
        "parameters_above_3x": len(errs3),
        "coverage_1sigma_all": frac(sum(e["within_1sigma"] for e in errs_all), len(errs_all)),
        "coverage_2sigma_all": frac(sum(e["within_2sigma"] for e in errs_all), len(errs_all)),
        "parameters_all": len(errs_all),
        "coverage_2sigma_above_3x": frac(sum(e["within_2sigma"] for e in errs3), len(errs3)),
        **out_of_library_summary(ool),
        "invisible_in_design": sum(r["outcome"] == "invisible_in_design" for r in rows),
        "max_seconds_per_diagnosis": float(np.max([r["seconds"] for r in rows])) if rows else None,
        "identification_failed": sum(r["outcome"] == "identification_failed" for r in rows),
        "draws_invisible_in_their_design": sorted({n for r in rows for n in r.get("invisible_in_design", [])}),
        "by_snr_bin": by_bin,
        "by_design": by_design,
        "gyro_channel_effects": by_gyro_effect,
        "median_seconds_per_diagnosis": float(np.median([r["seconds"] for r in rows])) if rows else None,
    }


def out_of_library_summary(ool: list[dict]) -> dict:
    """Out-of-library scores: reported as unexplained, confidently misnamed, located by the description."""
    def frac(a, b):
        return None if b == 0 else a / b

    vis = [r for r in ool if r.get("multiple") is not None and r["multiple"] >= 3.0]
    return {"out_of_library_cases": len(ool), "out_of_library_cases_above_3x": len(vis),
            "out_of_library_unexplained": frac(sum(r["outcome"] == "unexplained" for r in ool), len(ool)),
            "out_of_library_unexplained_above_3x": frac(sum(r["outcome"] == "unexplained" for r in vis), len(vis)),
            "out_of_library_confident_wrong_name": frac(sum(r["outcome"] == "confident_wrong_name" for r in ool), len(ool)),
            "out_of_library_located": frac(sum(bool(r.get("located")) for r in ool), len(ool)),
            "out_of_library_located_above_3x": frac(sum(bool(r.get("located")) for r in vis), len(vis))}


def nuisance_rows(rows: list[dict]) -> list[dict]:
    """Per nuisance: recordings, false names, unexplained systematics and the stated noise factors."""
    out = []
    for name, what in NUISANCES.items():
        rs = [r for r in rows if r["nuisance"] == name]
        factors = [r["noise_factor"] for r in rs if r.get("noise_factor_applied")]
        out.append({"nuisance": name, "what": what, "cases": len(rs),
                    "size_over_sigma": [round(r["size_over_sigma"], 2) for r in rs if r.get("size_over_sigma") is not None],
                    "false_names": sum(r["outcome"] == "false_name" for r in rs),
                    "named": sorted({n for r in rs for n in r["named"]}),
                    "unexplained": sum(bool(r.get("unexplained")) for r in rs),
                    "noise_factor_stated": len(factors),
                    "noise_factors": [round(f, 3) for f in factors]})
    return out


TARGETS = {"correct_naming_above_3x": (">=", 0.95), "false_discovery_rate_nulls": ("<=", 0.05),
           "nuisance_false_name_rate": ("<=", 0.0), "out_of_library_located_above_3x": (">=", 0.9),
           "median_param_error_above_3x": ("<=", 0.05)}


def run_benchmark(quick: bool = False, seed: int = 1, n_cases: int | None = None, show_progress: bool = True) -> dict:
    """Run the benchmark (module doc); quick: 12 cases of 10 frames, fewer bootstrap resamples."""
    frames = 10 if quick else 20
    n_cases = n_cases or (12 if quick else 120)
    # stability refits are part of the diagnose report but not scored here: off, for speed
    options = DiagnoseOptions(n_boot=10 if quick else 40, stability=False, seed=seed)
    base = base_scenario(frames)
    classes = candidate_classes()
    plan = make_cases(n_cases, seed, frames)
    nuisance_plan = make_nuisance_cases(seed, 1 if quick else 2)
    from threadpoolctl import threadpool_limits

    rows = []
    with threadpool_limits(limits=1, user_api="blas"), tempfile.TemporaryDirectory() as tmp, \
            progress_bar("bench discrepancy", len(plan) + len(nuisance_plan), show_progress) as advance:
        for i, (kind, design, exposure, cseed) in enumerate(plan):
            rows.append(run_case(i, kind, design, exposure, cseed, base, frames, classes, options, Path(tmp)))
            advance()
        for i, (nuisance, design, exposure, cseed) in enumerate(nuisance_plan, start=len(plan)):
            rows.append(run_nuisance_case(i, nuisance, design, exposure, cseed, base, frames, options, Path(tmp)))
            advance()
    summary = aggregate(rows)
    summary["targets"] = {k: {"target": f"{op} {v}", "value": summary[k],
                              "met": None if summary[k] is None else (summary[k] >= v if op == ">=" else summary[k] <= v)}
                          for k, (op, v) in TARGETS.items()}
    command = f"rollingstar bench discrepancy{' --quick' if quick else ''} --seed {seed}" + (f" --cases {n_cases}" if n_cases not in (12, 120) else "")
    return {"command": command, "quick": quick, "seed": seed, "frames": frames, "library": sorted(classes),
            "summary": summary, "cases": rows}


def format_markdown(result: dict) -> str:
    s = result["summary"]

    def f(v, fmt="{:.3g}"):
        return "n/a" if v is None else (fmt.format(v) if isinstance(v, float) else str(v))

    lines = [f"Command: `{result['command']}` ({s['cases']} recordings of {result['frames']} frames, "
             f"{s['nulls']} nulls, {s['out_of_library_cases']} out-of-library)", "",
             "| SNR bin (x detection limit) | cases | correct | wrong name | missed | not separable | median param error | 1-sigma coverage | 2-sigma coverage | median held-out gain (px) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for b in s["by_snr_bin"]:
        lines.append(f"| {b['bin']} | {b['cases']} | {f(b['correct'])} | {f(b['wrong_name'])} | {f(b['missed'])} | {b['not_separable']} | "
                     f"{f(b['median_param_error'])} | {f(b['coverage_1sigma'])} | {f(b['coverage_2sigma'])} | {f(b['median_heldout_gain_px'])} |")
    if "by_design" in s:
        lines += ["", "| motion design | gyro | library cases | above 3x | correct above 3x | nulls | false discoveries | correctly named effects |",
                  "|---|---|---|---|---|---|---|---|"]
        for d in s["by_design"]:
            lines.append(f"| {d['design']} | {'yes' if d['gyro'] else 'no'} | {d['cases']} | {d['cases_above_3x']} | "
                         f"{f(d['correct_above_3x'])} | {d['nulls']} | {d['false_discoveries']} | {', '.join(d['named_effects']) or '-'} |")
        lines += ["", "| effect (gyro / attitude-increment channel) | cases | above 3x | correct above 3x | designs |",
                  "|---|---|---|---|---|"]
        for g in s["gyro_channel_effects"]:
            lines.append(f"| {g['effect']} | {g['cases']} | {g['cases_above_3x']} | {f(g['correct_above_3x'])} | {', '.join(g['designs']) or '-'} |")
    if s.get("by_nuisance"):
        lines += ["", f"Nuisance-mismatch nulls ({s['nuisance_cases']} recordings; the simulation is the base scenario):", "",
                  "| nuisance | what differs | recordings | RMS added / stated sigma | false names | named | unexplained systematic | noise factor stated |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in s["by_nuisance"]:
            size = ", ".join(f"{v:.2f}" for v in r.get("size_over_sigma", [])) or "-"
            lines.append(f"| {r['nuisance']} | {r['what']} | {r['cases']} | {size} | {r['false_names']} | {', '.join(r['named']) or '-'} | "
                         f"{r['unexplained']} | {', '.join(f'{v:.2f}' for v in r['noise_factors']) or '-'} |")
    lines += ["", "| target | required | measured | met |", "|---|---|---|---|"]
    for k, t in s["targets"].items():
        lines.append(f"| {k} | {t['target']} | {f(t['value'])} | {t['met']} |")
    if "coverage_1sigma_all" in s:
        lines += ["", f"- interval coverage over every correctly named parameter (all bins, {s['parameters_all']}): "
                  f"{f(s['coverage_1sigma_all'])} within 1 sigma, {f(s['coverage_2sigma_all'])} within 2 sigma; above 3x "
                  f"({s['parameters_above_3x']}): {f(s['coverage_1sigma_above_3x'])} and {f(s['coverage_2sigma_above_3x'])}"]
    lines += ["", f"- out-of-library recordings reported as an unexplained systematic: {f(s['out_of_library_unexplained'])} "
              f"(above 3x: {f(s['out_of_library_unexplained_above_3x'])}); confidently given a wrong library name: "
              f"{f(s['out_of_library_confident_wrong_name'])}",
              f"- out-of-library perturbation located by the description (shape, axis, and the step's column or the "
              f"ripple's period): {f(s.get('out_of_library_located'))} of all, {f(s.get('out_of_library_located_above_3x'))} "
              f"of the {s.get('out_of_library_cases_above_3x', 'n/a')} above 3x",
              f"- effects drawn but invisible in their design (signature absorbed by the attitude, redrawn): "
              f"{', '.join(s['draws_invisible_in_their_design']) or 'none'}",
              f"- recordings whose stars the pipeline could not identify (excluded above): {s['identification_failed']}",
              f"- diagnosis time per recording (wall, one thread): median {f(s['median_seconds_per_diagnosis'])} s, "
              f"maximum {f(s.get('max_seconds_per_diagnosis'))} s"]
    return "\n".join(lines)
