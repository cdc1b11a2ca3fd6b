"""The diagnosis with 2 x 2 star position covariances: whitening, chi-square and the joint refit.

Synthetic recordings from the diagnosis forward model (tests/diagnosis/synthetic.py) whose noise is
drawn from stated anisotropic covariances (5x larger along one random direction per star).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from rollingstar.estimators.diagnosis import refit as R
from rollingstar.estimators.diagnosis import residuals
from rollingstar.estimators.diagnosis.library import library
from rollingstar.estimators.diagnosis.observations import (
    fit_nuisance,
    predict,
    star_chi2,
    whiten,
)
from rollingstar.pipelines.diagnose import _position_covariance
from tests.diagnosis.synthetic import synthetic

RS = library()["rolling_shutter"]


@pytest.fixture(autouse=True)
def _one_thread():
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def _anisotropic(rng, n: int, sigma_px: float, ratio: float = 5.0) -> np.ndarray:
    th = rng.uniform(0.0, np.pi, n)
    c, s = np.cos(th), np.sin(th)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    return rot @ np.diag([(ratio * sigma_px) ** 2, sigma_px**2]) @ np.swapaxes(rot, -1, -2)


def _with_2x2_noise(effects=(), seed: int = 0, sigma: float = 0.02, frames: int = 10, stars: int = 20):
    """A noise-free synthetic recording, then noise drawn from per-star anisotropic covariances it states."""
    obs, truth, cam, tim = synthetic(effects, frames=frames, stars=stars, seed=seed, noise=False)
    rng = np.random.default_rng(seed + 100)
    cov = _anisotropic(rng, obs.n, sigma)
    d = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=(obs.n, 2)))
    sig = np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]))
    obs = replace(obs, x=obs.x + d[:, 0], y=obs.y + d[:, 1], sigma=sig, cov=cov)
    return obs, truth, cam, tim


def test_whitening_is_the_inverse_cholesky_factor_and_reduces_to_sigma():
    obs, truth, cam, tim = _with_2x2_noise()
    v = np.random.default_rng(1).normal(size=(obs.n, 2, 3))
    w = whiten(obs, v)
    L = np.linalg.cholesky(obs.cov)
    assert np.allclose(np.einsum("nij,nj...->ni...", L, w), v, rtol=1e-10, atol=1e-12)
    iso = replace(obs, cov=None)
    assert np.array_equal(whiten(iso, v), v / iso.sigma[:, None, None])


def test_whitened_residuals_are_unit_normal_after_the_attitude_fit():
    """Whitened by their 2 x 2, the residuals of the refitted model are N(0, I) per star (3 of the
    2n dof per frame go to its attitude); divided by the isotropic sigma they are not (one axis
    carries 25x the variance of the other, whichever way the star's smear points)."""
    obs, truth, cam, tim = _with_2x2_noise(frames=12, stars=25)
    _, pred = fit_nuisance(obs, truth.attitude, cam, tim, (), None, moving=True)
    st = residuals.chi2_stats(obs, pred, np.ones(obs.n, bool), 3 * obs.n_frames)
    assert abs(st["chi2_dof"] - 1.0) < 4.5 * np.sqrt(2.0 / st["dof"])
    assert np.sum(star_chi2(obs, pred)) == pytest.approx(st["chi2"], rel=1e-12)
    # divided by the isotropic sigma (sqrt(13) times the short axis): along each star's long axis the
    # residuals scatter by sqrt(25 / 13) = 1.39, across it by sqrt(1 / 13) = 0.28
    _, V = np.linalg.eigh(obs.cov)
    r_px = np.column_stack([obs.x - pred.x, obs.y - pred.y])
    assert np.std(np.einsum("ni,ni->n", r_px, V[:, :, 1]) / obs.sigma) > 1.2
    assert np.std(np.einsum("ni,ni->n", r_px, V[:, :, 0]) / obs.sigma) < 0.4
    w = residuals.normalised(obs, pred)
    assert np.allclose(np.cov(w.T), np.eye(2), atol=0.12)


def test_joint_refit_with_2x2_noise_recovers_the_effect_within_its_sigma():
    eff = RS.instance(np.array([2.0]))
    obs, truth, cam, tim = _with_2x2_noise((eff,), seed=3)
    mask = np.ones(obs.n, bool)
    out = R.joint_refit(obs, truth, cam, tim, (), [RS], [np.array([1.5])], mask, moving=True)
    theta, sigma = out["thetas"][0][0], out["sigmas"][0][0]
    assert np.isfinite(sigma) and sigma > 0
    assert abs(theta - 2.0) < 4.5 * sigma
    # the 2 x 2 weighting carries information the isotropic one throws away
    iso = R.joint_refit(replace(obs, cov=None), truth, cam, tim, (), [RS], [np.array([1.5])], mask, moving=True)
    assert sigma < iso["sigmas"][0][0]


def test_prediction_is_independent_of_the_noise_model():
    obs, truth, cam, tim = _with_2x2_noise()
    a, b = predict(obs, truth, cam, tim), predict(replace(obs, cov=None), truth, cam, tim)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.att_jac, b.att_jac)


def test_recorded_covariances_are_used_only_when_some_are_anisotropic():
    sigma = np.array([0.1, 0.2, 0.3])
    iso = np.array([[0.01, 0.0, 0.01], [np.nan, np.nan, np.nan], [0.09, 0.0, 0.09]])
    cov, source = _position_covariance(iso, sigma, "recording")
    assert cov is None and source == "recording"
    aniso = iso.copy()
    aniso[0] = [0.04, 0.01, 0.01]
    cov, source = _position_covariance(aniso, sigma, "recording")
    assert source.startswith("recording") and "2 x 2" in source
    np.testing.assert_array_equal(cov[0], [[0.04, 0.01], [0.01, 0.01]])
    np.testing.assert_allclose(cov[1], 0.2**2 * np.eye(2), rtol=1e-15)  # no covariance recorded: sigma^2 I
    cov, _ = _position_covariance(aniso, np.array([0.1, np.nan, 0.3]), "estimated")
    assert cov is None  # an unknown sigma: the diagnosis estimates the noise, no 2 x 2
