"""Tests of the multiplicative EKF (estimators/attitude/mekf.py): maths, convergence, consistency."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from rollingstar.estimators.attitude.mekf import (
    MekfFilter,
    propagation_matrices,
    star_update,
)
from tests.estimators.attitude_scenes import (
    ARCSEC,
    errors_rad,
    nees,
    run_plugin,
    sim_frames,
    valid_estimates,
)

# Nearly-constant-rate model matched to the simulated constant-rate truth.
MATCHED = {"angular_accel_noise_deg_s_sqrt_s": 1e-6, "attitude_noise_arcsec_sqrt_s": 1e-3}


def test_propagation_matrix_is_the_linearised_error_kinematics():
    """Phi maps a small initial error (dtheta, dbeta) to the error after the step, to first order."""
    rng = np.random.default_rng(0)
    R = Rotation.random(random_state=1)
    u = np.radians([0.3, -0.2, 0.5])  # gyro rate
    beta = np.radians([0.01, 0.02, -0.01])
    dt = 0.02
    Phi, Q = propagation_matrices((u - beta) * dt, dt, 1e-6, 1e-7)
    for _ in range(5):
        d0 = np.concatenate([rng.normal(size=3) * 1e-6, rng.normal(size=3) * 1e-6])
        R_true, b_true = R * Rotation.from_rotvec(d0[:3]), beta + d0[3:]
        R1 = R * Rotation.from_rotvec((u - beta) * dt)
        R1_true = R_true * Rotation.from_rotvec((u - b_true) * dt)
        d1 = np.concatenate([(R1.inv() * R1_true).as_rotvec(), d0[3:]])
        np.testing.assert_allclose(Phi @ d0, d1, atol=1e-12 + 1e-5 * np.abs(d1).max())
    # Farrenkopf's Q is the covariance of the integrated noise: symmetric positive definite
    assert np.allclose(Q, Q.T) and np.all(np.linalg.eigvalsh(Q) > 0)
    # time reversal flips the cross term only
    _, Qb = propagation_matrices(-(u - beta) * dt, -dt, 1e-6, 1e-7)
    np.testing.assert_allclose(Qb[:3, 3:], -Q[:3, 3:])
    np.testing.assert_allclose(np.diag(Qb), np.diag(Q))


def test_star_update_adds_the_star_information_exactly():
    """Information form: one star adds (I - b b^T) / sigma^2 to the attitude block of P^-1."""
    rng = np.random.default_rng(2)
    A = rng.normal(size=(6, 6))
    P = A @ A.T * 1e-8 + np.eye(6) * 1e-9
    R = Rotation.random(random_state=3)
    b = np.array([0.05, -0.03, 1.0])
    b /= np.linalg.norm(b)
    ref = R.apply(b)  # noise-free star: z = 0, no correction
    sigma = 2e-5
    dx, P_new, nis = star_update(R, P, b[None], ref[None], np.array([sigma]))
    np.testing.assert_allclose(dx, 0.0, atol=1e-15)  # rad; the star's sigma is 2e-5
    assert nis == pytest.approx(0.0, abs=1e-12)
    gain = np.linalg.inv(P_new) - np.linalg.inv(P)
    expected = np.zeros((6, 6))
    expected[:3, :3] = (np.eye(3) - np.outer(b, b)) / sigma**2
    np.testing.assert_allclose(gain, expected, atol=1e-6 * np.abs(expected).max())


def test_noise_free_constant_rate_converges_to_truth():
    frames, motion, ctx, _ = sim_frames(30, sigma_px=0.0)
    outs = run_plugin(MekfFilter(**MATCHED, sigma_px=0.05), frames, ctx)
    ests = valid_estimates(outs)
    assert len(ests) == 30 * 15
    err = np.abs(errors_rad(ests[-15:], motion)) / ARCSEC
    assert err.max() < 0.05  # arcsec; the filter's own 1-sigma here is ~0.2 arcsec (z)


def test_static_scene_reaches_the_cramer_rao_scale():
    """Static scene, rate estimated: after K frames the attitude at the newest star has the
    variance of the end point of a straight-line fit, (4K - 2) / (K (K + 1)) times the single-frame
    CRB (the rate is estimated from the same stars); filter covariance and error both on that scale."""
    K = 40
    frames, motion, ctx, crb = sim_frames(K, rate_deg_s=(0.0, 0.0, 0.0), seed=3)
    outs = run_plugin(MekfFilter(**MATCHED), frames, ctx)
    last = valid_estimates(outs)[-1]
    bound = np.diag(crb) * (4 * K - 2) / (K * (K + 1))
    ratio = np.diag(last.covariance_rad2) / bound
    # measured 1.027-1.032 (isotropic sigma = sigma_px / f vs the CRB's exact pixel Jacobian)
    assert np.all((ratio > 0.95) & (ratio < 1.1)), ratio
    err = errors_rad([last], motion)[0]
    assert np.all(np.abs(err) < 4 * np.sqrt(np.diag(last.covariance_rad2)))


def test_nees_within_chi_square_bounds_over_monte_carlo():
    """NEES of the final estimate over M independent runs: sum ~ chi2(3M) (99 % two-sided)."""
    M, K = 24, 8
    values = []
    for seed in range(M):
        frames, motion, ctx, _ = sim_frames(K, seed=100 + seed)
        outs = run_plugin(MekfFilter(**MATCHED), frames, ctx)
        values.append(nees(valid_estimates(outs)[-1:], motion)[0])
    total = float(np.sum(values))
    assert chi2.ppf(0.005, 3 * M) < total < chi2.ppf(0.995, 3 * M), values
    # and the normalised innovations of the updates are consistent too (2 dof per star)
    f = MekfFilter(**MATCHED)
    frames, motion, ctx, _ = sim_frames(K, seed=7)
    run_plugin(f, frames, ctx)
    nis = np.asarray(f.nis)
    assert chi2.ppf(0.005, 2 * nis.size) < nis.sum() < chi2.ppf(0.995, 2 * nis.size)


def test_gyro_bias_recovered():
    bias_deg_h = np.array([20.0, -15.0, 10.0])
    gyro = {"rate_hz": 200.0, "bias_deg_h": tuple(bias_deg_h), "arw_deg_sqrt_h": 0.005, "rrw_deg_h_sqrt_h": 0.0}
    frames, motion, ctx, _ = sim_frames(100, gyro=gyro, seed=5)
    outs = run_plugin(MekfFilter(gyro_arw_deg_sqrt_h=0.005, gyro_rrw_deg_h_sqrt_h=0.001), frames, ctx)
    last = valid_estimates(outs)[-1]
    est = np.degrees(last.gyro_bias_rad_s) * 3600
    sigma = np.degrees(np.sqrt(np.diag(outs[-1].rate.covariance))) * 3600
    assert np.all(np.abs(est - bias_deg_h) < 4 * sigma), (est, sigma)
    assert np.all(np.abs(est - bias_deg_h) < 2.0)  # deg/h, against a 10-20 deg/h bias
    assert sigma.max() < 1.0
    # the rate it reports is the gyro minus the bias: the true body rate
    np.testing.assert_allclose(outs[-1].rate.omega_rad_s, np.radians([0.05, 0, 0]), atol=np.radians(5 / 3600))


def test_invalid_cases_are_flagged():
    frames, motion, ctx, _ = sim_frames(3)
    one = frames[0].evolve(stars=frames[0].stars.take(np.array([4])))
    none = frames[1].evolve(stars=frames[1].stars.take(np.zeros(15, dtype=bool)))
    f = MekfFilter()
    outs = run_plugin(f, [one, none, frames[2]], ctx)
    assert not outs[0].attitudes[0].valid and "not initialised" in outs[0].attitudes[0].reason
    assert not outs[1].attitudes[0].valid and "no identified stars" in outs[1].attitudes[0].reason
    assert all(a.valid for a in outs[2].attitudes) and "attitude_invalid" in outs[0].flags
    # gyro model requested on a recording without a gyro
    out = run_plugin(MekfFilter(motion_model="gyro"), frames[:1], ctx)[0]
    assert not out.attitudes[0].valid and "gyro" in out.attitudes[0].reason
