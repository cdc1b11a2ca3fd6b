"""pso-rate / pso-correction (fu2022 eqs 8-18): loss at the truth, recovery, determinism, invalid input.

``pso-correction`` is the registry alias of ``rate-correction`` that runs the PSO itself on frames
without a valid rate; :func:`pso_correction` builds it as a pipeline config does."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.estimators.corrections.rate import RateCorrection
from rollingstar.estimators.data import FrameData, SensorContext, StarTable
from rollingstar.estimators.rates.pso import (
    PsoRateEstimator,
    _pair_angles,
    angular_distance_loss,
    image_velocity_px_s,
)
from rollingstar.pipelines.registry import get_plugin_class, stage_params
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.catalog import StarCatalog
from rollingstar.sensors.conventions import attitude_from_radec_roll
from rollingstar.sensors.motion import constant_rate
from rollingstar.sensors.simulate import StarTrackerSimulator
from rollingstar.sensors.timing import DetectorTiming

DEG = np.pi / 180.0
OMEGA = np.array([1.0, -0.7, 0.0]) * DEG  # rad/s


def pso_correction(**params):
    """A ``pso-correction`` stage with ``params``, as the runner builds it from a pipeline config."""
    return get_plugin_class("pso-correction")(**stage_params("pso-correction", params))


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
        corr = pso_correction()
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
    corr = pso_correction(particles=40, max_iterations=200, tolerance_deg_s=1e-4)
    corr.setup(ctx)
    out = corr.process(frame)
    t_ref = ctx.timing.frame_reference_ns(0)
    assert np.all(out.stars.t_ns == t_ref)
    # true positions at t_ref: rotate the catalogue stars by the true attitude at t_ref
    att = constant_rate(ctx.initial_attitude, OMEGA).attitude(np.array([t_ref]))[0]
    x, y, _ = ctx.camera.project(att.inv().apply(frame.stars.ref_icrs))
    assert np.max(np.hypot(out.stars.x - x, out.stars.y - y)) < 1e-3
    assert np.max(np.hypot(frame.stars.x - x, frame.stars.y - y)) > 0.5  # the correction did something


def test_correction_reuses_the_pipeline_rate_and_runs_the_pso_once(setup, monkeypatch):
    """pso-rate then pso-correction: the correction takes frame.rate
    instead of re-running the swarm, and its stars equal those of a correction that estimates itself."""
    import rollingstar.estimators.rates.pso as pso

    ctx, frame = setup
    calls = []
    real = pso.pso_minimise

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(pso, "pso_minimise", counting)
    kw = dict(particles=40, max_iterations=200, tolerance_deg_s=1e-4)
    rate_stage, corr = PsoRateEstimator(**kw), pso_correction(**kw)
    for st in (rate_stage, corr):
        st.setup(ctx)
    out = corr.process(rate_stage.process(frame))
    assert len(calls) == 1  # the PSO ran once for the two stages
    alone = pso_correction(**kw, reuse_rate=False)
    alone.setup(ctx)
    ref = alone.process(frame)
    assert len(calls) == 2  # reuse_rate=False estimates again
    assert out.rate is not None and np.array_equal(out.rate.omega_rad_s, ref.rate.omega_rad_s)
    np.testing.assert_array_equal(out.stars.x, ref.stars.x)
    np.testing.assert_array_equal(out.stars.y, ref.stars.y)


def test_correction_with_an_exact_external_rate_is_exact(setup, monkeypatch):
    """A valid frame.rate from elsewhere (here the true 3-axis rate, as a gyro would give) is used as
    is: no PSO, and the rotation model moves the stars exactly to the reference time."""
    import rollingstar.estimators.rates.pso as pso
    from rollingstar.estimators.data import RateEstimate

    ctx, frame = setup

    def forbidden(*args, **kwargs):
        raise AssertionError("the PSO must not run when frame.rate is valid")

    monkeypatch.setattr(pso, "pso_minimise", forbidden)
    corr = pso_correction()
    corr.setup(ctx)
    out = corr.process(frame.evolve(rate=RateEstimate(t_ns=0, omega_rad_s=OMEGA.copy(), valid=True)))
    t_ref = ctx.timing.frame_reference_ns(0)
    att = constant_rate(ctx.initial_attitude, OMEGA).attitude(np.array([t_ref]))[0]
    x, y, _ = ctx.camera.project(att.inv().apply(frame.stars.ref_icrs))
    assert np.max(np.hypot(out.stars.x - x, out.stars.y - y)) < 1e-6
    # an invalid frame.rate is not reused: the PSO runs (and here is forbidden)
    with pytest.raises(AssertionError, match="must not run"):
        corr.process(frame.evolve(rate=RateEstimate(t_ns=0, omega_rad_s=np.full(3, np.nan), valid=False, reason="x")))


def test_pso_correction_params_are_the_estimators(setup):
    """A pso-correction config gives the PSO's parameters beside the correction's (configs written for the
    one-stage plugin): they become rate-correction's estimator_params."""
    corr = pso_correction(particles=40, seed=3, model="linear", reuse_rate=True)
    assert corr.params.estimator == "pso-rate" and corr.params.model == "linear"
    assert corr.params.estimator_params == {"particles": 40, "seed": 3}
    with pytest.raises(Exception, match="particels"):
        pso_correction(particels=40)


def test_rate_correction_after_pso_rate_equals_pso_correction(setup):
    """configs/pipelines/fu2022.yaml: pso-rate then rate-correction (rotation-vector form) moves the
    stars exactly as the one-stage pso-correction does, bit for bit."""
    ctx, frame = setup
    rate_stage, corr, alone = PsoRateEstimator(), RateCorrection(rotation_form="rotation-vector"), pso_correction()
    for st in (rate_stage, corr, alone):
        st.setup(ctx)
    assert isinstance(alone, RateCorrection)
    two = corr.process(rate_stage.process(frame))
    one = alone.process(frame)
    for column in ("x", "y", "t_ns"):
        np.testing.assert_array_equal(getattr(two.stars, column), getattr(one.stars, column))
    np.testing.assert_array_equal(two.rate.omega_rad_s, one.rate.omega_rad_s)
    linear = pso_correction(model="linear")
    linear.setup(ctx)
    assert linear.params.all_estimator_params()["model"] == "linear"  # the PSO's loss takes the correction's model
    assert not np.array_equal(linear.process(frame).stars.x, one.stars.x)
