"""The naming step's bookkeeping: each nonlinear refit is made once per naming, the refinement stops
when it cycles and does not offer an effect dropped twice again (an effect dropped once can come
back), and the positions of another effect chain at the same attitudes are what a full
prediction gives."""
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


def _scripted_refinement(monkeypatch, eliminate: dict, propose: dict):
    """``select_nonlinear`` with a scripted nonlinear elimination (names in -> names kept) and a
    scripted linearised forward step (names kept -> names it adds); returns its model, its rounds
    and the sets the forward step was run from."""
    cands = {n: _cand(n) for n in "abcd"}
    refits, _ = _counting_refits(monkeypatch, lambda names: 100.0)

    def backward(refits, cands, names, fit, min_delta_bic):
        kept = eliminate[frozenset(names)]
        return kept, fit, [{"dropped": n, "delta_bic_nonlinear": -1.0} for n in names if n not in kept]

    forward_from = []

    def linear_problem(obs, pred, others, effects, mask, blocks):
        return (pred, set(others)), None

    def forward(prob, min_delta_bic):
        kept, offered = prob
        forward_from.append(sorted(kept))
        return [{"name": n} for n in propose.get(frozenset(kept), []) if n in offered]

    monkeypatch.setattr(naming, "backward_eliminate", backward)
    monkeypatch.setattr(naming, "with_nuisance", lambda data, sensor, nuis0, names, chosen, fit: SimpleNamespace(
        names=names, prediction=list(names), effects=()))
    monkeypatch.setattr(naming, "linear_problem", linear_problem)
    monkeypatch.setattr(naming.selection, "forward_stepwise", forward)
    model, rounds = naming.select_nonlinear(refits, cands, ["a", "b"], None, SimpleNamespace(min_delta_bic=10.0))
    return model, rounds, forward_from


def test_a_refinement_that_comes_back_to_a_set_it_kept_stops_there(monkeypatch):
    """The linearised step re-adds ``b`` (it overstates it), the nonlinear elimination drops it
    again: the second time the elimination ends on ``{a}`` the refinement stops with it."""
    ab, a = frozenset("ab"), frozenset("a")
    model, rounds, forward_from = _scripted_refinement(monkeypatch, {ab: ["a"]}, {a: ["b"]})
    assert model.names == ["a"]
    assert forward_from == [["a"]]  # one forward step; the second round found the cycle
    assert rounds[-1] == {"cycle": ["a"]}


def test_an_effect_dropped_twice_is_not_offered_again(monkeypatch):
    """``b`` is dropped, re-added with ``c`` and dropped again: the linearised step that would add
    it a third time is not given it, and the refinement ends on ``{a, c}`` (no cycle: the last
    round added nothing)."""
    ab, a, abc, ac = frozenset("ab"), frozenset("a"), frozenset("abc"), frozenset("ac")
    model, rounds, forward_from = _scripted_refinement(
        monkeypatch, {ab: ["a"], abc: ["a", "c"], ac: ["a", "c"]}, {a: ["b", "c"], ac: ["b"]})
    assert model.names == ["a", "c"]
    assert [r["dropped"] for r in rounds if "dropped" in r] == ["b", "b"]
    assert not any("cycle" in r for r in rounds) and forward_from == [["a"], ["a", "c"]]


def test_an_effect_dropped_early_comes_back_when_the_model_changes(monkeypatch):
    """Without a cycle nothing is banned: ``b``, dropped while ``c`` was out of the model, is added
    back once ``c`` is in and kept by the elimination."""
    ab, a, ac, acb = frozenset("ab"), frozenset("a"), frozenset("ac"), frozenset("acb")
    model, rounds, _ = _scripted_refinement(monkeypatch, {ab: ["a"], ac: ["a", "c"], acb: ["a", "c", "b"]},
                                            {a: ["c"], ac: ["b"]})
    assert model.names == ["a", "c", "b"]
    assert [r for r in rounds if "added" in r] == [{"added": ["c"]}, {"added": ["b"]}]


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
