"""2 x 2 star position covariances in the rate estimator and the star-motion filters.

Monte Carlo with pixel noise drawn from the stated covariances (5x larger along one random direction
per star): the ls-rate GLS weighting with the 2 x 2 beats the scalar one and its covariance matches
the scatter; the Kalman filters' posterior covariances match the scatter of their estimates; the
compiled 2 x 2 kernel equals the numpy reference and filterpy; isotropic covariance columns change
no number.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from rollingstar.estimators.conformance.scenes import make_scene
from rollingstar.estimators.data import FrameData, SensorContext, StarTable
from rollingstar.estimators.filters.gyro_kf import GyroKalmanFilter
from rollingstar.estimators.filters.kf_cv import KfCvFilter, kf_cv_predict, kf_cv_update
from rollingstar.estimators.filters.kf_cv_kernel import kf_cv_step_cov_kernel
from rollingstar.estimators.rates.ls_rate import (
    LsRateEstimator,
    pixel_sensitivity,
    rotation_null_space,
    solve_rate,
    whitening,
    whitening_rotation_null,
)
from rollingstar.pipelines.simulate import build_simulator
from rollingstar.sensors.scenario import load_scenario

FU2022 = load_scenario("configs/scenarios/fu2022.yaml")


def _anisotropic(rng, n: int, sigma_px: float, ratio: float = 5.0) -> np.ndarray:
    th = rng.uniform(0.0, np.pi, n)
    c, s = np.cos(th), np.sin(th)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    return rot @ np.diag([(ratio * sigma_px) ** 2, sigma_px**2]) @ np.swapaxes(rot, -1, -2)


def _draw(rng, cov):
    return np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=(cov.shape[0], 2)))


def _rate_frame(rate_deg_s=(1.0, 1.0, 2.0)):
    """A noise-free fu2022 frame: exact rolling-shutter centroids, identified, and its context."""
    motion = FU2022.motion.model_copy(update={"rate_deg_s": tuple(rate_deg_s)})
    cfg = FU2022.model_copy(update={"motion": motion, "noise": FU2022.noise.model_copy(update={"centroid_sigma_px": 0.0})})
    sim = build_simulator(cfg)
    tr = sim.frame(0).truth
    stars = StarTable.build(tr.x, tr.y, tr.t_ns, tr.row_time_ns, catalog_id=tr.catalog_id, ref_icrs=tr.unit_icrs)
    return FrameData(index=0, t0_ns=int(sim.timing.frame_start_ns(0)), stars=stars), SensorContext.from_scenario(cfg)


# --------------------------------------------------------------------------------- ls-rate
def test_fast_whitening_with_2x2_covariances_is_the_pseudo_inverse():
    frame, ctx = _rate_frame()
    s = frame.stars
    w = ctx.camera.unproject(s.x, s.y)
    i, j = np.triu_indices(s.n, k=1)
    cov = _anisotropic(np.random.default_rng(3), s.n, 0.05)
    G = pixel_sensitivity(ctx.camera, w, i, j)
    U = rotation_null_space(w, cov)
    L = np.linalg.cholesky(cov)
    B = np.einsum("mnj,njk->mnk", G.reshape(G.shape[0], -1, 2), L).reshape(G.shape)
    assert np.abs(B @ U).max() < 1e-12 * np.abs(B).max() * np.abs(U).max()  # a common rotation changes no angle
    ref, fast = whitening(G, cov), whitening_rotation_null(G, cov, U)
    C = np.einsum("mnj,njk,pnk->mp", G.reshape(G.shape[0], -1, 2), cov, G.reshape(G.shape[0], -1, 2))
    C_plus = ref.T @ ref
    assert np.allclose(C @ C_plus @ C, C, atol=1e-9 * np.abs(C).max())  # the pseudo-inverse of G S G^T
    assert np.allclose(fast.T @ fast, C_plus, rtol=0, atol=1e-11 * np.abs(C_plus).max())


def test_ls_rate_with_2x2_weighting_beats_scalar_and_matches_its_covariance():
    frame, ctx = _rate_frame()
    s = frame.stars
    rng = np.random.default_rng(7)
    cov = _anisotropic(rng, s.n, 0.03)
    sig_iso = np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]))
    dt = (s.t_ns - ctx.timing.frame_reference_ns(frame.t0_ns)) * 1e-9
    truth = np.radians([1.0, 1.0, 2.0])
    trials = 300
    err_full, err_iso, nees = [], [], []
    for _ in range(trials):
        d = _draw(rng, cov)
        full = solve_rate(ctx.camera, s.x + d[:, 0], s.y + d[:, 1], dt, s.ref_icrs, cov)
        iso = solve_rate(ctx.camera, s.x + d[:, 0], s.y + d[:, 1], dt, s.ref_icrs, sig_iso)
        e = full.omega - truth
        err_full.append(e)
        err_iso.append(iso.omega - truth)
        nees.append(e @ np.linalg.solve(full.covariance, e))
    rmse = [np.sqrt(np.mean(np.sum(np.square(e), axis=1))) for e in (err_full, err_iso)]
    assert rmse[0] < 0.8 * rmse[1]  # measured 0.46
    assert abs(np.mean(nees) - 3.0) < 4.5 * np.sqrt(6.0 / trials)


def test_ls_rate_isotropic_covariance_columns_change_no_number():
    frame, ctx = _rate_frame()
    s = frame.stars
    rng = np.random.default_rng(1)
    sig = rng.uniform(0.02, 0.1, s.n)
    noisy = s.with_columns(x=s.x + rng.normal(0, sig), y=s.y + rng.normal(0, sig), sigma_px=sig)
    cols = noisy.with_columns(cov_xx=sig**2, cov_xy=np.zeros(s.n), cov_yy=sig**2)
    out = []
    for stars in (noisy, cols):
        plugin = LsRateEstimator()
        plugin.setup(ctx)
        out.append(plugin.process(frame.evolve(stars=stars)).rate)
    assert np.array_equal(out[0].omega_rad_s, out[1].omega_rad_s)
    assert np.array_equal(out[0].covariance, out[1].covariance)


# --------------------------------------------------------------------------------- kf-cv
def test_compiled_2x2_step_equals_the_numpy_reference():
    rng = np.random.default_rng(4)
    n = 7
    X = rng.normal(size=(n, 4)) * [100, 10, 100, 10]
    A = rng.normal(size=(n, 4, 4))
    P = A @ np.swapaxes(A, 1, 2) + np.eye(4)
    z = X[:, ::2] + rng.normal(size=(n, 2))
    dt = rng.uniform(0.05, 0.2, n)
    R = _anisotropic(rng, n, 0.3)
    Xr, Pr = kf_cv_update(*kf_cv_predict(X, P, dt, 1e-3), z, R)
    Xk, Pk = np.empty_like(X), np.empty_like(P)
    kf_cv_step_cov_kernel(X, P, z, dt, 1e-3, R, Xk, Pk)
    assert np.allclose(Xk, Xr, rtol=1e-12, atol=1e-9)
    assert np.allclose(Pk, Pr, rtol=1e-10, atol=1e-12)
    # with R = r I the general form is the scalar one
    Xs, Ps = kf_cv_update(X, P, z, 0.09)
    Xg, Pg = kf_cv_update(X, P, z, np.broadcast_to(0.09 * np.eye(2), (n, 2, 2)))
    assert np.allclose(Xs, Xg, rtol=1e-12) and np.allclose(Ps, Pg, rtol=1e-10)


def _track_frames(rng, n: int, sigma_px: float, n_frames: int, period_ns: int = 100_000_000):
    """Stars moving at constant image velocity, measured with noise drawn from a stated covariance
    whose long axis turns at random from frame to frame (a smear that changes direction)."""
    x0 = rng.uniform(100, 900, (n, 2))
    v = rng.normal(0, 30, (n, 2))
    frames, truth = [], []
    for k in range(n_frames):
        cov = _anisotropic(rng, n, sigma_px)
        pos = x0 + v * k * period_ns * 1e-9
        z = pos + _draw(rng, cov)
        st = StarTable.build(z[:, 0], z[:, 1], k * period_ns, catalog_id=np.arange(n) + 10,
                             sigma_px=np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1])),
                             cov_xx=cov[:, 0, 0], cov_xy=cov[:, 0, 1], cov_yy=cov[:, 1, 1])
        frames.append(FrameData(index=k, t0_ns=k * period_ns, stars=st))
        truth.append(pos)
    return frames, truth


def _filter_last(plugin, frames, context):
    plugin.setup(context)
    for f in frames:
        out = plugin.process(f)
    return out.stars


def test_kf_cv_with_2x2_noise_is_consistent_and_beats_scalar_noise():
    rng = np.random.default_rng(9)
    scene = make_scene(seed=1)
    sigma = 0.1
    r = 0.5 * (25 + 1) * sigma**2  # the isotropic equivalent of every star's covariance
    errs = {True: [], False: []}
    nees = []
    for _ in range(60):
        frames, truth = _track_frames(rng, 12, sigma, 8)
        for full in (True, False):
            st = _filter_last(KfCvFilter(q=0.0, r=r, star_covariance=full), frames, scene.context)
            e = np.column_stack([st.x, st.y]) - truth[-1]
            errs[full].append(e)
            if full:
                C = np.stack([np.stack([st.cov_xx, st.cov_xy], -1), np.stack([st.cov_xy, st.cov_yy], -1)], -2)
                nees.append(np.einsum("ni,ni->n", e, np.linalg.solve(C, e[..., None])[..., 0]))
    rmse = {k: np.sqrt(np.mean(np.square(v))) for k, v in errs.items()}
    assert rmse[True] < 0.8 * rmse[False]  # measured 0.46
    m = np.concatenate(nees)  # chi-square(2) per star
    assert abs(m.mean() - 2.0) < 4.5 * np.sqrt(4.0 / m.size)


def test_kf_cv_filterpy_backend_agrees_with_2x2_noise():
    rng = np.random.default_rng(10)
    frames, _ = _track_frames(rng, 6, 0.2, 6)
    scene = make_scene(seed=1)
    a = _filter_last(KfCvFilter(q=1e-3, backend="batched"), frames, scene.context)
    b = _filter_last(KfCvFilter(q=1e-3, backend="filterpy"), frames, scene.context)
    for col in ("x", "y", "vx", "vy", "sigma_px", "cov_xx", "cov_xy", "cov_yy"):
        np.testing.assert_allclose(getattr(a, col), getattr(b, col), rtol=0, atol=1e-9)


def test_gyro_kf_with_2x2_noise_is_consistent():
    """A static scene, no gyro motion: the posterior 2 x 2 of every spot matches its error scatter."""
    scene = make_scene(seed=13)
    rng = np.random.default_rng(5)
    cat = scene.context.catalog
    cov = _anisotropic(rng, scene.x.size, 0.1)
    period = int(scene.context.timing.frame_period_ns)
    nees = []
    for _ in range(40):
        kf = GyroKalmanFilter(process_sigma_px=0.0)
        kf.setup(scene.context)
        for k in range(6):
            d = _draw(rng, cov)
            st = StarTable.build(scene.x + d[:, 0], scene.y + d[:, 1], k * period, catalog_id=cat.ids[scene.catalog_index],
                                 ref_icrs=cat.unit_icrs[scene.catalog_index], cov_xx=cov[:, 0, 0], cov_xy=cov[:, 0, 1],
                                 cov_yy=cov[:, 1, 1])
            out = kf.process(FrameData(index=k, t0_ns=k * period, stars=st)).stars
        e = np.column_stack([out.x - scene.x, out.y - scene.y])
        C = np.stack([np.stack([out.cov_xx, out.cov_xy], -1), np.stack([out.cov_xy, out.cov_yy], -1)], -2)
        assert np.allclose(C, cov / 6, rtol=1e-9)  # six measurements of one static position
        nees.append(np.einsum("ni,ni->n", e, np.linalg.solve(C, e[..., None])[..., 0]))
    m = np.concatenate(nees)
    assert abs(m.mean() - 2.0) < 4.5 * np.sqrt(4.0 / m.size)


def test_ls_rate_unprojects_with_the_frames_fitted_camera():
    frame, ctx = _rate_frame()
    s = frame.stars
    fitted = dataclasses.replace(ctx.camera, focal_length_m=ctx.camera.focal_length_m * 1.02)
    dt = (s.t_ns - ctx.timing.frame_reference_ns(frame.t0_ns)) * 1e-9
    sig = np.full(s.n, LsRateEstimator.Params().default_sigma_px)
    direct = {cam: solve_rate(cam, s.x, s.y, dt, s.ref_icrs, np.maximum(sig, 1e-3)).omega for cam in (fitted, ctx.camera)}
    ctx0 = dataclasses.replace(ctx, centroid_sigma_px=None)  # the plugin's default sigma, as ``direct``
    plugin = LsRateEstimator()
    plugin.setup(ctx0)
    for cam, camera in ((fitted, fitted), (ctx.camera, None)):
        omega = plugin.process(frame.evolve(camera=camera)).rate.omega_rad_s
        np.testing.assert_allclose(omega, direct[cam], rtol=1e-9)
    assert not np.allclose(direct[fitted], direct[ctx.camera], rtol=1e-6)
