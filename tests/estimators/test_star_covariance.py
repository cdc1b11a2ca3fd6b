"""2 x 2 star position covariances: their direction covariance, and the attitude solvers weighted by them.

The direction covariance ``E^T J C J^T E`` is checked against finite differences of the camera's
unprojection and against the scatter of unprojected noisy pixels; the solvers (quest + Gauss-Newton,
mekf, gtsam) against Monte Carlo runs whose pixel noise is drawn from the stated covariances, 5x
larger along one random direction per star: the 2 x 2 weighting must beat the scalar one and its
reported covariance must match the scatter (mean NEES 3 within the sampling error of the trials).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.gtsam_smoother import GtsamSmoother
from rollingstar.estimators.attitude.mekf import MekfFilter
from rollingstar.estimators.attitude.quest import QuestSolver
from rollingstar.estimators.attitude.request import RequestSolver
from rollingstar.estimators.attitude.star_covariance import (
    anisotropic_covariance,
    direction_covariance,
    direction_jacobian,
    tangent_basis,
)
from rollingstar.estimators.attitude.wahba import quest, quest_covariance, refine_attitude
from rollingstar.estimators.conformance.scenes import identified, make_scene
from rollingstar.estimators.data import FrameData, StarTable
from rollingstar.sensors.camera import PinholeCamera

CAMERA = PinholeCamera(focal_length_m=0.025, pixel_size_m=5.5e-6, width=2048, height=2048)  # 25.6 deg field


def _edge_pixels():
    """Pixels from the principal point to the corners (foreshortening is largest there)."""
    return np.array([1023.5, 0.0, 2047.0, 100.0, 1900.0]), np.array([1023.5, 0.0, 2047.0, 1800.0, 30.0])


def _anisotropic(rng, n: int, sigma_px: float, ratio: float = 5.0) -> np.ndarray:
    """Covariances (n, 2, 2) px^2 with 1-sigma ``ratio * sigma_px`` along a random direction, ``sigma_px`` across."""
    th = rng.uniform(0.0, np.pi, n)
    c, s = np.cos(th), np.sin(th)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    return rot @ np.diag([(ratio * sigma_px) ** 2, sigma_px**2]) @ np.swapaxes(rot, -1, -2)


# --------------------------------------------------------------------------- direction covariance
@pytest.mark.parametrize("k1", [0.0, -0.08])
def test_direction_jacobian_matches_finite_differences(k1):
    if k1 and "k1" not in {f.name for f in dataclasses.fields(PinholeCamera)}:
        pytest.skip("this PinholeCamera has no radial distortion")
    cam = dataclasses.replace(CAMERA, k1=k1) if k1 else CAMERA
    x, y = _edge_pixels()
    body, J = direction_jacobian(cam, x, y)
    h = 1e-3
    fd = np.stack([(cam.unproject(x + h, y) - cam.unproject(x - h, y)) / (2 * h),
                   (cam.unproject(x, y + h) - cam.unproject(x, y - h)) / (2 * h)], axis=-1)
    assert np.allclose(J, fd, rtol=1e-6, atol=1e-12)
    assert np.allclose(np.einsum("ni,nik->nk", body, J), 0.0, atol=1e-15)  # tangent to the sphere
    # at the principal point one pixel is 1 / focal_px rad along each axis
    assert np.allclose(np.linalg.norm(J[0], axis=0), 1.0 / cam.focal_px, rtol=1e-12)


def test_direction_covariance_matches_monte_carlo():
    rng = np.random.default_rng(11)
    x, y = _edge_pixels()
    C = _anisotropic(rng, x.size, 0.3)
    d = direction_covariance(CAMERA, x, y, C)
    trials = 20000
    noise = np.einsum("nij,tnj->tni", np.linalg.cholesky(C), rng.normal(size=(trials, x.size, 2)))
    b = CAMERA.unproject(x[None] + noise[..., 0], y[None] + noise[..., 1])  # (T, n, 3)
    e = np.einsum("nik,tni->tnk", d.basis, b - d.body[None])  # tangent-plane errors
    for i in range(x.size):
        emp = np.cov(e[:, i].T)
        # 20000 samples: variances within ~4.5 sigma of their sampling error (sqrt(2/T) = 1 %)
        scale = np.sqrt(np.outer(np.diag(d.cov[i]), np.diag(d.cov[i])))
        assert np.allclose(emp, d.cov[i], atol=0.05 * scale), i
    assert np.allclose(d.whiten @ d.cov @ np.swapaxes(d.whiten, -1, -2), np.eye(2), atol=1e-12)
    assert np.allclose(np.swapaxes(d.whiten, -1, -2) @ d.whiten, d.info, rtol=1e-10)
    assert np.allclose(d.info @ d.cov, np.eye(2), atol=1e-10)


def test_isotropic_pixel_noise_is_foreshortened_off_axis():
    """At the principal point s^2 I px^2 is (s / f)^2 I rad^2; off axis the radial sigma shrinks by
    cos^2 of the off-axis angle and the tangential one by cos (the pinhole's foreshortening)."""
    x, y = _edge_pixels()
    d = direction_covariance(CAMERA, x, y, np.broadcast_to(np.eye(2) * 0.04, (x.size, 2, 2)))
    f = CAMERA.focal_px
    assert np.allclose(d.cov[0], np.eye(2) * 0.04 / f**2, rtol=1e-12)
    cos = d.body[1:, 2]
    ev = np.linalg.eigvalsh(d.cov[1:])
    assert np.allclose(np.sqrt(ev[:, 0]), 0.2 / f * cos**2, rtol=1e-9)
    assert np.allclose(np.sqrt(ev[:, 1]), 0.2 / f * cos, rtol=1e-9)


def test_the_scalar_path_applies_exactly_when_every_star_is_isotropic():
    stars = StarTable.build([1.0, 2.0], [3.0, 4.0], 0, sigma_px=[0.1, 0.2])
    assert anisotropic_covariance(stars, 0.05) is None
    iso = stars.with_columns(cov_xx=[0.01, 0.04], cov_xy=[0.0, 0.0], cov_yy=[0.01, 0.04])
    assert anisotropic_covariance(iso, 0.05) is None
    aniso = iso.with_columns(cov_xy=[0.0, 0.01])
    assert anisotropic_covariance(aniso, 0.05).shape == (2, 2, 2)
    assert anisotropic_covariance(aniso, 0.05, star_covariance=False) is None


# --------------------------------------------------------------------------- Gauss-Newton refinement
def test_refinement_with_isotropic_information_is_quest():
    """With W_i = a_i I the Gauss-Newton attitude is QUEST's and its covariance Shuster's."""
    rng = np.random.default_rng(5)
    x, y = rng.uniform(0, 2047, 12), rng.uniform(0, 2047, 12)
    truth = Rotation.random(random_state=rng)
    obs = CAMERA.unproject(x + rng.normal(0, 0.1, 12), y + rng.normal(0, 0.1, 12))
    ref = truth.apply(CAMERA.unproject(x, y))
    a = 1.0 / (rng.uniform(0.05, 0.3, 12) / CAMERA.focal_px) ** 2
    res = quest(ref[None], obs[None], a[None])
    q, P = refine_attitude(res.q_xyzw[0], ref, obs, tangent_basis(obs), a[:, None, None] * np.eye(2))
    assert (Rotation.from_quat(q).inv() * Rotation.from_quat(res.q_xyzw[0])).magnitude() < 1e-13
    assert np.allclose(P, quest_covariance(obs[None], a[None])[0], rtol=1e-8)


# --------------------------------------------------------------------------- the solvers, Monte Carlo
SIGMA_ACROSS_PX = 0.05


def _noisy_frame(scene, index: int, t0_ns: int, cov_px: np.ndarray, rng) -> FrameData:
    """The scene's identified stars with pixel noise drawn from ``cov_px`` and stating it."""
    stars = identified(scene, t0_ns, rng, sigma_px=0.0)
    d = np.einsum("nij,nj->ni", np.linalg.cholesky(cov_px), rng.normal(size=(stars.n, 2)))
    stars = stars.with_columns(x=stars.x + d[:, 0], y=stars.y + d[:, 1],
                               sigma_px=np.sqrt(0.5 * (cov_px[:, 0, 0] + cov_px[:, 1, 1])),
                               cov_xx=cov_px[:, 0, 0], cov_xy=cov_px[:, 0, 1], cov_yy=cov_px[:, 1, 1])
    return FrameData(index=index, t0_ns=t0_ns, stars=stars)


def _run(plugin, frames, context):
    plugin.setup(context)
    outs = [plugin.process(f) for f in frames]
    if plugin.defers_output:
        outs = plugin.release() + list(plugin.finish())
    return outs[-1].attitudes[-1]


def _monte_carlo(make_plugin, trials: int, n_frames: int, seed: int):
    """Per trial the last estimate's error (rad, camera frame) and NEES, with the 2 x 2 weighting and
    with the scalar one, on the same noise."""
    scene = make_scene(seed=seed)
    rng = np.random.default_rng(seed)
    cov_px = _anisotropic(rng, scene.x.size, SIGMA_ACROSS_PX)
    period = int(scene.context.timing.frame_period_ns)
    out = {True: ([], []), False: ([], [])}
    for _ in range(trials):
        frames = [_noisy_frame(scene, k, k * period, cov_px, rng) for k in range(n_frames)]
        for full in (True, False):
            est = _run(make_plugin(full), frames, scene.context)
            assert est.valid
            err = (est.rotation.inv() * scene.truth).as_rotvec()
            out[full][0].append(err)
            out[full][1].append(err @ np.linalg.solve(est.covariance_rad2, err))
    return {k: (np.array(e), np.array(n)) for k, (e, n) in out.items()}


def _check(res, trials: int):
    err_full, nees_full = res[True]
    err_scalar, _ = res[False]
    rmse_full = np.sqrt(np.mean(np.sum(err_full**2, axis=1)))
    rmse_scalar = np.sqrt(np.mean(np.sum(err_scalar**2, axis=1)))
    assert rmse_full < 0.8 * rmse_scalar  # measured 0.44 (quest), 0.54 (mekf, gtsam): 5:1 noise, 14 stars
    # mean NEES of chi-square(3) samples: 3 +- 4.5 sigma of its sampling error sqrt(6 / trials)
    assert abs(np.mean(nees_full) - 3.0) < 4.5 * np.sqrt(6.0 / trials)


def test_quest_refined_with_2x2_beats_scalar_weighting_and_is_consistent():
    trials = 400
    res = _monte_carlo(lambda full: QuestSolver(star_covariance=full), trials, 1, seed=21)
    _check(res, trials)


def test_mekf_with_2x2_noise_beats_scalar_weighting_and_is_consistent():
    trials = 300
    res = _monte_carlo(lambda full: MekfFilter(star_covariance=full, merge_us=1e5), trials, 3, seed=22)
    _check(res, trials)


def test_gtsam_with_2x2_noise_beats_scalar_weighting_and_is_consistent():
    trials = 250
    res = _monte_carlo(lambda full: GtsamSmoother(star_covariance=full, merge_us=1e5), trials, 3, seed=23)
    _check(res, trials)


def test_request_reports_the_actual_covariance_of_its_scalar_weighted_attitude():
    """REQUEST's K takes scalar weights: the attitude is the scalar-weighted one, and with 2 x 2 noise
    its reported covariance is the sandwich, which the Monte Carlo scatter matches."""
    trials = 400
    res = _monte_carlo(lambda full: RequestSolver(star_covariance=full), trials, 1, seed=25)
    assert np.array_equal(res[True][0], res[False][0])
    assert abs(np.mean(res[True][1]) - 3.0) < 4.5 * np.sqrt(6.0 / trials)


def test_isotropic_covariance_columns_change_no_number():
    """Stars stating s^2 I as their 2 x 2 covariance give bit-identical estimates to stars stating s."""
    scene = make_scene(seed=24)
    rng = np.random.default_rng(0)
    stars = identified(scene, 0, rng, sigma_px=0.07)
    s2 = stars.sigma_px**2
    cols = stars.with_columns(cov_xx=s2, cov_xy=np.zeros(stars.n), cov_yy=s2)
    for make in (QuestSolver, MekfFilter, GtsamSmoother, RequestSolver):
        a = _run(make(), [FrameData(index=0, t0_ns=0, stars=stars)], scene.context)
        b = _run(make(), [FrameData(index=0, t0_ns=0, stars=cols)], scene.context)
        assert np.array_equal(a.q_xyzw, b.q_xyzw) and np.array_equal(a.covariance_rad2, b.covariance_rad2)


def test_solvers_unproject_with_the_frames_fitted_camera():
    """Stars imaged by a camera whose focal length differs from the context's by 2 %: every solver
    recovers the truth with the frame's camera (``FrameData.camera``), not with the context's (gtsam
    then reports the data inconsistent with its model: an invalid estimate)."""
    scene = make_scene(seed=26)
    fitted = dataclasses.replace(scene.context.camera, focal_length_m=scene.context.camera.focal_length_m * 1.02)
    x, y, _ = fitted.project(scene.truth.inv().apply(scene.context.catalog.unit_icrs[scene.catalog_index]))
    stars = identified(scene, 0, np.random.default_rng(0), sigma_px=0.0).with_columns(x=x, y=y)
    for make in (QuestSolver, MekfFilter, GtsamSmoother, RequestSolver):
        errs = []
        for camera in (fitted, None):
            est = _run(make(), [FrameData(index=0, t0_ns=0, stars=stars, camera=camera)], scene.context)
            errs.append(np.degrees((est.rotation.inv() * scene.truth).magnitude()) * 3600 if est.valid else np.inf)
        assert errs[0] < 1e-3 < 1.0 < errs[1], (make.name, errs)
