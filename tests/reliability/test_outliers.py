"""Planted false matches must not drag the attitude: every solver with the robust gate
(estimators/attitude/robust.py) vs plain. Full table: benchmarks/outliers.py, docs/reliability.md."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.estimators.attitude.robust import RobustParams, robust_gate
from rollingstar.studies.outlier_bench import (
    SOLVERS,
    clean_scene,
    plant_false_matches,
    rms_error_arcsec,
    run_solver,
)

from .helpers import ROOT


@pytest.fixture(scope="module")
def scene():
    return clean_scene(8, seed=3, root=ROOT)


@pytest.mark.parametrize("solver", sorted(SOLVERS))
def test_ransac_keeps_the_clean_error_with_three_false_matches(scene, solver):
    clean, _ = rms_error_arcsec(run_solver(solver, SOLVERS[solver], scene.frames, scene.context), scene.motion)
    frames = plant_false_matches(scene, 3, seed=7)
    plain, _ = rms_error_arcsec(run_solver(solver, SOLVERS[solver], frames, scene.context), scene.motion)
    robust, n = rms_error_arcsec(run_solver(solver, {**SOLVERS[solver], "robust": "ransac"}, frames, scene.context),
                                 scene.motion)
    assert n > 0
    # the false matches are gross (up to the field width): plain is dragged by > 100x the clean error
    assert plain > 100 * clean
    # RANSAC rejects exactly the planted stars, so the error is the clean one (benchmark: ratio 1.00 everywhere)
    assert robust <= 1.05 * clean


def test_gate_rejects_exactly_the_planted_stars_and_flags_them(scene):
    frames = plant_false_matches(scene, 2, seed=11)
    ctx = scene.context
    for f in frames:
        stars, flags = robust_gate(f.stars, ctx.camera, RobustParams(robust="ransac"), 0.05)
        n_true = f.stars.n - 2
        assert flags == ("outliers_rejected:2",)
        assert stars.identified[:n_true].all() and not stars.identified[n_true:].any()
        assert np.isnan(stars.ref_icrs[n_true:]).all()


def test_huber_bounds_the_influence(scene):
    frames = plant_false_matches(scene, 1, seed=5)
    plain, _ = rms_error_arcsec(run_solver("quest", {}, frames, scene.context), scene.motion)
    huber, _ = rms_error_arcsec(run_solver("quest", {"robust": "huber"}, frames, scene.context), scene.motion)
    # influence bounded by the threshold k = 3 px (~140 arcsec at 47 arcsec/px) over ~15 stars
    assert huber < plain / 20


def test_too_few_stars_to_decide_are_left_alone(scene):
    f = scene.frames[0]
    three = f.stars.take(np.arange(3))
    stars, flags = robust_gate(three, scene.context.camera, RobustParams(robust="ransac"), 0.05)
    assert stars is three and flags == ()  # three consistent stars: all inliers
    two = f.stars.take(np.arange(2))
    assert robust_gate(two, scene.context.camera, RobustParams(robust="ransac"), 0.05) == (two, ())
