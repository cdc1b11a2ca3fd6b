"""Lost-in-space identifier on simulated Hipparcos frames: correct identifications at random
attitudes, rejection of random points and mirrored frames, then tracking with fall-back."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from scipy.stats import binom

from rollingstar.estimators.data import (
    AttitudeEstimate,
    FrameData,
    SensorContext,
    StarTable,
)
from rollingstar.estimators.identifiers.lost_in_space import LostInSpaceIdentifier
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.catalog import StarCatalog
from rollingstar.sensors.motion import PiecewiseMotion, Segment
from rollingstar.sensors.simulate import StarTrackerSimulator
from rollingstar.sensors.timing import DetectorTiming

CAM = PinholeCamera(focal_length_m=0.025, pixel_size_m=5.5e-6, width=1024, height=1024)  # 12.8 deg field
TIMING = DetectorTiming(mode="rolling", exposure_ns=20_000_000, line_delay_ns=10_000, rows=1024)
SIGMA_PX = 0.1


@pytest.fixture(scope="module")
def context():
    # as rollingstar.sensors.build.build_catalog: close doubles (here < 3 px) dropped, they blend in any real image
    catalog = StarCatalog.from_hipparcos(2000.0, 6.5).without_close_pairs(3 * CAM.ifov_rad)
    return SensorContext(camera=CAM, timing=TIMING, catalog=catalog, bit_depth=12)


def simulated(context, attitude: Rotation, seed: int, rate=(0.0, 0.0, 0.0), frames: int = 1):
    """Centroid-level frames (0.1 px noise) and, per frame, the true catalogue id of each detection."""
    motion = PiecewiseMotion(attitude, [Segment(10**12, np.asarray(rate, dtype=float))])
    sim = StarTrackerSimulator(CAM, TIMING, context.catalog, motion, centroid_sigma_px=SIGMA_PX, seed=seed)
    out = []
    for k in range(frames):
        f = sim.frame(k)
        c = f.centroids
        # the true star of each centroid: the nearest true position (noise 0.1 px << star separations)
        dist, j = cKDTree(np.column_stack([f.truth.x, f.truth.y])).query(np.column_stack([c["x"], c["y"]]))
        assert dist.max() < 10 * SIGMA_PX
        det = StarTable.build(c["x"], c["y"], c["t_ns"], c["row_time_ns"], flux=c["flux"])
        out.append((FrameData(index=k, t0_ns=f.t0_ns, stars=det), f.truth.catalog_id[j]))
    return out


def random_attitude(rng) -> Rotation:
    return Rotation.from_quat(rng.normal(size=4))


def test_identifies_random_attitudes_correctly(context):
    """12 random attitudes: every frame with >= 6 stars is accepted, no identification is wrong,
    and at least 90 % of the imaged stars are identified (the re-match gate covers all of them;
    misses can only come from the mutual-nearest-neighbour rule between close pairs)."""
    rng = np.random.default_rng(4)
    lis = LostInSpaceIdentifier(track=False)
    lis.setup(context)
    checked = 0
    for seed in range(12):
        (frame, truth_ids), = simulated(context, random_attitude(rng), seed)
        out = lis.process(frame)
        if truth_ids.size < 6:
            continue
        checked += 1
        sol = lis.last_solution
        assert sol.accepted, (seed, sol.reason)
        assert out.stars.n + out.unmatched.n == frame.stars.n
        # map each identified star back to its detection (positions are copied unchanged)
        det_index = {(x, y): i for i, (x, y) in enumerate(zip(frame.stars.x, frame.stars.y))}
        idx = np.array([det_index[(x, y)] for x, y in zip(out.stars.x, out.stars.y)])
        np.testing.assert_array_equal(out.stars.catalog_id, truth_ids[idx])
        assert out.stars.n >= 0.9 * truth_ids.size
        np.testing.assert_allclose(out.stars.ref_icrs, context.catalog.unit_icrs[context.catalog.index_of(out.stars.catalog_id)])
        assert sol.residual_rms_px < 5 * SIGMA_PX and sol.false_match_prob < 1e-9
    assert checked >= 8


def test_random_points_are_rejected(context):
    """Frames of uniformly random points: never identified, flagged with a reason, nothing matched."""
    rng = np.random.default_rng(5)
    lis = LostInSpaceIdentifier(track=False)
    lis.setup(context)
    for k in range(8):
        n = 40
        det = StarTable.build(rng.uniform(0, 1023, n), rng.uniform(0, 1023, n), np.zeros(n, dtype=np.int64),
                              flux=rng.uniform(100, 10000, n))
        out = lis.process(FrameData(index=k, t0_ns=0, stars=det))
        assert not lis.last_solution.accepted
        assert out.stars.n == 0 and out.unmatched.n == n
        assert any(f.startswith("lost_in_space_rejected:") for f in out.flags), out.flags


def test_mirrored_frame_is_not_identified(context):
    """A mirrored star field has the right pair distances but the wrong handedness: rejected."""
    rng = np.random.default_rng(6)
    lis = LostInSpaceIdentifier(track=False)
    lis.setup(context)
    for seed in range(3):
        (frame, truth_ids), = simulated(context, random_attitude(rng), 100 + seed)
        mirrored = frame.evolve(stars=frame.stars.with_columns(x=CAM.width - 1 - frame.stars.x))
        out = lis.process(mirrored)
        assert out.stars.n == 0 and not lis.last_solution.accepted


def test_false_match_probability_matches_monte_carlo(context):
    """The binomial model behind the false-match probability: random detections falling within the
    gate of N predicted stars. Simulated chance-match counts follow Binomial(n, N pi g^2 / (W H))
    (mean within 3 standard errors; tail frequency P(k >= 3) within 30 %)."""
    rng = np.random.default_rng(7)
    N, n, g = 40, 60, 10.0
    pred = np.column_stack([rng.uniform(50, 974, N), rng.uniform(50, 974, N)])  # no gate overlaps the edge
    trials = 4000
    pts = rng.uniform(-0.5, 1023.5, (trials, n, 2))
    d = np.linalg.norm(pts[:, :, None, :] - pred[None, None], axis=-1).min(axis=-1)
    k = (d <= g).sum(axis=1)
    # (overlapping gates make the union slightly smaller than N pi g^2: the model is conservative)
    p = N * np.pi * g**2 / (1024 * 1024)
    assert abs(k.mean() - n * p) < 3 * np.sqrt(n * p * (1 - p) / trials) + n * p * 0.05
    assert 0.7 < np.mean(k >= 3) / binom.sf(2, n, p) < 1.3


def test_tracks_after_lost_in_space_and_falls_back(context):
    """Frame 0 lost-in-space, then tracking with the prior the runner passes back; a frame of
    random points loses track (flag) and the next real frame is identified lost-in-space again."""
    rng = np.random.default_rng(8)
    att = random_attitude(rng)
    frames = simulated(context, att, 200, rate=(0.002, -0.001, 0.003), frames=4)
    lis = LostInSpaceIdentifier(track=True)
    lis.setup(context)
    modes = []
    for k, (frame, truth_ids) in enumerate(frames):
        if k == 2:
            n = 30
            det = StarTable.build(rng.uniform(0, 1023, n), rng.uniform(0, 1023, n), np.full(n, frame.t0_ns))
            out = lis.process(frame.evolve(stars=det))
            assert out.stars.n == 0 and "track_lost" in out.flags
            modes.append(lis.last_mode)
            continue
        out = lis.process(frame)
        modes.append(lis.last_mode)
        assert out.stars.n >= 0.9 * truth_ids.size
        det_index = {(x, y): i for i, (x, y) in enumerate(zip(frame.stars.x, frame.stars.y))}
        idx = np.array([det_index[(x, y)] for x, y in zip(out.stars.x, out.stars.y)])
        np.testing.assert_array_equal(out.stars.catalog_id, truth_ids[idx])
        # what the runner does after the solver: pass back the attitude fitted to these stars
        fit, _ = Rotation.align_vectors(out.stars.ref_icrs, CAM.unproject(out.stars.x, out.stars.y))
        t_ref = int(TIMING.frame_reference_ns(frame.t0_ns))
        lis.update_prior(out.evolve(attitudes=(AttitudeEstimate(t_ref, fit.as_quat(), out.stars.n),)))
    assert modes == ["lost-in-space", "tracking", "lost-in-space", "lost-in-space"]


def test_needs_detections(context):
    lis = LostInSpaceIdentifier()
    lis.setup(context)
    with pytest.raises(ValueError, match="frame 3: no detections"):
        lis.process(FrameData(index=3, t0_ns=0))
    with pytest.raises(ValueError, match="catalogue"):
        LostInSpaceIdentifier().setup(replace(context, catalog=None))
