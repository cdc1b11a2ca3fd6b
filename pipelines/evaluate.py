"""Metrics of an output log against the truth it carries.

Attitude error: the rotation from truth (at each estimate's own timestamp) to the estimate,
in the camera frame, per axis (arcsec). Centroid error: each output star against the true image
position of its catalogue star at the time the position claims to refer to (``t_ns``). Star-pair
distance error (he2021a section 3): for every pair of identified stars of a frame, the measured
pixel distance minus the true distance of the two stars imaged at one common time (the mean of
the two claimed times). Rate error: norm of the estimated minus the true body rate (``rmse``,
``max``) and its RMSE per camera axis (``x_rmse`` ...).

Bounds, all single-frame Cramér–Rao bounds (RMS over frames of each frame's bound, per camera axis):

- centroid level, given sigma: ``attitude_crb_arcsec`` (:func:`rollingstar.pipelines.truth.attitude_crb_rad2`,
  the rate known) and, when the log holds rate estimates, ``rate_crb_deg_s``
  (:func:`rollingstar.pipelines.truth.rate_crb_rad2`, exact row times), for each frame's identified
  stars with every centroid's sigma taken as the scenario's ``noise.centroid_sigma_px`` (at image
  level too: the number is then the bound *if* the centroids had that sigma, not derived from the
  pixels);
- pixel level, image-level recordings: ``pixel_crb_arcsec`` and ``pixel_rate_crb_deg_s``
  (:func:`rollingstar.pipelines.truth.pixel_frame_crb_rad2`), the joint bound on the attitude at the
  frame's attitude estimate's own ``t_ns`` and the body rate (both unknown) from the pixels of all
  the frame's true stars on the detector, identified or not (the bound is on the information in the
  pixels), with the scenario's photometry and detector noise (hot pixels, the scenario's effects
  and the detector's edges left out: every star is imaged through the camera alone, on pixels all
  around it). One bound per valid attitude estimate (per frame, at the frame's reference time, when
  there is none), every k-th of them with ``k = ceil(n / PIXEL_BOUND_FRAMES)``: the bound moves
  slowly from frame to frame and costs about 10 ms per frame of 36 stars. The rate bound is
  reported whether or not the log holds rate estimates (the attitude bound is the joint one, with
  the rate unknown, either way).

``efficiency`` is RMSE / centroid-level bound and ``efficiency_pixel`` RMSE / pixel-level bound,
per axis (1 = efficient; below 1 is possible only for estimators that combine frames, which the
single-frame bounds do not cover).
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.logs.reader import LogReader
from rollingstar.logs.topics import (
    TOPIC_EST_ATTITUDE,
    TOPIC_EST_FRAME,
    TOPIC_EST_RATE,
    TOPIC_EST_STARS,
    TOPIC_TRUTH_STARS,
)
from rollingstar.pipelines.outcomes import Outcomes
from rollingstar.pipelines.truth import (
    TruthTrajectory,
    attitude_crb_rad2,
    joint_crb_rad2,
    pixel_frame_crb_rad2,
    rate_crb_rad2,
    true_positions,
)
from rollingstar.sensors import build
from rollingstar.sensors.conventions import CAMERA_AXES, RAD_TO_ARCSEC, S_PER_NS, attitude_error_body_arcsec
from rollingstar.sensors.image_sim import ImageModel
from rollingstar.sensors.pixel_crb import FrameDetector

PAIR_MATCH_RADIUS_PX = 3.0
PIXEL_BOUND_FRAMES = 30  # frames the pixel-level bound is averaged over, at most (evenly spaced)
# A median attitude error above TRUTH_MISMATCH_DEG is no estimator's error: the truth is then read in
# the conventions other tools use, and one that brings the estimates within TRUTH_READING_DEG is named
TRUTH_MISMATCH_DEG = 1.0
TRUTH_READING_DEG = 0.05
_AXES = ("x", "y", "z")


def _stats(values: np.ndarray) -> dict[str, float | None]:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"rmse": None, "max": None}
    return {"rmse": float(np.sqrt(np.mean(v**2))), "max": float(np.max(np.abs(v)))}


def evaluate_log(path: str | Path, skip_first: int = 0, skip_first_s: float = 0.0, series: bool = False) -> dict:
    """Compute the metrics dictionary (``rollingstar evaluate --json``) for an output log.

    ``skip_first`` frames, and the frames that start within ``skip_first_s`` seconds of the first
    frame, are left out of every metric (a filter's start-up transient); ``outcomes`` counts the
    frames that remain (:mod:`rollingstar.pipelines.outcomes`). ``notes`` gives, for every metric
    that is ``None``, the reason. ``series``: also return the per-estimate errors the plots draw
    (``result["series"]``, numpy arrays; not JSON)."""
    reader = LogReader(path)
    scenario = reader.scenario("cannot evaluate without it")
    camera = build.build_camera(scenario)
    timing = build.build_timing(scenario)
    effects = build.build_effects(scenario)
    reader.require_topics([TOPIC_EST_FRAME])

    samples = reader.truth_attitude()
    truth = TruthTrajectory(**samples) if samples["t_ns"].size else None
    truth_stars = reader.stars(TOPIC_TRUTH_STARS)
    est_stars = reader.stars(TOPIC_EST_STARS)  # with each frame's t0_ns: the effects' context needs it
    records: dict[str, list[dict]] = {TOPIC_EST_ATTITUDE: [], TOPIC_EST_RATE: [], TOPIC_EST_FRAME: []}
    for m in reader.messages(list(records)):
        records[m.topic].append(m.data)
    kept = _kept_frames(records[TOPIC_EST_FRAME], skip_first, skip_first_s)
    attitudes, rates, frames = ([r for r in records[topic] if int(r.get("frame", -1)) in kept]
                                for topic in (TOPIC_EST_ATTITUDE, TOPIC_EST_RATE, TOPIC_EST_FRAME))
    est_stars = {k: v for k, v in est_stars.items() if k in kept}

    valid = [a for a in attitudes if a.get("valid") and a.get("q") is not None]
    n_frames = len(frames)
    duration_s = n_frames * timing.frame_period_ns * S_PER_NS
    outcomes = Outcomes.from_records(frames, attitudes)
    result: dict = {
        "frames": n_frames,
        "skipped_frames": len(records[TOPIC_EST_FRAME]) - n_frames,
        "outcomes": outcomes.as_dict(),
        "attitude_updates": len(valid),
        "invalid_attitude_estimates": len(attitudes) - len(valid),
        "update_rate_hz": (len(valid) / duration_s) if duration_s > 0 else None,
        "flagged_frames": outcomes.flagged,
        "identified_stars_per_frame": float(np.mean([f["n_identified"] for f in frames])) if frames else None,
        "axes": dict(CAMERA_AXES),
    }
    result["attitude_error_arcsec"] = _attitude_errors(valid, truth)
    hint = _truth_convention(valid, truth)
    if hint:  # present only when it says something: compare's metric tables flatten every None into a column
        result["truth_convention"] = hint
    env = _EffectEnvironment(scenario, timing, effects) if effects else None
    result["centroid_error_px"] = _centroid_errors(est_stars, truth_stars, truth, camera, effects, env)
    result["star_pair_distance_error_px"] = _pair_errors(est_stars, truth_stars, truth, camera, effects, env)
    result["rate_error_deg_s"] = _rate_errors(rates, truth)
    result["attitude_crb_arcsec"] = _crb(est_stars, truth_stars, truth, camera, scenario)
    has_rate = result["rate_error_deg_s"]["rmse"] is not None
    result["rate_crb_deg_s"] = _rate_crb(est_stars, truth_stars, truth, camera, scenario, has_rate)
    result["attitude_crb_rate_unknown_arcsec"] = _joint_attitude_crb(est_stars, truth_stars, truth, camera, scenario,
                                                                     valid)
    result["pixel_crb_arcsec"], result["pixel_rate_crb_deg_s"] = _pixel_crb(
        truth_stars, valid, truth, camera, timing, scenario)
    result["efficiency"] = _efficiency(result, "attitude_crb_arcsec", "rate_crb_deg_s")
    result["efficiency_pixel"] = _efficiency(result, "pixel_crb_arcsec", "pixel_rate_crb_deg_s")
    result["notes"] = _notes(result, truth, truth_stars, scenario, valid, rates)
    if series:
        result["series"] = _series(valid, rates, est_stars, truth_stars, truth, camera, effects, env)
    return result


def _kept_frames(frames: list[dict], skip_first: int, skip_first_s: float) -> set[int]:
    """Indices of the frames evaluated: all but the first ``skip_first`` and those that start within
    ``skip_first_s`` of the first frame."""
    order = sorted(frames, key=lambda f: (int(f.get("t0_ns", 0)), int(f.get("frame", -1))))
    if not order:
        return set()
    start = int(order[0].get("t0_ns", 0)) + round(skip_first_s * 1e9)
    return {int(f.get("frame", -1)) for f in order[skip_first:] if int(f.get("t0_ns", 0)) >= start}


def _notes(m: dict, truth, truth_stars: dict, scenario, valid: list, rates: list) -> dict[str, str]:
    """Why each metric that is ``None`` is missing, in words."""
    notes = {}
    no_truth = "the log carries no /truth/attitude (a real recording): errors and bounds need the truth"
    if truth is None:
        for key in ("attitude_error_arcsec", "rate_error_deg_s", "centroid_error_px", "star_pair_distance_error_px",
                    "attitude_crb_arcsec", "attitude_crb_rate_unknown_arcsec", "rate_crb_deg_s", "pixel_crb_arcsec",
                    "pixel_rate_crb_deg_s", "efficiency", "efficiency_pixel"):
            notes[key] = no_truth
        return notes
    if not valid:
        notes["attitude_error_arcsec"] = "no valid attitude estimate to compare with the truth"
    if not rates:
        notes["rate_error_deg_s"] = "the pipeline wrote no rate estimate (no stage estimates the rate)"
    elif not any(r.get("valid") for r in rates):
        notes["rate_error_deg_s"] = "every rate estimate the pipeline wrote is invalid"
    if "rate_error_deg_s" in notes:
        notes["rate_crb_deg_s"] = "reported only beside valid rate estimates"
    if not truth_stars:
        for key in ("centroid_error_px", "star_pair_distance_error_px", "attitude_crb_arcsec"):
            notes[key] = "the log carries no /truth/stars"
    else:
        if m["centroid_error_px"]["rmse"] is None:
            notes["centroid_error_px"] = "no estimated star matched a true one"
        if m["star_pair_distance_error_px"]["rmse"] is None:
            notes["star_pair_distance_error_px"] = "no frame with two estimated stars matched to true ones"
    if m["attitude_crb_arcsec"].get("x") is None and "attitude_crb_arcsec" not in notes:
        notes["attitude_crb_arcsec"] = ("the scenario states no centroid sigma" if not scenario.noise.centroid_sigma_px
                                        else "no frame with two identified stars matched to the truth")
    if m["attitude_crb_rate_unknown_arcsec"].get("x") is None and "attitude_crb_rate_unknown_arcsec" not in notes:
        notes["attitude_crb_rate_unknown_arcsec"] = (
            "the scenario states no centroid sigma" if not scenario.noise.centroid_sigma_px
            else "no frame with three identified stars at distinct times matched to the truth")
    if m["pixel_crb_arcsec"].get("x") is None:
        notes["pixel_crb_arcsec"] = ("a centroid-level recording: the pixel-level bound needs the pixels "
                                     "(an image-level recording)" if scenario.level != "image"
                                     else "no frame with three true stars and truth at its reference time")
        notes["pixel_rate_crb_deg_s"] = notes["pixel_crb_arcsec"]
    if m["update_rate_hz"] is None:
        notes["update_rate_hz"] = "the log has no frames"
    for key, bound in (("efficiency", "attitude_crb_arcsec"), ("efficiency_pixel", "pixel_crb_arcsec")):
        if all(v is None for v in m[key].values()):
            notes[key] = notes.get(bound) or notes.get("attitude_error_arcsec") or "error or bound missing"
    return notes


def _efficiency(m: dict, attitude_bound: str, rate_bound: str) -> dict:
    """RMSE / the Cramér–Rao bounds ``m[attitude_bound]``, ``m[rate_bound]`` per axis (None where either is missing)."""
    out = {}
    for prefix, err, crb in (("attitude", m["attitude_error_arcsec"], m[attitude_bound]),
                             ("rate", m["rate_error_deg_s"], m[rate_bound])):
        for ax in "xyz":
            e, b = err.get(f"{ax}_rmse"), crb.get(ax)
            out[f"{prefix}_{ax}"] = float(e / b) if e is not None and b else None
    return out


def _covered_estimates(valid: list[dict], truth: TruthTrajectory) -> tuple[np.ndarray, Rotation | None]:
    """The times and attitudes of the valid estimates the truth covers (None: none)."""
    t = np.array([a["t_ns"] for a in valid], dtype=np.int64)
    ok = truth.covers(t)
    if not ok.any():
        return t[ok], None
    q = np.array([[a["q"]["x"], a["q"]["y"], a["q"]["z"], a["q"]["w"]] for a in valid])[ok]
    return t[ok], Rotation.from_quat(q)


def _truth_convention(valid: list[dict], truth: TruthTrajectory | None) -> str | None:
    """When the estimates miss the truth by more than ``TRUTH_MISMATCH_DEG`` (median), but the
    truth read in another convention (:meth:`TruthTrajectory.other_readings`) agrees with them
    within ``TRUTH_READING_DEG``, the sentence saying so (the errors are reported as the truth
    stands); else None."""
    if truth is None or not valid:
        return None
    t, est = _covered_estimates(valid, truth)
    if est is None:
        return None
    off = float(np.degrees(np.median((truth.attitude(t).inv() * est).magnitude())))
    if off <= TRUTH_MISMATCH_DEG:
        return None
    for reading, other in truth.other_readings().items():
        err = float(np.degrees(np.median((other.attitude(t).inv() * est).magnitude())))
        if err <= TRUTH_READING_DEG:
            return (f"the estimates miss /truth/attitude by {off:.3g} deg (median) but agree with it within "
                    f"{err * 3600:.3g} arcsec when it is read {reading}: one of the two (the recording's truth, or "
                    f"the estimator that wrote the estimates) follows another convention than docs/conventions.md "
                    f"states (camera-to-ICRS, our camera frame, named quaternion fields); the attitude errors are "
                    f"against the truth as written")
    return None


def _attitude_errors(valid: list[dict], truth: TruthTrajectory | None) -> dict:
    keys = ("x_rmse", "y_rmse", "z_rmse", "x_max", "y_max", "z_max")
    if truth is None or not valid:
        return dict.fromkeys(keys)
    t, est = _covered_estimates(valid, truth)
    if est is None:
        return dict.fromkeys(keys)
    err = attitude_error_body_arcsec(truth.attitude(t), est)
    rmse = np.sqrt(np.mean(err**2, axis=0))
    mx = np.max(np.abs(err), axis=0)
    return {"x_rmse": float(rmse[0]), "y_rmse": float(rmse[1]), "z_rmse": float(rmse[2]),
            "x_max": float(mx[0]), "y_max": float(mx[1]), "z_max": float(mx[2])}


def _match_to_truth(est: dict, tru: dict) -> tuple[np.ndarray, np.ndarray]:
    """Indices (est_i, truth_j) of matched stars: by catalogue id, else nearest within 3 px."""
    ids_e = np.asarray(est.get("catalog_id", np.full(len(est["x"]), -1)), dtype=np.int64)
    ids_t = np.asarray(tru["catalog_id"], dtype=np.int64)
    pos = {int(c): j for j, c in enumerate(ids_t)}
    ei, tj = [], []
    for i, c in enumerate(ids_e):
        if c >= 0 and int(c) in pos:
            ei.append(i)
            tj.append(pos[int(c)])
    unid = np.flatnonzero(ids_e < 0)
    if unid.size and len(ids_t):
        d = np.hypot(est["x"][unid, None] - tru["x"][None, :], est["y"][unid, None] - tru["y"][None, :])
        j = np.argmin(d, axis=1)
        close = d[np.arange(unid.size), j] < PAIR_MATCH_RADIUS_PX
        ei.extend(unid[close].tolist())
        tj.extend(j[close].tolist())
    return np.asarray(ei, dtype=int), np.asarray(tj, dtype=int)


def _matched_frames(est_stars, truth_stars, min_matches: int):
    """Per frame with truth: (est, truth, est indices, truth indices) of at least ``min_matches`` matches."""
    for frame, est in est_stars.items():
        tru = truth_stars.get(frame)
        if tru is None or len(est["x"]) == 0:
            continue
        ei, tj = _match_to_truth(est, tru)
        if ei.size >= min_matches:
            yield est, tru, ei, tj


class _EffectEnvironment:
    """What the scenario's effects need besides the truth (rollingstar.sensors.effects.base.EffectContext fields):
    timing, ground-site zenith, covariates and, only when an effect needs it, catalogue proper motions."""

    def __init__(self, scenario, timing, effects):
        self.timing = timing
        self.zenith = build.build_zenith(scenario)
        self.covariates = build.build_covariates(scenario)
        self.needs = {n for e in effects for n in e.needs}
        self._scenario = scenario
        self._catalog = None

    def pm(self, ids) -> np.ndarray | None:
        if "pm_rad_yr" not in self.needs:
            return None
        if self._catalog is None:
            self._catalog = build.build_catalog(self._scenario)
        if self._catalog.pm_rad_yr is None:
            return None
        idx = self._catalog.index_of(ids)
        return np.where((idx >= 0)[:, None], self._catalog.pm_rad_yr[np.maximum(idx, 0)], np.nan)


def _effect_context(est, tru, tj, t, truth, env, row=None) -> dict:
    """Context fields for the scenario's effects at the matched truth stars ``tj`` seen at ``t``
    (``row``: the detector row timing each observation, for rolling-shutter effects)."""
    if env is None:
        return {}
    mag = tru.get("magnitude")
    ids = tru.get("catalog_id")
    n = len(t)
    return {"omega_rad_s": truth.angular_velocity(t), "timing": env.timing, "t0_ns": est.get("t0_ns"),
            "magnitude": None if mag is None else np.asarray(mag, dtype=float)[tj],
            "zenith_icrs": None if env.zenith is None else np.broadcast_to(env.zenith, (n, 3)),
            "covariates": {k: f(t) for k, f in env.covariates.items()},
            "pm_rad_yr": None if ids is None else env.pm(np.asarray(ids)[tj]), "row": row}


def _centroid_residuals(est_stars, truth_stars, truth, camera, effects, env=None):
    """Every matched star's measured position ``(x, y)`` and its error ``(dx, dy)`` (px), four arrays."""
    parts = []
    for est, tru, ei, tj in _matched_frames(est_stars, truth_stars, 1):
        t = np.asarray(est["t_ns"], dtype=np.int64)[ei]
        ok = truth.covers(t)
        if not ok.any():
            continue
        ei, tj, t = ei[ok], tj[ok], t[ok]
        x, y = true_positions(camera, effects, truth.attitude(t), tru["ref_icrs"][tj], t,
                              **_effect_context(est, tru, tj, t, truth, env, row=est["y"][ei]))
        parts.append(np.stack([est["x"][ei], est["y"][ei], est["x"][ei] - x, est["y"][ei] - y]))
    return tuple(np.concatenate(parts, axis=1)) if parts else tuple(np.zeros(0) for _ in range(4))


def _centroid_errors(est_stars, truth_stars, truth, camera, effects, env=None) -> dict:
    if truth is None:
        return {"rmse": None, "max": None}
    _, _, dx, dy = _centroid_residuals(est_stars, truth_stars, truth, camera, effects, env)
    return _stats(np.hypot(dx, dy)) if dx.size else {"rmse": None, "max": None}


def _series(valid, rates, est_stars, truth_stars, truth, camera, effects, env) -> dict:
    """Per-estimate errors for the plots: attitude (t s, error (n, 3) arcsec), rate (t s, error (n, 3)
    deg/s) and the centroid residuals over the detector; empty arrays where there is nothing."""
    out = {"attitude_t_s": np.zeros(0), "attitude_error_arcsec": np.zeros((0, 3)), "rate_t_s": np.zeros(0),
           "rate_error_deg_s": np.zeros((0, 3)), "centroid": tuple(np.zeros(0) for _ in range(4))}
    if truth is None:
        return out
    t = np.array([a["t_ns"] for a in valid], dtype=np.int64)
    t_first = int(truth.t_ns[0]) if len(truth.t_ns) else 0
    if t.size and truth.covers(t).any():
        ok = truth.covers(t)
        q = np.array([[a["q"]["x"], a["q"]["y"], a["q"]["z"], a["q"]["w"]] for a in valid])[ok]
        out["attitude_t_s"] = (t[ok] - t_first) * S_PER_NS
        out["attitude_error_arcsec"] = attitude_error_body_arcsec(truth.attitude(t[ok]), Rotation.from_quat(q))
    good = [r for r in rates if r.get("valid") and r.get("omega") is not None]
    tr = np.array([r["t_ns"] for r in good], dtype=np.int64)
    if tr.size and truth.covers(tr).any():
        ok = truth.covers(tr)
        w = np.array([[r["omega"]["x"], r["omega"]["y"], r["omega"]["z"]] for r in good])[ok]
        out["rate_t_s"] = (tr[ok] - t_first) * S_PER_NS
        out["rate_error_deg_s"] = np.degrees(w - truth.angular_velocity(tr[ok]))
    out["centroid"] = _centroid_residuals(est_stars, truth_stars, truth, camera, effects, env)
    return out


def _pair_errors(est_stars, truth_stars, truth, camera, effects, env=None) -> dict:
    if truth is None:
        return {"rmse": None, "max": None}
    errs = []
    for est, tru, ei, tj in _matched_frames(est_stars, truth_stars, 2):
        i, j = np.triu_indices(ei.size, k=1)
        t = np.asarray(est["t_ns"], dtype=np.int64)[ei]
        tc = (t[i] + t[j]) // 2
        ok = truth.covers(tc)
        if not ok.any():
            continue
        i, j, tc = i[ok], j[ok], tc[ok]
        att = truth.attitude(tc)
        ci = _effect_context(est, tru, tj[i], tc, truth, env)
        cj = _effect_context(est, tru, tj[j], tc, truth, env)
        xi, yi = true_positions(camera, effects, att, tru["ref_icrs"][tj[i]], tc, **ci)
        xj, yj = true_positions(camera, effects, att, tru["ref_icrs"][tj[j]], tc, **cj)
        d_true = np.hypot(xi - xj, yi - yj)
        d_meas = np.hypot(est["x"][ei[i]] - est["x"][ei[j]], est["y"][ei[i]] - est["y"][ei[j]])
        errs.append(d_meas - d_true)
    return _stats(np.concatenate(errs)) if errs else {"rmse": None, "max": None}


def _rate_errors(rates, truth) -> dict:
    valid = [r for r in rates if r.get("valid") and r.get("omega") is not None]
    empty = {"rmse": None, "max": None, "x_rmse": None, "y_rmse": None, "z_rmse": None}
    if truth is None or not valid:
        return empty
    t = np.array([r["t_ns"] for r in valid], dtype=np.int64)
    w = np.array([[r["omega"]["x"], r["omega"]["y"], r["omega"]["z"]] for r in valid])
    diff = (w - truth.angular_velocity(t)) * 180.0 / np.pi
    diff = diff[np.all(np.isfinite(diff), axis=1)]
    if diff.size == 0:
        return empty
    out = _stats(np.linalg.norm(diff, axis=1))
    rmse = np.sqrt(np.mean(diff**2, axis=0))
    out.update({"x_rmse": float(rmse[0]), "y_rmse": float(rmse[1]), "z_rmse": float(rmse[2])})
    return out


def _rate_crb(est_stars, truth_stars, truth, camera, scenario, has_rate: bool) -> dict:
    """RMS over frames of the single-frame rate bound (deg/s per axis), identified stars, row times exact."""
    keys = ("x", "y", "z")
    sigma = scenario.noise.centroid_sigma_px
    if truth is None or not sigma or not has_rate:
        return dict.fromkeys(keys)
    variances = []
    for est, tru, ei, tj in _matched_frames(est_stars, truth_stars, 3):
        t = np.asarray(tru["t_ns"], dtype=np.int64)[tj]
        if not truth.covers(t).all() or np.ptp(t) == 0:
            continue
        w = truth.attitude(t).inv().apply(tru["ref_icrs"][tj])
        variances.append(np.diag(rate_crb_rad2(camera, w, (t - t.min()) * S_PER_NS, sigma)))
    if not variances:
        return dict.fromkeys(keys)
    rms = np.sqrt(np.mean(variances, axis=0)) * 180.0 / np.pi
    return dict(zip(keys, map(float, rms)))


def _joint_attitude_crb(est_stars, truth_stars, truth, camera, scenario, valid: list[dict]) -> dict:
    """RMS over the valid attitude estimates of the single-frame attitude bound with the body rate
    unknown too (arcsec per axis): the attitude block of
    :func:`rollingstar.pipelines.truth.joint_crb_rad2`, from the frame's identified stars, at the
    estimate's own time (at the stars' mean time for a frame without a valid estimate). This is the bound of an estimator that knows neither, as one frame alone leaves
    every single-frame estimator; ``attitude_crb_arcsec`` holds the rate known."""
    keys = ("x", "y", "z")
    sigma = scenario.noise.centroid_sigma_px
    if truth is None or not sigma:
        return dict.fromkeys(keys)
    t_ref: dict[int, list[int]] = {}
    for a in valid:
        if "frame" in a:
            t_ref.setdefault(int(a["frame"]), []).append(int(a["t_ns"]))
    variances = []
    for frame, est in est_stars.items():
        tru = truth_stars.get(frame)
        ei, tj = _match_to_truth(est, tru) if tru is not None and len(est["x"]) else (np.zeros(0), np.zeros(0, int))
        t = np.asarray(tru["t_ns"], dtype=np.int64)[tj] if tru is not None else np.zeros(0, np.int64)
        if ei.size < 3 or not truth.covers(t).all() or np.ptp(t) == 0:
            continue
        w = truth.attitude(t).inv().apply(tru["ref_icrs"][tj])
        for ref in t_ref.get(frame, [int(np.mean(t))]):  # every estimate of the frame, at its own time
            variances.append(np.diag(joint_crb_rad2(camera, w, (t - ref) * S_PER_NS, sigma)[:3, :3]))
    if not variances:
        return dict.fromkeys(keys)
    rms = np.sqrt(np.mean(variances, axis=0)) * RAD_TO_ARCSEC
    return dict(zip(keys, map(float, rms)))


def _crb(est_stars, truth_stars, truth, camera, scenario) -> dict:
    """RMS over frames of the single-frame attitude bound (arcsec per axis) for each frame's identified
    stars, each with the scenario's centroid sigma."""
    keys = ("x", "y", "z")
    sigma = scenario.noise.centroid_sigma_px
    if truth is None or not sigma:
        return dict.fromkeys(keys)
    variances = []
    for est, tru, ei, tj in _matched_frames(est_stars, truth_stars, 2):
        t = np.asarray(tru["t_ns"], dtype=np.int64)[tj]
        if not truth.covers(t).all():
            continue
        w = truth.attitude(t).inv().apply(tru["ref_icrs"][tj])
        variances.append(np.diag(attitude_crb_rad2(camera, w, sigma)))
    if not variances:
        return dict.fromkeys(keys)
    rms = np.sqrt(np.mean(variances, axis=0)) * RAD_TO_ARCSEC
    return dict(zip(keys, map(float, rms)))


def _pixel_bound_frames(truth_stars: dict, valid: list[dict], timing) -> list[tuple[int, int]]:
    """(frame, reference time) pairs the pixel-level bound is averaged over (module docstring)."""
    pairs = [(int(a["frame"]), int(a["t_ns"])) for a in valid if a.get("frame") in truth_stars]
    pairs = pairs or [(k, timing.frame_reference_ns(truth_stars[k]["t0_ns"])) for k in sorted(truth_stars)]
    return pairs[::max(1, math.ceil(len(pairs) / PIXEL_BOUND_FRAMES))]


def _star_magnitudes(tru: dict, catalog: Callable) -> np.ndarray:
    """The truth stars' catalogue magnitudes: carried by the truth topic, else looked up by catalogue
    id in ``catalog()`` (the scenario's catalogue, built on first need)."""
    mag = tru.get("magnitude")
    if mag is not None and np.all(np.isfinite(mag)):
        return np.asarray(mag, dtype=float)
    catalog = catalog()
    idx = catalog.index_of(np.asarray(tru["catalog_id"], dtype=np.int64))
    return np.where(idx >= 0, catalog.magnitude[np.maximum(idx, 0)], np.nan)


def _pixel_crb(truth_stars, valid, truth, camera, timing, scenario) -> tuple[dict, dict]:
    """RMS over frames of the pixel-level bounds on attitude (arcsec) and rate (deg/s) per axis, all
    true stars of each frame (module docstring)."""
    none = dict.fromkeys(_AXES)
    if truth is None or scenario.level != "image" or not truth_stars:
        return none, none
    model = ImageModel(**scenario.image.model_dump())
    det = FrameDetector.from_image_model(model, timing.exposure_ns, timing.effective_line_delay_ns)
    catalog = functools.cache(lambda: build.build_catalog(scenario))
    att, rate = [], []
    for k, t_ref in _pixel_bound_frames(truth_stars, valid, timing):
        tru = truth_stars[k]
        if len(tru["x"]) < 3 or not truth.covers(t_ref):
            continue
        electrons = model.star_electrons(_star_magnitudes(tru, catalog), timing.exposure_ns)
        ok = np.isfinite(electrons) & np.all(np.isfinite(tru["ref_icrs"]), axis=1)
        a, r = pixel_frame_crb_rad2(camera, det, truth, t_ref, tru["t0_ns"], tru["ref_icrs"][ok], electrons[ok])
        if np.all(np.isfinite(np.diag(a))) and np.all(np.isfinite(np.diag(r))):
            att.append(np.diag(a))
            rate.append(np.diag(r))
    if not att:
        return none, none
    att_rms = np.sqrt(np.mean(att, axis=0)) * RAD_TO_ARCSEC
    rate_rms = np.degrees(np.sqrt(np.mean(rate, axis=0)))
    return dict(zip(_AXES, map(float, att_rms))), dict(zip(_AXES, map(float, rate_rms)))
