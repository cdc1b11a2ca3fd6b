"""``rollingstar diagnose``: locate a simulation/recording mismatch, name it, model it, show the fit improve.

Orchestrates :mod:`rollingstar.estimators.diagnosis` (see docs/diagnosis.md for the method):

0. Run the pipeline on the recording (identified stars, a first attitude per frame) and split off
   held-out frames (single images: held-out stars) *before* any fit.
1. Locate: predict every training observation with the simulation scenario at the refitted
   attitude and rate, chi-square per dof against the recording's noise, residual structure by
   covariate, channel, field region and time span (:mod:`rollingstar.estimators.diagnosis.residuals`).
2. Name: project the attitude out of the residuals and of every library effect's signature,
   screen, forward-stepwise BIC, bootstrap inclusion, aliases (:mod:`rollingstar.estimators.diagnosis.selection`).
3. Model: nonlinear refit with uncertainties and stability (:mod:`rollingstar.estimators.diagnosis.refit`);
   test what is left against generic bases (:mod:`rollingstar.estimators.diagnosis.catchall`).
4. Show the fit improve: residual RMS and chi2/dof before and after on training and held-out data;
   re-simulate with the input and the updated model and compare residual distributions
   (:mod:`rollingstar.estimators.diagnosis.resimulate`).

With ``/gyro`` in the recording, attitude increments against the gyro are a second residual
channel throughout (:mod:`rollingstar.estimators.diagnosis.gyro_channel`); the final parameters and sigmas
come from a joint fit with the rates tied to the attitudes (:func:`rollingstar.estimators.diagnosis.refit.joint_refit`).
"""
from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.config import parse_yaml, to_yaml, validate
from rollingstar.errors import UserError
from rollingstar.estimators.diagnosis import (
    catchall,
    gyro_channel,
    residuals,
    resimulate,
    selection,
)
from rollingstar.estimators.diagnosis import refit as refit_mod
from rollingstar.estimators.diagnosis.library import (
    Candidate,
    library,
    separating_experiment,
)
from rollingstar.estimators.diagnosis.observations import (
    Observations,
    fit_attitudes,
    fit_nuisance,
    frame_reference_times,
)
from rollingstar.logs.reader import LogReader
from rollingstar.logs.topics import TOPIC_EST_ATTITUDE, TOPIC_EST_STARS
from rollingstar.pipelines.config import PipelineConfig, load_pipeline
from rollingstar.sensors import build
from rollingstar.sensors.scenario import ScenarioConfig, load_scenario

# Tracking gate 30 px: the second frame is predicted without a rate (the identifier extrapolates
# from two estimates), and 2 deg/s over a 130 ms frame period moves stars ~20 px on a 4380 px focal
# length; the refine pass (2 px) then drops mismatches.
DEFAULT_PIPELINE_YAML = """
name: diagnose-default
stages:
  - {kind: cog, params: {threshold_sigma: 5.0}}
  - {kind: tracking, params: {gate_px: 30.0}}
  - {kind: none}
  - {kind: quest}
"""
FALLBACK_PIPELINE_YAML = """
name: diagnose-lost-in-space
stages:
  - {kind: cog, params: {threshold_sigma: 5.0}}
  - {kind: lost-in-space, params: {tracking: {gate_px: 30.0}}}
  - {kind: none}
  - {kind: quest}
"""
HELDOUT_FRACTION = 0.25
MIN_STARS_PER_FRAME = 4
CHI2_Z_LIMIT = 5.0
MIN_INCLUSION = 0.5
SAME_STAR_RAD = 1e-3  # a catalogue id names the recorded star only if their directions agree this well
OUTLIER_SIGMA = 30.0  # far beyond noise, below the identifier's refine gate: a wrong match, not physics


@dataclass(frozen=True)
class DiagnoseOptions:
    heldout_fraction: float = HELDOUT_FRACTION
    seed: int = 0
    n_boot: int = 50
    min_delta_bic: float = selection.MIN_DELTA_BIC
    stability: bool = True
    resimulate: bool = True
    show_progress: bool = False


# ---------------------------------------------------------------------------------------- loading
def recording_scenario(recording: Path) -> ScenarioConfig:
    return LogReader(recording).scenario("pass --sim SCENARIO.yaml")


def default_pipeline() -> PipelineConfig:
    return validate(PipelineConfig, parse_yaml(DEFAULT_PIPELINE_YAML, "<diagnose default pipeline>"), "<diagnose default pipeline>")


def fallback_pipeline() -> PipelineConfig:
    return validate(PipelineConfig, parse_yaml(FALLBACK_PIPELINE_YAML, "<diagnose lost-in-space pipeline>"),
                    "<diagnose lost-in-space pipeline>")


def run_and_read(recording: Path, pipeline: PipelineConfig, source: str, show_progress: bool):
    """Run ``pipeline`` on the recording; per frame the identified stars and the first valid attitude."""
    from rollingstar.pipelines.runner import run_pipeline

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "diagnose_run.mcap"
        run_pipeline(recording, pipeline, out, pipeline_source=source, show_progress=show_progress)
        reader = LogReader(out)
        stars = {k: (s["t0_ns"], s) for k, s in reader.stars(TOPIC_EST_STARS).items()}
        att = {}
        for m in reader.messages([TOPIC_EST_ATTITUDE]):
            d = m.data
            if d.get("valid") and d.get("q") is not None and int(d["frame"]) not in att:
                q = d["q"]
                att[int(d["frame"])] = np.array([q["x"], q["y"], q["z"], q["w"]], dtype=float)
    return stars, att


def build_observations(stars: dict, att: dict, scenario: ScenarioConfig, catalog) -> tuple[Observations, Rotation]:
    """Flatten the identified stars of frames with a valid attitude into :class:`Observations`."""
    timing = build.build_timing(scenario)
    frames = sorted(k for k in stars if k in att)
    cols = {k: [] for k in ("frame", "x", "y", "sigma", "t_ns", "u", "cat", "flux")}
    f_index, f_t0, f_q, f_exp = [], [], [], []
    for k in frames:
        t0, c = stars[k]
        cat = c.get("catalog_id", np.full(len(c["x"]), -1))
        ref = c.get("ref_icrs", np.full((len(c["x"]), 3), np.nan))
        ok = (cat >= 0) & np.all(np.isfinite(ref), axis=1) & np.isfinite(c["x"]) & np.isfinite(c["y"])
        if ok.sum() < MIN_STARS_PER_FRAME:
            continue
        j = len(f_index)
        f_index.append(k)
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
        sig = c.get("sigma_px", np.full(len(c["x"]), np.nan))[ok]
        cols["sigma"].append(sig)
        cols["t_ns"].append(c["t_ns"][ok])
        cols["u"].append(ref[ok])
        cols["cat"].append(cat[ok])
        cols["flux"].append(c.get("flux", np.full(len(c["x"]), np.nan))[ok])
    if not f_index:
        raise UserError("no frame has a valid attitude and at least "
                        f"{MIN_STARS_PER_FRAME} identified stars: nothing to diagnose (check the pipeline and the sensor model)")
    cat_ids = np.concatenate(cols["cat"])
    u_all = np.concatenate(cols["u"])
    idx = catalog.index_of(cat_ids) if catalog is not None else np.full(cat_ids.size, -1)
    if catalog is not None:
        # the ids must name the same star (imported data may use another catalogue's ids): same direction
        same = np.einsum("ij,ij->i", catalog.unit_icrs[np.maximum(idx, 0)], u_all) > np.cos(SAME_STAR_RAD)
        idx = np.where(same, idx, -1)
    mag = np.where(idx >= 0, catalog.magnitude[np.maximum(idx, 0)] if catalog is not None else np.nan, np.nan)
    pm = None
    if catalog is not None and getattr(catalog, "pm_rad_yr", None) is not None and np.all(idx >= 0):
        pm = catalog.pm_rad_yr[idx]  # every star is a catalogue star with a known proper motion
    flux = np.concatenate(cols["flux"])
    with np.errstate(divide="ignore", invalid="ignore"):
        mag = np.where(np.isfinite(mag), mag, -2.5 * np.log10(flux))  # instrumental magnitude when uncatalogued
    sigma = np.concatenate(cols["sigma"])
    source = "recording (StarTable.sigma_px)"
    bad = ~(np.isfinite(sigma) & (sigma > 0))
    if bad.any():
        s = scenario.noise.centroid_sigma_px if scenario.level == "centroid" else 0.0
        if s > 0:
            sigma = np.where(bad, s, sigma)
            source = "scenario noise.centroid_sigma_px" if bad.all() else "recording, scenario where missing"
        else:
            sigma = np.where(bad, np.nan, sigma)
            source = "estimated"
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
        pm_rad_yr=pm, exposure_ns=expo)
    return obs, Rotation.from_quat(np.asarray(f_q))


def read_gyro(recording: Path, scenario: ScenarioConfig):
    """The recording's gyro samples (``/gyro``) as :class:`gyro_channel.GyroData`, None without any.

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
    return gyro_channel.GyroData(t[keep], w[keep], float(arw))


def scenario_moves(scenario: ScenarioConfig) -> bool:
    """Whether the scenario declares any motion (rate, acceleration, segments with motion, jitter).

    A recording of a still sensor (or of unrelated scenes, such as imported single images) gets no
    rate from its attitude sequence: consecutive frames are not one trajectory.
    """
    m = scenario.motion
    vals = list(m.rate_deg_s) + list(m.accel_deg_s2)
    for seg in m.segments:
        vals += list(seg.rate_deg_s) + list(seg.accel_deg_s2)
    return any(v != 0 for v in vals) or bool(m.jitter)


def split_heldout(obs: Observations, fraction: float, seed: int) -> tuple[np.ndarray, str]:
    """Held-out mask decided before any fit: whole frames (>= 4 frames), else stars within frames."""
    rng = np.random.default_rng([seed, 7])
    if obs.n_frames >= 4:
        n_out = max(1, int(round(fraction * obs.n_frames)))
        out_frames = rng.choice(obs.n_frames, size=n_out, replace=False)
        return np.isin(obs.frame, out_frames), "frames"
    mask = np.zeros(obs.n, dtype=bool)
    perm = rng.permutation(obs.n)
    # per frame keep at least MIN_STARS_PER_FRAME training stars
    for k in range(obs.n_frames):
        idx = perm[obs.frame[perm] == k]
        n_out = min(int(round(fraction * idx.size)), max(idx.size - MIN_STARS_PER_FRAME, 0))
        mask[idx[:n_out]] = True
    return mask, "stars"


# ------------------------------------------------------------------------------------ the analysis
def _estimate_sigma(obs: Observations, scenario, catalog_free_pred) -> Observations:
    from dataclasses import replace

    r = np.concatenate([obs.x - catalog_free_pred.x, obs.y - catalog_free_pred.y])
    s = 1.4826 * np.median(np.abs(r - np.median(r)))
    return replace(obs, sigma=np.where(np.isfinite(obs.sigma), obs.sigma, max(s, 1e-6)),
                   sigma_source="estimated from the residual scatter (MAD): the chi-square test is then uninformative")


def _signatures(obs, pred, cands: dict[str, Candidate], base_effects, mask):
    """Whitened, prior-scaled, attitude-projected signatures of every testable candidate (train rows)."""
    sig = obs.sigma
    aj = pred.att_jac / sig[:, None, None]
    groups, raw, untestable = {}, {}, []
    chan = obs.channel
    for name, c in cands.items():
        why = c.testable(pred.ctx, gyro=chan is not None)
        if why is not None:
            untestable.append({"name": name, "reason": why})
            continue
        try:
            j = c.signature(pred.ctx, base_effects, pred.exposure_ns)
        except (ValueError, TypeError, NotImplementedError) as exc:
            untestable.append({"name": name, "reason": f"signature not available: {exc}"})
            continue
        j = j / sig[:, None, None] * c.scales[None, None, :]
        p = selection.project_frames(obs.frame, obs.n_frames, aj, j)
        groups[name] = np.concatenate([p[mask, 0, :], p[mask, 1, :]])  # rows: all x residuals, then all y
        raw[name] = np.concatenate([j[mask, 0, :], j[mask, 1, :]])
        if chan is not None:  # then the attitude-increment rows (gyro_channel module doc)
            inc = gyro_channel.image_effect_signature(gyro_channel.absorbed_rotations(obs.frame, obs.n_frames, aj, j))
            if "gyro" in c.channels:
                inc = inc + gyro_channel.gyro_signature(c.instance(), chan.gyro, obs.t_ref_ns) * c.scales[None, None, :]
            g = chan.whiten(inc)
            groups[name] = np.concatenate([groups[name], g])
            raw[name] = np.concatenate([raw[name], g])
    return groups, raw, untestable


def _whitened_residual(obs, pred, mask):
    aj = pred.att_jac / obs.sigma[:, None, None]
    r = np.stack([(obs.x - pred.x) / obs.sigma, (obs.y - pred.y) / obs.sigma], axis=-1)[:, :, None]
    p = selection.project_frames(obs.frame, obs.n_frames, aj, r)[:, :, 0]
    return np.concatenate([p[mask, 0], p[mask, 1], gyro_channel.channel_rows(obs, pred)])


def _ks(obs, pred0, pred1, m) -> dict | None:
    """Kolmogorov-Smirnov test of the held-out residuals / sigma against N(0, 1), before and after.

    (The attitude of held-out frames is fitted to their own stars, which narrows the distribution
    slightly: 3 of 2 n dof per frame; the comparison before/after is what matters.)
    """
    from scipy import stats

    if m.sum() < 5:
        return None
    out = {}
    for key, p in (("before", pred0), ("after", pred1)):
        r = np.concatenate([(obs.x - p.x)[m] / obs.sigma[m], (obs.y - p.y)[m] / obs.sigma[m]])
        ks = stats.kstest(r, "norm")
        out[key] = {"ks_statistic": float(ks.statistic), "p_value": float(ks.pvalue), "std": float(np.std(r))}
    return out


def _chi2_sf(chi2: float, dof: int) -> float:
    from scipy import stats

    return float(stats.chi2.sf(chi2, dof))


def _heldout_chi2(obs, pred, heldout, frames_fitted: int, chan_out) -> list[tuple[str, float, int]]:
    """Chi-square and dof of the held-out data under ``pred``: image rows, and gyro pairs touching
    a held-out frame (when the recording has a gyro)."""
    out = []
    if heldout.any():
        c = float(np.sum(((obs.x - pred.x)[heldout] ** 2 + (obs.y - pred.y)[heldout] ** 2) / obs.sigma[heldout] ** 2))
        out.append(("image", c, int(2 * heldout.sum() - 3 * frames_fitted)))
    if chan_out is not None:
        e = chan_out.residual(pred.nuisance.attitude, obs.t_ref_ns, pred.effects)
        out.append(("gyro increments", float(e @ e), chan_out.rows))
    return out


def _rms(obs, pred, m):
    if not m.any():
        return None
    return float(np.sqrt(np.mean(((obs.x - pred.x)[m] ** 2 + (obs.y - pred.y)[m] ** 2) / 2)))


def _chi2_dof(obs, pred, m, frames_fitted: int):
    if not m.any():
        return None
    c = np.sum(((obs.x - pred.x)[m] ** 2 + (obs.y - pred.y)[m] ** 2) / obs.sigma[m] ** 2)
    return float(c / max(2 * m.sum() - 3 * frames_fitted, 1))


def diagnose(recording: str | Path, scenario: ScenarioConfig | None = None, pipeline: PipelineConfig | None = None,
             options: DiagnoseOptions = DiagnoseOptions(), pipeline_source: str = "<diagnose default pipeline>",
             sim_source: str | None = None, exclude_effects=()) -> tuple[dict, dict]:
    """Diagnose ``recording`` against ``scenario`` (default: the model its metadata declares).

    Returns ``(result, internals)``: ``result`` is the JSON-able report; ``internals`` holds the
    observations, predictions and masks the report's plots need. BLAS runs single-threaded here:
    the matrices are small (thousands x tens) and a threaded BLAS on a busy machine was measured
    16x slower on them (80 ms vs 5 ms for a 1078 x 32 SVD on 2 loaded cores).
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _diagnose(recording, scenario, pipeline, options, pipeline_source, sim_source, exclude_effects)


def _diagnose(recording, scenario, pipeline, options, pipeline_source, sim_source, exclude_effects):
    recording = Path(recording)
    if not recording.exists():
        raise UserError(f"{recording}: recording not found")
    if scenario is None:
        scenario = recording_scenario(recording)
        sim_source = sim_source or f"{recording} (metadata 'scenario')"
    camera = build.build_camera(scenario)
    timing = build.build_timing(scenario)
    base_effects = tuple(build.build_effects(scenario))
    try:
        catalog = build.build_catalog(scenario, camera)
    except UserError:
        catalog = None
    user_pipeline = pipeline is not None
    pipeline = pipeline or default_pipeline()
    stars, att = run_and_read(recording, pipeline, pipeline_source, options.show_progress)
    if not user_pipeline and len(att) < 0.5 * max(len(stars), 1):
        # tracking from the declared initial attitude lost lock (e.g. a large boresight offset):
        # identify without a prior (lost in space), then track
        pipeline, pipeline_source = fallback_pipeline(), "<diagnose lost-in-space pipeline>"
        stars, att = run_and_read(recording, pipeline, pipeline_source, options.show_progress)
    obs, att0 = build_observations(stars, att, scenario, catalog)

    # ---- held-out split, before any fit
    heldout, unit = split_heldout(obs, options.heldout_fraction, options.seed)
    from dataclasses import replace

    obs = replace(obs, heldout=heldout)
    train = ~heldout
    frame_has_train = np.bincount(obs.frame[train], minlength=obs.n_frames) > 0
    att_mask = train | ~frame_has_train[obs.frame]  # held-out frames fit their own attitude (nuisance)

    # ---- 1. locate
    moving = scenario_moves(scenario)
    nuis0, pred0 = fit_nuisance(obs, att0, camera, timing, base_effects, att_mask, moving)
    if obs.sigma_source == "estimated":
        obs = _estimate_sigma(obs, scenario, pred0)
        nuis0, pred0 = fit_nuisance(obs, att0, camera, timing, base_effects, att_mask, moving)
    # gross outliers (misidentified stars: the tracking refine gate is 2 px = 40 sigma at 0.05 px)
    far = np.hypot(obs.x - pred0.x, obs.y - pred0.y) > OUTLIER_SIGMA * obs.sigma
    n_rejected = int(far.sum())
    if n_rejected:
        obs = obs.take(~far)
        train, heldout = ~obs.heldout, obs.heldout
        frame_has_train = np.bincount(obs.frame[train], minlength=obs.n_frames) > 0
        att_mask = train | ~frame_has_train[obs.frame]
        nuis0, pred0 = fit_nuisance(obs, att0, camera, timing, base_effects, att_mask, moving)
    n_train_frames = int(frame_has_train.sum())
    n_out_frames = int((~frame_has_train).sum())
    # second channel: attitude increments of consecutive training frames against the gyro
    gyro_data = read_gyro(recording, scenario) if unit == "frames" else None
    chan = gyro_channel.build_channel(gyro_data, obs, pred0, frame_has_train, att_mask)
    chan_out = gyro_channel.build_channel(gyro_data, obs, pred0, frame_has_train, att_mask, heldout=True)
    if chan is not None:
        obs = replace(obs, channel=chan)
        nuis0, pred0 = fit_nuisance(obs, nuis0, camera, timing, base_effects, att_mask, moving)
    gyro_before = None if chan is None else float(np.sum(gyro_channel.channel_rows(obs, pred0) ** 2))
    located_full = residuals.locate(obs, pred0, camera, train, 3 * n_train_frames)
    located = {k: v for k, v in located_full.items() if not k.startswith("_")}
    located["structure"] = located["structure"][:12]

    # ---- 2. name (linearised at the simulation as given) and 3. model (nonlinear), iterated
    cands = library(exclude=exclude_effects)
    blocks_all = obs.frame if unit == "frames" else np.arange(obs.n)
    blocks = np.concatenate([blocks_all[train], blocks_all[train], np.repeat(chan.pairs, 3) if chan is not None else []])
    problem0, untestable = _problem_at(obs, pred0, cands, base_effects, train, blocks)
    first = selection.forward_stepwise(problem0, options.min_delta_bic)
    names = [st["name"] for st in first]
    names, fit, nuis1, pred1, rounds = _select_nonlinear(obs, nuis0, camera, timing, base_effects, cands, names, train,
                                                         att_mask, blocks, options, moving)
    chosen = [cands[n] for n in names]
    effects_final = refit_mod.chain_with(base_effects, chosen, fit["thetas"])
    # the selection statistics on the problem linearised at the final model, selected effects added back
    problem, _ = _problem_at(obs, pred1, cands, effects_final, train, blocks,
                             add_back={c.name: (th - c.defaults) / c.scales for c, th in zip(chosen, fit["thetas"])})
    sel = selection.select(problem, n_boot=options.n_boot, seed=options.seed, min_delta_bic=options.min_delta_bic)
    n_res = 2 * int(train.sum()) + (chan.rows if chan is not None else 0)
    drop_one = _drop_one_delta_bic(obs, nuis0, camera, timing, base_effects, chosen, fit, train, n_res)
    # an effect is named only when it also wins the majority of bootstrap resamples of the problem
    # linearised at the fitted model; otherwise it is a weak candidate, reported but not named
    # (inclusion pooled over the candidates the data cannot tell from it: those split the votes)
    alias_of = {n: [h for h in problem.groups if h != n and n in problem.groups
                    and selection.canonical_correlation(selection.design(problem, [n]), selection.design(problem, [h]))
                    > selection.CORR_LIMIT] for n in names}
    pooled = {n: selection.pooled_inclusion(sel["bootstrap_sets"], n, alias_of[n]) for n in names}
    weak = [n for n in names if (options.n_boot > 0 and pooled[n] < MIN_INCLUSION)
            or drop_one.get(n, 0.0) < options.min_delta_bic]  # or no longer earning its place nonlinearly
    if weak:
        names = [n for n in names if n not in weak]
        chosen = [cands[n] for n in names]
        fit = _refit_chi2(obs, nuis0, camera, timing, base_effects, chosen, train)
        effects_final = refit_mod.chain_with(base_effects, chosen, fit["thetas"])
        nuis1, pred1 = fit_nuisance(obs, nuis0, camera, timing, effects_final, att_mask, moving)
        weak_rows = [{"name": n, "delta_bic_nonlinear": drop_one.get(n), "inclusion_probability": sel["inclusion"].get(n),
                      "inclusion_with_aliases": pooled[n]} for n in weak]
        drop_one = _drop_one_delta_bic(obs, nuis0, camera, timing, base_effects, chosen, fit, train, n_res)
    else:
        weak_rows = []
    if chosen:
        # final estimate and covariance with the rates tied to the attitudes (refit.joint_refit):
        # the variable-projection refit holds the rates fixed and its sigmas ignore their error
        jf = refit_mod.joint_refit(obs, fit["nuisance"], camera, timing, base_effects, chosen, fit["thetas"], train, moving)
        if jf["cost"] is not None:
            fit = {**fit, "thetas": jf["thetas"], "sigmas": jf["sigmas"], "corr": jf["corr"], "joint_success": jf["success"]}
            effects_final = refit_mod.chain_with(base_effects, chosen, fit["thetas"])
            nuis1, pred1 = fit_nuisance(obs, jf["nuisance"], camera, timing, effects_final, att_mask, moving)
    sel["selected"] = names
    screened = [row["name"] for row in sel["screen"]]
    sel["ambiguous"] = selection.ambiguities(problem, names, screened)
    sel["correlations"] = {g: {h: selection.canonical_correlation(selection.design(problem, [g]), selection.design(problem, [h]))
                               for h in screened if h != g} for g in names if g in problem.groups}
    stab = refit_mod.stability(obs, nuis1, pred1, camera, timing, base_effects, chosen, fit["thetas"], train) \
        if (chosen and options.stability) else []
    bases = catchall.generic_bases(obs, pred1, camera)
    aj = pred1.att_jac / obs.sigma[:, None, None]
    gproj = {}
    for name, g in bases.items():
        p = selection.project_frames(obs.frame, obs.n_frames, aj, g / obs.sigma[:, None, None])
        gproj[name] = np.concatenate([p[train, 0, :], p[train, 1, :], np.zeros((chan.rows if chan is not None else 0, p.shape[2]))])
    r1 = _whitened_residual(obs, pred1, train)
    left = catchall.residual_structure(r1, gproj)
    after_stats = residuals.chi2_stats(obs, pred1, train, 3 * n_train_frames + sum(len(c.parameters) for c in chosen))
    evidence = [row for row in left if row["significant"]]
    if after_stats["z"] > CHI2_Z_LIMIT and obs.sigma_source.startswith(("recording", "scenario")):
        evidence.append({"basis": "total chi-square", "delta_chi2": after_stats["chi2"] - after_stats["dof"],
                         "dof": after_stats["dof"], "z": after_stats["z"], "significant": True})
    # held-out data the final model leaves far outside its noise is a mismatch even when the
    # training data show nothing (e.g. the only frames that could show an effect were held out)
    known_noise = obs.sigma_source.startswith(("recording", "scenario"))
    for label, chi2, dof in _heldout_chi2(obs, pred1, heldout, n_out_frames if unit == "frames" else 0, chan_out):
        z = residuals.z_from_sf(_chi2_sf(chi2, dof)) if dof > 0 else 0.0
        if known_noise and z > CHI2_Z_LIMIT:
            evidence.append({"basis": f"held-out chi-square ({label})", "delta_chi2": chi2 - dof, "dof": dof,
                             "z": float(z), "significant": True})
    unexplained = bool(evidence)

    # ---- 4. show the fit improve
    result = {
        "recording": str(recording),
        "sim": sim_source or scenario.name,
        "pipeline": pipeline.name,
        "mismatch": bool(chosen) or unexplained,
        "verdict": None,
        "noise": {"sigma_px_median": float(np.median(obs.sigma)), "source": obs.sigma_source},
        "rejected_outliers": n_rejected,
        "split": {"unit": unit, "frames": obs.n_frames, "train_frames": n_train_frames, "heldout_frames": n_out_frames,
                  "train_observations": int(train.sum()), "heldout_observations": int(heldout.sum())},
        "located": located,
        "screen": sel["screen"],
        "selection_steps": sel["steps"],
        "selection_rounds": rounds,
        "weak_candidates": weak_rows,
        "effects": [],
        "ambiguous": [],
        "absorbed_by_attitude": [],
        "not_testable": untestable,
        "unexplained_systematic": {"present": unexplained, "evidence": evidence, "tests": left},
        "train_rms_before_px": _rms(obs, pred0, train),
        "train_rms_after_px": _rms(obs, pred1, train),
        "heldout_rms_before_px": _rms(obs, pred0, heldout),
        "heldout_rms_after_px": _rms(obs, pred1, heldout),
        "train_chi2_dof_before": _chi2_dof(obs, pred0, train, n_train_frames),
        "train_chi2_dof_after": _chi2_dof(obs, pred1, train, n_train_frames),
        "heldout_chi2_dof_before": _chi2_dof(obs, pred0, heldout, n_out_frames if unit == "frames" else 0),
        "heldout_chi2_dof_after": _chi2_dof(obs, pred1, heldout, n_out_frames if unit == "frames" else 0),
        "heldout_residual_distribution": _ks(obs, pred0, pred1, heldout),
        "gyro_channel": None if chan is None else {
            "pairs": int(chan.pairs.size), "rows": chan.rows, "arw_rad_sqrt_s": chan.gyro.arw_rad_sqrt_s,
            "chi2_dof_before": gyro_before / chan.rows,
            "chi2_dof_after": float(np.sum(gyro_channel.channel_rows(obs, pred1) ** 2)) / chan.rows,
            "heldout_pairs": 0 if chan_out is None else int(chan_out.pairs.size),
            "heldout_chi2_dof_before": None if chan_out is None else float(np.sum(chan_out.residual(
                pred0.nuisance.attitude, obs.t_ref_ns, pred0.effects) ** 2)) / chan_out.rows,
            "heldout_chi2_dof_after": None if chan_out is None else float(np.sum(chan_out.residual(
                pred1.nuisance.attitude, obs.t_ref_ns, pred1.effects) ** 2)) / chan_out.rows},
        "stability": stab,
        "refit_success": fit["success"],
        "resimulation": resimulate.resimulation_check(
            obs, {"before": (base_effects, nuis0, pred0), "after": (effects_final, nuis1, pred1)}, camera, timing,
            att_mask, moving, options.seed) if options.resimulate else None,
    }
    for name in problem.absorbed:
        c = cands[name]
        declared = c.alias_of("attitude") or c.alias_of("rate")
        if declared is None and "time" in c.channels and not moving:
            text = "a recording in which the tracker turns (constant rate, rate reversal): time effects move stars only with motion"
        else:
            text = separating_experiment(c, "attitude")
        result["absorbed_by_attitude"].append({"name": name, "separating_experiment": text})
    step_bic = drop_one
    # a named model must hold up on data the fit never saw: held-out chi-square must drop
    hb, ha = result["heldout_chi2_dof_before"], result["heldout_chi2_dof_after"]
    if hb is not None and ha is not None:  # chi-square sums over held-out image rows and gyro pairs
        n_img = max(2 * int(heldout.sum()) - (3 * n_out_frames if unit == "frames" else 0), 1)
        hb, ha = hb * n_img, ha * n_img
        g = result["gyro_channel"]
        if g is not None and g["heldout_chi2_dof_before"] is not None:
            hb += g["heldout_chi2_dof_before"] * 3 * g["heldout_pairs"]
            ha += g["heldout_chi2_dof_after"] * 3 * g["heldout_pairs"]
    heldout_confirms = hb is None or ha is None or ha < hb
    result["heldout_confirms"] = bool(heldout_confirms)
    k = 0
    for c, th, sg in zip(chosen, fit["thetas"], fit["sigmas"]):
        params = {p.name: {"value": float(v), "sigma": float(s), "unit": p.unit} for p, v, s in zip(c.parameters, th, sg)}
        checked = [{"name": h, "corr": float(v)} for h, v in sorted(sel["correlations"].get(c.name, {}).items(), key=lambda kv: -kv[1])]
        unstable = [s for s in stab if s["effect"] == c.name and s["stable"] is False]
        at_bound = [p.name for p, v in zip(c.parameters, th) if v <= p.bounds[0] + 1e-9 * (p.bounds[1] - p.bounds[0])
                    or v >= p.bounds[1] - 1e-9 * (p.bounds[1] - p.bounds[0])]
        result["effects"].append({
            "name": c.name, "params": params, "delta_bic": step_bic.get(c.name),
            "inclusion_probability": sel["inclusion"].get(c.name), "inclusion_with_aliases": pooled.get(c.name), "aliases_checked": checked,
            "declared_aliases": [getattr(a, "other", str(a)) for a in c.aliases],
            "explanation": c.explanation, "stable": not unstable, "at_bound": at_bound,
            "confidence": "tentative" if (unexplained or unstable or at_bound or not heldout_confirms) else "confident",
            "tentative_because": [why for why, flag in (("residual structure left", unexplained),
                                                       ("unstable across subsets", bool(unstable)),
                                                       ("parameter at its bound", bool(at_bound)),
                                                       ("no held-out improvement", not heldout_confirms)) if flag],
        })
        k += len(c.parameters)
    seen = set()
    for a in sel["ambiguous"]:
        key = tuple(sorted((a["selected"], a["alternative"])))
        if key in seen:
            continue
        seen.add(key)
        result["ambiguous"].append({"candidates": list(key), "corr": a["corr"], "delta_bic_swap": a["delta_bic_swap"],
                                    "separating_experiment": separating_experiment(cands[key[0]], cands[key[1]])})
    thetas = fit["thetas"]
    result["rejected_on_heldout"] = []
    if not heldout_confirms and result["effects"]:
        # a claim must hold up on data the fit never saw: a model that does not lower the held-out
        # chi-square is not named (its effects become weak candidates; the "after" numbers above
        # describe that rejected model, and scenario_updated.yaml leaves it out)
        result["rejected_on_heldout"] = [e["name"] for e in result["effects"]]
        for e in result["effects"]:
            result["weak_candidates"].append({"name": e["name"], "delta_bic_nonlinear": e["delta_bic"],
                                              "inclusion_probability": e["inclusion_probability"],
                                              "inclusion_with_aliases": e.get("inclusion_with_aliases"),
                                              "reason": "no held-out improvement", "params": e["params"]})
        result["effects"], result["ambiguous"] = [], []
        result["mismatch"] = unexplained
        chosen, thetas = [], []
    result["verdict"] = _verdict(result)
    internals = {"obs": obs, "pred_before": pred0, "pred_after": pred1, "train": train, "heldout": heldout,
                 "camera": camera, "scenario": scenario, "chosen": chosen, "thetas": thetas,
                 "located_full": located_full, "base_effects": base_effects}
    return result, internals


def _problem_at(obs, pred, cands, chain, mask, blocks, add_back=None):
    """The projected, whitened linear problem at the model ``chain`` (``pred`` its prediction).

    ``add_back`` (name -> prior-scaled parameter offsets) adds the selected effects' linear
    contributions back to the residual, so that the problem is the selection problem linearised
    at the fitted model (used for screening, bootstrap and aliases of the final model).
    """
    groups, raw, untestable = _signatures(obs, pred, cands, chain, mask)
    r = _whitened_residual(obs, pred, mask)
    for name, z in (add_back or {}).items():
        if name in groups:
            r = r + groups[name] @ z
    reach = {n: np.maximum(c.upper - c.defaults, c.defaults - c.lower) / c.scales for n, c in cands.items()}
    return selection.build_problem(r, groups, blocks, raw, reach), untestable


def _refit_chi2(obs, nuis0, camera, timing, base_effects, chosen, mask, warm=None):
    """Nonlinear refit; ``warm`` (name -> theta) starts parameters from a previous fit."""
    theta0 = None if not warm else [warm.get(c.name, c.defaults) for c in chosen]
    fit = refit_mod.refit(obs, nuis0, camera, timing, base_effects, chosen, mask, theta0)
    if fit["cost"] is None:  # no effect: chi2 of the effect-free model with the attitude refitted
        _, pred = fit_attitudes(obs, nuis0, camera, timing, base_effects, mask)
        fit["cost"] = float(np.sum(((obs.x - pred.x)[mask] ** 2 + (obs.y - pred.y)[mask] ** 2) / obs.sigma[mask] ** 2)
                            + np.sum(gyro_channel.channel_rows(obs, pred) ** 2))
    return fit


def _select_nonlinear(obs, nuis0, camera, timing, base_effects, cands, names, mask, att_mask, blocks, options,
                      moving: bool = True, max_rounds: int = 3):
    """Refine a linear selection with the nonlinear model: backward elimination by nonlinear
    delta BIC, then forward stepwise on the problem re-linearised at the fitted model; repeat
    until nothing changes. Returns names, the fit, the final nuisance/prediction and the rounds."""
    n_res = 2 * int(mask.sum()) + (obs.channel.rows if obs.channel is not None else 0)
    rounds = []
    for _ in range(max_rounds):
        chosen = [cands[n] for n in names]
        fit = _refit_chi2(obs, nuis0, camera, timing, base_effects, chosen, mask)
        changed = False
        while len(names) > 1:  # backward: drop the effect that earns least, if below the margin
            worst, worst_bic, worst_fit = None, None, None
            chosen = [cands[n] for n in names]  # the names fit["thetas"] belong to
            warm = {c.name: t for c, t in zip(chosen, fit["thetas"])}
            for n in names:
                rest = [cands[m] for m in names if m != n]
                f = _refit_chi2(obs, nuis0, camera, timing, base_effects, rest, mask, warm)
                d = f["cost"] - fit["cost"] - len(cands[n].parameters) * np.log(n_res)
                if worst_bic is None or d < worst_bic:
                    worst, worst_bic, worst_fit = n, d, f
            if worst_bic >= options.min_delta_bic:
                break
            names = [m for m in names if m != worst]
            fit, changed = worst_fit, True
            rounds.append({"dropped": worst, "delta_bic_nonlinear": float(worst_bic)})
        chosen = [cands[n] for n in names]
        chain = refit_mod.chain_with(base_effects, chosen, fit["thetas"])
        nuis1, pred1 = fit_nuisance(obs, nuis0, camera, timing, chain, att_mask, moving)
        others = {k: c for k, c in cands.items() if k not in names}
        prob, _ = _problem_at(obs, pred1, others, chain, mask, blocks)
        steps = selection.forward_stepwise(prob, options.min_delta_bic)
        if steps:
            names = names + [st["name"] for st in steps]
            changed = True
            rounds.append({"added": [st["name"] for st in steps]})
        if not changed:
            return names, fit, nuis1, pred1, rounds
    chosen = [cands[n] for n in names]
    fit = _refit_chi2(obs, nuis0, camera, timing, base_effects, chosen, mask)
    chain = refit_mod.chain_with(base_effects, chosen, fit["thetas"])
    nuis1, pred1 = fit_nuisance(obs, nuis0, camera, timing, chain, att_mask, moving)
    return names, fit, nuis1, pred1, rounds


def _drop_one_delta_bic(obs, nuis0, camera, timing, base_effects, chosen, fit, mask, n_res) -> dict:
    """Nonlinear delta BIC of each selected effect: chi2 without it minus chi2 with all, minus its penalty."""
    out = {}
    warm = {c.name: t for c, t in zip(chosen, fit["thetas"])}
    for c in chosen:
        rest = [d for d in chosen if d is not c]
        f = _refit_chi2(obs, nuis0, camera, timing, base_effects, rest, mask, warm)
        out[c.name] = float(f["cost"] - fit["cost"] - len(c.parameters) * np.log(n_res))
    return out


def _verdict(res: dict) -> str:
    names = [e["name"] for e in res["effects"]]
    rejected = res.get("rejected_on_heldout") or []
    note = f"; not named, no held-out improvement: {', '.join(rejected)}" if rejected else ""
    if not res["mismatch"]:
        return ("no mismatch: the simulation explains the recording within its noise "
                f"(chi2/dof {res['located']['chi2_dof']:.3f} over {res['split']['train_observations']} training stars){note}")
    parts = [note[2:]] if note else []
    if names:
        parts.append("named: " + ", ".join(names))
    for a in res["ambiguous"]:
        parts.append(f"cannot tell {a['candidates'][0]} from {a['candidates'][1]} (separate them with: {a['separating_experiment']})")
    if res["unexplained_systematic"]["present"]:
        ev = res["unexplained_systematic"]["evidence"]
        parts.append("unexplained systematic left (" + ", ".join(f"{e['basis']} z={e['z']:.1f}" for e in ev) + ")")
    return "; ".join(parts)


def updated_scenario(scenario: ScenarioConfig, chosen: list[Candidate], thetas: list[np.ndarray]) -> ScenarioConfig:
    """The input scenario with the selected effects enabled (a kind already present gets base + delta)."""
    effects = [dict(e.model_dump()) for e in scenario.effects]
    for c, th in zip(chosen, thetas):
        delta = {p.name: float(v - p.default) for p, v in zip(c.parameters, th)}
        for e in effects:
            if e["kind"] == c.name:
                e["params"] = {p.name: float(e["params"].get(p.name, p.default)) + delta[p.name] for p in c.parameters}
                break
        else:
            effects.append(c.scenario_entry(th))
    data = scenario.model_dump(mode="json")
    data["effects"] = effects
    data["description"] = (scenario.description + "\n" if scenario.description else "") + \
        "updated by rollingstar diagnose: " + ", ".join(c.name for c in chosen)
    return validate(ScenarioConfig, data, "<updated scenario>")


def run_diagnose(recording: Path, sim: Path | None, pipeline: Path | None, out_dir: Path | None,
                 options: DiagnoseOptions = DiagnoseOptions()) -> dict:
    """The CLI entry: load configs, diagnose, write the report directory; returns the JSON object."""
    scenario = load_scenario(sim) if sim is not None else None
    pipe = load_pipeline(pipeline) if pipeline is not None else None
    result, internals = diagnose(recording, scenario, pipe, options,
                                 pipeline_source=str(pipeline) if pipeline else "<diagnose default pipeline>",
                                 sim_source=str(sim) if sim else None)
    if out_dir is not None:
        from rollingstar.estimators.diagnosis.report import write_report

        upd = updated_scenario(internals["scenario"], internals["chosen"], internals["thetas"])
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "scenario_updated.yaml").write_text(to_yaml(upd))
        result["scenario_updated"] = str(out_dir / "scenario_updated.yaml")
        write_report(result, internals, out_dir)
    return result


def print_summary(result: dict, console) -> None:
    """Human-readable summary of a diagnosis on the terminal (rich)."""
    from rich.table import Table

    def f(v):
        return "n/a" if v is None else f"{v:.4g}"

    loc = result["located"]
    console.print(f"[bold]verdict:[/] {result['verdict']}", highlight=False)
    console.print(f"located: chi2/dof {f(loc['chi2_dof'])} (z {f(loc['z'])}), strongest covariate "
                  f"{loc['strongest_covariate']} / {loc['strongest_channel']} (z {f(loc['strongest_z'])})", highlight=False)
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
