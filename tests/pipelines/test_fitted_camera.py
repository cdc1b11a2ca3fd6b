"""One camera model through the pipeline: the camera lost-in-space fits on a wide, distorted frame
is the one QUEST solves with, and the run records it."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.quest import QuestSolver
from rollingstar.estimators.data import SensorContext
from rollingstar.estimators.identifiers.lost_in_space import LostInSpaceIdentifier
from rollingstar.pipelines.sink import _fitted_camera
from rollingstar.pipelines.stages import StagePipeline
from rollingstar.sensors.catalog import StarCatalog
from tests.estimators.test_distortion_fit import CAM, K1, TIMING, distorted_frame


@pytest.fixture(scope="module")
def context():
    catalog = StarCatalog.from_hipparcos(2000.0, 5.5).without_close_pairs(4 * CAM.ifov_rad)
    return SensorContext(camera=CAM, timing=TIMING, catalog=catalog, bit_depth=12)


def _solve(context, frame, **params):
    stages = [LostInSpaceIdentifier(track=False, pattern_match_max_error=0.005, **params), QuestSolver()]
    for s in stages:
        s.setup(context)
    return StagePipeline(stages, holds_centroids=True, context=context).process(frame)[0]


def _error_arcsec(out, truth: Rotation) -> float:
    est = next(a for a in out.attitudes if a.valid)
    return float(np.degrees((truth.inv() * Rotation.from_quat(est.q_xyzw)).magnitude()) * 3600.0)


def test_quest_solves_with_the_fitted_camera(context):
    """k1 = -0.30 on a 39 deg field: with the fit, every later stage projects with the fitted
    model (frame.camera), and the attitude lands within the noise (0.2 px on 740 px focal length:
    ~1 arcmin per star, ~20 arcsec over the frame's stars) of the truth."""
    rng = np.random.default_rng(5)
    errors, nominal = [], []
    for seed in range(4):
        truth = Rotation.random(random_state=rng)
        frame, _ = distorted_frame(context, truth, seed)
        out = _solve(context, frame, fit_distortion="radial", distortion_terms=1, max_residual_px=4.0)
        assert out.camera is not None and abs(out.camera.k1 - K1) < 0.05
        assert _fitted_camera(out)["k1"] == out.camera.k1
        errors.append(_error_arcsec(out, truth))
        quest = QuestSolver()
        quest.setup(context)  # the same identified stars, solved with the declared pinhole
        pinhole = quest.process(out.evolve(camera=None, attitudes=()))
        nominal.append(_error_arcsec(pinhole, truth))
    assert max(errors) < 60.0, errors
    assert min(nominal) > 3 * max(errors), (nominal, errors)


def test_auto_fits_the_distortion_of_a_wide_field_and_the_focal_length_of_a_narrow_one(context):
    wide = LostInSpaceIdentifier(fit_distortion="auto")
    wide.setup(context)
    assert wide._fit_names == ("focal_px", "k1", "k2")  # 39 deg > 20 deg
    narrow = LostInSpaceIdentifier(fit_distortion="auto", auto_distortion_fov_deg=45.0)
    narrow.setup(context)
    assert narrow._fit_names == ("focal_px",)
    fixed = LostInSpaceIdentifier(fit_distortion="none")
    fixed.setup(context)
    assert not fixed._fitting
