"""Tests of the he2021b REQUEST solver (estimators/attitude/request.py)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.quest import QuestSolver
from rollingstar.estimators.attitude.request import (
    RequestSolver,
    davenport_k,
    dominant_quaternion,
    propagate_k,
    transition_matrix,
)
from rollingstar.estimators.conformance.scenes import frames_for_role, make_scene
from rollingstar.estimators.data import (
    FrameData,
    RateEstimate,
    SensorContext,
    StarTable,
    TruthSamples,
)
from rollingstar.pipelines.simulate import build_simulator, truth_sample_times
from rollingstar.sensors.conventions import attitude_error_body_arcsec
from rollingstar.sensors.scenario import load_scenario

SCENARIO = "configs/scenarios/he2021b_table2.yaml"


def _sim_frames(n_frames=3, sigma_px=0.0, rate=0.05):
    cfg = load_scenario(SCENARIO)
    cfg = cfg.model_copy(update={"frames": n_frames,
                                 "noise": cfg.noise.model_copy(update={"centroid_sigma_px": sigma_px}),
                                 "motion": cfg.motion.model_copy(update={"rate_deg_s": (rate, 0.0, 0.0)})})
    sim = build_simulator(cfg)
    ctx = SensorContext.from_scenario(cfg)
    period = int(sim.timing.frame_period_ns)
    frames = []
    for f in sim.frames(n_frames):
        c, tr = f.centroids, f.truth
        # noise-free: match each centroid to its true star exactly
        j = np.argmin(np.hypot(tr.x[None] - c["x"][:, None], tr.y[None] - c["y"][:, None]), axis=1)
        times = truth_sample_times(f.t0_ns, period, 1000.0)
        truth = TruthSamples(times, sim.motion.attitude(times).as_quat(), sim.motion.angular_velocity(times))
        stars = StarTable.build(c["x"], c["y"], c["t_ns"], c["row_time_ns"], catalog_id=tr.catalog_id[j],
                                ref_icrs=tr.unit_icrs[j])
        frames.append(FrameData(index=f.index, t0_ns=f.t0_ns, stars=stars, truth=truth))
    return frames, sim.motion, ctx


def _run(plugin, frames, ctx):
    plugin.setup(ctx)
    return [plugin.process(f) for f in frames]


@pytest.mark.parametrize("group", [1, 3, 5, "frame"])
@pytest.mark.parametrize("source", ["truth", "fixed"])
def test_noise_free_exact_at_reference_rows(group, source):
    frames, motion, ctx = _sim_frames()
    outs = _run(RequestSolver(group_size=group, rate_source=source, rate_deg_s=(0.05, 0, 0)), frames, ctx)
    ests = [a for o in outs for a in o.attitudes]
    g = 15 if group == "frame" else group
    assert len(ests) == 3 * (15 // g)
    valid = [a for a in ests if a.valid]
    assert len(valid) == len(ests) - (1 if group == 1 else 0)  # one star alone fixes no attitude
    t = np.array([a.t_ns for a in valid])
    err = attitude_error_body_arcsec(motion.attitude(t), Rotation.from_quat([a.q_xyzw for a in valid]))
    # linear (first-order) correction over <= 50 ms: residual ~1e-6 arcsec
    assert np.max(np.abs(err)) < 1e-3


def test_update_count_and_timestamps():
    frames, _, ctx = _sim_frames(n_frames=2)
    for group, per_frame in ((1, 15), (3, 5), (5, 3), ("frame", 1), (4, 4)):
        outs = _run(RequestSolver(group_size=group), frames, ctx)
        for f, o in zip(frames, outs):
            t_sorted = np.sort(f.stars.t_ns)
            g = 15 if group == "frame" else group
            expected = t_sorted[np.minimum(np.arange(g, 15 + g, g), 15) - 1][:per_frame]  # each group's last star
            assert [a.t_ns for a in o.attitudes] == expected.tolist()
            assert [a.n_stars for a in o.attitudes] == [min(g, 15 - k * g) for k in range(per_frame)]


def test_frame_group_zero_rate_equals_quest():
    scene = make_scene(seed=7)
    frames = frames_for_role("attitude", scene, n_frames=3)
    quest = QuestSolver()
    quest.setup(scene.context)
    q_quest = [quest.process(f).attitudes[0] for f in frames]
    req = RequestSolver(group_size="frame", rate_source="fixed", forgetting=0.0)
    outs = _run(req, frames, scene.context)
    for qa, o in zip(q_quest, outs):
        (est,) = o.attitudes
        assert est.valid
        d = np.abs(est.q_xyzw - qa.q_xyzw).max()
        assert min(d, np.abs(est.q_xyzw + qa.q_xyzw).max()) < 1e-9
        np.testing.assert_allclose(est.covariance_rad2, qa.covariance_rad2, rtol=1e-9)
    # with memory (forgetting 1) the first frame is still exactly QUEST
    first = _run(RequestSolver(group_size="frame"), frames[:1], scene.context)[0].attitudes[0]
    assert np.abs(first.q_xyzw - q_quest[0].q_xyzw).max() < 1e-9


def test_transition_matrix_matches_body_rate_kinematics():
    rng = np.random.default_rng(3)
    theta = rng.normal(size=(5, 3)) * 0.3
    R1 = Rotation.random(5, random_state=4)
    q2 = np.einsum("nij,nj->ni", transition_matrix(theta), R1.as_quat())  # eq (11)
    expected = (R1 * Rotation.from_rotvec(theta)).as_quat()
    np.testing.assert_allclose(q2, expected, atol=1e-14)
    Phi = transition_matrix(theta)
    np.testing.assert_allclose(Phi @ np.swapaxes(Phi, -1, -2), np.broadcast_to(np.eye(4), Phi.shape), atol=1e-14)


def test_propagated_k_equals_k_of_rotated_vectors():
    rng = np.random.default_rng(5)
    R1 = Rotation.random(random_state=6)
    v = rng.normal(size=(7, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    w1 = R1.inv().apply(v) + rng.normal(size=(7, 3)) * 1e-3  # noisy: K need not be exact
    a = rng.uniform(0.5, 2.0, 7)
    theta = np.array([0.02, -0.05, 0.03])
    K1, _ = davenport_k(w1[None], v[None], a[None])
    w2 = Rotation.from_rotvec(theta).inv().apply(w1)  # camera vectors after the body rotation
    K2, _ = davenport_k(w2[None], v[None], a[None])
    np.testing.assert_allclose(propagate_k(K1[0], theta), K2[0], atol=1e-13)
    # and the eigenvector of the propagated K is the propagated attitude (eq 17)
    q1, _ = dominant_quaternion(K1[0])
    q2, _ = dominant_quaternion(propagate_k(K1[0], theta))
    expected = (Rotation.from_quat(q1) * Rotation.from_rotvec(theta)).as_quat(canonical=True)
    np.testing.assert_allclose(q2, expected, atol=1e-12)


def test_forgetting_weights_and_noise_reduce_with_group_size():
    frames, motion, ctx = _sim_frames(n_frames=20, sigma_px=0.05)
    rms = {}
    for g in (1, 5):
        outs = _run(RequestSolver(group_size=g, rate_source="truth", forgetting=0.5), frames, ctx)
        v = [a for o in outs for a in o.attitudes if a.valid]
        err = attitude_error_body_arcsec(motion.attitude(np.array([a.t_ns for a in v])),
                                         Rotation.from_quat([a.q_xyzw for a in v]))
        rms[g] = np.sqrt(np.mean(err**2, axis=0))
    assert np.all(rms[1] > rms[5])


def test_invalid_cases_flagged_not_invented():
    frames, _, ctx = _sim_frames(n_frames=2)
    # truth requested but absent: every update invalid with a reason
    out = _run(RequestSolver(group_size=5, rate_source="truth"), [frames[0].evolve(truth=None)], ctx)[0]
    assert len(out.attitudes) == 3 and not any(a.valid for a in out.attitudes)
    assert all("truth" in a.reason for a in out.attitudes) and "rate_unavailable" in out.flags
    # estimate source without any frame.rate
    out = _run(RequestSolver(rate_source="estimate"), frames[:1], ctx)[0]
    assert not out.attitudes[0].valid and "attitude_invalid" in out.flags
    # ... with one: valid, and held on the next frame
    r = RateEstimate(t_ns=frames[0].t0_ns, omega_rad_s=np.radians([0.05, 0, 0]))
    req = RequestSolver(rate_source="estimate")
    outs = _run(req, [frames[0].evolve(rate=r), frames[1]], ctx)
    assert all(a.valid for o in outs for a in o.attitudes) and "rate_held" in outs[1].flags
    # a single star: invalid; collinear information never reported valid
    one = frames[0].evolve(stars=frames[0].stars.take(np.array([3])))
    out = _run(RequestSolver(group_size=1, forgetting=0.0), [one], ctx)[0]
    assert not out.attitudes[0].valid and out.attitudes[0].reason
    empty = frames[0].evolve(stars=frames[0].stars.take(np.zeros(15, dtype=bool)))
    out = _run(RequestSolver(), [empty], ctx)[0]
    assert len(out.attitudes) == 1 and not out.attitudes[0].valid


def test_gyro_source_and_needs_truth():
    assert RequestSolver(rate_source="truth").needs_truth and not RequestSolver().needs_truth
    from rollingstar.estimators.data import GyroSamples

    frames, motion, ctx = _sim_frames(n_frames=3)
    gyro = [f.evolve(gyro=GyroSamples(f.truth.t_ns[::5], f.truth.omega_rad_s[::5])) for f in frames]
    outs = _run(RequestSolver(group_size=5, rate_source="gyro"), gyro, ctx)
    v = [a for o in outs for a in o.attitudes]
    assert all(a.valid for a in v)
    err = attitude_error_body_arcsec(motion.attitude(np.array([a.t_ns for a in v])), Rotation.from_quat([a.q_xyzw for a in v]))
    assert np.max(np.abs(err)) < 1e-3


def test_params_validation():
    import pydantic

    with pytest.raises(pydantic.ValidationError):
        RequestSolver(group_size=0)
    with pytest.raises(pydantic.ValidationError):
        RequestSolver(group_size="row")
    with pytest.raises(pydantic.ValidationError):
        RequestSolver(forgetting=1.5)
    assert RequestSolver(group_size="frame").params.group_size == "frame"
