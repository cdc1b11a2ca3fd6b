"""time-domain correction (he2021a eqs 12-18): known answers."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from rollingstar.estimators.corrections.time_domain import (
    TimeDomainCorrection,
    reference_time_ns,
    time_domain_correct,
)
from rollingstar.estimators.data import FrameData, StarTable
from rollingstar.sensors.timing import DetectorTiming

TIMING = DetectorTiming(mode="rolling", exposure_ns=44_900_000, line_delay_ns=43_900, rows=1024)


def _linear_stars(rng, n, t0):
    """Stars moving linearly; positions given at their own rolling-shutter time (mid-exposure of their row)."""
    p_ref = rng.uniform(20, 1000, (n, 2))  # positions at t = t0
    v = rng.normal(0, 150, (n, 2))
    y = p_ref[:, 1].copy()
    for _ in range(10):  # y = Y(t0 + y ld + T/2)
        t = TIMING.row_mid_exposure_ns(t0, y)
        y = p_ref[:, 1] + v[:, 1] * (t - t0) * 1e-9
    t = TIMING.row_mid_exposure_ns(t0, y)
    pos = p_ref + v * ((t - t0) * 1e-9)[:, None]
    return p_ref, v, pos, t


@pytest.mark.parametrize("reference_row", [None, 0.0, 300.25, 1023.0])
def test_exact_moves_star_to_reference_row_time(reference_row):
    rng = np.random.default_rng(0)
    t0 = 5_000_000_000
    p_at_t0, v, pos, t = _linear_stars(rng, 50, t0)
    stars = StarTable.build(pos[:, 0], pos[:, 1], t, vx=v[:, 0], vy=v[:, 1], catalog_id=np.arange(50))
    plug = TimeDomainCorrection(reference_row=reference_row)
    plug.setup(SimpleNamespace(timing=TIMING))
    frame = FrameData(index=0, t0_ns=t0, stars=stars)
    out = plug.process(frame)
    t_ref = reference_time_ns(TIMING, t0, reference_row)
    k_s = 511.5 if reference_row is None else reference_row
    assert t_ref == t0 + round(k_s * 43_900)
    assert np.all(out.stars.t_ns == t_ref)
    truth = p_at_t0 + v * (t_ref - t0) * 1e-9
    np.testing.assert_allclose(out.stars.x, truth[:, 0], atol=1e-9)
    np.testing.assert_allclose(out.stars.y, truth[:, 1], atol=1e-9)
    np.testing.assert_array_equal(frame.stars.x, pos[:, 0])  # input untouched
    assert out.flags == ()


def test_single_star_by_hand():
    # star at row 100 (own time t0 + 100 ld + T/2), vx = 200 px/s, vy = -50 px/s, moved to row 612
    t0 = 0
    t = TIMING.row_mid_exposure_ns(t0, 100.0)
    xc, yc, tc, ok = time_domain_correct([10.0], [100.0], [200.0], [-50.0], t, t0, TIMING, reference_row=612)
    dt = (100 - 612) * 43.9e-6 + 0.0449 / 2  # seconds from reference time to the star's time
    assert ok.all() and tc[0] == 612 * 43_900
    assert xc[0] == pytest.approx(10.0 - 200.0 * dt, abs=1e-12)
    assert yc[0] == pytest.approx(100.0 + 50.0 * dt, abs=1e-12)


def test_paper_variant_is_eqs_12_to_18_and_claims_its_own_time():
    rng = np.random.default_rng(1)
    t0 = 0
    p_at_t0, v, pos, t = _linear_stars(rng, 20, t0)
    h, k_s = 5.0, 400.0
    xc, yc, tc, ok = time_domain_correct(pos[:, 0], pos[:, 1], v[:, 0], v[:, 1], t, t0, TIMING, k_s, "paper", h)
    # eqs (12)-(18) literally
    t_i = (h - 1) * 43.9e-6 + 44.9e-3
    xp, yp = pos[:, 0] - 0.5 * v[:, 0] * t_i, pos[:, 1] - 0.5 * v[:, 1] * t_i
    np.testing.assert_allclose(xc, xp - v[:, 0] * (yp - k_s) * 43.9e-6, atol=1e-12)
    np.testing.assert_allclose(yc, yp - v[:, 1] * (yp - k_s) * 43.9e-6, atol=1e-12)
    # the claimed t_ns is the time the result represents under constant velocity (to the ns)
    truth = p_at_t0 + v * ((tc - t0) * 1e-9)[:, None]
    np.testing.assert_allclose(np.column_stack([xc, yc]), truth, atol=1e-9 * 300 + 1e-9)
    assert np.all(tc != reference_time_ns(TIMING, t0, k_s))  # not one common time


def test_missing_velocity_left_alone_and_flagged():
    t0 = 0
    t = TIMING.row_mid_exposure_ns(t0, np.array([10.0, 20.0, 30.0]))
    stars = StarTable.build([1.0, 2.0, 3.0], [10.0, 20.0, 30.0], t, vx=[1.0, np.nan, 2.0], vy=[0.0, 1.0, np.nan])
    plug = TimeDomainCorrection()
    plug.setup(SimpleNamespace(timing=TIMING))
    out = plug.process(FrameData(index=0, t0_ns=t0, stars=stars))
    assert out.flags == ("time_domain_no_velocity:2",)
    np.testing.assert_array_equal(out.stars.x[1:], [2.0, 3.0])
    np.testing.assert_array_equal(out.stars.t_ns[1:], t[1:])
    assert out.stars.t_ns[0] == reference_time_ns(TIMING, t0)


def test_simulated_rotation_noise_free():
    """Simulator truth at 2.8 deg/s: true image velocity in, true position at t_ref out.

    The remaining error is the constant-velocity model's: the pinhole projection bends the image
    track (image acceleration); over the <= 45 ms extrapolation it stays below 0.005 px here."""
    from rollingstar.pipelines.simulate import build_simulator
    from rollingstar.pipelines.truth import true_positions
    from rollingstar.sensors import build
    from rollingstar.sensors.scenario import load_scenario

    cfg = load_scenario("configs/scenarios/he2021a.yaml")
    cfg = cfg.model_copy(update={"level": "centroid", "noise": cfg.noise.model_copy(update={"centroid_sigma_px": 0.0}),
                                 "motion": cfg.motion.model_copy(update={"rate_deg_s": (2.0, 2.0, 0.0)})})
    sim = build_simulator(cfg)
    fr = sim.frame(3)
    tr = fr.truth
    cam = build.build_camera(cfg)
    h = 1_000_000  # 1 ms central difference for the true image velocity

    def pos(t):
        t = np.full(len(tr), t, dtype=np.int64) if np.ndim(t) == 0 else t
        return np.column_stack(true_positions(cam, [], sim.motion.attitude(t), tr.unit_icrs, t))

    v = (pos(tr.t_ns + h) - pos(tr.t_ns - h)) / 2e-3
    xc, yc, tc, ok = time_domain_correct(tr.x, tr.y, v[:, 0], v[:, 1], tr.t_ns, fr.t0_ns, sim.timing)
    ref = pos(int(tc[0]))
    err = np.hypot(xc - ref[:, 0], yc - ref[:, 1])
    assert err.max() < 5e-3
    assert np.median(err) < 1e-3
