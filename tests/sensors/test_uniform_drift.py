"""Uniform image-velocity simulator (he2021a eq 19): known answers and invariants."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.wahba import quest
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.catalog import StarCatalog
from rollingstar.sensors.image_sim import ImageModel
from rollingstar.sensors.motion import constant_rate
from rollingstar.sensors.timing import DetectorTiming
from rollingstar.sensors.uniform_drift import (
    UniformDriftSimulator,
    drift_reference_vectors,
    image_velocity_px_s,
)

CAM = PinholeCamera(focal_length_m=24.09e-3, pixel_size_m=5.5e-6, width=1024, height=1024)  # he2021a Table 1
TIMING = DetectorTiming(mode="rolling", exposure_ns=44_900_000, line_delay_ns=43_900, rows=1024)
R0 = Rotation.from_euler("zyx", [30.0, -10.0, 5.0], degrees=True)


def _catalog(n=400, seed=0):
    rng = np.random.default_rng(seed)
    # stars uniformly on the detector plane and well beyond it, so that stars drift in and out
    xy = rng.uniform(-1500, 2500, (n, 2))
    unit = R0.apply(CAM.unproject(xy[:, 0], xy[:, 1]))
    return StarCatalog.synthetic(unit, magnitude=np.full(n, 4.0), epoch_year=2025.0)


@pytest.mark.parametrize("axis", [0, 1])
def test_eq19_velocity_is_rate_over_ifov(axis):
    omega = np.zeros(3)
    omega[axis] = np.radians(2.0)
    v = image_velocity_px_s(CAM, constant_rate(R0, omega))
    # eq (19): V = omega * 3600 / IFOV (arcsec), IFOV = pixel / f at the principal point
    speed = np.degrees(omega[axis]) * 3600 / np.degrees(CAM.ifov_rad * 3600)
    assert np.hypot(*v) == pytest.approx(speed, rel=1e-6)
    assert abs(v[axis]) < 1e-6 * speed  # rotation about x moves the image along y, and vice versa


@pytest.mark.parametrize("velocity", [(0.0, 229.0), (-170.0, 80.0), (0.0, 0.0)])
def test_truth_moves_uniformly_and_solves_the_row_equation(velocity):
    sim = UniformDriftSimulator(CAM, TIMING, _catalog(), R0, velocity, centroid_sigma_px=0.0, seed=3)
    f3, f7 = sim.frame(3).truth, sim.frame(7).truth
    assert len(f3) > 20
    # row equation y = Y(t0 + y ld + T/2): the solved centroid is where the drifting star is at t_ns
    t0 = TIMING.frame_start_ns(3)
    t_exact = t0 + f3.y * TIMING.line_delay_ns + TIMING.exposure_ns / 2
    x0, y0, _ = CAM.project(R0.inv().apply(f3.unit_icrs))
    np.testing.assert_allclose(f3.x, x0 + velocity[0] * t_exact * 1e-9, atol=1e-7)
    np.testing.assert_allclose(f3.y, y0 + velocity[1] * t_exact * 1e-9, atol=1e-7)
    np.testing.assert_allclose(f3.t_ns, TIMING.row_mid_exposure_ns(t0, f3.y))
    # the same star in two frames: displacement = V * (time difference), every star alike
    common, i3, i7 = np.intersect1d(f3.catalog_id, f7.catalog_id, return_indices=True)
    assert common.size > 10
    dt = (f7.t_ns[i7] - f3.t_ns[i3]) * 1e-9
    np.testing.assert_allclose(f7.x[i7] - f3.x[i3], velocity[0] * dt, atol=1e-6)
    np.testing.assert_allclose(f7.y[i7] - f3.y[i3], velocity[1] * dt, atol=1e-6)


def test_stars_drift_in_from_outside_the_initial_field():
    sim = UniformDriftSimulator(CAM, TIMING, _catalog(), R0, (0.0, 229.0), seed=0)
    ids0 = set(sim.frame(0).truth.catalog_id)
    late = sim.frame(60).truth  # 60 frames * 90 ms * 229 px/s = 1235 px: the field is fully renewed
    assert len(late) > 20 and not ids0 & set(late.catalog_id)


def test_centroid_noise_and_true_xy():
    sim = UniformDriftSimulator(CAM, TIMING, _catalog(2000), R0, (0.0, 229.0), centroid_sigma_px=0.3, seed=1)
    fr = sim.frame(2)
    tr = fr.truth
    np.testing.assert_allclose(sim.true_xy(tr.unit_icrs, tr.t_ns), np.column_stack([tr.x, tr.y]), atol=1e-6)
    c = fr.centroids
    # measured sorted by y; match back by nearest truth (stars are hundreds of px apart, noise 0.3 px)
    j = np.argmin(np.hypot(c["x"][:, None] - tr.x[None], c["y"][:, None] - tr.y[None]), axis=1)
    err = np.concatenate([c["x"] - tr.x[j], c["y"] - tr.y[j]])
    assert np.std(err) == pytest.approx(0.3, rel=0.15) and abs(np.mean(err)) < 0.1
    np.testing.assert_array_equal(c["t_ns"], TIMING.row_mid_exposure_ns(TIMING.frame_start_ns(2), c["y"]))


def test_image_level_star_centroid_is_the_truth():
    # one bright star drifting at 229 px/s: the centre of gravity of its rendered smear is the true
    # position at its centroid row's mid-exposure (uniform motion: the streak is symmetric about it)
    unit = R0.apply(CAM.unproject(np.array([400.0]), np.array([300.0])))
    cat = StarCatalog.synthetic(unit, magnitude=np.array([1.0]), epoch_year=2025.0)
    model = ImageModel(background_e_per_px_s=0.0, dark_e_per_px_s=0.0, read_noise_e=0.0, full_well_e=1e9, bit_depth=16,
                       photons_per_s_mag0=2e6)
    sim = UniformDriftSimulator(CAM, TIMING, cat, R0, (60.0, 229.0), image_model=model, level="image", seed=0)
    fr = sim.frame(1)
    img = fr.image.astype(float) - model.bias_adu
    r0, c0 = int(fr.truth.y[0]) - 25, int(fr.truth.x[0]) - 25
    win = np.clip(img[r0:r0 + 50, c0:c0 + 50], 0, None)
    yy, xx = np.mgrid[r0:r0 + 50, c0:c0 + 50]
    cx, cy = (win * xx).sum() / win.sum(), (win * yy).sum() / win.sum()
    assert abs(cx - fr.truth.x[0]) < 0.05 and abs(cy - fr.truth.y[0]) < 0.05


def test_reference_vectors_make_quest_return_the_fixed_attitude():
    sim = UniformDriftSimulator(CAM, TIMING, _catalog(), R0, (150.0, -60.0), seed=0)
    tr = sim.frame(10).truth
    refs = drift_reference_vectors(CAM, R0, tr.x, tr.y)
    obs = CAM.unproject(tr.x, tr.y)
    res = quest(refs[None], obs[None], np.ones((1, len(tr))))
    err = (Rotation.from_quat(res.q_xyzw[0]) * R0.inv()).magnitude()
    assert err < 1e-9
