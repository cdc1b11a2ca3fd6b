"""Reproduction of he2021a (He et al., Acta Photonica Sinica 50(3), 2021), section 3.

Sensor: Table 1 (``configs/scenarios/he2021a.yaml``: f = 24.09 mm, 5.5 um pixels, 1024 x 1024,
line delay 43.9 us, exposure 44.9 ms, frame period eq (5) 89.85 ms), Hipparcos stars (Hp <= 6)
around (ra, dec) = (83.8, -5.4) deg. Pipeline ``configs/pipelines/he2021a.yaml`` (kf-cv with
Q = 1e-4, time-domain to the middle row's exposure start, QUEST); the "before" branch is the same
frame's identified raw centroids.

Every experiment runs in two motion modes, side by side:

- ``drift`` -- the paper's own assumption, eq (19): every star moves at the same image velocity
  ``V = omega / IFOV`` (:class:`rollingstar.sensors.uniform_drift.UniformDriftSimulator`; attitude fixed, the
  whole image translates; stars labelled from the truth, as the paper's simulated stars are known).
- ``sky`` -- a rigid rotation of a pinhole camera over the real sky (the project simulator,
  tracking identification): image velocity depends on the position, so stars accelerate.

"Q = 1e-4" is read as the random-acceleration variance ``q`` in px^2/s^4 (eq 8 with t_f in s, as
the paper's px/s velocities imply); a Q sweep (full run only) shows the other readings.

Experiments (each trial = one simulator seed ``seed * 1000 + offset + trial``; noise differs):

- Figs 6-7 (filter, offset 0): centroid level, centroid noise variance R (px^2) = the filter's
  ``r``, 1 deg/s about camera x (Fig 6) and y (Fig 7), 100 frames. Error of each filtered star
  against the truth at the star's ``t_ns``; velocity against the true image velocity there
  (central difference of the truth, +-0.5 ms). Reported: RMS per axis over stars whose track is
  >= 50 frames old ("after 50 frames").
- Fig 10 (smear centroid, offset 500): image level (our PSF sigma 1 px), CoG centroids, rates about
  x. "Before": raw centroid vs the truth at the time it claims (mid-exposure of its row). "After":
  eqs (12)-(16) with the filtered velocity (``x' = x_f - v t_e / 2``) vs the truth at the exposure
  start of the star's row (the time ``x'`` refers to). RMS radial error, tracks >= 10 frames old,
  stars >= ``EDGE_PX`` inside the detector (a streak cut by the edge biases any centroid).
- Fig 12 (star-pair distance, offset 100): centroid level, rates 0-3 deg/s about x and y,
  R = 0.05 and 0.1. Pair distance of two identified stars minus the true distance at the pair's
  common time (mean of the two claimed times), as ``rollingstar.pipelines.evaluate``. "After": pairs of
  corrected stars whose tracks are >= 10 frames old. Statistics: RMS over all pair-frames ("per
  frame"), and RMS over pairs of each pair's mean error over its frames ("systematic").
- Figs 14-15 (attitude): the same runs, QUEST on five well-spread stars per frame (the one nearest
  the centre, then farthest-point; tracks >= 10 frames old; the same stars before and after),
  error per body axis vs the truth at the estimate's time (drift mode: see
  :func:`_attitude_error`); RMS over frames (arcsec).
- Q sweep (full run, offsets 700/800): filter error after 50 frames at 1 deg/s about x and the
  3 deg/s pair error after correction for q from 1e-4 to 10 px^2/s^4, both modes.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from rollingstar.config import CONFIGS
from rollingstar.estimators.data import FrameData, SensorContext, StarTable
from rollingstar.estimators.filters.kf_cv import KfCvFilter
from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.runner import build_stages
from rollingstar.pipelines.simulate import build_simulator
from rollingstar.pipelines.truth import true_positions
from rollingstar.progress import progress_bar
from rollingstar.sensors import build
from rollingstar.sensors.conventions import S_PER_NS, attitude_error_body_arcsec
from rollingstar.sensors.scenario import load_scenario
from rollingstar.sensors.uniform_drift import (
    UniformDriftSimulator,
    drift_reference_vectors,
    image_velocity_px_s,
)
from rollingstar.studies.reproduce import Row, paper_values

SCENARIO = CONFIGS / "scenarios" / "he2021a.yaml"
PIPELINE = CONFIGS / "pipelines" / "he2021a.yaml"
AGE_CONVERGED = 50  # "after 50 frames" (Figs 6-7)
AGE_MIN = 10  # tracks younger than this are excluded from the pair / smear statistics
N_ATT_STARS = 5  # "five stars" for the QUEST part
VEL_H_NS = 500_000
EDGE_PX = 12.0  # Fig 10: stars whose streak may be cut by the detector edge (3 deg/s: 10 px streak) are left out


@dataclass
class RunRecord:
    """Per-frame measurements of one simulated run (concatenated arrays)."""

    age: list = field(default_factory=list)  # track age per filtered star
    pos_err: list = field(default_factory=list)  # (m, 2) filtered - truth at t_ns
    vel_err: list = field(default_factory=list)  # (m, 2)
    smear_before: list = field(default_factory=list)  # radial, raw vs truth at t_ns
    smear_after: list = field(default_factory=list)  # radial, eqs 12-16 vs truth at row start
    pair_before: list = field(default_factory=list)  # (err, pair_key)
    pair_after: list = field(default_factory=list)
    att_before: list = field(default_factory=list)  # (3,) arcsec
    att_after: list = field(default_factory=list)


def _scenario(level: str, rate_xyz, r: float, seed: int, frames: int):
    cfg = load_scenario(SCENARIO)
    return cfg.model_copy(update={
        "level": level, "seed": seed, "frames": frames,
        "noise": cfg.noise.model_copy(update={"centroid_sigma_px": float(np.sqrt(r))}),
        "motion": cfg.motion.model_copy(update={"rate_deg_s": tuple(float(v) for v in rate_xyz)})})


def _stages(r: float, level: str, q: float | None):
    pipe = load_pipeline(PIPELINE)
    stages = build_stages(pipe, str(PIPELINE))
    out = []
    for st, cfg in zip(stages, pipe.stages):
        if isinstance(st, KfCvFilter):
            st = KfCvFilter(**{**cfg.params, "r": r, **({} if q is None else {"q": q})})
        if st.role == "centroider" and level == "centroid":
            continue
        out.append(st)
    return out


def build_run_simulator(cfg, mode: str):
    """The simulator of a run: ``"sky"`` (rigid rotation, real pinhole sky) or ``"drift"`` (eq 19)."""
    sim = build_simulator(cfg)
    if mode == "sky":
        if sim.effects:
            raise ValueError("the he2021a scenario must have no effects (the truth below is the plain pinhole)")
        return sim
    if mode != "drift":
        raise ValueError(f"mode must be 'sky' or 'drift', got {mode!r}")
    return UniformDriftSimulator(sim.camera, sim.timing, sim.catalog, build.initial_attitude(cfg),
                                 image_velocity_px_s(sim.camera, sim.motion), centroid_sigma_px=sim.centroid_sigma_px,
                                 image_model=sim.image_model, level=sim.level, seed=sim.seed)


def _truth_xy(sim, unit, t_ns):
    """True image positions (m, 2) of directions ``unit`` at ``t_ns``: drift truth, or the pinhole at the attitude then."""
    t = np.asarray(t_ns, dtype=np.int64)
    if isinstance(sim, UniformDriftSimulator):
        return sim.true_xy(unit, t)
    return np.column_stack(true_positions(sim.camera, (), sim.motion.attitude(t), unit, t))


def _identify_by_truth(stars: StarTable, truth, gate_px: float = 2.0) -> StarTable:
    """Drift mode: label detections with the nearest true star within ``gate_px`` (the paper's stars are known)."""
    cid = np.full(stars.n, -1, dtype=np.int64)
    ref = np.full((stars.n, 3), np.nan)
    if stars.n and len(truth):
        d, j = cKDTree(np.column_stack([truth.x, truth.y])).query(np.column_stack([stars.x, stars.y]))
        ok = d <= gate_px
        uniq, cnt = np.unique(j[ok], return_counts=True)
        ok &= ~np.isin(j, uniq[cnt > 1])
        cid[ok] = truth.catalog_id[j[ok]]
        ref[ok] = truth.unit_icrs[j[ok]]
    return stars.with_columns(catalog_id=cid, ref_icrs=ref)


def _pairs(stars: StarTable, sim, ok):
    idx = np.flatnonzero(ok)
    if idx.size < 2:
        return np.zeros(0), np.zeros((0, 2), dtype=np.int64)
    i, j = np.triu_indices(idx.size, k=1)
    a, b = idx[i], idx[j]
    tc = (stars.t_ns[a] + stars.t_ns[b]) // 2
    pa = _truth_xy(sim, stars.ref_icrs[a], tc)
    pb = _truth_xy(sim, stars.ref_icrs[b], tc)
    d_true = np.hypot(*(pa - pb).T)
    d_meas = np.hypot(stars.x[a] - stars.x[b], stars.y[a] - stars.y[b])
    keys = np.column_stack([stars.catalog_id[a], stars.catalog_id[b]])
    return d_meas - d_true, keys


def _spread_pick(x, y, n: int, cx: float, cy: float) -> np.ndarray:
    """``n`` well-spread stars: the one nearest the image centre, then repeatedly the one farthest from those picked."""
    pick = [int(np.argmin(np.hypot(x - cx, y - cy)))]
    dmin = np.hypot(x - x[pick[0]], y - y[pick[0]])
    while len(pick) < min(n, x.size):
        k = int(np.argmax(dmin))
        pick.append(k)
        dmin = np.minimum(dmin, np.hypot(x - x[k], y - y[k]))
    return np.array(pick, dtype=int)


def _attitude_error(quest, frame, stars, sim, mode: str):
    """QUEST on ``stars``; error (arcsec per body axis) against the truth at the estimate's own time.

    Drift mode has no rigid attitude: the references are the directions the stars' true positions
    at the estimate's time unproject to (:func:`drift_reference_vectors`), the truth the fixed attitude.
    """
    out = quest.process(frame.evolve(stars=stars, attitudes=()))
    est = out.attitudes[-1]
    if not est.valid:
        return None
    if mode == "drift":
        t = np.full(stars.n, est.t_ns, dtype=np.int64)
        R0 = sim.motion.attitude(t[:1])[0]
        xy = _truth_xy(sim, stars.ref_icrs, t)
        refs = drift_reference_vectors(sim.camera, R0, xy[:, 0], xy[:, 1])
        est = quest.process(frame.evolve(stars=stars.with_columns(ref_icrs=refs), attitudes=())).attitudes[-1]
        if not est.valid:
            return None
    truth = sim.motion.attitude(np.array([est.t_ns], dtype=np.int64))
    return attitude_error_body_arcsec(truth, Rotation.from_quat(est.q_xyzw[None]))[0]


def _quest(quest, frame, stars):
    out = quest.process(frame.evolve(stars=stars, attitudes=()))
    est = out.attitudes[-1]
    return est if est.valid else None


def simulate_run(level: str, rate_xyz, r: float, seed: int, frames: int, mode: str = "sky",
                 q: float | None = None) -> RunRecord:
    """Simulate one run and apply the he2021a pipeline frame by frame (see the module docstring).

    ``mode``: ``"sky"`` (real sky, rigid rotation, tracking identification) or ``"drift"`` (eq 19
    uniform image velocity, stars labelled from the truth). ``q``: the filter's random-acceleration
    variance (px^2/s^4); None: the pipeline config's.
    """
    cfg = _scenario(level, rate_xyz, r, seed, frames)
    sim = build_run_simulator(cfg, mode)
    ctx = SensorContext.from_scenario(cfg, catalog=sim.catalog)
    stages = _stages(r, level, q)
    for s in stages:
        s.setup(ctx)
    cen = [s for s in stages if s.role == "centroider"]
    ident = next(s for s in stages if s.role == "identifier")
    kf = next(s for s in stages if s.role == "filter")
    td = next(s for s in stages if s.role == "correction")
    quest = next(s for s in stages if s.role == "attitude")
    rec = RunRecord()
    ages: dict[int, int] = {}
    for k in range(frames):
        sf = sim.frame(k)
        if sf.image is not None:
            frame = FrameData(index=k, t0_ns=sf.t0_ns, image=sf.image)
            frame = cen[0].process(frame)
        else:
            c = sf.centroids
            frame = FrameData(index=k, t0_ns=sf.t0_ns, stars=StarTable.build(
                c["x"], c["y"], c["t_ns"], c["row_time_ns"], flux=c["flux"], sigma_px=np.full(len(c["x"]), np.sqrt(r))))
        if mode == "sky":
            frame = ident.process(frame)
        else:
            frame = frame.evolve(stars=_identify_by_truth(frame.stars, sf.truth))
        raw = frame.stars
        filt_frame = kf.process(frame)
        filt = filt_frame.stars
        corr_frame = td.process(filt_frame)
        corr = corr_frame.stars
        # track ages (frames since the track started; 0 = first sighting)
        ids = filt.catalog_id[filt.catalog_id >= 0]
        ages = {int(c): ages.get(int(c), -1) + 1 for c in ids}
        age = np.array([ages.get(int(c), -1) for c in filt.catalog_id], dtype=int)
        has_v = np.isfinite(filt.vx) & np.isfinite(filt.vy)
        if has_v.any():
            _record_filter(rec, sim, raw, filt, age, has_v)
        if level == "centroid":
            _record_pairs_and_attitude(rec, sim, quest, frame, raw, filt, corr, age >= AGE_MIN, has_v, mode)
        if mode == "sky":  # advance the tracking prior with the corrected solution (as the runner does)
            est = _quest(quest, corr_frame, corr.take(np.flatnonzero(corr.identified)))
            ident.update_prior(corr_frame.evolve(attitudes=(est,) if est is not None else ()))
    return rec


def _record_filter(rec: RunRecord, sim, raw: StarTable, filt: StarTable, age: np.ndarray, has_v: np.ndarray) -> None:
    """Filter accuracy (Figs 6-7) of the stars with a velocity, and the smear centroid (Fig 10):
    before = raw at its t_ns; after = eqs (12)-(16), which refer to the row's exposure start."""
    cam, timing = sim.camera, sim.timing
    unit = filt.ref_icrs[has_v]
    t = filt.t_ns[has_v]
    p = _truth_xy(sim, unit, t)
    v = (_truth_xy(sim, unit, t + VEL_H_NS) - _truth_xy(sim, unit, t - VEL_H_NS)) / (2 * VEL_H_NS * S_PER_NS)
    pe = np.column_stack([filt.x[has_v], filt.y[has_v]]) - p
    ve = np.column_stack([filt.vx[has_v], filt.vy[has_v]]) - v
    rec.age.append(age[has_v])
    rec.pos_err.append(pe)
    rec.vel_err.append(ve)
    old = (age[has_v] >= AGE_MIN) & cam.contains(p[:, 0], p[:, 1], margin_px=EDGE_PX)
    if old.any():
        raw_ok = raw.take(np.flatnonzero(has_v)[old])
        pr = _truth_xy(sim, raw_ok.ref_icrs, raw_ok.t_ns)
        rec.smear_before.append(np.hypot(raw_ok.x - pr[:, 0], raw_ok.y - pr[:, 1]))
        f_ok = filt.take(np.flatnonzero(has_v)[old])
        half_te = 0.5 * timing.exposure_ns * S_PER_NS  # eqs (12)-(16) with h_i = 1
        xs, ys = f_ok.x - f_ok.vx * half_te, f_ok.y - f_ok.vy * half_te
        ps = _truth_xy(sim, f_ok.ref_icrs, f_ok.t_ns - timing.exposure_ns // 2)
        rec.smear_after.append(np.hypot(xs - ps[:, 0], ys - ps[:, 1]))


def _record_pairs_and_attitude(rec: RunRecord, sim, quest, frame: FrameData, raw: StarTable, filt: StarTable,
                               corr: StarTable, converged: np.ndarray, has_v: np.ndarray, mode: str) -> None:
    """Star-pair distance errors (Fig 12) before and after correction, and the attitude error
    (Figs 14-15) of five well-spread stars with a converged track, the same stars before and after."""
    e, keys = _pairs(raw, sim, raw.catalog_id >= 0)
    rec.pair_before.append((e, keys))
    e, keys = _pairs(corr, sim, has_v & converged)
    rec.pair_after.append((e, keys))
    cand = np.flatnonzero(has_v & converged)
    if cand.size >= N_ATT_STARS:
        pick = cand[_spread_pick(filt.x[cand], filt.y[cand], N_ATT_STARS, sim.camera.cx, sim.camera.cy)]
        for stars, out in ((raw.take(pick), rec.att_before), (corr.take(pick), rec.att_after)):
            err = _attitude_error(quest, frame, stars, sim, mode)
            if err is not None:
                out.append(err)


def _cat(lst, width=None):
    if not lst:
        return np.zeros((0,) if width is None else (0, width))
    return np.concatenate(lst)


def _rms(a):
    a = np.asarray(a, dtype=float)
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a**2))) if a.size else None


def _pair_stats(recs: list[RunRecord], attr: str):
    """(per-frame RMS, systematic RMS) of pair errors over runs; pairs keyed per run."""
    per_frame, systematic = [], []
    for ri, rec in enumerate(recs):
        errs = [e for e, _ in getattr(rec, attr)]
        keys = [k for _, k in getattr(rec, attr)]
        if not errs or not sum(len(e) for e in errs):
            continue
        e = np.concatenate(errs)
        k = np.concatenate(keys)
        per_frame.append(e)
        _, inv = np.unique(k, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        sums = np.bincount(inv, weights=e)
        cnt = np.bincount(inv)
        systematic.append(sums[cnt >= 5] / cnt[cnt >= 5])
    return _rms(_cat(per_frame)), _rms(_cat(systematic)), (np.concatenate(per_frame) if per_frame else np.zeros(0))


MODES = ("drift", "sky")
MODE_LABEL = {"drift": "paper eq 19 (uniform image velocity)", "sky": "real sky (rigid rotation, pinhole)"}
Q_PAPER = 1e-4  # the paper's "Q = 1e-4", read as the random-acceleration variance in px^2/s^4
FRAME_PERIOD_S = 0.08985  # eq (5): t_e + N dt = 44.9 ms + 1024 * 43.9 us


def q_per_frame_reading() -> float:
    """"Q = 1e-4" read as px^2/frame^4 (a filter run with t_f = 1 frame), converted to px^2/s^4."""
    return Q_PAPER / FRAME_PERIOD_S**4


def _config(quick: bool) -> dict:
    if quick:
        return {"filter_trials": 2, "filter_axes": (0,), "rates": [0.0, 3.0], "pair_trials": 1, "frames": 100,
                "image_rates": [3.0], "image_trials": 1, "image_frames": 20, "r_values": [0.05], "sweep": None}
    return {"filter_trials": 10, "filter_axes": (0, 1), "rates": [0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0], "pair_trials": 4,
            "frames": 100, "image_rates": [0.0, 1.0, 2.0, 3.0], "image_trials": 1, "image_frames": 40,
            "r_values": [0.05, 0.1],
            "sweep": {"q": [1e-4, 1e-3, 1e-2, 0.1, 0.3, 1.0, q_per_frame_reading(), 10.0], "trials": 2}}


def _filter_stats(recs, age_min: int = AGE_CONVERGED):
    age = _cat([_cat(r.age) for r in recs])
    pe = _cat([_cat(r.pos_err, 2) for r in recs], 2)
    ve = _cat([_cat(r.vel_err, 2) for r in recs], 2)
    conv = age >= age_min
    return age, pe, ve, conv


def q_sweep(modes, qs, trials: int, seed: int, frames: int = 100, advance=lambda n=1: None) -> dict:
    """Filter error after 50 frames at 1 deg/s about x, and the 3 deg/s pair error after correction, vs q.

    Returns ``{(mode, q): (pos_rms (2,), vel_rms (2,), pair_after_systematic)}``; the same seeds for every q.
    """
    out = {}
    for mode in modes:
        for q in qs:
            recs = [simulate_run("centroid", [1.0, 0.0, 0.0], 0.05, seed * 1000 + 700 + t, frames, mode, q) for t in range(trials)]
            _, pe, ve, conv = _filter_stats(recs)
            advance(trials)
            prs = [simulate_run("centroid", [3.0, 0.0, 0.0], 0.05, seed * 1000 + 800 + t, frames, mode, q) for t in range(trials)]
            advance(trials)
            out[(mode, q)] = (np.sqrt(np.mean(pe[conv] ** 2, axis=0)), np.sqrt(np.mean(ve[conv] ** 2, axis=0)),
                              _pair_stats(prs, "pair_after")[1])
    return out


def _n_runs(cfg) -> int:
    n = len(MODES) * len(cfg["filter_axes"]) * cfg["filter_trials"]
    n += len(MODES) * len(cfg["image_rates"]) * cfg["image_trials"]
    n += len(MODES) * 2 * len(cfg["r_values"]) * len(cfg["rates"]) * cfg["pair_trials"]
    if cfg["sweep"]:
        n += len(MODES) * len(cfg["sweep"]["q"]) * 2 * cfg["sweep"]["trials"]
    return n


def run(quick: bool, plots_dir: Path | None, seed: int) -> list[Row]:
    start = time.perf_counter()
    paper = paper_values("he2021a")
    cfg = _config(quick)
    plot_data: dict = {"filter": {}, "smear": {}, "pair": {}, "att": {}, "sweep": {}}
    with progress_bar("he2021a runs", _n_runs(cfg)) as advance:
        rows = _filter_rows(cfg, seed, paper, plot_data, advance)
        rows += _smear_rows(cfg, seed, paper, plot_data, advance)
        rows += _pair_and_attitude_rows(cfg, seed, paper, plot_data, advance)
        if cfg["sweep"]:
            rows += _q_sweep_rows(cfg, seed, paper, plot_data, advance)
    elapsed = time.perf_counter() - start
    rows.append(Row("run time", "quick" if quick else "full", None, elapsed, "s", "", None, seed))
    if plots_dir is not None:
        _plots(Path(plots_dir), plot_data, cfg)
    return rows


def _filter_rows(cfg: dict, seed: int, paper: dict, plot_data: dict, advance) -> list[Row]:
    """Figs 6-7: the filter at 1 deg/s about x and y, R = 0.05."""
    pv = paper["position_error_after_50_frames"]
    vv = paper["velocity_deviation_after_50_frames"]
    rows = []
    for mode in MODES:
        for axis in cfg["filter_axes"]:
            rate = [0.0, 0.0, 0.0]
            rate[axis] = 1.0
            n = cfg["filter_trials"]
            recs = []
            for t in range(n):
                recs.append(simulate_run("centroid", rate, 0.05, seed * 1000 + t, cfg["frames"], mode))
                advance()
            age, pe, ve, conv = _filter_stats(recs)
            name = "xy"[axis]
            cond = f"{mode}: 1 deg/s about {name}, R=0.05 px^2, q={Q_PAPER:g} px^2/s^4, track age >= {AGE_CONVERGED} frames"
            per_trial = [_filter_stats([r]) for r in recs]
            for ax in (0, 1):
                spread = [_rms(p[c, ax]) for _, p, _, c in per_trial]
                rows.append(Row(f"filtered position error {'xy'[ax]} (RMS)", cond, pv["value"], _rms(pe[conv, ax]), "px",
                                pv["source"], n, seed, f"{int(conv.sum())} star-frames; per trial {_span(spread)}"))
            for ax in (0, 1):
                spread = [_rms(v[c, ax]) for _, _, v, c in per_trial]
                rows.append(Row(f"filtered velocity deviation v{'xy'[ax]} (RMS)", cond, vv["value"], _rms(ve[conv, ax]),
                                "px/s", vv["source"], n, seed, f"vs the true image velocity at the star's t_ns; per trial {_span(spread)}"))
            plot_data["filter"][(mode, name)] = (age, pe, ve)
    return rows


def _smear_rows(cfg: dict, seed: int, paper: dict, plot_data: dict, advance) -> list[Row]:
    """Fig 10: the smear centroid, image level, before and after eqs 12-16."""
    sm = paper["smear_centroid_error_before"], paper["smear_centroid_error_after"]
    rows = []
    for mode in MODES:
        for w in cfg["image_rates"]:
            recs = []
            for t in range(cfg["image_trials"]):
                recs.append(simulate_run("image", [w, 0.0, 0.0], 0.05, seed * 1000 + 500 + t, cfg["image_frames"], mode))
                advance()
            b = _rms(_cat([_cat(r.smear_before) for r in recs]))
            a = _rms(_cat([_cat(r.smear_after) for r in recs]))
            cond = f"{mode}: {w:g} deg/s about x, image level, {cfg['image_frames']} frames, track age >= {AGE_MIN}"
            rows.append(Row("smear centroid error before (RMS radial)", cond, sm[0]["value"], b, "px", sm[0]["source"],
                            cfg["image_trials"], seed, f"raw CoG vs truth at its claimed time; stars >= {EDGE_PX:g} px inside"))
            rows.append(Row("smear centroid error after eqs 12-16 (RMS radial)", cond, sm[1]["value"], a, "px",
                            sm[1]["source"], cfg["image_trials"], seed, "kf-cv + eqs 12-16 vs truth at the row's exposure start"))
            plot_data["smear"][(mode, w)] = (b, a)
    return rows


def _pair_and_attitude_rows(cfg: dict, seed: int, paper: dict, plot_data: dict, advance) -> list[Row]:
    """Fig 12 and Figs 14-15: pair distance and attitude, centroid level, per mode, axis, R and rate."""
    pp = paper["pair_distance_error_after"]
    pa = paper["attitude_error_after"]
    rows = []
    cache: dict = {}
    for mode in MODES:
        for axis in (0, 1):
            for r in cfg["r_values"]:
                for w in cfg["rates"]:
                    rate = [0.0, 0.0, 0.0]
                    rate[axis] = w
                    recs = []
                    for t in range(cfg["pair_trials"]):
                        key = (mode, tuple(rate), r, t)  # 0 deg/s about x and about y are the same run
                        if key not in cache:
                            cache[key] = simulate_run("centroid", rate, r, seed * 1000 + 100 + t, cfg["frames"], mode)
                        recs.append(cache[key])
                        advance()
                    cond = f"{mode}: {w:g} deg/s about {'xy'[axis]}, R={r:g} px^2"
                    pair_rows, plot_data["pair"][(mode, axis, r, w)] = _pair_rows(recs, cond, pp, seed)
                    rows += pair_rows
                    if r == cfg["r_values"][0]:
                        att_rows, plot_data["att"][(mode, axis, w)] = _attitude_rows(recs, cond, pa, seed)
                        rows += att_rows
    return rows


def _pair_rows(recs: list[RunRecord], cond: str, pp: dict, seed: int) -> tuple[list[Row], tuple]:
    """Pair distance error before (systematic) and after (per frame, systematic) correction; and
    (before per frame, before systematic, after per frame, after systematic) for the plots."""
    n = len(recs)
    bf, bs, _ = _pair_stats(recs, "pair_before")
    af, as_, _ = _pair_stats(recs, "pair_after")
    spread = [_pair_stats([x], "pair_after")[1] for x in recs]
    rows = [Row("pair distance error before, systematic (RMS)", cond, None, bs, "px", pp["source"], n,
                seed, f"RMS over pairs of each pair's mean error; per frame {_fmt(bf)}"),
            Row("pair distance error after, per frame (RMS)", cond, pp["value"], af, "px", pp["source"],
                n, seed, f"track age >= {AGE_MIN}"),
            Row("pair distance error after, systematic (RMS)", cond, pp["value"], as_, "px",
                pp["source"], n, seed, f"track age >= {AGE_MIN}; per trial {_span(spread)}")]
    return rows, (bf, bs, af, as_)


def _attitude_rows(recs: list[RunRecord], cond: str, pa: dict, seed: int) -> tuple[list[Row], tuple]:
    """Attitude error per body axis before and after correction; and (RMS before, RMS after) per axis for the plots."""
    n = len(recs)
    ab = _cat([np.asarray(rr.att_before).reshape(-1, 3) for rr in recs], 3)
    aa = _cat([np.asarray(rr.att_after).reshape(-1, 3) for rr in recs], 3)
    rows = []
    for ax, label in enumerate(("x", "y", "z")):
        rows.append(Row(f"attitude error {label} before (RMS, 5 stars)", cond, None, _rms(ab[:, ax]),
                        "arcsec", pa["source"], n, seed))
        spread = [_rms(np.asarray(rr.att_after).reshape(-1, 3)[:, ax]) for rr in recs]
        rows.append(Row(f"attitude error {label} after (RMS, 5 stars)", cond, pa["value"],
                        _rms(aa[:, ax]), "arcsec", pa["source"], n, seed,
                        f"frames with 5 tracks >= {AGE_MIN} frames old; mean |e| {_fmt(_mean_abs(aa[:, ax]))}; "
                        f"per trial {_span(spread)}"))
    plot = (np.sqrt(np.mean(ab**2, axis=0)) if len(ab) else np.full(3, np.nan),
            np.sqrt(np.mean(aa**2, axis=0)) if len(aa) else np.full(3, np.nan))
    return rows, plot


def _q_sweep_rows(cfg: dict, seed: int, paper: dict, plot_data: dict, advance) -> list[Row]:
    """The Q sweep (our addition: which reading of "Q = 1e-4" the paper's numbers need)."""
    pv = paper["position_error_after_50_frames"]
    vv = paper["velocity_deviation_after_50_frames"]
    pp = paper["pair_distance_error_after"]
    sw = q_sweep(MODES, cfg["sweep"]["q"], cfg["sweep"]["trials"], seed, cfg["frames"], advance)
    rows = []
    for (mode, q), (pos, vel, pair) in sw.items():
        cond = f"{mode}: q={q:.4g} px^2/s^4, 1 deg/s about x (filter) / 3 deg/s about x (pair), R=0.05 px^2"
        n = cfg["sweep"]["trials"]
        rows.append(Row("Q sweep: filtered position error (RMS over x, y)", cond, pv["value"],
                        _rms(pos), "px", pv["source"], n, seed, "track age >= 50"))
        rows.append(Row("Q sweep: filtered velocity deviation (RMS over x, y)", cond, vv["value"],
                        _rms(vel), "px/s", vv["source"], n, seed, "track age >= 50"))
        rows.append(Row("Q sweep: pair distance error after, systematic (RMS)", cond, pp["value"], pair, "px",
                        pp["source"], n, seed, f"track age >= {AGE_MIN}"))
    plot_data["sweep"] = sw
    return rows


def _fmt(v) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.3g}"


def _span(vals) -> str:
    vals = [v for v in vals if v is not None and np.isfinite(v)]
    return f"{min(vals):.3g}-{max(vals):.3g}" if vals else "-"


def _mean_abs(a):
    a = np.asarray(a, dtype=float)
    a = a[np.isfinite(a)]
    return float(np.mean(np.abs(a))) if a.size else None


COLORS = {"drift": "C0", "sky": "C3"}


def _pyplot():
    """matplotlib's pyplot on the Agg backend, imported only when plots are asked for."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _plots(d: Path, data: dict, cfg: dict) -> None:
    _plot_filter(d, data)
    if data["smear"]:
        _plot_smear(d, data)
    if data["pair"]:
        _plot_pairs(d, data, cfg)
    _plot_attitude(d, data)
    if data["sweep"]:
        _plot_q_sweep(d, data)


def _plot_filter(d: Path, data: dict) -> None:
    """Figs 6-7: filtered position and velocity error against the track age."""
    plt = _pyplot()
    for name, fig_no in (("x", 6), ("y", 7)):
        keys = [k for k in data["filter"] if k[1] == name]
        if not keys:
            continue
        fig, axs = plt.subplots(1, 2, figsize=(11, 4))
        for mode, _ in keys:
            age, pe, ve = data["filter"][(mode, name)]
            ages = np.arange(1, age.max() + 1) if age.size else np.zeros(0, int)
            pos = np.array([np.sqrt(np.mean(pe[age == a] ** 2)) if np.any(age == a) else np.nan for a in ages])
            vel = np.array([np.sqrt(np.mean(ve[age == a] ** 2)) if np.any(age == a) else np.nan for a in ages])
            axs[0].plot(ages, pos, c=COLORS[mode], label=MODE_LABEL[mode])
            axs[1].plot(ages, vel, c=COLORS[mode], label=MODE_LABEL[mode])
        axs[0].axhline(0.1, ls="--", c="k", lw=0.8, label="paper: < 0.1 after 50 frames")
        axs[1].axhline(0.02, ls="--", c="k", lw=0.8, label="paper: < 0.02 after 50 frames")
        for a in axs:
            a.axvline(AGE_CONVERGED, ls=":", c="grey", lw=0.8)
            a.legend(fontsize=7)
        axs[0].set(xlabel="track age (frames)", ylabel="RMS position error, x and y (px)", yscale="log",
                   title=f"Fig {fig_no}: 1 deg/s about {name}, R=0.05 px^2, q=1e-4 px^2/s^4")
        axs[1].set(xlabel="track age (frames)", ylabel="RMS velocity deviation, x and y (px/s)", yscale="log")
        fig.tight_layout()
        fig.savefig(d / f"he2021a_fig{fig_no}_filter_{name}.png", dpi=110)
        plt.close(fig)


def _plot_smear(d: Path, data: dict) -> None:
    """Fig 10: smear centroid error before and after eqs 12-16 against the rate."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for mode in MODES:
        w = sorted(k[1] for k in data["smear"] if k[0] == mode)
        ax.plot(w, [data["smear"][(mode, k)][0] for k in w], "o--", c=COLORS[mode], label=f"before, {mode}")
        ax.plot(w, [data["smear"][(mode, k)][1] for k in w], "s-", c=COLORS[mode], label=f"after eqs 12-16, {mode}")
    ax.axhline(0.06, ls="--", c="k", lw=0.8, label="paper: after < 0.06")
    ax.axhline(0.1, ls=":", c="k", lw=0.8, label="paper: before max > 0.1")
    ax.set(xlabel="rate about x (deg/s)", ylabel="RMS centroid error (px)", title="Fig 10: smear centroid (image level)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(d / "he2021a_fig10_smear.png", dpi=110)
    plt.close(fig)


def _plot_pairs(d: Path, data: dict, cfg: dict) -> None:
    """Fig 12: star-pair distance error (systematic) against the rate, about x and y."""
    plt = _pyplot()
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.5), sharey=True)
    for axis in (0, 1):
        for mode in MODES:
            for r, mk in zip(cfg["r_values"], ("o", "^")):
                w = sorted(k[3] for k in data["pair"] if k[:3] == (mode, axis, r))
                vals = np.array([data["pair"][(mode, axis, r, x)] for x in w], dtype=float)
                if r == cfg["r_values"][0]:
                    axs[axis].plot(w, vals[:, 1], mk + ":", c=COLORS[mode], alpha=0.6, label=f"before (syst.), {mode}")
                axs[axis].plot(w, vals[:, 3], mk + "-", c=COLORS[mode], label=f"after (syst.), {mode}, R={r:g}")
        axs[axis].axhline(0.1, ls="--", c="k", lw=0.8, label="paper: after < 0.1")
        axs[axis].set(xlabel=f"rate about {'xy'[axis]} (deg/s)", ylabel="pair distance error (px)", yscale="log",
                      title="Fig 12: star-pair distance, q=1e-4 px^2/s^4")
        axs[axis].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(d / "he2021a_fig12_pairs.png", dpi=110)
    plt.close(fig)


def _plot_attitude(d: Path, data: dict) -> None:
    """Figs 14-15: attitude error per body axis before and after correction against the rate."""
    plt = _pyplot()
    for axis, fig_no in ((0, 14), (1, 15)):
        fig, axs = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
        for i_m, mode in enumerate(MODES):
            w = sorted(k[2] for k in data["att"] if k[0] == mode and k[1] == axis)
            if not w:
                continue
            b = np.array([data["att"][(mode, axis, x)][0] for x in w])
            a = np.array([data["att"][(mode, axis, x)][1] for x in w])
            for i, lab in enumerate("xyz"):
                axs[i_m].plot(w, b[:, i], "o--", c=f"C{i}", label=f"{lab} before")
                axs[i_m].plot(w, a[:, i], "s-", c=f"C{i}", label=f"{lab} after")
            axs[i_m].axhline(10, ls=":", c="k", lw=0.8, label="paper: about 10")
            axs[i_m].set(xlabel=f"rate about {'xy'[axis]} (deg/s)", ylabel="RMS attitude error (arcsec)", yscale="log",
                         title=f"Fig {fig_no}: QUEST, 5 stars, {MODE_LABEL[mode]}")
            axs[i_m].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(d / f"he2021a_fig{fig_no}_attitude_{'xy'[axis]}.png", dpi=110)
        plt.close(fig)


def _plot_q_sweep(d: Path, data: dict) -> None:
    """The Q sweep: filter and pair errors against q, with the paper's bounds and both readings of Q."""
    plt = _pyplot()
    fig, axs = plt.subplots(1, 3, figsize=(14, 4))
    for mode in MODES:
        qs = sorted(q for m, q in data["sweep"] if m == mode)
        vals = [data["sweep"][(mode, q)] for q in qs]
        axs[0].plot(qs, [np.sqrt(np.mean(v[0] ** 2)) for v in vals], "o-", c=COLORS[mode], label=MODE_LABEL[mode])
        axs[1].plot(qs, [np.sqrt(np.mean(v[1] ** 2)) for v in vals], "o-", c=COLORS[mode], label=MODE_LABEL[mode])
        axs[2].plot(qs, [v[2] for v in vals], "o-", c=COLORS[mode], label=MODE_LABEL[mode])
    for a, bound, lab in zip(axs, (0.1, 0.02, 0.1), ("position error after 50 frames (px)",
                                                      "velocity deviation after 50 frames (px/s)",
                                                      "pair error after, systematic, 3 deg/s (px)")):
        a.axhline(bound, ls="--", c="k", lw=0.8, label=f"paper bound {bound:g}")
        a.axvline(Q_PAPER, ls=":", c="grey", lw=0.8, label="q = 1e-4 px^2/s^4 (literal)")
        a.axvline(q_per_frame_reading(), ls="-.", c="grey", lw=0.8, label="q = 1e-4 px^2/frame^4")
        a.set(xscale="log", yscale="log", xlabel="q (px^2/s^4)", ylabel=lab)
        a.legend(fontsize=6)
    axs[0].set_title("Q sweep, 1 deg/s about x, R=0.05 px^2")
    axs[2].set_title("Q sweep, 3 deg/s about x")
    fig.tight_layout()
    fig.savefig(d / "he2021a_q_sweep.png", dpi=110)
    plt.close(fig)


def markdown_table(rows) -> str:
    """The rows as a Markdown table (the doc's results section is generated with this)."""
    out = ["| quantity | condition | paper | ours | unit | ratio | trials | note |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        paper = "-" if r.paper is None else f"{r.paper:g}"
        ours = "-" if r.ours is None else f"{r.ours:.3g}"
        ratio = "-" if r.ratio is None else f"{r.ratio:.2f}"
        out.append(f"| {r.quantity} | {r.condition} | {paper} | {ours} | {r.unit} | {ratio} | {r.trials or '-'} | {r.note} |")
    return "\n".join(out)


if __name__ == "__main__":  # python -m rollingstar.studies.reproduce.he2021a RESULT.json: the doc's table from a --json run
    with open(sys.argv[1]) as fh:
        _rows = [Row(**{k: v for k, v in r.items() if k != "ratio"}) for r in json.load(fh)["rows"]]
    print(markdown_table(_rows))
