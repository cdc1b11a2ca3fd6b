"""Joint refit (rates tied to attitudes), interval coverage, re-simulation, mixed exposures.

Known answers on synthetic recordings built from the diagnosis forward model itself
(tests/diagnosis/synthetic.py), so that the truth is exact.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats
from threadpoolctl import threadpool_limits

from rollingstar.estimators.diagnosis import refit as R
from rollingstar.estimators.diagnosis import resimulate, selection
from rollingstar.estimators.diagnosis.library import library
from rollingstar.estimators.diagnosis.observations import (
    by_exposure,
    fit_nuisance,
    predict,
)
from tests.diagnosis.synthetic import synthetic

RS = library()["rolling_shutter"]


@pytest.fixture(autouse=True)
def _one_thread():
    with threadpool_limits(limits=1, user_api="blas"):  # small matrices: threaded BLAS only contends
        yield


def test_rate_operator_recovers_the_chosen_difference_and_ties_rates():
    obs, truth, cam, tim = synthetic((), frames=6, stars=8, rate_deg_s=(0.5, -1.0, 0.2), seed=3)
    c = R.rate_operator(truth, obs.t_ref_ns)
    # constant rate: every difference equals the truth, so the tied rates are the truth
    np.testing.assert_allclose(R.tied_rates(truth.attitude, obs.t_ref_ns, c), truth.omega, rtol=1e-6, atol=1e-12)
    assert np.allclose(c.sum(axis=1), 1.0)  # every rate is an average of steps


def _with_problem(fit):
    """``fit()``'s result and the residual function and Jacobian it handed to least_squares."""
    captured, orig = {}, R.least_squares

    def spy(fun, x0, jac=None, **kw):
        captured["fun"], captured["jac"] = fun, jac
        return orig(fun, x0, jac=jac, **kw)

    R.least_squares = spy
    try:
        return fit(), captured
    finally:
        R.least_squares = orig


def test_joint_jacobian_matches_finite_differences_and_noise_free_recovery():
    eff = RS.instance(np.array([2.0]))
    obs, truth, cam, tim = synthetic((eff,), frames=8, stars=15, seed=1, noise=False)
    mask = np.ones(obs.n, bool)
    out, captured = _with_problem(lambda: R.joint_refit(obs, truth, cam, tim, (), [RS], [np.array([1.5])], mask, moving=True))
    assert out["thetas"][0][0] == pytest.approx(2.0, abs=2e-3)  # sigma is ~0.2 us: 1 % of it
    fun, jac = captured["fun"], captured["jac"]
    x = np.zeros(3 * obs.n_frames + 1)
    x[-1] = 0.1
    ja = jac(x)
    for i in (0, 4, 3 * obs.n_frames - 1, 3 * obs.n_frames):  # attitude columns (incl. rate coupling), effect column
        h = 1e-7 if i < 3 * obs.n_frames else 1e-3
        e = np.zeros_like(x)
        e[i] = h
        num = (fun(x + e) - fun(x - e)) / (2 * h)
        # first order in the inter-frame rotation (1 deg/s x 0.1 s = 1.7 mrad): agreement to 1 %
        assert np.max(np.abs(ja[:, i] - num)) <= 0.01 * np.max(np.abs(num)), i


def test_interval_coverage_on_a_fixed_synthetic_problem():
    """Pulls (estimate - truth) / sigma of the line-delay error over independent noise draws: the
    fractions within 1 and 2 sigma must lie in the central 99.8 % binomial range of 0.683 / 0.954."""
    n = 30
    pulls = []
    for s in range(n):
        obs, truth, cam, tim = synthetic((RS.instance(np.array([2.0])),), frames=10, stars=20, seed=100 + s)
        mask = np.ones(obs.n, bool)
        nuis0, _ = fit_nuisance(obs, truth.attitude, cam, tim, (), mask, True)
        f = R.refit(obs, nuis0, cam, tim, (), [RS], mask)
        j = R.joint_refit(obs, f["nuisance"], cam, tim, (), [RS], f["thetas"], mask, True)
        pulls.append((j["thetas"][0][0] - 2.0) / j["sigmas"][0][0])
    pulls = np.abs(pulls)
    for k, p in ((1, 0.683), (2, 0.954)):
        lo, hi = stats.binom.ppf([0.001, 0.999], n, p)
        assert lo <= np.sum(pulls < k) <= hi, (k, np.sort(pulls))


def test_resimulation_tells_the_missing_effect_and_accepts_the_right_model():
    eff = RS.instance(np.array([10.0]))
    obs, truth, cam, tim = synthetic((eff,), frames=12, stars=25, seed=7)
    mask = np.ones(obs.n, bool)
    n0, p0 = fit_nuisance(obs, truth.attitude, cam, tim, (), mask, True)
    n1, p1 = fit_nuisance(obs, truth.attitude, cam, tim, (eff,), mask, True)
    out = resimulate.resimulation_check(obs, {"before": ((), n0, p0), "after": ((eff,), n1, p1)}, cam, tim, mask, True, seed=0)
    for key in ("before", "after"):
        assert set(out[key]) >= {"ks_statistic", "ks_p_value", "ad_statistic", "ad_p_value", "rms_recording", "rms_resimulated", "n"}
        assert out[key]["n"] == 2 * obs.n
    assert out["before"]["ks_p_value"] < 1e-3 and out["before"]["rms_recording"] > 1.3 * out["before"]["rms_resimulated"]
    assert out["after"]["ks_p_value"] > 0.01
    assert out["after"]["rms_recording"] == pytest.approx(out["after"]["rms_resimulated"], rel=0.1)


def test_by_exposure_evaluates_each_group_with_its_own_exposure():
    smear = library()["exposure_smear"].instance(np.array([0.1]))
    obs, truth, cam, tim = synthetic((), frames=4, stars=10, seed=2)
    p = predict(obs, truth, cam, tim, ())
    expo = np.where(obs.frame % 2 == 0, 20_000_000, 80_000_000)
    from dataclasses import replace

    from rollingstar.sensors.effects.chain import predict as chain_predict

    got = by_exposure(p.ctx, expo, lambda c: chain_predict((smear,), c))
    for e in (20_000_000, 80_000_000):
        m = expo == e
        want = chain_predict((smear,), p.ctx.take(np.flatnonzero(m)).evolve(timing=replace(tim, exposure_ns=e)))
        np.testing.assert_allclose(got[0][m], want[0])
        np.testing.assert_allclose(got[1][m], want[1])
    # the shift along the motion is 4x larger at the 4x longer exposure
    d = np.hypot(got[0] - p.x_ideal, got[1] - p.y_ideal)
    assert np.median(d[expo == 80_000_000]) == pytest.approx(4 * np.median(d[expo == 20_000_000]), rel=1e-3)


def test_pooled_inclusion_counts_aliases():
    sets = [{"a"}, {"b"}, {"a", "c"}, set()]
    assert selection.pooled_inclusion(sets, "a", []) == 0.5
    assert selection.pooled_inclusion(sets, "a", ["b"]) == 0.75


def test_variable_projection_jacobian_matches_finite_differences():
    """The refit's Jacobian (Kaufman: effect columns at the refitted attitudes, attitudes projected
    out) equals central differences of the projected residual, every frame's attitude refitted at
    each step, to 1 % near the solution of a noise-free recording (the neglected term is residual
    x curvature)."""
    rad = library()["radial_distortion"]
    obs, truth, cam, tim = synthetic((RS.instance(np.array([2.0])), rad.instance(np.array([0.02, 0.0]))),
                                     frames=8, stars=20, seed=2, noise=False)
    mask = np.ones(obs.n, bool)
    out, captured = _with_problem(lambda: R.refit(obs, truth, cam, tim, (), [RS, rad], mask))
    assert out["thetas"][0][0] == pytest.approx(2.0, abs=2e-3) and out["thetas"][1][0] == pytest.approx(0.02, abs=1e-4)
    fun, jac = captured["fun"], captured["jac"]
    z = np.concatenate([(t - c.defaults) / c.scales for c, t in zip([RS, rad], out["thetas"])]) * 0.98
    ja = jac(z)
    for i in range(z.size):
        h = 1e-4 * max(1.0, abs(z[i]))
        e = np.zeros_like(z)
        e[i] = h
        num = (fun(z + e) - fun(z - e)) / (2 * h)
        assert np.max(np.abs(ja[:, i] - num)) <= 0.01 * np.max(np.abs(num)), i


@pytest.mark.parametrize("tiled", [True, False])
@pytest.mark.parametrize("mixed", [True, False])
def test_projected_jacobian_columns_are_whole_predictions_differenced(tiled, mixed, monkeypatch):
    """Each column of the refit's Jacobian reruns only the effect chain from its own effect on
    (rebuilt): it must equal, to the bit, the whole prediction of the perturbed chain differenced,
    with a scenario chain in front of the candidates and a time-stage effect, with one exposure
    time or frames of two (``mixed``: each exposure group runs its own whole chain); with the chain
    run over 5n copies of the stars (``tiled``) or star by star."""
    from dataclasses import replace

    from rollingstar.estimators.diagnosis import observations

    if not tiled:
        monkeypatch.setattr(observations, "TILED_MAX_STARS", 0)
    lib = library()
    base_effects = (lib["exposure_smear"].instance(np.array([0.05])), lib["focal_length"].instance(np.array([300.0])))
    cands = [lib["radial_distortion"], RS, lib["principal_point"]]
    obs, truth, cam, tim = synthetic(base_effects, frames=4, stars=12, seed=8)
    if mixed:
        obs = replace(obs, exposure_ns=np.where(np.arange(obs.n_frames) % 2 == 0, 20_000_000, 60_000_000))
    z = np.array([0.7, -0.4, 1.3, 0.2, -0.9])
    mask = np.ones(obs.n, bool)
    hi = np.full(z.size, np.inf)
    got = R.projected_jacobian(obs, truth, cam, tim, base_effects, cands, mask, z, hi)
    base = predict(obs, truth, cam, tim, R.chain_with(base_effects, cands, R.split_theta(cands, z)))
    cols = np.empty((obs.n, 2, z.size))
    for j in range(z.size):
        zz = z.copy()
        h = 1e-4 * max(1.0, abs(z[j]))
        zz[j] = z[j] + h
        whole = predict(obs, truth, cam, tim, R.chain_with(base_effects, cands, R.split_theta(cands, zz)),
                        attitude_jacobian=False)
        cols[:, 0, j], cols[:, 1, j] = (whole.x - base.x) / (zz[j] - z[j]), (whole.y - base.y) / (zz[j] - z[j])
    aj = observations.whiten(obs, base.att_jac)
    p = selection.project_frames(obs.frame, obs.n_frames, aj, observations.whiten(obs, cols))
    np.testing.assert_array_equal(got, np.nan_to_num(np.concatenate([-p[:, 0, :], -p[:, 1, :]])))
