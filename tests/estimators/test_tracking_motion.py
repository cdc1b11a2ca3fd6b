"""Tracking at speed: each star predicted at its own row time with the body motion, the gate from
the prediction covariance (he2021a sensor, rolling shutter, up to 10 deg/s)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from rollingstar.estimators.data import AttitudeEstimate, RateEstimate, StarTable
from rollingstar.estimators.identifiers import tracking
from rollingstar.estimators.identifiers.tracking import (
    BodyMotion,
    TrackingIdentifier,
    match_mahalanobis,
    predict_at_rows,
    prediction_covariance,
)
from tests.estimators.motion_frames import CAM, TIMING, he2021a_context, motion_frames, pointing

DEG = np.pi / 180.0
ARCSEC = DEG / 3600.0


@pytest.fixture(scope="module")
def context():
    return he2021a_context()


def _estimate(motion, t_ns: int, rng, sigma_arcsec: float) -> AttitudeEstimate:
    """The true attitude at ``t_ns`` with a random error of ``sigma_arcsec`` per axis, stating that covariance."""
    err = Rotation.from_rotvec(rng.normal(0.0, sigma_arcsec * ARCSEC, 3))
    return AttitudeEstimate(t_ns, (motion.attitude(np.int64(t_ns)) * err).as_quat(), 30,
                            covariance_rad2=(sigma_arcsec * ARCSEC) ** 2 * np.eye(3))


def _run(context, frames, rng, feed, **params):
    """Track ``frames`` from the true attitude of frame 0's reference time, passing back what ``feed``
    makes of each frame; returns per frame (identified, wrong identifications, true stars)."""
    motion = frames[0][2]
    t_ref0 = TIMING.frame_reference_ns(frames[0][0].t0_ns)
    t = TrackingIdentifier(**params)
    t.setup(replace(context, initial_attitude=motion.attitude(np.int64(t_ref0))))
    out = []
    for frame, truth_ids, *_ in frames:
        res = t.process(frame)
        det_index = {(x, y): i for i, (x, y) in enumerate(zip(frame.stars.x, frame.stars.y))}
        idx = np.array([det_index[(x, y)] for x, y in zip(res.stars.x, res.stars.y)], dtype=int)
        wrong = int(np.count_nonzero(res.stars.catalog_id != truth_ids[idx])) if idx.size else 0
        out.append((res.stars.n, wrong, truth_ids.size))
        t.update_prior(feed(frame, motion))
    return out


def test_row_time_prediction_reproduces_the_rolling_shutter_simulator(context):
    """Each star predicted at its own row time with the exact attitude and rate lands on the position
    the simulator solved independently (its own fixed point), at 10 deg/s about x, y and z."""
    rng = np.random.default_rng(1)
    for rate in ([10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [3.0, -4.0, 8.0]):
        (frame, ids, motion, (tx, ty, tt)), = motion_frames(context, pointing(rng), np.radians(rate), 1, seed=2,
                                                             velocities=False)
        t_ref = TIMING.frame_reference_ns(frame.t0_ns)
        R = motion.attitude(np.int64(t_ref))
        cat = context.catalog
        w0 = R.inv().apply(cat.unit_icrs[cat.index_of(ids)])
        motion_model = BodyMotion(t_ref, omega=np.radians(rate))
        # two iterations of the fixed point (the default) leave (|v_y| ld)^2 = 0.1 % of the first guess'
        # error (up to half the 34 px sweep), four leave nothing visible
        x, y, front, t, _ = predict_at_rows(w0, motion_model, CAM.project, TIMING, frame.t0_ns)
        assert np.all(front)
        np.testing.assert_allclose(x, tx, atol=0.03)
        np.testing.assert_allclose(y, ty, atol=0.03)
        x, y, front, t, _ = predict_at_rows(w0, motion_model, CAM.project, TIMING, frame.t0_ns, iterations=4)
        np.testing.assert_allclose(x, tx, atol=1e-4)
        np.testing.assert_allclose(y, ty, atol=1e-4)
        assert np.max(np.abs(t - tt)) < 100  # ns: t is the time the positions refer to, one iteration behind
        # a single time for every star (no row times) misses by up to half the frame's sweep
        xs, ys, _, _, _ = predict_at_rows(w0, BodyMotion(t_ref, omega=np.radians(rate)), CAM.project, TIMING,
                                          frame.t0_ns, row_times=False)
        assert np.max(np.hypot(xs - tx, ys - ty)) > 5.0


def test_prediction_covariance_matches_monte_carlo():
    """The pixel covariance of a prediction, ``J (P_att + P_rate dt^2 + P_acc dt^4 / 4) J^T``, against
    the scatter of predictions made with attitudes, rates and accelerations drawn from those covariances."""
    rng = np.random.default_rng(3)
    w = CAM.unproject(np.array([100.0, 900.0, 511.5]), np.array([50.0, 700.0, 511.5]))
    dt = np.array([0.05, 0.12, 0.09])
    P_att = np.diag([20.0, 30.0, 200.0]) ** 2 * ARCSEC**2
    P_rate = np.diag([0.05, 0.02, 0.1]) ** 2 * DEG**2
    P_acc = np.eye(3) * (2.0 * DEG) ** 2
    cov = prediction_covariance(CAM, w, dt, P_att, P_rate, P_acc)
    m = 20000
    delta = (rng.multivariate_normal(np.zeros(3), P_att, m)[:, None, :]
             + rng.multivariate_normal(np.zeros(3), P_rate, m)[:, None, :] * dt[None, :, None]
             + 0.5 * rng.multivariate_normal(np.zeros(3), P_acc, m)[:, None, :] * dt[None, :, None] ** 2)
    wt = Rotation.from_rotvec(delta.reshape(-1, 3)).inv().apply(np.tile(w, (m, 1)))
    x, y, _ = CAM.project(wt)
    pix = np.stack([x, y], axis=-1).reshape(m, 3, 2)
    for i in range(3):
        emp = np.cov(pix[:, i].T)
        np.testing.assert_allclose(emp, cov[i], rtol=0.05, atol=0.02 * np.sqrt(cov[i, 0, 0] * cov[i, 1, 1]))


def test_covariance_gate_accepts_its_probability_and_matches_one_to_one():
    """Detections drawn from N(prediction, S + C) are accepted at the gate's probability (binomial
    3 sigma); matches are one-to-one and do not depend on the detections' order."""
    rng = np.random.default_rng(4)
    n = 4000
    ppos = np.column_stack([np.arange(n) * 50.0, np.zeros(n)])  # far apart: each detection has one candidate
    a = rng.uniform(0.5, 3.0, n)
    pcov = np.zeros((n, 2, 2))
    pcov[:, 0, 0], pcov[:, 1, 1], pcov[:, 0, 1] = a**2, 1.0, 0.5 * a
    pcov[:, 1, 0] = pcov[:, 0, 1]
    dcov = np.broadcast_to(0.25 * np.eye(2), (n, 2, 2)).copy()
    dpos = ppos + np.array([rng.multivariate_normal(np.zeros(2), pcov[i] + dcov[i]) for i in range(n)])
    prob = 0.99
    d, s = match_mahalanobis(dpos, dcov, ppos, pcov, chi2.ppf(prob, 2), gate_px=25.0)
    assert np.all(d == s)
    assert abs(d.size / n - prob) < 3 * np.sqrt(prob * (1 - prob) / n)
    # crowded: several detections per prediction, still one-to-one and order-independent
    ppos = rng.uniform(0, 200, (60, 2))
    dpos = np.vstack([ppos + rng.normal(0, 1.0, ppos.shape), rng.uniform(0, 200, (40, 2))])
    pcov = np.broadcast_to(np.eye(2) * 2.0, (60, 2, 2)).copy()
    dcov = np.broadcast_to(np.eye(2) * 0.5, (100, 2, 2)).copy()
    d, s = match_mahalanobis(dpos, dcov, ppos, pcov, chi2.ppf(0.9999, 2), gate_px=10.0)
    assert np.unique(d).size == d.size and np.unique(s).size == s.size
    perm = rng.permutation(100)
    d2, s2 = match_mahalanobis(dpos[perm], dcov, ppos, pcov, chi2.ppf(0.9999, 2), gate_px=10.0)
    assert sorted(zip(perm[d2].tolist(), s2.tolist())) == sorted(zip(d.tolist(), s.tolist()))


@pytest.mark.parametrize("rate_deg_s", [3.0, 10.0])
def test_tracks_at_speed_with_rate_estimates(context, rate_deg_s):
    """20 frames at up to 10 deg/s (69 px between frames) with a 10 px gate: with the rate estimates
    and 10 arcsec attitude estimates passed back, every star of every frame is identified, none
    wrongly; extrapolating nothing (the last attitude) loses them."""
    rng = np.random.default_rng(5)
    rate = np.radians([rate_deg_s, 0.0, 0.0])
    frames = motion_frames(context, pointing(rng), rate, 20, seed=6, velocities=False)

    def feed(frame, motion):
        t_ref = TIMING.frame_reference_ns(frame.t0_ns)
        omega = motion.angular_velocity(np.int64(t_ref)) + rng.normal(0, 0.01 * DEG, 3)
        return frame.evolve(attitudes=(_estimate(motion, t_ref, rng, 10.0),),
                            rate=RateEstimate(t_ref, omega, covariance=(0.01 * DEG) ** 2 * np.eye(3)))

    res = _run(context, frames, rng, feed, gate_px=10.0)
    assert all(wrong == 0 for _, wrong, _ in res)
    # frame 0 is predicted from the initial attitude alone (no rate yet); a star at the detector's
    # edge may be missed
    assert all(n >= total - 1 for n, _, total in res[1:]), res
    still = _run(context, frames, rng, feed, gate_px=10.0, extrapolate=False)
    assert sum(n for n, _, _ in still[1:]) < 0.2 * sum(total for _, _, total in still[1:])


def test_rate_from_two_estimates_and_angular_acceleration(context):
    """Without rate estimates the rate comes from the last two attitudes; with rate estimates of a
    camera accelerating at 20 deg/s^2 the angular acceleration is extrapolated: every star identified."""
    rng = np.random.default_rng(7)
    frames = motion_frames(context, pointing(rng), np.radians([6.0, 0.0, 0.0]), 15, seed=8, velocities=False)
    res = _run(context, frames, rng, lambda f, m: f.evolve(
        attitudes=(_estimate(m, TIMING.frame_reference_ns(f.t0_ns), rng, 5.0),)), gate_px=10.0)
    assert all(wrong == 0 for _, wrong, _ in res) and all(n >= total - 1 for n, _, total in res[2:]), res
    alpha = np.radians([0.0, 20.0, 0.0])
    frames = motion_frames(context, pointing(rng), np.radians([2.0, 0.0, 0.0]), 15, seed=9, velocities=False,
                           alpha_rad_s2=alpha)

    def feed(frame, motion):
        t_ref = TIMING.frame_reference_ns(frame.t0_ns)
        return frame.evolve(attitudes=(_estimate(motion, t_ref, rng, 2.0),), rate=RateEstimate(
            t_ref, motion.angular_velocity(np.int64(t_ref)) + rng.normal(0, 0.002 * DEG, 3),
            covariance=(0.002 * DEG) ** 2 * np.eye(3)))

    res = _run(context, frames, rng, feed, gate_px=5.0, rate_sigma_deg_s=0.002)
    assert all(wrong == 0 for _, wrong, _ in res) and all(n >= total - 1 for n, _, total in res), res
    # the angular acceleration the tracker holds is the true one
    t = TrackingIdentifier(rate_sigma_deg_s=0.002)
    t.setup(replace(context, initial_attitude=frames[0][2].attitude(np.int64(0))))
    for frame, _, motion, _ in frames[:3]:
        t.update_prior(feed(frame, motion))
    np.testing.assert_allclose(t.motion().alpha, alpha, atol=np.radians(0.2))


def test_gyro_propagates_the_prior(context):
    """One attitude estimate only (no rate): with 200 Hz gyro samples the next frames at 10 deg/s are
    identified from the integrated gyro; without the gyro the prior stays still and the stars are lost."""
    rng = np.random.default_rng(10)
    frames = motion_frames(context, pointing(rng), np.radians([10.0, 0.0, 0.0]), 6, seed=11, velocities=False,
                           gyro_hz=200.0)

    def feed(frame, motion):
        if frame.index:
            return frame.evolve(attitudes=())
        return frame.evolve(attitudes=(_estimate(motion, TIMING.frame_reference_ns(frame.t0_ns), rng, 5.0),))

    res = _run(context, frames, rng, feed, gate_px=10.0)
    assert all(wrong == 0 for _, wrong, _ in res) and all(n >= total - 1 for n, _, total in res[1:]), res
    blind = _run(context, frames, rng, feed, gate_px=10.0, use_gyro=False)
    assert sum(n for n, _, _ in blind[1:]) < 0.2 * sum(total for _, _, total in blind[1:])


def test_covariance_gate_rejects_what_the_fixed_gate_takes(context):
    """Once estimates with honest covariances are passed back, a spot 5 px from a star's prediction
    (the star itself missing) is many sigma off and stays unmatched; the fixed 10 px circle takes it."""
    rng = np.random.default_rng(12)
    frames = motion_frames(context, pointing(rng), np.radians([3.0, 0.0, 0.0]), 4, seed=13, velocities=False)
    frame, truth_ids, _, (tx, ty, _) = frames[3]
    moved = frame.stars.with_columns(x=frame.stars.x + np.where(np.arange(frame.stars.n) == 0, 5.0, 0.0))
    frames[3] = (frame.evolve(stars=moved), truth_ids, frames[3][2], (tx, ty, None))

    def feed(frame, motion):
        t_ref = TIMING.frame_reference_ns(frame.t0_ns)
        return frame.evolve(attitudes=(_estimate(motion, t_ref, rng, 3.0),), rate=RateEstimate(
            t_ref, motion.angular_velocity(np.int64(t_ref)) + rng.normal(0, 0.005 * DEG, 3),
            covariance=(0.005 * DEG) ** 2 * np.eye(3)))

    gated = _run(context, frames, rng, feed, refine=False, gate_px=10.0)
    fixed = _run(context, frames, rng, feed, refine=False, gate_px=10.0, gate="fixed")
    assert gated[3] == (truth_ids.size - 1, 0, truth_ids.size)  # all but the moved one, none wrong
    assert fixed[3][0] == truth_ids.size  # the moved spot matched too (5 px off its star)


def test_all_pairs_and_tree_matching_agree(monkeypatch):
    """The all-pairs matching used for a frame's few tens of stars and the k-d tree one used beyond
    agree pair for pair (Euclidean and Mahalanobis), with spurious spots and a non-finite detection."""
    rng = np.random.default_rng(14)
    ppos = rng.uniform(0, 300, (50, 2))
    dpos = np.vstack([ppos[:40] + rng.normal(0, 1.5, (40, 2)), rng.uniform(0, 300, (20, 2)), [[np.nan, 5.0]]])
    pcov = np.broadcast_to(np.eye(2) * 1.5, (50, 2, 2)).copy()
    dcov = np.broadcast_to(np.eye(2) * 0.5, (61, 2, 2)).copy()
    det = StarTable.build(dpos[:, 0], dpos[:, 1], 0)
    dense = (match_mahalanobis(dpos, dcov, ppos, pcov, chi2.ppf(0.9999, 2), 8.0),
             TrackingIdentifier._match(det, ppos[:, 0], ppos[:, 1], 8.0))
    monkeypatch.setattr(tracking, "BRUTE_FORCE_PAIRS", 0)
    trees = (match_mahalanobis(dpos, dcov, ppos, pcov, chi2.ppf(0.9999, 2), 8.0),
             TrackingIdentifier._match(det, ppos[:, 0], ppos[:, 1], 8.0))
    for a, b in zip(dense, trees):
        assert a[0].size >= 35
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
