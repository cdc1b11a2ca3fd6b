"""Selection on synthetic linear problems with known answers (rollingstar.estimators.diagnosis.selection)."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.estimators.diagnosis import selection as sel


def _groups(rng, n, sizes):
    return {f"g{i}": rng.normal(size=(n, m)) for i, m in enumerate(sizes)}


def _problem(r, groups, blocks=None):
    blocks = np.arange(r.size) % 20 if blocks is None else blocks
    return sel.build_problem(r, groups, blocks)


def test_project_frames_matches_dense_least_squares_per_frame():
    rng = np.random.default_rng(0)
    n, frames = 60, 4
    frame = np.repeat(np.arange(frames), n // frames)
    att = rng.normal(size=(n, 2, 3))
    cols = rng.normal(size=(n, 2, 2))
    got = sel.project_frames(frame, frames, att, cols)
    for k in range(frames):
        m = frame == k
        a = np.concatenate([att[m, 0], att[m, 1]])  # independent: dense lstsq on the stacked rows
        c = np.concatenate([cols[m, 0], cols[m, 1]])
        coef, *_ = np.linalg.lstsq(a, c, rcond=None)
        want = c - a @ coef
        np.testing.assert_allclose(np.concatenate([got[m, 0], got[m, 1]]), want, atol=1e-12)
    # the nuisance itself is removed entirely
    np.testing.assert_allclose(sel.project_frames(frame, frames, att, att), 0.0, atol=1e-12)


def test_canonical_correlation_of_known_angle():
    t = 0.3
    a = np.array([[1.0], [0.0], [0.0]])
    b = np.array([[np.cos(t)], [np.sin(t)], [0.0]])
    assert sel.canonical_correlation(a, b) == pytest.approx(np.cos(t), abs=1e-12)
    assert sel.canonical_correlation(a, np.array([[0.0], [0.0], [1.0]])) == pytest.approx(0.0, abs=1e-12)


def test_selects_the_true_group_with_its_delta_bic():
    rng = np.random.default_rng(1)
    n = 800
    groups = _groups(rng, n, [1, 2, 2, 3, 1])
    theta = np.array([0.4, -0.3])
    r = groups["g2"] @ theta + rng.normal(size=n)
    p = _problem(r, groups)
    steps = sel.forward_stepwise(p)
    assert [s["name"] for s in steps] == ["g2"]
    # delta BIC = chi2(none) - chi2(g2) - 2 ln n, computed independently with lstsq
    coef, *_ = np.linalg.lstsq(groups["g2"], r, rcond=None)
    d_chi2 = r @ r - np.sum((r - groups["g2"] @ coef) ** 2)
    assert steps[0]["delta_bic"] == pytest.approx(d_chi2 - 2 * np.log(n), rel=1e-9)
    out = sel.select(p, n_boot=30, seed=2)
    assert out["inclusion"]["g2"] >= 0.9
    assert all(out["inclusion"][g] <= 0.1 for g in groups if g != "g2")


def test_two_true_groups_are_both_selected():
    rng = np.random.default_rng(3)
    n = 1000
    groups = _groups(rng, n, [1, 1, 2, 2, 1, 3])
    r = 0.3 * groups["g0"][:, 0] + groups["g3"] @ np.array([0.2, 0.25]) + rng.normal(size=n)
    assert sorted(s["name"] for s in sel.forward_stepwise(_problem(r, groups))) == ["g0", "g3"]


def test_pure_noise_selects_nothing_over_many_seeds():
    # per group P(chi2_m > 10 + m ln n) < 1e-4 here: any selection in 40 seeds would be a bug
    hits = 0
    for seed in range(40):
        rng = np.random.default_rng([seed, 99])
        n = 500
        groups = _groups(rng, n, [1, 2, 1, 3])
        hits += bool(sel.forward_stepwise(_problem(rng.normal(size=n), groups)))
    assert hits == 0


def test_nearly_collinear_groups_are_reported_ambiguous():
    rng = np.random.default_rng(4)
    n = 600
    a = rng.normal(size=(n, 1))
    groups = {"a": a, "a_twin": a + 0.1 * rng.normal(size=(n, 1)), "other": rng.normal(size=(n, 1))}
    r = 0.5 * a[:, 0] + rng.normal(size=n)
    out = sel.select(_problem(r, groups), n_boot=0)
    assert len(out["selected"]) == 1 and out["selected"][0] in ("a", "a_twin")
    pairs = [{x["selected"], x["alternative"]} for x in out["ambiguous"]]
    assert {"a", "a_twin"} in pairs
    assert all("other" not in p for p in pairs)


def test_group_absorbed_by_the_nuisance_is_dropped():
    rng = np.random.default_rng(5)
    n = 100
    raw = {"zero": rng.normal(size=(n, 1)), "faint": rng.normal(size=(n, 1)), "real": rng.normal(size=(n, 1))}
    projected = {"zero": 1e-9 * raw["zero"], "faint": 1e-3 * raw["faint"], "real": raw["real"]}
    # faint: norm ~ 1e-3 * 10 = 0.01 per prior scale; at a reach of 10 prior scales it moves the data < 1 sigma
    p = sel.build_problem(rng.normal(size=n), projected, np.arange(n), raw, reach={"faint": np.array([10.0])})
    assert sorted(p.absorbed) == ["faint", "zero"] and list(p.groups) == ["real"]
    # with a reach of 1e4 prior scales the faint group can show itself: kept
    p = sel.build_problem(rng.normal(size=n), projected, np.arange(n), raw, reach={"faint": np.array([1e4])})
    assert p.absorbed == ["zero"] and sorted(p.groups) == ["faint", "real"]


def test_a_collinear_pair_the_data_decide_is_not_ambiguous():
    """Correlation above the limit alone does not make a pair ambiguous when swapping costs more
    than DECISIVE_SWAP_BIC: the strong signal picks its own group; the weak one stays ambiguous."""
    rng = np.random.default_rng(5)
    n = 600
    a = rng.normal(size=(n, 1))
    twin = a + 0.2 * rng.normal(size=(n, 1))
    groups = {"a": a, "a_twin": twin}
    assert sel.canonical_correlation(a, twin) > sel.CORR_LIMIT
    strong = sel.select(_problem(5.0 * a[:, 0] + rng.normal(size=n), groups), n_boot=0)
    assert strong["selected"] == ["a"]
    assert strong["ambiguous"] == [], strong["ambiguous"]
    weak = sel.select(_problem(0.3 * a[:, 0] + rng.normal(size=n), groups), n_boot=0)
    assert weak["ambiguous"] and weak["ambiguous"][0]["delta_bic_swap"] < sel.DECISIVE_SWAP_BIC
