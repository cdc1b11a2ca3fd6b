"""Gyro simulation: exact integration, noise statistics, scale factor, determinism, prefix stability."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rollingstar.sensors.gyro import NOISE_BLOCK, GyroModel, simulate_gyro
from rollingstar.sensors.motion import (
    JitterMotion,
    constant_acceleration,
    constant_rate,
    inertial_hold,
)

NS = 1_000_000_000
HOLD = inertial_hold(Rotation.identity())


def test_sample_times():
    rec = simulate_gyro(GyroModel(rate_hz=3.0), HOLD, 10, 10 + 2 * NS, seed=0)
    np.testing.assert_array_equal(rec.t_ns, 10 + np.array([0, 333_333_333, 666_666_667, NS, 1_333_333_333, 1_666_666_667, 2 * NS]))
    assert rec.t_ns.dtype == np.int64
    # end is inclusive, and only samples <= end are produced
    assert len(simulate_gyro(GyroModel(rate_hz=100.0), HOLD, 0, NS - 1, seed=0)) == 100
    assert len(simulate_gyro(GyroModel(rate_hz=100.0), HOLD, 0, NS, seed=0)) == 101
    assert len(simulate_gyro(GyroModel(rate_hz=100.0), HOLD, 5, 5, seed=0)) == 1


def test_noise_free_constant_rate_exact():
    w = np.array([0.01, -0.02, 0.3])
    m = constant_rate(Rotation.from_rotvec([0.4, 0.5, -0.6]), w, start_ns=-7)
    rec = simulate_gyro(GyroModel(rate_hz=200.0), m, 0, 2 * NS, seed=3)
    # exact up to rounding: attitude round-off ~1e-16 rad divided by dt = 5 ms
    np.testing.assert_allclose(rec.omega_rad_s, np.broadcast_to(w, rec.omega_rad_s.shape), rtol=0, atol=1e-13)
    np.testing.assert_array_equal(rec.omega_rad_s, rec.true_omega_rad_s)
    np.testing.assert_array_equal(rec.bias_rad_s, 0.0)


def test_integrating_gyro_reproduces_attitude():
    # the samples' increments Exp(omega_k dt_k) compose to the true attitude change exactly
    m = JitterMotion(constant_acceleration(Rotation.identity(), [0.2, -0.1, 0.4], [0.3, 0.5, -0.2]),
                     [[1e-3, 2e-3, 0.0]], [7.0], [[0.0, 1.0, 2.0]])
    model = GyroModel(rate_hz=250.0)
    rec = simulate_gyro(model, m, 0, NS, seed=1)
    dt = np.diff(np.concatenate([[-4_000_000], rec.t_ns])) / NS
    r = m.attitude(-4_000_000)
    for inc in Rotation.from_rotvec(rec.omega_rad_s * dt[:, None]):
        r = r * inc
    assert (r.inv() * m.attitude(rec.t_ns[-1])).magnitude() < 1e-12
    # the interval average differs from the mid-interval instantaneous rate by O(dt^2)
    fine = simulate_gyro(GyroModel(rate_hz=500.0), m, 0, NS, seed=1)
    err_coarse = np.max(np.abs(m.angular_velocity(rec.t_ns - 2_000_000) - rec.true_omega_rad_s))
    err_fine = np.max(np.abs(m.angular_velocity(fine.t_ns - 1_000_000) - fine.true_omega_rad_s))
    assert 3.5 < err_coarse / err_fine < 4.5


def test_bias_and_scale_factor_applied():
    w = np.array([0.5, -0.25, 0.1])
    s = np.array([100e-6, -200e-6, 1e-3])
    b = np.array([1e-4, -2e-4, 3e-5])
    rec = simulate_gyro(GyroModel(rate_hz=100.0, bias_rad_s=b, scale_factor=s), constant_rate(Rotation.identity(), w), 0, NS, seed=0)
    np.testing.assert_allclose(rec.omega_rad_s, np.broadcast_to((1 + s) * w + b, rec.omega_rad_s.shape), rtol=1e-12)
    np.testing.assert_array_equal(rec.bias_rad_s, np.broadcast_to(b, rec.bias_rad_s.shape))


def test_arw_white_noise_sigma_and_allan_deviation():
    n_arw, rate = 2e-4, 400.0
    model = GyroModel(rate_hz=rate, arw_rad_sqrt_s=n_arw)
    rec = simulate_gyro(model, HOLD, 0, 60 * NS, seed=11)
    noise = rec.omega_rad_s
    assert noise.shape[0] == 24001
    # per-sample sigma N / sqrt(dt)
    assert np.std(noise) == pytest.approx(n_arw * np.sqrt(rate), rel=0.05)
    assert np.abs(np.mean(noise)) < 5 * n_arw * np.sqrt(rate) / np.sqrt(noise.size)
    # Allan deviation of white rate noise: sigma(tau) = N / sqrt(tau), tau = 10 samples
    m = 10
    means = noise[: noise.shape[0] // m * m].reshape(-1, m, 3).mean(axis=1)
    adev = np.sqrt(0.5 * np.mean(np.diff(means, axis=0) ** 2))
    assert adev == pytest.approx(n_arw / np.sqrt(m / rate), rel=0.05)
    # independent axes
    assert abs(np.corrcoef(noise[:, 0], noise[:, 1])[0, 1]) < 0.05


def test_rrw_bias_variance_grows_linearly():
    k_rrw, rate, horizon_s = 1e-5, 100.0, 5.0
    model = GyroModel(rate_hz=rate, rrw_rad_s_sqrt_s=k_rrw)
    finals, halves = [], []
    for seed in range(300):
        rec = simulate_gyro(model, HOLD, 0, int(horizon_s * NS), seed=seed)
        finals.append(rec.bias_rad_s[-1])
        halves.append(rec.bias_rad_s[len(rec) // 2])
        np.testing.assert_array_equal(rec.omega_rad_s, rec.bias_rad_s)  # no other error source
    finals, halves = np.array(finals), np.array(halves)
    # 900 samples of a chi-square: relative sd of the variance estimate ~ sqrt(2/900) = 4.7 %
    assert np.mean(finals**2) == pytest.approx(k_rrw**2 * horizon_s, rel=0.15)
    assert np.mean(halves**2) == pytest.approx(k_rrw**2 * horizon_s / 2, rel=0.15)
    # random walk: independent increments
    inc = finals - halves
    assert abs(np.mean(inc * halves)) < 0.15 * k_rrw**2 * horizon_s / 2


def test_deterministic_and_seed_dependent():
    model = GyroModel(rate_hz=100.0, arw_rad_sqrt_s=1e-4, rrw_rad_s_sqrt_s=1e-5)
    a = simulate_gyro(model, HOLD, 0, NS, seed=5)
    b = simulate_gyro(model, HOLD, 0, NS, seed=5)
    c = simulate_gyro(model, HOLD, 0, NS, seed=6)
    np.testing.assert_array_equal(a.omega_rad_s, b.omega_rad_s)
    assert not np.any(a.omega_rad_s == c.omega_rad_s)


def test_prefix_stable_when_end_changes():
    model = GyroModel(rate_hz=1000.0, arw_rad_sqrt_s=1e-4, rrw_rad_s_sqrt_s=1e-5, bias_rad_s=[1e-3, 0, 0])
    m = constant_rate(Rotation.identity(), [0.1, 0.0, 0.0])
    short = simulate_gyro(model, m, 0, 5 * NS, seed=9)
    long = simulate_gyro(model, m, 0, 15 * NS + 7, seed=9)
    assert len(short) > NOISE_BLOCK and len(long) > 3 * NOISE_BLOCK
    n = len(short)
    np.testing.assert_array_equal(long.t_ns[:n], short.t_ns)
    np.testing.assert_array_equal(long.omega_rad_s[:n], short.omega_rad_s)
    np.testing.assert_array_equal(long.bias_rad_s[:n], short.bias_rad_s)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(rate_hz=0.0), "rate_hz"),
        (dict(rate_hz=100.0, arw_rad_sqrt_s=-1.0), "arw_rad_sqrt_s"),
        (dict(rate_hz=100.0, rrw_rad_s_sqrt_s=np.nan), "rrw_rad_s_sqrt_s"),
        (dict(rate_hz=100.0, bias_rad_s=[1.0, 2.0]), "bias_rad_s"),
        (dict(rate_hz=100.0, scale_factor=np.zeros(4)), "scale_factor"),
    ],
)
def test_model_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GyroModel(**kwargs)


def test_simulate_validation():
    model = GyroModel(rate_hz=100.0)
    with pytest.raises(ValueError, match="end_ns"):
        simulate_gyro(model, HOLD, 10, 5, seed=0)
    with pytest.raises(ValueError, match="seed"):
        simulate_gyro(model, HOLD, 0, 5, seed=-1)
    with pytest.raises(ValueError, match="start_ns"):
        simulate_gyro(model, HOLD, 0.5, 5, seed=0)
