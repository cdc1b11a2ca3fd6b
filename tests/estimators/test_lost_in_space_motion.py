"""Lost-in-space under motion (he2021a sensor, rolling shutter, 0-10 deg/s): detections referred
to one time with the body rate fitted to their image velocities, each star re-matched at its own
row time, and re-acquisition in the frame where tracking loses the stars."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rollingstar.estimators.data import AttitudeEstimate, RateEstimate
from rollingstar.estimators.identifiers.lost_in_space import LostInSpaceIdentifier, fit_body_rate
from rollingstar.sensors.effects.geometry import image_velocity
from rollingstar.sensors.so3 import skew
from tests.estimators.motion_frames import CAM, SIGMA_PX, TIMING, he2021a_context, motion_frames, pointing

DEG = np.pi / 180.0


@pytest.fixture(scope="module")
def context():
    return he2021a_context()


def _wrong(frame, out, truth_ids) -> int:
    """Identified stars whose catalogue id is not the true one (positions are copied unchanged)."""
    det_index = {(x, y): i for i, (x, y) in enumerate(zip(frame.stars.x, frame.stars.y))}
    idx = np.array([det_index[(x, y)] for x, y in zip(out.stars.x, out.stars.y)], dtype=int)
    return int(np.count_nonzero(out.stars.catalog_id != truth_ids[idx])) if idx.size else 0


def test_body_rate_from_image_velocities():
    """The rigid rate whose image velocities are given is recovered exactly; with 2 px/s noise and a
    quarter of the stars carrying unrelated velocities (blends, spurious streaks) still within the
    noise's reach: 0.02 deg/s about x and y (2 px/s over a 4380 px focal length), 0.2 deg/s about the
    boresight (2 px/s over a few hundred px from the centre)."""
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0, 1023, 40), rng.uniform(0, 1023, 40)
    omega = np.radians([7.0, -3.0, 20.0])
    vx, vy = image_velocity(CAM, x, y, omega)
    np.testing.assert_allclose(fit_body_rate(CAM, x, y, vx, vy), omega, atol=1e-9)
    bad = rng.permutation(40)[:10]
    vx = vx + rng.normal(0, 2.0, 40)
    vy = vy + rng.normal(0, 2.0, 40)
    vx[bad], vy[bad] = rng.uniform(-800, 800, 10), rng.uniform(-800, 800, 10)
    err = np.degrees(fit_body_rate(CAM, x, y, vx, vy) - omega)
    assert np.all(np.abs(err) < [0.02, 0.02, 0.2]), err
    # plain least squares is pulled far off by the same outliers
    A = (CAM.projection_jacobian(CAM.unproject(x, y)) @ skew(CAM.unproject(x, y))).reshape(-1, 3)
    plain = np.linalg.lstsq(A, np.column_stack([vx, vy]).reshape(-1), rcond=None)[0]
    assert np.max(np.abs(np.degrees(plain - omega))) > 0.1
    vx[2:] = np.nan
    assert fit_body_rate(CAM, x, y, vx, vy) is None  # three finite velocities needed


@pytest.mark.parametrize("rate_deg_s", [0.0, 3.0, 6.0, 10.0])
def test_cold_start_under_motion(context, rate_deg_s):
    """Lost-in-space on single frames at random attitudes turning about camera x (a 10 deg/s frame's
    stars are imaged up to 45 ms = 34 px apart): with the detections' image velocities at least 95 %
    of the frames with eight or more stars are identified, no star wrongly, 90 % of the stars kept."""
    rng = np.random.default_rng(20 + int(rate_deg_s))
    lis = LostInSpaceIdentifier(track=False)
    lis.setup(context)
    tried = accepted = wrong = 0
    kept = []
    for seed in range(24):
        (frame, truth_ids, _, _), = motion_frames(context, pointing(rng), np.radians([rate_deg_s, 0.0, 0.0]), 1, seed)
        if truth_ids.size < 8:
            continue
        tried += 1
        out = lis.process(frame)
        wrong += _wrong(frame, out, truth_ids)
        if lis.last_solution.accepted:
            accepted += 1
            kept.append(out.stars.n / truth_ids.size)
            assert lis.last_solution.residual_rms_px < 5 * SIGMA_PX
            # image velocities of 2 px/s: 0.01 deg/s about x and y, 0.1 deg/s about the boresight
            err = np.degrees(lis.last_solution.rate_rad_s - np.radians([rate_deg_s, 0, 0]))
            assert np.all(np.abs(err) < [0.03, 0.03, 0.3]), err
    assert tried >= 15 and accepted >= 0.95 * tried, (accepted, tried)
    assert wrong == 0 and min(kept) >= 0.9


def test_cold_start_without_velocities_fits_the_rate_to_the_matches(context):
    """Without image velocities (a centre-of-gravity centroider) the pattern search sees the
    stretched frame; the stars it matches give the rate (attitude-and-rate fit at their own times),
    with which every star is re-matched: no wrong identification, and accepted frames fit to 5 sigma."""
    rng = np.random.default_rng(30)
    lis = LostInSpaceIdentifier(track=False)
    lis.setup(context)
    accepted = 0
    for seed in range(12):
        (frame, truth_ids, _, _), = motion_frames(context, pointing(rng), np.radians([6.0, 0.0, 0.0]), 1, seed,
                                                  velocities=False)
        out = lis.process(frame)
        assert _wrong(frame, out, truth_ids) == 0
        if lis.last_solution.accepted:
            accepted += 1
            assert lis.last_solution.residual_rms_px < 5 * SIGMA_PX
            np.testing.assert_allclose(lis.last_solution.rate_rad_s[0], np.radians(6.0), atol=np.radians(0.3))
    assert accepted >= 6


def test_reacquires_in_the_frame_tracking_is_lost(context):
    """10 deg/s: lost-in-space on frame 0, tracking after with the estimates passed back; a wrong
    estimate (a 1 deg jump) passed back after frame 2 loses the stars on frame 3, which is identified
    lost-in-space in that same frame; frame 4 is tracked again."""
    rng = np.random.default_rng(40)
    frames = motion_frames(context, pointing(rng), np.radians([10.0, 0.0, 0.0]), 6, seed=41)
    lis = LostInSpaceIdentifier(track=True)
    lis.setup(context)
    modes = []
    for frame, truth_ids, motion, _ in frames:
        out = lis.process(frame)
        modes.append(lis.last_mode)
        assert _wrong(frame, out, truth_ids) == 0
        assert out.stars.n >= 0.9 * truth_ids.size, (frame.index, out.stars.n, truth_ids.size, out.flags)
        assert ("track_lost" in out.flags) == (frame.index == 3)
        t_ref = TIMING.frame_reference_ns(frame.t0_ns)
        att = motion.attitude(np.int64(t_ref))
        if frame.index == 2:
            att = att * Rotation.from_rotvec([0.0, DEG, 0.0])
        lis.update_prior(out.evolve(attitudes=(AttitudeEstimate(t_ref, att.as_quat(), out.stars.n),),
                                    rate=RateEstimate(t_ref, motion.angular_velocity(np.int64(t_ref)))))
    assert modes == ["lost-in-space", "tracking", "tracking", "lost-in-space", "tracking", "tracking"]


def test_cold_start_with_the_velocities_reversed(context):
    """A streak's direction of travel is ambiguous on a cold start: with every velocity reversed
    (the rate of the wrong sign) the frames at 10 deg/s are still identified, with the right rate."""
    rng = np.random.default_rng(50)
    lis = LostInSpaceIdentifier(track=False)
    lis.setup(context)
    tried = 0
    for seed in range(8):
        (frame, truth_ids, _, _), = motion_frames(context, pointing(rng), np.radians([10.0, 0.0, 0.0]), 1, seed)
        if truth_ids.size < 8:
            continue
        tried += 1
        reversed_ = frame.evolve(stars=frame.stars.with_columns(vx=-frame.stars.vx, vy=-frame.stars.vy))
        out = lis.process(reversed_)
        assert lis.last_solution.accepted and _wrong(frame, out, truth_ids) == 0
        assert abs(np.degrees(lis.last_solution.rate_rad_s[0]) - 10.0) < 0.05
    assert tried >= 5


def test_a_tracked_frame_carries_the_check_the_stage_mechanics_would_compute(context):
    """Tracked frames carry their identification check (verifies_identification), equal to the one
    the stage mechanics compute from scratch, and no camera of their own (not fitting intrinsics);
    an identifier that does not declare it has whatever it put in frame.identification replaced by
    the stage mechanics' own check."""
    from dataclasses import replace

    from rollingstar.estimators.data import frame_camera
    from rollingstar.estimators.identifiers.integrity import check_frame
    from rollingstar.pipelines.stages import verify_identification

    rng = np.random.default_rng(60)
    frames = motion_frames(context, pointing(rng), np.radians([3.0, 0.0, 0.0]), 4, seed=61)
    lis = LostInSpaceIdentifier(track=True)
    lis.setup(context)
    bound = lis.params.max_false_match_prob
    for frame, _, motion, _ in frames:
        out = lis.process(frame)
        fresh = check_frame(out, frame_camera(out, context), context.catalog, bound)
        # the focal length of the solved field helps matching only; later stages keep the context's camera
        assert out.camera is None
        if lis.last_mode == "tracking":
            assert out.identification == fresh
        else:
            assert out.identification is None
        t_ref = TIMING.frame_reference_ns(frame.t0_ns)
        lis.update_prior(out.evolve(attitudes=(AttitudeEstimate(t_ref, motion.attitude(np.int64(t_ref)).as_quat(),
                                                                out.stars.n),),
                                    rate=RateEstimate(t_ref, motion.angular_velocity(np.int64(t_ref)))))
    assert lis.last_mode == "tracking"
    forged = out.evolve(identification=replace(fresh, passed=False, reason="forged"))
    assert verify_identification(forged, context, bound, own=False).identification == fresh
    assert verify_identification(forged, context, bound * 10, own=True).identification.bound == bound * 10


SHIPPED = dict(fov_tolerance=0.2, pattern_match_max_error=0.005, residual_spread=2.0)  # high_dynamic.yaml's


@pytest.mark.parametrize("params", [dict(pattern_match_max_error=0.005), SHIPPED], ids=["defaults", "shipped"])
def test_the_camera_is_fitted_on_a_still_frame_and_kept_on_a_fast_one(params):
    """``fit_distortion: focal`` with a declared focal length 1 % off the lens's (the simulator's
    camera). A motionless frame fits it back within 0.1 %. A frame turning at 6 deg/s about x (its
    stars moved ~18 px between their row times, far beyond ``fit_max_motion_px``) is not fitted,
    since a fit there would trade the focal length against the rolling shutter's stretch: it hands
    on the camera fitted last (the still frame's), or before any fit the declared one."""
    true_focal = CAM.focal_px
    exact = he2021a_context()
    off = replace(exact, camera=replace(CAM, focal_length_m=1.01 * CAM.focal_length_m))
    rng = np.random.default_rng(7)

    def frame(rate, seed):  # a field with 20 stars or more
        while (f := motion_frames(exact, pointing(rng), rate, 1, seed=seed)[0][0]).stars.n < 20:
            pass
        return f

    still, fast = frame([0.0, 0.0, 0.0], 71), frame([6.0 * DEG, 0.0, 0.0], 72)

    def identifier(context, fit="focal"):
        lis = LostInSpaceIdentifier(track=False, fit_distortion=fit, **params)
        lis.setup(context)
        return lis

    for context in (exact, off):
        lis = identifier(context)
        out = lis.process(fast)
        assert lis.last_solution.accepted and lis.last_solution.rate_rad_s is not None
        assert out.camera.focal_px == context.camera.focal_px and lis.last_solution.camera_sigma == {}

    lis = identifier(off)
    out = lis.process(still)
    assert lis.last_solution.accepted
    fitted = out.camera.focal_px
    assert abs(fitted / true_focal - 1.0) < 1e-3, (fitted, true_focal)
    out = lis.process(fast)
    assert lis.last_solution.accepted and out.camera.focal_px == fitted


def test_fast_frames_match_as_without_the_fit_whatever_the_declared_focal_length():
    """Frames at 6 deg/s with the declared focal length 6 % off: with ``fit_distortion: focal`` (not
    fitted, too fast) every frame gets the identification it gets with ``none``, the same matches
    and the same accepted frames (the solved field's scale matches them in both)."""
    exact = he2021a_context()
    off = replace(exact, camera=replace(CAM, focal_length_m=1.06 * CAM.focal_length_m))
    rng = np.random.default_rng(11)
    frames = [motion_frames(exact, pointing(rng), [6.0 * DEG, 0.0, 0.0], 1, seed=90 + k)[0][0] for k in range(6)]
    results = {}
    for fit in ("none", "focal"):
        lis = LostInSpaceIdentifier(track=False, fit_distortion=fit, **SHIPPED)
        lis.setup(off)
        results[fit] = [(lis.last_solution.accepted, tuple(out.stars.catalog_id))
                        for out in (lis.process(f) for f in frames)]
    assert results["focal"] == results["none"]
    assert sum(accepted for accepted, _ in results["none"]) >= 4, results["none"]


def test_auto_fits_nothing_on_a_camera_the_fit_does_not_model():
    """``auto`` (shipped in high_dynamic) on a fisheye: the identifier sets up with the declared camera
    instead of refusing it, as ``radial`` does."""
    fisheye = replace(he2021a_context(), camera=replace(CAM, projection="equidistant"))
    lis = LostInSpaceIdentifier(fit_distortion="auto")
    lis.setup(fisheye)
    assert not lis._fitting
    with pytest.raises(ValueError, match="use fit_distortion 'none'"):
        LostInSpaceIdentifier(fit_distortion="radial").setup(fisheye)
