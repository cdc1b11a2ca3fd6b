"""Distortion-aware lost-in-space on simulated wide-field frames: the radial distortion of
sensors/effects/radial_distortion.py is planted by the simulator and recovered by the identifier's
joint fit within its stated uncertainty; the pinhole identifier fails on the same frames."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from rollingstar.estimators.data import FrameData, SensorContext, StarTable
from rollingstar.estimators.identifiers.camera_fit import RadialCamera, fit_camera
from rollingstar.estimators.identifiers.lost_in_space import LostInSpaceIdentifier
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.catalog import StarCatalog
from rollingstar.sensors.effects.base import EffectContext
from rollingstar.sensors.effects.radial_distortion import RadialDistortion
from rollingstar.sensors.motion import PiecewiseMotion, Segment
from rollingstar.sensors.simulate import StarTrackerSimulator
from rollingstar.sensors.timing import DetectorTiming

# an 8 mm lens on 5.5 um pixels: 1024 x 768, 38.8 deg horizontal field (the creusot 8 mm lens is 28 deg)
CAM = PinholeCamera(focal_length_m=0.008, pixel_size_m=5.5e-6, width=1024, height=768)
TIMING = DetectorTiming(mode="global", exposure_ns=50_000_000, line_delay_ns=0, rows=768)
K1 = -0.30  # barrel: -24 px at the middle of the side edge
SIGMA_PX = 0.2


@pytest.fixture(scope="module")
def context():
    catalog = StarCatalog.from_hipparcos(2000.0, 5.5).without_close_pairs(4 * CAM.ifov_rad)
    return SensorContext(camera=CAM, timing=TIMING, catalog=catalog, bit_depth=12)


def distorted_frame(context, attitude: Rotation, seed: int, k1: float = K1):
    motion = PiecewiseMotion(attitude, [Segment(10**12, np.zeros(3))])
    sim = StarTrackerSimulator(CAM, TIMING, context.catalog, motion, effects=[RadialDistortion(k1=k1)],
                               centroid_sigma_px=SIGMA_PX, seed=seed)
    f = sim.frame(0)
    c = f.centroids
    dist, j = cKDTree(np.column_stack([f.truth.x, f.truth.y])).query(np.column_stack([c["x"], c["y"]]))
    assert dist.max() < 10 * SIGMA_PX
    det = StarTable.build(c["x"], c["y"], c["t_ns"], c["row_time_ns"], flux=c["flux"])
    return FrameData(index=0, t0_ns=f.t0_ns, stars=det), f.truth.catalog_id[j]


def test_radial_camera_matches_the_effect_model():
    """RadialCamera.distort is rollingstar.sensors.effects' RadialDistortion.apply; undistort is its inverse."""
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-200, 1224, 500), rng.uniform(-200, 968, 500)
    cam = RadialCamera.from_pinhole(CAM, k1=-0.3, k2=0.2)
    eff = RadialDistortion(k1=-0.3, k2=0.2)
    w = CAM.unproject(x, y)
    ctx = EffectContext(camera=CAM, x=x, y=y, t_ns=np.zeros(x.size, dtype=np.int64))
    ex, ey = eff.apply(x, y, ctx)
    dx, dy = cam.distort(x, y)
    np.testing.assert_allclose(dx, ex, atol=1e-9)
    np.testing.assert_allclose(dy, ey, atol=1e-9)
    ux, uy = cam.undistort(dx, dy)
    np.testing.assert_allclose(ux, x, atol=1e-8)
    np.testing.assert_allclose(uy, y, atol=1e-8)
    np.testing.assert_allclose(cam.unproject(*cam.project(w)[:2]), w, atol=1e-12)


def test_k1_recovered_within_its_uncertainty(context):
    """Ten random attitudes, k1 = -0.30 planted: every frame identified with no wrong id, residual
    at the noise level, and k1 recovered with |k1_hat - k1| < 3.5 sigma_k1 (the fit's stated
    1-sigma); the normalised errors over the ten frames have an RMS near 1 (0.5-1.6: the stated
    uncertainty is neither optimistic nor inflated)."""
    rng = np.random.default_rng(11)
    lis = LostInSpaceIdentifier(track=False, fit_distortion="radial", distortion_terms=1, pattern_match_max_error=0.005)
    lis.setup(context)
    z = []
    for seed in range(10):
        frame, truth_ids = distorted_frame(context, Rotation.from_quat(rng.normal(size=4)), seed)
        out = lis.process(frame)
        sol = lis.last_solution
        assert sol.accepted, (seed, sol.reason)
        rows = np.array([np.flatnonzero((frame.stars.x == a) & (frame.stars.y == b))[0] for a, b in zip(out.stars.x, out.stars.y)])
        np.testing.assert_array_equal(out.stars.catalog_id, truth_ids[rows])
        assert out.stars.n >= 0.9 * truth_ids.size
        assert sol.residual_rms_px < 2 * SIGMA_PX
        z.append((sol.camera.k1 - K1) / sol.camera_sigma["k1"])
        assert abs(z[-1]) < 3.5, (seed, sol.camera.k1, sol.camera_sigma["k1"])
        assert abs(sol.camera.focal_px - CAM.focal_px) < 4 * sol.camera_sigma["focal_px"]
    assert 0.5 < np.sqrt(np.mean(np.square(z))) < 1.6, z


def test_pinhole_identifier_rejects_what_the_distortion_fit_accepts(context):
    """Same distorted frames: without the fit the residuals exceed the 2 px bound (or the
    pattern search fails); with it the frame is accepted. The fit is what makes the difference."""
    rng = np.random.default_rng(5)
    plain = LostInSpaceIdentifier(track=False, pattern_match_max_error=0.005)
    plain.setup(context)
    fitting = LostInSpaceIdentifier(track=False, fit_distortion="radial", pattern_match_max_error=0.005)
    fitting.setup(context)
    for seed in range(3):
        frame, _ = distorted_frame(context, Rotation.from_quat(rng.normal(size=4)), 100 + seed)
        plain.process(frame)
        fitting.process(frame)
        assert not plain.last_solution.accepted
        assert fitting.last_solution.accepted


def test_joint_fit_of_several_frames_shares_the_intrinsics(context):
    """fit_camera over four frames (known matches, perturbed start): one f, k1, k2 recovered within
    4 sigma, and the joint sigma of k1 is smaller than any single frame's."""
    rng = np.random.default_rng(3)
    obs, att, single = [], [], []
    start = RadialCamera.from_pinhole(CAM)
    start = RadialCamera(start.focal_px * 1.01, start.cx, start.cy)
    for seed in range(4):
        R = Rotation.from_quat(rng.normal(size=4))
        frame, ids = distorted_frame(context, R, 200 + seed)
        ref = context.catalog.unit_icrs[context.catalog.index_of(ids)]
        obs.append((frame.stars.x, frame.stars.y, ref))
        att.append(R * Rotation.from_rotvec(rng.normal(scale=1e-3, size=3)))
        single.append(fit_camera([obs[-1]], [att[-1]], start).sigma["k1"])
    f = fit_camera(obs, att, start)
    assert abs(f.camera.k1 - K1) < 4 * f.sigma["k1"]
    assert abs(f.camera.k2) < 4 * f.sigma["k2"]
    assert abs(f.camera.focal_px - CAM.focal_px) < 4 * f.sigma["focal_px"]
    assert f.sigma["k1"] < min(single)
    assert f.rms_px < 1.5 * SIGMA_PX
