"""pso-rate / pso-correction (fu2022 eqs 8-18): loss at the truth, recovery, determinism, invalid input."""
from __future__ import annotations

import numpy as np
import pytest

from estimators.data import FrameData, StarTable
from estimators.rates.pso import (PsoCorrection, PsoRateEstimator, angular_distance_loss, image_velocity_px_s,
                                  _pair_angles)
from sensors.camera import PinholeCamera
from sensors.catalog import StarCatalog
from sensors.conventions import attitude_from_radec_roll
from sensors.motion import constant_rate
from sensors.simulate import StarTrackerSimulator
from sensors.timing import DetectorTiming
from estimators.data import SensorContext

DEG = np.pi / 180.0
OMEGA = np.array([1.0, -0.7, 0.0]) * DEG  # rad/s


@pytest.fixture(scope="module")
def setup():
    """Table 1 camera, three stars spread over the rows, exact rolling-shutter centroids (no noise)."""
    cam = PinholeCamera(0.042, 5.5e-6, 2048, 1280)
    timing = DetectorTiming("rolling", exposure_ns=100_000_000, line_delay_ns=20_000, rows=1280)
    att = attitude_from_radec_roll(40.0, 20.0, 10.0)
    xy = np.array([[300.0, 150.0], [1700.0, 600.0], [800.0, 1150.0]])
    unit = att.apply(cam.unproject(xy[:, 0], xy[:, 1]))
    catalog = StarCatalog.synthetic(unit, magnitude=np.array([3.0, 4.0, 5.0]), ids=np.array([11, 22, 33]))
    ctx = SensorContext(camera=cam, timing=timing, catalog=catalog, initial_attitude=att, centroid_sigma_px=0.0)
    sim = StarTrackerSimulator(cam, timing, catalog, constant_rate(att, OMEGA))
    tr = sim.frame(0).truth
    assert len(tr) == 3
    stars = StarTable.build(tr.x, tr.y, tr.t_ns, tr.row_time_ns, flux=10 ** (-0.4 * tr.magnitude),
                            catalog_id=tr.catalog_id, ref_icrs=tr.unit_icrs)
    return ctx, FrameData(index=0, t0_ns=0, stars=stars)


def test_velocity_matches_eq8_at_principal_point():
    cam = PinholeCamera(0.042, 5.5e-6, 2048, 1280)
    vx, vy = image_velocity_px_s(cam, OMEGA, cam.cx, cam.cy)
    assert np.isclose(vx, cam.focal_px * OMEGA[1]) and np.isclose(vy, -cam.focal_px * OMEGA[0])


def test_loss_zero_at_true_rate(setup):
    ctx, frame = setup
    s = frame.stars
    t_ref = ctx.timing.frame_reference_ns(0)
    dt = (s.t_ns - t_ref) * 1e-9
    pairs = np.triu_indices(3, k=1)
    cat = _pair_angles(s.ref_icrs, *pairs)
    J = angular_distance_loss(ctx.camera, np.array([OMEGA[:2], [0.0, 0.0], OMEGA[:2] + 0.01 * DEG]),
                              s.x, s.y, dt, cat, pairs, "rotation")
    assert J[0] < 1e-10  # rad: integer-ns row times (1 ns x 133 px/s per deg/s ~ 2e-11 rad)
    assert J[1] > 1e-6 and J[2] > 1e-8


def test_recovers_true_rate_noise_free(setup):
    ctx, frame = setup
    tol = 1e-4
    est = PsoRateEstimator(particles=40, max_iterations=200, tolerance_deg_s=tol)
    est.setup(ctx)
    rate = est.process(frame).rate
    assert rate.valid and rate.omega_rad_s[2] == 0.0
    assert np.max(np.abs(rate.omega_rad_s - OMEGA)) / DEG < tol
    assert 0 < rate.iterations <= 200
    assert rate.t_ns == ctx.timing.frame_reference_ns(0)


def test_deterministic_and_seed_dependent(setup):
    ctx, frame = setup
    out = []
    for seed in (0, 0, 1):
        est = PsoRateEstimator(seed=seed)
        est.setup(ctx)
        out.append(est.process(frame).rate)
    assert np.array_equal(out[0].omega_rad_s, out[1].omega_rad_s) and out[0].iterations == out[1].iterations
    assert not np.array_equal(out[0].omega_rad_s, out[2].omega_rad_s)


def test_too_few_stars_invalid(setup):
    ctx, frame = setup
    two = frame.evolve(stars=frame.stars.take(np.array([0, 1])))
    unid = frame.evolve(stars=frame.stars.with_columns(catalog_id=np.array([5, -1, 7])))
    for f in (two, unid, frame.evolve(stars=StarTable.empty())):
        est = PsoRateEstimator()
        est.setup(ctx)
        out = est.process(f)
        assert not out.rate.valid and "too_few_stars" in out.rate.reason and "rate_invalid" in out.flags
        corr = PsoCorrection()
        corr.setup(ctx)
        c = corr.process(f)
        assert np.array_equal(c.stars.x, f.stars.x) and "rate_invalid" in c.flags


def test_params_validated():
    with pytest.raises(Exception):
        PsoRateEstimator(n_stars=2)
    with pytest.raises(Exception):
        PsoRateEstimator(selection="spread", n_stars="all")
    PsoRateEstimator(n_stars="all")


def test_correction_moves_stars_to_reference_time(setup):
    ctx, frame = setup
    corr = PsoCorrection(particles=40, max_iterations=200, tolerance_deg_s=1e-4)
    corr.setup(ctx)
    out = corr.process(frame)
    t_ref = ctx.timing.frame_reference_ns(0)
    assert np.all(out.stars.t_ns == t_ref)
    # true positions at t_ref: rotate the catalogue stars by the true attitude at t_ref
    att = constant_rate(ctx.initial_attitude, OMEGA).attitude(np.array([t_ref]))[0]
    x, y, _ = ctx.camera.project(att.inv().apply(frame.stars.ref_icrs))
    assert np.max(np.hypot(out.stars.x - x, out.stars.y - y)) < 1e-3
    assert np.max(np.hypot(frame.stars.x - x, frame.stars.y - y)) > 0.5  # the correction did something
