"""The attitude-increment channel against a gyro (rollingstar.estimators.diagnosis.gyro_channel)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rollingstar.config import validate
from rollingstar.estimators.diagnosis import gyro_channel as gc
from rollingstar.pipelines.diagnose import DiagnoseOptions, diagnose_recording
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.effects import EFFECTS
from rollingstar.sensors.scenario import ScenarioConfig
from rollingstar.studies.bench import discrepancy as D


def _constant_rate_gyro(omega, t0=0, rate_hz=200.0, seconds=1.0):
    t = (t0 + np.arange(int(seconds * rate_hz) + 1) * (1e9 / rate_hz)).astype(np.int64)
    return gc.GyroData(t, np.tile(omega, (t.size, 1)))


def test_gyro_increments_integrate_a_known_motion():
    """Noise-free samples of a constant rate: the increment over any window is Exp(omega dt),
    including windows that start and end inside a sample interval."""
    omega = np.array([0.02, -0.01, 0.005])
    g = _constant_rate_gyro(omega)
    t_ref = np.array([12_345_678, 140_000_000, 301_000_001, 455_555_555], dtype=np.int64)
    inc = gc.gyro_increments(g, t_ref)
    want = Rotation.from_rotvec(np.outer(np.diff(t_ref) / 1e9, omega))
    np.testing.assert_allclose((want.inv() * inc).magnitude(), 0.0, atol=1e-12)
    att = Rotation.from_rotvec([0.1, 0.2, 0.3]) * Rotation.from_rotvec(np.outer((t_ref - t_ref[0]) / 1e9, omega))
    np.testing.assert_allclose(gc.increment_residual(att, t_ref, g), 0.0, atol=1e-12)
    # a gyro bias b shows as -b dt, and the gyro_bias effect with the same b removes it again
    bias = EFFECTS["gyro_bias"](bx_deg_h=36.0)
    gb = gc.GyroData(g.t_ns, bias.apply_gyro(g.t_ns, g.omega))
    e = gc.increment_residual(att, t_ref, gb)
    np.testing.assert_allclose(e[:, 0], -36.0 * np.pi / 180 / 3600 * np.diff(t_ref) / 1e9, rtol=1e-6)
    np.testing.assert_allclose(gc.increment_residual(att, t_ref, gb, (bias,)), 0.0, atol=1e-11)
    sig = gc.gyro_signature(bias.with_values(bx_deg_h=0.0), g, t_ref)[:, :, 0]  # d e / d b_x
    np.testing.assert_allclose(sig[:, 0] * 36.0, e[:, 0], rtol=1e-5)  # linear vs exact composition: O(|omega dt|)


def test_whitener_of_the_tridiagonal_covariance():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4, 3, 3))
    cov_att = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(3)
    pairs = np.array([0, 1, 2])
    t_ref = np.array([0, 100, 200, 300], dtype=np.int64) * 1_000_000
    w = gc.whitener(cov_att, pairs, t_ref, 1e-3)
    # independent: the covariance of e = D delta + n by Monte Carlo-free algebra
    d = np.zeros((9, 12))
    for i, k in enumerate(pairs):
        d[3 * i:3 * i + 3, 3 * k:3 * k + 3] = -np.eye(3)
        d[3 * i:3 * i + 3, 3 * k + 3:3 * k + 6] = np.eye(3)
    big = np.zeros((12, 12))
    for k in range(4):
        big[3 * k:3 * k + 3, 3 * k:3 * k + 3] = cov_att[k]
    cov = d @ big @ d.T + 1e-6 * 0.1 * np.eye(9)
    np.testing.assert_allclose(w @ cov @ w.T, np.eye(9), atol=1e-9)


@pytest.fixture(scope="module")
def gyro_recordings(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("gyro")
    base = D.base_scenario(16)
    cfg = D.design_scenario(base, "rate_reversal", 20.0, np.random.default_rng(3), 16, 3)
    assert cfg.gyro.enabled
    out = {}
    for label, effects in (("null", []), ("bias", [{"kind": "gyro_bias", "params": {"by_deg_h": -40.0}}])):
        rec = tmp / f"{label}.mcap"
        simulate_to_log(validate(ScenarioConfig, {**cfg.model_dump(mode="json"), "effects": effects}, "t"), rec,
                        show_progress=False)
        out[label] = diagnose_recording(rec, cfg, None, DiagnoseOptions(n_boot=10, stability=False))[0]
    return out


def test_gyro_bias_is_named_from_the_increment_channel(gyro_recordings):
    res = gyro_recordings["bias"]
    assert [e["name"] for e in res["effects"]] == ["gyro_bias"], res["verdict"]
    by = res["effects"][0]["params"]["by_deg_h"]
    assert abs(by["value"] + 40.0) < 4 * by["sigma"] and by["sigma"] < 10.0, by
    g = res["gyro_channel"]
    assert g["chi2_dof_before"] > 5 and abs(g["chi2_dof_after"] - 1) < 5 * np.sqrt(2 / g["rows"]), g


def test_null_with_gyro_is_explained_within_noise(gyro_recordings):
    res = gyro_recordings["null"]
    assert res["mismatch"] is False and res["effects"] == [], res["verdict"]
    g = res["gyro_channel"]
    assert g is not None and abs(g["chi2_dof_before"] - 1) < 5 * np.sqrt(2 / g["rows"]), g
    assert not any(u["name"] in ("gyro_bias", "gyro_scale") for u in res["not_testable"])
