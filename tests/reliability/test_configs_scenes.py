"""Configs with wrong units, a plugin that raises, and hostile scenes through the runner (docs/reliability.md)."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.errors import PipelineError
from rollingstar.estimators.attitude.base import AttitudeSolver
from rollingstar.logs.reader import LogReader
from rollingstar.outputs import PartialOutputWarning
from rollingstar.pipelines import runner as runner_module
from rollingstar.pipelines.config import PipelineConfig
from rollingstar.pipelines.runner import run_pipeline

from .helpers import SCENARIO, assert_exit_2, rewrite


def test_wrong_units_name_the_key_with_the_unit(tmp_path):
    p = tmp_path / "s.yaml"
    p.write_text(SCENARIO.read_text().replace("exposure_ms: 50.0", "exposure_s: 0.05"))
    print(assert_exit_2(("simulate", p, "-o", tmp_path / "r.mcap"), "shutter.exposure_s: unknown key",
                        "did you mean 'exposure_ms'", "shutter.exposure_ms: Field required"))


class Exploding(AttitudeSolver):
    """A plugin that raises on frame 4."""

    name = "exploding"

    def process(self, frame):
        if frame.index == 4:
            raise ZeroDivisionError("division by zero")
        return frame


def test_a_plugin_that_raises_names_stage_and_frame_and_keeps_earlier_frames(tmp_path, small_recording, monkeypatch):
    real = runner_module.get_plugin_class
    monkeypatch.setattr(runner_module, "get_plugin_class", lambda kind: Exploding if kind == "exploding" else real(kind))
    out = tmp_path / "o.mcap"
    with pytest.raises(PipelineError, match=r"stage 'exploding' \(attitude\) failed on frame 4 \(t0 = \d+ ns\): "
                                            r"ZeroDivisionError: division by zero"), \
            pytest.warns(PartialOutputWarning, match="o.mcap.partial; .*o.mcap is untouched"):
        run_pipeline(small_recording, PipelineConfig(stages=[{"kind": "tracking"}, {"kind": "exploding"}]), out,
                     show_progress=False)
    assert not out.exists()  # what was written is kept under its own name
    assert [m.data["frame"] for m in LogReader(tmp_path / "o.mcap.partial").messages("/estimate/frame")] == [0, 1, 2, 3]


def _keep(n_by_frame):
    def edit(ms):
        out = []
        for m in ms:
            if m.topic == "/camera/centroids" and m.data["frame"] in n_by_frame:
                n = n_by_frame[m.data["frame"]]
                m = type(m)(m.topic, m.log_time_ns, m.schema_name,
                            {k: (v[:n] if isinstance(v, list) else v) for k, v in m.data.items()})
            out.append(m)
        return out
    return edit


def test_no_stars_and_one_star_frames_are_flagged_and_tracking_recovers(tmp_path, small_recording):
    rec = rewrite(small_recording, tmp_path / "sparse.mcap", _keep({5: 0, 6: 0, 7: 1}))
    out = tmp_path / "o.mcap"
    s = run_pipeline(rec, PipelineConfig(stages=[{"kind": "tracking"}, {"kind": "quest"}]), out, show_progress=False)
    est = {m.data["frame"]: m.data for m in LogReader(out).messages("/estimate/attitude")}
    flags = {m.data["frame"]: m.data["flags"] for m in LogReader(out).messages("/estimate/frame")}
    assert s.frames == 20 and s.valid_estimates == 17
    for f in (5, 6, 7):
        assert not est[f]["valid"] and est[f]["q"] is None and est[f]["reason"]
        assert "too_few_stars" in flags[f] and "attitude_invalid" in flags[f]
    print({f: est[f]["reason"] for f in (5, 6, 7)})
    assert est[5]["reason"] == est[6]["reason"] == "no stars"
    assert est[7]["reason"].startswith("fewer than 2 identified stars")
    assert all(est[f]["valid"] and not flags[f] for f in range(8, 20))  # tracking picks the stars up again


def test_a_planet_among_the_stars_is_rejected_by_the_gate(tmp_path, small_recording):
    """A bright non-catalogue spot the identifier matched (planted: a spot with a wrong catalogue
    direction, i.e. a centroid recording already identified, as `import corr` writes)."""
    from rollingstar.studies.outlier_bench import (
        clean_scene,
        plant_false_matches,
        rms_error_arcsec,
        run_solver,
    )

    from .helpers import ROOT

    scene = clean_scene(4, seed=9, root=ROOT)
    frames = plant_false_matches(scene, 1, seed=2)
    gated = run_solver("quest", {"robust": "ransac"}, frames, scene.context)
    clean = run_solver("quest", {}, scene.frames, scene.context)
    assert np.isclose(rms_error_arcsec(gated, scene.motion)[0], rms_error_arcsec(clean, scene.motion)[0], rtol=1e-9)


# --- all stars saturated (docs/reliability.md, Scenes) ------------------------------------------

_SATURATED_SCENE = """
name: all_saturated
level: image
sensor: {{focal_length_mm: 8.0, pixel_size_um: 5.5, width_px: 256, height_px: 256}}
shutter: {{mode: rolling, exposure_ms: 50.0, line_delay_us: 49.0}}
catalog: {{source: hipparcos, magnitude_limit: 6.0, epoch_year: 2025.0}}
motion:
  initial_attitude: {{ra_deg: {ra}, dec_deg: {dec}, roll_deg: {roll}}}
  rate_deg_s: [0.05, 0.0, 0.0]
noise: {{centroid_sigma_px: 0.05}}
image: {{psf_sigma_px: 1.0, photons_per_s_mag0: 1.0e9, background_e_per_px_s: 50.0, read_noise_e: 5.0, bit_depth: 12}}
frames: 4
seed: {seed}
"""
# Six pointings around Orion (10 x 10 deg field, 140 arcsec/px): the sub-pixel phases of the
# stars, hence the clipped spots' sampling errors, differ between pointings (between frames of one
# pointing they hardly change: the stars move 0.06 px per frame).
_POINTINGS = [(83.8, -5.4, 0.0), (84.4, -4.9, 23.0), (83.1, -6.0, 61.0), (85.0, -5.8, 97.0), (82.6, -4.6, 140.0),
              (84.0, -6.5, 200.0)]


def _saturated_runs(tmp_path, reject_border: bool = True):
    from rollingstar.pipelines.config import load_pipeline
    from rollingstar.pipelines.simulate import simulate_to_log
    from rollingstar.sensors.scenario import load_scenario

    from .helpers import PIPELINE

    for k, (ra, dec, roll) in enumerate(_POINTINGS):
        scen = tmp_path / f"sat{k}.yaml"
        scen.write_text(_SATURATED_SCENE.format(ra=ra, dec=dec, roll=roll, seed=k + 1))
        rec, out = tmp_path / f"sat{k}.mcap", tmp_path / f"sat{k}.out.mcap"
        simulate_to_log(load_scenario(scen), rec, show_progress=False)
        # the baseline pipeline; with reject_border its centroider drops the spots cut by the
        # detector's edge, so that every detection is saturated (a cut spot whose peak is off the
        # detector is not); kept, they get the cut's CoG bias in sigma_px (edge.py)
        pipeline = load_pipeline(PIPELINE)
        assert pipeline.stages[0].kind == "cog"
        pipeline.stages[0].params["reject_border"] = reject_border
        yield run_pipeline(rec, pipeline, out, show_progress=False), out


def _errors_against_truth(out):
    """Per identified star: (x, y, dx, dy, sigma_px, saturated); per valid attitude: (error arcsec, 1-sigma arcsec)."""
    from scipy.spatial.transform import Rotation

    from rollingstar.logs.records import stars_to_arrays
    from rollingstar.pipelines.truth import TruthTrajectory, true_positions
    from rollingstar.sensors import build
    from rollingstar.sensors.conventions import (
        RAD_TO_ARCSEC,
        attitude_error_body_arcsec,
    )
    from rollingstar.sensors.scenario import scenario_from_yaml

    reader = LogReader(out)
    camera = build.build_camera(scenario_from_yaml(reader.metadata()["scenario"]["yaml"], str(out)))
    t_, q_, w_, tru, stars, att = [], [], [], {}, [], []
    for m in reader.messages(["/truth/attitude", "/truth/stars", "/estimate/stars", "/estimate/attitude"]):
        d = m.data
        if m.topic == "/truth/attitude":
            t_.append(d["t_ns"])
            q_.append(np.column_stack([d[k] for k in ("qx", "qy", "qz", "qw")]))
            w_.append(np.column_stack([d[k] for k in ("wx", "wy", "wz")]))
        elif m.topic == "/truth/stars":
            tru[d["frame"]] = stars_to_arrays(d)
        elif m.topic == "/estimate/stars":
            stars.append(stars_to_arrays(d) | {"frame": d["frame"]})
        else:
            att.append(d)
    truth = TruthTrajectory(np.concatenate(t_).astype(np.int64), np.concatenate(q_), np.concatenate(w_))
    rows = []
    for e in stars:
        t = tru[e["frame"]]
        where = {int(c): j for j, c in enumerate(t["catalog_id"])}
        ei = np.flatnonzero(np.asarray(e["catalog_id"]) >= 0)
        tj = np.array([where[int(c)] for c in np.asarray(e["catalog_id"])[ei]], dtype=int)
        ts = np.asarray(e["t_ns"], dtype=np.int64)[ei]
        x, y = true_positions(camera, [], truth.attitude(ts), np.asarray(t["ref_icrs"])[tj], ts)
        ex, ey = np.asarray(e["x"])[ei], np.asarray(e["y"])[ei]
        rows.append(np.column_stack([ex, ey, ex - x, ey - y, np.asarray(e["sigma_px"])[ei], np.asarray(e["saturated"])[ei]]))
    valid = [a for a in att if a["valid"]]
    q = Rotation.from_quat([[a["q"][k] for k in "xyzw"] for a in valid])
    err = attitude_error_body_arcsec(truth.attitude(np.array([a["t_ns"] for a in valid], dtype=np.int64)), q)
    sd = np.array([np.sqrt(np.diag(np.reshape(a["covariance_rad2"], (3, 3)))) * RAD_TO_ARCSEC for a in valid])
    return np.concatenate(rows), err, sd


def test_all_stars_saturated_attitude_is_kept_flagged_and_its_sigma_is_honest(tmp_path):
    """Every star of every frame saturates (12-bit, 1e9 e/s from a magnitude-0 star: a magnitude-6
    star peaks at ~7x the full scale; 400 detections in 24 frames), the baseline pipeline (cog, tracking,
    quest; the centroider with ``reject_border``, see _saturated_runs), 6 pointings x 4 frames.

    The user sees: every detection ``saturated: true``; every frame flagged
    ``saturated_stars:<n detected>`` and ``attitude_degraded:all_stars_saturated``; the attitude
    valid (kept, not invented: it is still good to about an arcsec across the boresight).

    Measured (`pytest -s -k all_stars_saturated tests/reliability/test_configs_scenes.py` prints
    them): 400 of 400 detections saturated; attitude error RMS x 0.73, y 0.82, z 10.1 arcsec
    (max 1.5 / 1.7 / 19.4; 140 arcsec/px); centroid error RMS 0.020 px per axis against a
    reported sigma_px RMS of 0.022 px: normalised centroid error RMS 0.94 (with the noise-only
    sigma_px, before the clipping term, it is ~11: tests/estimators/test_saturation_sigma.py);
    attitude error / the covariance's 1-sigma, RMS over frames and axes 1.09 (per pointing 0.71 -
    1.79: the frames of a pointing share their stars' phase errors, so the 6 pointings are ~6
    independent samples). Bounds: attitude RMS below 2x the measured (1.5, 1.5, 20 arcsec); both
    normalised RMS within [0.6, 1.6] (the per-pointing spread).
    """
    stars, errs, sds, per_pointing, n_sat_all, n_det_all = [], [], [], [], [], []
    for summary, out in _saturated_runs(tmp_path):
        frames = [m.data for m in LogReader(out).messages("/estimate/frame")]
        est = [m.data for m in LogReader(out).messages("/estimate/stars")]
        assert summary.frames == summary.valid_estimates == summary.flagged_frames == 4
        for f, e in zip(frames, est):
            assert len(e["x"]) >= 10 and all(e["saturated"]), e["saturated"]
            n_sat = [int(x.split(":")[1]) for x in f["flags"] if x.startswith("saturated_stars:")]
            n_sat_all.append(n_sat[0])
            n_det_all.append(f["n_detected"])
            assert n_sat == [f["n_detected"]], f  # every detection (matched or not) saturated
            assert "attitude_degraded:all_stars_saturated" in f["flags"]
            assert "attitude_invalid" not in f["flags"] and f["n_identified"] >= 10
        s, err, sd = _errors_against_truth(out)
        stars.append(s)
        errs.append(err)
        sds.append(sd)
        per_pointing.append(np.sqrt(np.mean((err / sd) ** 2)))
    s, err, sd = np.concatenate(stars), np.concatenate(errs), np.concatenate(sds)
    print(f"saturated / detected: {sum(n_sat_all)} / {sum(n_det_all)}")
    assert s[:, 5].all()
    d = np.concatenate([s[:, 2], s[:, 3]])
    sig = np.concatenate([s[:, 4], s[:, 4]])
    z_star = float(np.sqrt(np.mean((d / sig) ** 2)))
    rms = np.sqrt(np.mean(err**2, axis=0))
    z_att = float(np.sqrt(np.mean((err / sd) ** 2)))
    print(f"attitude RMS arcsec {np.round(rms, 2)}, max {np.round(np.abs(err).max(axis=0), 1)}; centroid RMS "
          f"{np.sqrt(np.mean(d ** 2)):.4f} px, sigma_px RMS {np.sqrt(np.mean(sig ** 2)):.4f} px, normalised {z_star:.2f}; "
          f"attitude error / 1-sigma RMS {z_att:.2f} (per pointing {np.round(per_pointing, 2)})")
    assert rms[0] < 1.5 and rms[1] < 1.5 and rms[2] < 20.0
    assert 0.6 < z_star < 1.6
    assert 0.6 < z_att < 1.6


def test_saturated_scene_with_spots_cut_by_the_edge_keeps_an_honest_sigma(tmp_path):
    """The same scene with the plain baseline (``reject_border: false``): spots cut by the detector
    edge are kept, their frames flagged ``edge_truncated_stars:N``, and their CoG bias (up to
    ~0.9 px here) is in sigma_px (estimators/centroiders/edge.py), so QUEST weights them less.
    Measured (`pytest -s -k cut_by_the_edge`): attitude RMS 0.73 / 0.81 / 9.9 arcsec (as with the
    cut spots dropped), attitude error / 1-sigma RMS 1.08, normalised centroid error RMS 0.89;
    with ``edge_sigma: false`` (the centroider before edge.py) 1.55 / 2.02 / 29.3 arcsec, 2.48 and
    3.26. Bounds as in the all-saturated test."""
    stars, errs, sds, n_flagged = [], [], [], 0
    for summary, out in _saturated_runs(tmp_path, reject_border=False):
        for f in (m.data for m in LogReader(out).messages("/estimate/frame")):
            n_flagged += any(x.startswith("edge_truncated_stars:") for x in f["flags"])
        s, err, sd = _errors_against_truth(out)
        stars.append(s)
        errs.append(err)
        sds.append(sd)
    s, err, sd = np.concatenate(stars), np.concatenate(errs), np.concatenate(sds)
    d = np.concatenate([s[:, 2], s[:, 3]])
    sig = np.concatenate([s[:, 4], s[:, 4]])
    z_star = float(np.sqrt(np.mean((d / sig) ** 2)))
    z_att = float(np.sqrt(np.mean((err / sd) ** 2)))
    rms = np.sqrt(np.mean(err**2, axis=0))
    print(f"frames with cut spots {n_flagged} / 24; attitude RMS {np.round(rms, 2)} arcsec; normalised centroid "
          f"RMS {z_star:.2f}, attitude error / 1-sigma RMS {z_att:.2f}; largest |centroid error| {np.abs(d).max():.3f} px")
    assert n_flagged >= 4 and np.abs(d).max() > 0.1  # the scene does cut spots, by more than their noise
    assert rms[0] < 1.5 and rms[1] < 1.5 and rms[2] < 20.0
    assert 0.6 < z_star < 1.6
    assert 0.6 < z_att < 1.6


def test_saturation_flags_count_detections_and_degrade_only_all_saturated_solutions():
    """``saturated_stars:N`` counts saturated detections (matched and unmatched); the attitude is
    flagged degraded only when every identified star is saturated and the attitude is valid."""
    from rollingstar.estimators.data import AttitudeEstimate, FrameData, StarTable
    from rollingstar.pipelines.stages import finish_frame as _finish_frame

    def frame(sat, ids, unmatched_sat=(), valid=True):
        n = len(sat)
        stars = StarTable.build(np.arange(n, dtype=float), np.zeros(n), np.zeros(n, dtype=np.int64), saturated=sat,
                                catalog_id=ids, ref_icrs=np.tile([0.0, 0.0, 1.0], (n, 1)))
        un = StarTable.build(np.zeros(len(unmatched_sat)), np.zeros(len(unmatched_sat)),
                             np.zeros(len(unmatched_sat), dtype=np.int64), saturated=list(unmatched_sat))
        att = AttitudeEstimate(0, np.array([0.0, 0.0, 0.0, 1.0]), n) if valid else AttitudeEstimate.invalid(0, n, "x")
        return _finish_frame(FrameData(index=0, t0_ns=0, stars=stars, unmatched=un, attitudes=(att,))).flags

    assert frame([True, True, True], [1, 2, 3], [True]) == ("saturated_stars:4", "attitude_degraded:all_stars_saturated")
    # the one unsaturated star is not used (unidentified): the solution still rests on saturated stars only
    assert frame([True, True, False], [1, 2, -1]) == ("saturated_stars:2", "attitude_degraded:all_stars_saturated")
    assert frame([True, True, False], [1, 2, 3]) == ("saturated_stars:2",)
    assert frame([False, False, False], [1, 2, 3], [False]) == ()
    assert frame([True, True, True], [1, 2, 3], valid=False) == ("saturated_stars:3",)
