"""QUEST (Shuster & Oh 1981) against the SVD solution of Wahba's problem, and the quest plugin."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.quest import QuestSolver
from rollingstar.estimators.attitude.wahba import quest, quest_covariance, wahba_loss
from rollingstar.estimators.conformance.scenes import identified, make_scene
from rollingstar.estimators.corrections.none import NoCorrection
from rollingstar.estimators.data import FrameData

MIN_SEP_RAD = np.radians(2.0)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _geometry(rng, n, fov_half_rad):
    """n camera-frame directions in a cone of half-angle fov_half_rad, pairwise >= MIN_SEP_RAD apart
    (closer pairs make Wahba's problem itself ill-conditioned: attitude error ~ eps / sep^2)."""
    axis = _unit(rng.normal(size=3))
    out = []
    for _ in range(2000):  # rejection sampling, test set-up only
        v = _unit(axis + np.tan(fov_half_rad) * rng.uniform(-1, 1, 3))
        if all(np.arccos(np.clip(v @ u, -1, 1)) >= MIN_SEP_RAD for u in out):
            out.append(v)
            if len(out) == n:
                return np.array(out)
    return np.array(out)


def _rotation(rng, near_pi: bool) -> Rotation:
    if near_pi:  # within 1e-6 rad of a 180-degree rotation about a random axis
        return Rotation.from_rotvec(_unit(rng.normal(size=3)) * (np.pi - rng.uniform(0, 1e-6)))
    return Rotation.random(random_state=rng)


def _angle(q1, q2) -> np.ndarray:
    """Rotation angle(s) between quaternions, always an array (rad)."""
    return np.atleast_1d((Rotation.from_quat(q1).inv() * Rotation.from_quat(q2)).magnitude())


case = st.fixed_dictionaries({
    "seed": st.integers(0, 2**32 - 1),
    "n": st.integers(2, 30),
    "near_pi": st.booleans(),
    "noise_rad": st.sampled_from([0.0, 1e-5, 1e-3]),
    "fov_deg": st.sampled_from([10.0, 40.0, 120.0]),
    "weighted": st.booleans(),
})


def _problem(c):
    rng = np.random.default_rng(c["seed"])
    obs_true = _geometry(rng, c["n"], np.radians(c["fov_deg"]) / 2)
    R = _rotation(rng, c["near_pi"])
    ref = R.apply(obs_true)
    obs = _unit(obs_true + c["noise_rad"] * rng.normal(size=obs_true.shape))
    w = rng.uniform(0.2, 5.0, len(obs)) if c["weighted"] else np.ones(len(obs))
    return R, ref, obs, w


@settings(max_examples=150, deadline=None)
@given(case)
def test_quest_agrees_with_svd_solution(c):
    R, ref, obs, w = _problem(c)
    res = quest(ref[None], obs[None], w[None])
    assert res.valid[0]
    assert np.isclose(np.linalg.norm(res.q_xyzw[0]), 1.0, atol=1e-12)
    # scipy: align_vectors(a, b, weights) minimises sum w |a - R b|^2, i.e. R maps b (camera) to a (ICRS)
    R_svd, _ = Rotation.align_vectors(ref, obs, w)
    assert _angle(res.q_xyzw[0], R_svd.as_quat())[0] < 1e-9
    # the loss is Wahba's loss at the optimum (with the weights as given)
    assert np.isclose(res.loss[0], wahba_loss(res.q_xyzw, ref, obs, w)[0], rtol=1e-6, atol=1e-12 * w.sum())
    if c["noise_rad"] == 0.0:
        assert _angle(res.q_xyzw[0], R.as_quat())[0] < 1e-10
        assert res.loss[0] < 1e-12 * w.sum()


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 8))
def test_batched_equals_per_frame_with_ragged_mask(seed, F):
    rng = np.random.default_rng(seed)
    N = 12
    ref = np.zeros((F, N, 3))
    obs = np.zeros((F, N, 3))
    mask = np.zeros((F, N), dtype=bool)
    w = rng.uniform(0.5, 2.0, (F, N))
    for f in range(F):
        n = int(rng.integers(2, N + 1))
        o = _geometry(rng, n, np.radians(10.0))
        R = _rotation(rng, near_pi=bool(rng.integers(2)))
        ref[f, :n] = R.apply(o)
        obs[f, :n] = _unit(o + 1e-4 * rng.normal(size=o.shape))
        mask[f, :n] = True
        # padding holds garbage that must be ignored
        ref[f, n:] = rng.normal(size=(N - n, 3))
        obs[f, n:] = np.nan
    batch = quest(ref, obs, w, mask)
    for f in range(F):
        m = mask[f]
        one = quest(ref[f, m][None], obs[f, m][None], w[f, m][None])
        assert batch.valid[f] and one.valid[0]
        assert _angle(batch.q_xyzw[f], one.q_xyzw[0])[0] < 1e-12
        assert np.isclose(batch.loss[f], one.loss[0], rtol=1e-9, atol=1e-15)


def test_weight_scale_invariance_and_loss_scaling():
    rng = np.random.default_rng(3)
    o = _geometry(rng, 6, np.radians(10))
    ref = Rotation.random(random_state=rng).apply(o)
    obs = _unit(o + 1e-4 * rng.normal(size=o.shape))
    w = rng.uniform(0.5, 2, 6)
    a, b = quest(ref, obs, w), quest(ref, obs, 1e10 * w)
    assert _angle(a.q_xyzw, b.q_xyzw)[0] < 1e-12
    assert np.isclose(b.loss[0], 1e10 * a.loss[0], rtol=1e-8)


def test_sequential_rotations_are_needed_at_exactly_180_deg():
    """An exact 180-degree rotation makes QUEST's [X; gamma] vanish; the flips recover it."""
    rng = np.random.default_rng(0)
    o = _geometry(rng, 5, np.radians(20))
    for axis in np.eye(3):
        R = Rotation.from_rotvec(np.pi * axis)
        res = quest(R.apply(o), o)
        assert res.valid[0]
        assert _angle(res.q_xyzw[0], R.as_quat())[0] < 1e-10


@pytest.mark.parametrize(
    "ref, obs, why",
    [
        (np.array([[0, 0, 1.0]]), np.array([[0, 0, 1.0]]), "one star"),
        (np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 0, 1.0]]), np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 0, 1.0]]), "collinear"),
        (np.array([[0, 0, 1.0], [0, 1.0, 0]]), np.array([[0, 0, 1.0], [np.nan, 1.0, 0]]), "nan"),
    ],
)
def test_invalid_cases(ref, obs, why):
    res = quest(ref, obs)
    assert not res.valid[0], why
    assert np.all(np.isnan(res.q_xyzw[0])) and np.isnan(res.loss[0])


def test_invalid_frame_does_not_spoil_the_batch():
    rng = np.random.default_rng(1)
    o = _geometry(rng, 4, np.radians(10))
    R = Rotation.random(random_state=rng)
    ref = np.stack([R.apply(o), R.apply(o)])
    obs = np.stack([o, o])
    mask = np.array([[True] * 4, [True, False, False, False]])
    res = quest(ref, obs, mask=mask)
    assert res.valid.tolist() == [True, False]
    assert _angle(res.q_xyzw[0], R.as_quat())[0] < 1e-10


def test_covariance_matches_monte_carlo():
    """Shuster's P = (sum a_i (I - b b^T))^-1 is the covariance of the QUEST error for small noise."""
    rng = np.random.default_rng(7)
    o = _geometry(rng, 8, np.radians(10))
    R = Rotation.random(random_state=rng)
    sigma = 1e-4
    trials = 2000
    noise = rng.normal(size=(trials, 8, 3)) * sigma
    obs = o[None] + noise - np.einsum("tni,ni->tn", noise, o)[..., None] * o[None]  # tangent-plane noise
    obs = _unit(obs)
    res = quest(np.broadcast_to(R.apply(o), obs.shape), obs)
    err = (R.inv() * Rotation.from_quat(res.q_xyzw)).as_rotvec()  # camera-frame error
    P = quest_covariance(o, np.full(8, 1 / sigma**2))[0]
    emp = np.cov(err.T)
    # 2000 samples: each variance is within ~10% (4.5 sigma of a chi-square with 2000 dof ~ 14%)
    assert np.allclose(np.diag(emp), np.diag(P), rtol=0.15)
    assert np.allclose(emp, P, atol=0.15 * np.sqrt(np.outer(np.diag(P), np.diag(P))))


def test_rejects_mismatched_shapes_and_bad_weights():
    with pytest.raises(ValueError, match="shape"):
        quest(np.zeros((1, 3, 3)), np.zeros((1, 4, 3)))
    with pytest.raises(ValueError, match="weights"):
        quest(np.eye(3), np.eye(3), weights=[1.0, -1.0, 1.0])


# --- plugin -------------------------------------------------------------------------------


def _solve(frame, scene, **params):
    solver = QuestSolver(**params)
    solver.setup(scene.context)
    return solver.process(frame)


def test_plugin_recovers_truth_within_covariance():
    scene = make_scene(seed=4)
    rng = np.random.default_rng(0)
    frame = FrameData(index=0, t0_ns=0, stars=identified(scene, 0, rng, sigma_px=0.05))
    out = _solve(frame, scene)
    est = out.attitudes[-1]
    assert est.valid and est.n_stars == scene.x.size
    err = (scene.truth.inv() * est.rotation).as_rotvec()
    P = est.covariance_rad2
    chi2 = err @ np.linalg.solve(P, err)
    assert chi2 < 16.3  # chi-square 3 dof, p = 0.001
    # cross-boresight sigma ~ (0.05 px / focal_px) / sqrt(n), roll is worse by ~ 1 / field radius
    ifov = scene.context.camera.ifov_rad
    assert np.sqrt(P[0, 0]) == pytest.approx(0.05 * ifov / np.sqrt(scene.x.size), rel=0.1)
    assert np.sqrt(P[2, 2]) > 5 * np.sqrt(P[0, 0])
    assert np.all(np.abs(err) < 4 * np.sqrt(np.diag(P)))


def test_plugin_time_is_weighted_mean_of_star_times():
    scene = make_scene(seed=5)
    rng = np.random.default_rng(0)
    stars = identified(scene, 1_000_000_000_000, rng)
    out = _solve(FrameData(index=0, t0_ns=1_000_000_000_000, stars=stars), scene)
    # equal sigma_px -> equal weights -> the plain mean
    assert out.attitudes[-1].t_ns == int(np.rint(stars.t_ns.astype(float).mean()))
    assert isinstance(out.attitudes[-1].t_ns, int)


def test_plugin_invalid_with_reason_and_ignores_unidentified():
    scene = make_scene(seed=6)
    rng = np.random.default_rng(0)
    stars = identified(scene, 0, rng)
    one = stars.with_columns(catalog_id=np.where(np.arange(stars.n) == 0, stars.catalog_id, -1))
    out = _solve(FrameData(index=3, t0_ns=0, stars=one), scene)
    est = out.attitudes[-1]
    assert not est.valid and "fewer than 2" in est.reason and est.n_stars == 1
    assert "attitude_invalid" in out.flags
    bad = stars.with_columns(x=np.where(np.arange(stars.n) == 2, np.nan, stars.x))
    est = _solve(FrameData(index=3, t0_ns=0, stars=bad), scene).attitudes[-1]
    assert not est.valid and "non-finite" in est.reason


def test_plugin_sigma_weighting():
    """A star with a 100x larger sigma has (almost) no influence on the solution."""
    scene = make_scene(seed=8)
    rng = np.random.default_rng(0)
    stars = identified(scene, 0, rng, sigma_px=0.0)  # exact positions
    shifted = stars.with_columns(x=stars.x + np.where(np.arange(stars.n) == 0, 5.0, 0.0),
                                 sigma_px=np.where(np.arange(stars.n) == 0, 5.0, 0.05))
    est = _solve(FrameData(index=0, t0_ns=0, stars=shifted), scene).attitudes[-1]
    unweighted = _solve(FrameData(index=0, t0_ns=0, stars=shifted), scene, use_star_sigma=False).attitudes[-1]
    e_w = (scene.truth.inv() * est.rotation).magnitude()
    e_u = (scene.truth.inv() * unweighted.rotation).magnitude()
    assert e_w < e_u / 50


def test_no_correction_is_identity():
    scene = make_scene(seed=9)
    stars = identified(scene, 0, np.random.default_rng(0))
    frame = FrameData(index=0, t0_ns=0, stars=stars)
    corr = NoCorrection()
    corr.setup(scene.context)
    out = corr.process(frame)
    assert out is not frame and out.stars is frame.stars
    assert out == frame
