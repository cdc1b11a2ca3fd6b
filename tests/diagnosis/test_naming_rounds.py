"""The naming step's bookkeeping: each nonlinear refit is made once per naming, an effect the
nonlinear test dropped is not offered back by the linearised forward step, and the positions of
another effect chain at the same attitudes are what a full prediction gives."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.estimators.diagnosis import naming
from rollingstar.estimators.diagnosis.library import library
from rollingstar.estimators.diagnosis.observations import Nuisance, camera_rotations, chain_positions, predict
from rollingstar.sensors.so3 import quat_multiply
from tests.diagnosis.synthetic import synthetic


def _cand(name, k=1):
    return SimpleNamespace(name=name, parameters=(None,) * k, defaults=np.zeros(k))


def _data(n_residuals=400):
    return SimpleNamespace(n_residuals=n_residuals, obs=None, train=None)


def _counting_refits(monkeypatch, cost):
    """A Refits whose refits are counted; ``cost(names)`` is the chi-square of a subset."""
    calls = []

    def refit_chi2(data, sensor, nuis0, chosen, warm=None):
        names = tuple(c.name for c in chosen)
        calls.append((names, None if warm is None else tuple(sorted(warm))))
        return {"cost": cost(names), "thetas": [np.zeros(len(c.parameters)) for c in chosen]}

    monkeypatch.setattr(naming, "refit_chi2", refit_chi2)
    return naming.Refits(_data(), None, None), calls


def test_a_refit_is_made_once_for_its_effects_and_start(monkeypatch):
    refits, calls = _counting_refits(monkeypatch, lambda names: 100.0 - len(names))
    a, b = _cand("a"), _cand("b", 2)
    first = refits([a, b], {"a": np.array([1.0]), "c": np.array([5.0])})
    assert refits([a, b], {"a": np.array([1.0])}) is first  # a start for an effect not refitted does not count
    refits([a, b], {"a": np.array([2.0])})  # another start: another refit
    refits([b, a], {"a": np.array([1.0])})  # another order of the parameter vector
    refits([a, b])
    assert refits([a, b], {}) is refits([a, b])  # no start is every effect from its defaults
    assert len(calls) == 4


def test_the_drop_one_statistics_reuse_the_last_elimination_pass(monkeypatch):
    """When backward elimination keeps every effect, it has refitted each subset without one from
    the full fit; the drop-one delta BIC asks for the same refits and makes none."""
    monkeypatch.setattr(naming, "wald_delta_bic", lambda chosen, fit, n: [(c.name, 1.0) for c in chosen])
    refits, calls = _counting_refits(monkeypatch, lambda names: 1000.0 - 100.0 * len(names))  # each effect earns 100
    cands = {n: _cand(n) for n in "abc"}
    fit = refits(list(cands.values()))
    names, fit, dropped = naming.backward_eliminate(refits, cands, list(cands), fit, min_delta_bic=10.0)
    assert names == list("abc") and not dropped
    made = len(calls)
    delta, method = naming.drop_one_delta_bic(refits, list(cands.values()), fit, min_delta_bic=10.0)
    assert len(calls) == made == 4
    assert set(method.values()) == {"refit"}
    np.testing.assert_allclose(list(delta.values()), 100.0 - np.log(400))


def test_an_effect_the_nonlinear_test_dropped_is_not_offered_again(monkeypatch):
    """The linearised forward step here offers every candidate it is given (it overstates them all);
    the nonlinear elimination keeps only ``a``. The refinement ends with ``a`` alone, and no round
    adds back an effect an earlier round dropped."""
    cands = {n: _cand(n) for n in "abcd"}
    refits, _ = _counting_refits(monkeypatch, lambda names: 100.0)

    def backward(refits, cands, names, fit, min_delta_bic):
        gone = [n for n in names if n != "a"]
        return ["a"], fit, [{"dropped": n, "delta_bic_nonlinear": -1.0} for n in gone]

    offered = []

    def linear_problem(obs, pred, others, effects, mask, blocks):
        offered.append(sorted(others))
        return sorted(others), None

    monkeypatch.setattr(naming, "backward_eliminate", backward)
    monkeypatch.setattr(naming, "with_nuisance", lambda data, sensor, nuis0, names, chosen, fit: SimpleNamespace(
        names=names, prediction=None, effects=()))
    monkeypatch.setattr(naming, "linear_problem", linear_problem)
    monkeypatch.setattr(naming.selection, "forward_stepwise", lambda prob, m: [{"name": n} for n in prob[:1]])
    model, rounds = naming.select_nonlinear(refits, cands, ["a", "b"], None, SimpleNamespace(min_delta_bic=10.0))
    assert model.names == ["a"]
    assert offered == [["c", "d"], ["d"], []]
    dropped_before = set()
    for r in rounds:
        assert not set(r.get("added", ())) & dropped_before, rounds
        dropped_before |= {r["dropped"]} if "dropped" in r else set()


def test_another_chain_at_the_same_attitudes_gives_the_full_predictions_positions():
    lib = library()
    effects = (lib["radial_distortion"].instance(np.array([0.02, -0.01])), lib["rolling_shutter"].instance(np.array([3.0])))
    obs, truth, camera, timing = synthetic(effects, frames=4, stars=15, seed=2)
    base = predict(obs, truth, camera, timing, effects)
    other = (lib["principal_point"].instance(np.array([0.4, -0.3])),) + effects
    full = predict(obs, truth, camera, timing, other, attitude_jacobian=False)
    x, y = chain_positions(base, other)
    np.testing.assert_array_equal(x, full.x)
    np.testing.assert_array_equal(y, full.y)


def test_at_rate_zero_each_star_sees_its_frames_attitude():
    obs, truth, _, _ = synthetic((), frames=3, stars=6, seed=5)
    still = Nuisance(truth.attitude, np.zeros_like(truth.omega))
    composed = Rotation.from_quat(quat_multiply(truth.attitude.as_quat()[obs.frame],
                                                Rotation.from_rotvec(np.zeros((obs.n, 3))).as_quat()))
    np.testing.assert_array_equal(camera_rotations(obs, still).as_quat(), composed.as_quat())
    turning = camera_rotations(obs, truth)
    assert not np.allclose(turning.as_quat(), composed.as_quat())  # with a rate each row turns on
