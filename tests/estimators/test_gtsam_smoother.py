"""Tests of the GTSAM attitude smoother (estimators/attitude/gtsam_smoother.py)."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.gtsam_graph import (
    ahrs_factor,
    rotation_params,
    star_factors,
)
from rollingstar.estimators.attitude.gtsam_smoother import GtsamSmoother
from rollingstar.estimators.attitude.mekf import MekfFilter
from tests.estimators.attitude_scenes import (
    ARCSEC,
    errors_rad,
    nees,
    run_plugin,
    sim_frames,
    valid_estimates,
)

# Nearly-constant-rate model matched to the simulated constant-rate truth.
MATCHED = {"angular_accel_noise_deg_s_sqrt_s": 1e-6, "attitude_noise_arcsec_sqrt_s": 0.1}


def test_factor_conventions_match_the_project():
    """AttitudeFactorRot3 is zero for v_icrs = R v_cam; AHRSFactor for R_j = R_i Exp((w - b) dt)."""
    R = Rotation.random(random_state=1)
    b = np.array([0.02, -0.01, 1.0])
    b /= np.linalg.norm(b)
    (f,) = star_factors(0, b[None], R.apply(b)[None], np.array([1e-5]))
    v = gtsam.Values()
    v.insert(0, gtsam.Rot3(R.as_matrix()))
    assert f.error(v) < 1e-20
    v2 = gtsam.Values()
    v2.insert(0, gtsam.Rot3((R * Rotation.from_rotvec([1e-5, 0, 0])).as_matrix()))
    assert f.error(v2) == pytest.approx(0.5 * (1e-5 * np.hypot(b[1], b[2]) / 1e-5) ** 2, rel=1e-3)
    w, beta, dt = np.array([0.1, 0.02, -0.05]), np.array([0.01, 0.0, 0.003]), 0.05
    g = ahrs_factor(0, 1, 2, w, dt, rotation_params(1e-6))
    v = gtsam.Values()
    v.insert(0, gtsam.Rot3(R.as_matrix()))
    v.insert(1, gtsam.Rot3((R * Rotation.from_rotvec((w - beta) * dt)).as_matrix()))
    v.insert(2, beta)
    assert np.abs(g.unwhitenedError(v)).max() < 1e-9  # AHRS bias correction is first order: |beta dt|^2 terms


def test_noise_free_recovers_the_truth_at_every_star():
    frames, motion, ctx, _ = sim_frames(10, sigma_px=0.0)
    outs = run_plugin(GtsamSmoother(**MATCHED, sigma_px=0.05), frames, ctx)
    ests = valid_estimates(outs)
    assert len(ests) == 150 and [o.index for o in outs] == list(range(10))
    assert np.abs(errors_rad(ests, motion)).max() / ARCSEC < 1e-3
    np.testing.assert_allclose(outs[-1].rate.omega_rad_s, np.radians([0.05, 0, 0]), atol=1e-10)


def test_static_scene_mid_log_covariance_is_crb_over_k():
    """Static scene, rate estimated: in the middle of K frames the attitude variance is the
    single-frame CRB / K (the straight-line fit's centre); error within that scale."""
    K = 41  # 0.5 px centroids: the attitude random walk of the model (0.1 arcsec/sqrt(s)) stays negligible
    frames, motion, ctx, crb = sim_frames(K, rate_deg_s=(0.0, 0.0, 0.0), seed=3, sigma_px=0.5)
    outs = run_plugin(GtsamSmoother(**MATCHED), frames, ctx)
    mid = outs[K // 2].attitudes
    P = np.mean([a.covariance_rad2 for a in mid], axis=0)
    ratio = np.diag(P) / (np.diag(crb) / K)
    assert np.all((ratio > 0.95) & (ratio < 1.1)), ratio  # measured 1.013-1.018 (isotropic sigma, motion noise)
    err = errors_rad(mid, motion)
    assert np.all(np.abs(err).max(axis=0) < 4 * np.sqrt(np.diag(P)))


def test_covariance_consistent_over_monte_carlo():
    """NEES of the middle state of M independent logs is chi2(3) distributed: mean in the 99 % band."""
    from scipy.stats import chi2

    M, K = 16, 6
    vals = []
    for seed in range(M):
        frames, motion, ctx, _ = sim_frames(K, seed=200 + seed)
        outs = run_plugin(GtsamSmoother(**MATCHED), frames, ctx)
        vals.append(nees(outs[K // 2].attitudes[7:8], motion)[0])
    assert chi2.ppf(0.005, 3 * M) < np.sum(vals) < chi2.ppf(0.995, 3 * M), vals


def test_smoother_beats_the_filter():
    frames, motion, ctx, _ = sim_frames(60, seed=11)
    rms = {}
    for name, plugin in (("mekf", MekfFilter()), ("gtsam", GtsamSmoother())):
        rms[name] = np.sqrt(np.mean(errors_rad(valid_estimates(run_plugin(plugin, frames, ctx)), motion) ** 2, axis=0))
    assert np.all(rms["gtsam"] < 0.8 * rms["mekf"]), rms


@pytest.mark.parametrize("backend", ["batch", "isam2"])
def test_batch_equals_fixed_lag_covering_the_whole_log(backend):
    frames, motion, ctx, _ = sim_frames(12, seed=4)
    batch = valid_estimates(run_plugin(GtsamSmoother(), frames, ctx))
    lag = GtsamSmoother(mode="fixed-lag", lag_s=100.0, fixed_lag_backend=backend)
    fl = valid_estimates(run_plugin(lag, frames, ctx))
    assert [a.t_ns for a in fl] == [a.t_ns for a in batch]
    d = (Rotation.from_quat([a.q_xyzw for a in batch]).inv() * Rotation.from_quat([a.q_xyzw for a in fl])).magnitude()
    assert d.max() / ARCSEC < 1e-4
    # covariances equal on the scale of each entry's sigmas (ISAM2 evaluates them at its own,
    # lazily updated linearisation point: measured 1.5e-4 of the sigmas; the batch backend 1e-9)
    P_fl, P_b = np.array([a.covariance_rad2 for a in fl]), np.array([a.covariance_rad2 for a in batch])
    s = np.sqrt(np.einsum("nii->ni", P_b))
    assert P_fl.shape == P_b.shape
    assert np.max(np.abs(P_fl - P_b) / (s[:, :, None] * s[:, None, :])) < (1e-6 if backend == "batch" else 1e-3)


def test_fixed_lag_releases_frames_in_order_after_the_lag():
    frames, motion, ctx, _ = sim_frames(12, seed=4)
    p = GtsamSmoother(mode="fixed-lag", lag_s=0.3)
    p.setup(ctx)
    released = []
    for f in frames:
        p.process(f)
        got = p.release()
        for g in got:  # final once the newest star is at least lag_s later
            assert g.attitudes[-1].t_ns <= f.stars.t_ns.max() - 0.3e9
        released += got
    released += p.finish()
    assert [o.index for o in released] == list(range(12))
    assert all(a.valid and a.covariance_rad2 is not None for o in released for a in o.attitudes)
    # a gap longer than the window (frames 4-9 dropped: 0.7 s > 0.2 s lag + 3 frame periods): the
    # frames before it are released before GTSAM marginalises them, still valid
    gap = frames[:4] + frames[10:]
    outs = run_plugin(GtsamSmoother(mode="fixed-lag", lag_s=0.2), gap, ctx)
    assert [o.index for o in outs] == [0, 1, 2, 3, 10, 11]
    assert all(a.valid and a.covariance_rad2 is not None for o in outs for a in o.attitudes)


def test_gyro_bias_recovered():
    bias_deg_h = np.array([20.0, -15.0, 10.0])
    gyro = {"rate_hz": 200.0, "bias_deg_h": tuple(bias_deg_h), "arw_deg_sqrt_h": 0.005, "rrw_deg_h_sqrt_h": 0.0}
    frames, motion, ctx, _ = sim_frames(100, gyro=gyro, seed=5)
    outs = run_plugin(GtsamSmoother(gyro_arw_deg_sqrt_h=0.005, gyro_rrw_deg_h_sqrt_h=0.001), frames, ctx)
    mid = outs[50]
    est = np.degrees(mid.attitudes[0].gyro_bias_rad_s) * 3600
    sigma = np.degrees(np.sqrt(np.diag(mid.rate.covariance))) * 3600
    assert np.all(np.abs(est - bias_deg_h) < 4 * sigma), (est, sigma)
    assert np.all(np.abs(est - bias_deg_h) < 2.0) and sigma.max() < 1.0


def test_invalid_cases_are_flagged_not_invented():
    frames, motion, ctx, _ = sim_frames(4)
    empty = frames[1].evolve(stars=frames[1].stars.take(np.zeros(15, dtype=bool)))
    outs = run_plugin(GtsamSmoother(), [frames[0], empty, frames[2], frames[3]], ctx)
    assert not outs[1].attitudes[0].valid and "no identified stars" in outs[1].attitudes[0].reason
    assert all(a.valid for o in (outs[0], outs[2], outs[3]) for a in o.attitudes)
    # one star in the whole log: the attitude about it is unobservable
    one = [f.evolve(stars=f.stars.take(np.array([3]))) for f in frames[:3]]
    outs = run_plugin(GtsamSmoother(), one, ctx)
    assert all(not a.valid and "unobservable" in a.reason for o in outs for a in o.attitudes)


def test_runner_writes_each_smoothed_frame_once(tmp_path):
    from rollingstar.pipelines.config import PipelineConfig
    from rollingstar.pipelines.evaluate import evaluate_log
    from rollingstar.pipelines.runner import run_pipeline
    from rollingstar.pipelines.simulate import simulate_to_log
    from rollingstar.sensors.scenario import load_scenario

    rec = tmp_path / "rec.mcap"
    simulate_to_log(load_scenario("configs/scenarios/he2021b_table2.yaml"), rec, frames=8, seed=2, show_progress=False)
    for mode in ("batch", "fixed-lag"):
        cfg = PipelineConfig(name=f"gtsam_{mode}", stages=[{"kind": "tracking", "params": {}},
                                                            {"kind": "gtsam", "params": {"mode": mode, "lag_s": 0.25}}])
        out = tmp_path / f"{mode}.mcap"
        summary = run_pipeline(rec, cfg, out, show_progress=False)
        m = evaluate_log(out)
        assert summary.frames == m["frames"] == 8
        assert m["attitude_updates"] == summary.valid_estimates == 8 * 15
        assert max(m["attitude_error_arcsec"][f"{a}_rmse"] for a in "xyz") < 20.0


def test_data_inconsistent_with_the_model_is_reported_not_smoothed():
    """A frame whose stars all carry wrong references (a 1 deg misidentification) cannot be fitted:
    the normalised chi-square of the solution exceeds max_chi2_dof and every estimate is invalid."""
    frames, motion, ctx, _ = sim_frames(6, seed=200)
    bad = frames[3].stars
    bad = bad.with_columns(ref_icrs=Rotation.from_rotvec([0.0, np.radians(1.0), 0.0]).apply(bad.ref_icrs))
    frames[3] = frames[3].evolve(stars=bad)
    outs = run_plugin(GtsamSmoother(), frames, ctx)
    assert all(not a.valid and "did not converge" in a.reason for o in outs for a in o.attitudes)
