"""gyro-kf: Joseph-form covariance, known-answer steady state, gyro-driven prediction, integrator."""
from __future__ import annotations

import numpy as np

from rollingstar.estimators.conformance.scenes import make_scene
from rollingstar.estimators.data import FrameData, GyroSamples, StarTable
from rollingstar.estimators.filters.gyro_kf import (
    GyroKalmanFilter,
    star_motion_jacobian,
)
from rollingstar.sensors.gyro import GyroIntegrator


def _frames(scene, n, rng, sigma, omega=None, jitter=0.0):
    """Identified spots of a scene moving with constant body rate ``omega`` (first order, eq 8)."""
    ctx = scene.context
    period = int(ctx.timing.frame_period_ns)
    omega = np.zeros(3) if omega is None else np.asarray(omega, dtype=float)
    cat = ctx.catalog
    x, y = scene.x.copy(), scene.y.copy()
    out, truth = [], []
    for k in range(n):
        t0 = k * period
        if k:
            d = np.einsum("nij,j->ni", star_motion_jacobian(x, y, ctx.camera), omega * period * 1e-9)
            x, y = x + d[:, 0], y + d[:, 1]
        zx = x + rng.normal(0, sigma, x.size)
        zy = y + rng.normal(0, sigma, y.size)
        st = StarTable.build(zx, zy, t_ns=t0, row_time_ns=t0, sigma_px=rng.uniform(0.5, 2.0, x.size) * sigma * jitter + sigma * (1 - jitter),
                             catalog_id=cat.ids[scene.catalog_index], ref_icrs=cat.unit_icrs[scene.catalog_index])
        gyro = GyroSamples(np.array([t0], dtype=np.int64), omega[None, :]) if k else GyroSamples.empty()
        out.append(FrameData(index=k, t0_ns=t0, stars=st, gyro=gyro))
        truth.append(np.column_stack([x, y]))
    return out, truth


def test_joseph_covariance_symmetric_psd():
    scene = make_scene(seed=11)
    rng = np.random.default_rng(1)
    frames, _ = _frames(scene, 60, rng, 0.2, omega=[1e-3, -2e-3, 5e-3], jitter=1.0)
    kf = GyroKalmanFilter(process_sigma_px=0.01, gyro_arw_rad_sqrt_s=1e-4)
    kf.setup(scene.context)
    for f in frames:
        kf.process(f)
        P = kf._P
        assert np.array_equal(P, P.transpose(0, 2, 1))
        assert np.all(np.linalg.eigvalsh(P) > 0)


def test_known_answer_steady_state():
    """Static star, no gyro: P- = (Q + sqrt(Q^2 + 4 Q R)) / 2, P = P- R / (P- + R)."""
    scene = make_scene(seed=12)
    rng = np.random.default_rng(2)
    r, q = 0.1, 0.01
    frames, truth = _frames(scene, 400, rng, r)
    kf = GyroKalmanFilter(process_sigma_px=q, measurement_sigma_px=r)
    kf.setup(scene.context)
    errs = []
    for f, tr in zip(frames, truth):
        out = kf.process(f)
        errs.append(np.column_stack([out.stars.x, out.stars.y]) - tr)
    Q, R = q * q, r * r
    p_minus = (Q + np.sqrt(Q * Q + 4 * Q * R)) / 2
    p_ss = p_minus * R / (p_minus + R)
    cid = int(frames[0].stars.catalog_id[0])
    np.testing.assert_allclose(kf.covariance(cid), p_ss * np.eye(2), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(out.stars.sigma_px, np.sqrt(p_ss), rtol=1e-9)
    # the actual error of a static star is far below the measurement noise (q models motion that is absent)
    e = np.concatenate(errs[50:])
    assert np.std(e) < 0.5 * r


def test_gyro_prediction_removes_motion():
    """With the gyro rate the filter follows a moving star without lag: error ~ filtered noise."""
    scene = make_scene(seed=13)
    rng = np.random.default_rng(3)
    omega = [0.02, -0.03, 0.05]  # several px per frame
    frames, truth = _frames(scene, 150, rng, 0.1, omega=omega)
    kf = GyroKalmanFilter(process_sigma_px=0.01, measurement_sigma_px=0.1, reference="instant")
    kf.setup(scene.context)
    errs = [np.column_stack([o.stars.x, o.stars.y]) - tr for o, tr in ((kf.process(f), tr) for f, tr in zip(frames, truth))]
    e = np.concatenate(errs[30:])
    assert np.abs(np.mean(e)) < 0.01
    assert np.std(e) < 0.06
    out = kf.process(frames[-1].evolve(index=999))  # vx, vy are J omega
    J = star_motion_jacobian(out.stars.x, out.stars.y, scene.context.camera)
    np.testing.assert_allclose(np.column_stack([out.stars.vx, out.stars.vy]), J @ np.asarray(omega), rtol=1e-9)


def test_integrator_window_mean_exact():
    """Piecewise-constant rate: instant and exposure-mean increments agree with closed forms."""
    g = GyroIntegrator()
    t = np.arange(1, 6, dtype=np.int64) * 10_000_000
    w = np.array([[1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0], [4.0, 0, 0], [5.0, 0, 0]]) * 1e-3
    g.add(GyroSamples(t, w))  # sample i covers (t_i - 10 ms, t_i]
    inc = g.increment(np.int64(15_000_000), np.int64(35_000_000))
    np.testing.assert_allclose(inc[0], (2 * 5 + 3 * 10 + 4 * 5) * 1e-6)
    # mean of Theta over [10, 20] ms vs [20, 30] ms windows: triangular weighting of the rates
    m = g.increment(np.int64(10_000_000), np.int64(20_000_000), exposure_ns=10_000_000)
    np.testing.assert_allclose(m[0], 0.5 * (2 + 3) * 1e-3 * 0.01)
