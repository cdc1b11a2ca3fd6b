"""Identification integrity: the chance probability of a frame's matches, for any identifier."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import binom

from rollingstar.config import CONFIGS
from rollingstar.estimators.data import SensorContext, StarTable
from rollingstar.estimators.identifiers.integrity import check_identification, fit_residuals, predicted_count
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.scenario import load_scenario


def _context():
    return SensorContext.from_scenario(load_scenario(CONFIGS / "scenarios" / "he2021a.yaml"))


def _field(context, rng, min_stars=8):
    cam, cat = context.camera, context.catalog
    while True:
        R = Rotation.random(random_state=rng)
        idx = np.asarray(cat.cone(R.apply([0, 0, 1.0]), cam.half_diagonal_rad), dtype=np.intp)
        x, y, front = cam.project(R.inv().apply(cat.unit_icrs[idx]))
        ok = front & cam.contains(x, y, margin_px=-2)
        if ok.sum() >= min_stars:
            return R, idx[ok], x[ok], y[ok]


def _identified(context, idx, x, y, t_ns=0, sigma=0.1):
    cat = context.catalog
    return StarTable.build(x, y, t_ns, sigma_px=np.full(len(x), sigma), catalog_id=cat.ids[idx], ref_icrs=cat.unit_icrs[idx])


def test_true_identification_passes_with_tiny_probability():
    context, rng = _context(), np.random.default_rng(1)
    for _ in range(20):
        _, idx, x, y = _field(context, rng)
        stars = _identified(context, idx, x + rng.normal(0, 0.1, x.size), y + rng.normal(0, 0.1, y.size))
        check = check_identification(stars, None, context.camera, context.catalog)
        assert check.passed and check.false_match_prob < 1e-12
        assert check.n_matched == check.n_detections == x.size


def test_shuffled_identities_fail():
    """Right stars, wrong names: a rotation cannot fit them, residuals are hundreds of px."""
    context, rng = _context(), np.random.default_rng(2)
    for _ in range(20):
        _, idx, x, y = _field(context, rng)
        stars = _identified(context, rng.permutation(idx), x, y)
        check = check_identification(stars, None, context.camera, context.catalog)
        assert not check.passed and check.reason.startswith("false_match_probability")


def test_probability_is_the_binomial_tail_of_the_stated_model():
    """P = binom.sf(k - 3, n - 2, N pi g^2 / (W H)) with g the largest residual, N the stars
    predicted: the two anchor stars an attitude can always be fitted to are not evidence."""
    context, rng = _context(), np.random.default_rng(3)
    R, idx, x, y = _field(context, rng, min_stars=5)
    idx, x, y = idx[:5], x[:5], y[:5]
    x = x + np.array([3.0, -3.0, 0.0, 0.0, 0.0])  # residuals of a few px
    stars = _identified(context, idx, x, y)
    extra = StarTable.build(rng.uniform(0, 1000, 20), rng.uniform(0, 1000, 20), 0)
    check = check_identification(stars, extra, context.camera, context.catalog)
    resid, fit, _ = fit_residuals(stars, context.camera)
    cam = context.camera
    n_pred = predicted_count(fit, cam, context.catalog)
    p = n_pred * np.pi * resid.max() ** 2 / (cam.width * cam.height)
    assert check.n_detections == 25 and check.n_matched == 5 and check.n_predicted == n_pred
    np.testing.assert_allclose(check.gate_px, resid.max())
    np.testing.assert_allclose(check.false_match_prob, binom.sf(2, 23, p), rtol=1e-9)


def test_rolling_shutter_motion_is_fitted_not_read_as_residual():
    """At 3 deg/s over a 45 ms readout the rows see different attitudes; the rate fit absorbs it."""
    context, rng = _context(), np.random.default_rng(4)
    cam, cat, timing = context.camera, context.catalog, context.timing
    R0, idx, x0, y0 = _field(context, rng, min_stars=10)
    omega = np.radians([3.0, 1.0, 0.5])
    t = timing.row_mid_exposure_ns(0, y0)
    dt = (t - np.median(t)) * S_PER_NS
    w = np.stack([(R0 * Rotation.from_rotvec(omega * d)).inv().apply(cat.unit_icrs[i]) for i, d in zip(idx, dt)])
    x, y, _ = cam.project(w)
    stars = _identified(context, idx, x, y, t_ns=t)
    resid, _, _ = fit_residuals(stars, cam)
    assert resid.max() < 0.05
    assert check_identification(stars, None, cam, cat).passed


def test_two_stars_can_match_anything_and_are_never_verified():
    """Two true stars fit to 1e-3 px, yet any two detections can be fitted by some attitude: the
    identification is unverifiable (not chance: the ids stay), P = 1."""
    context, rng = _context(), np.random.default_rng(6)
    _, idx, x, y = _field(context, rng)
    check = check_identification(_identified(context, idx[:2], x[:2], y[:2]), None, context.camera, context.catalog)
    assert not check.passed and check.false_match_prob == 1.0 and check.reason.startswith("unverifiable")


def test_fewer_than_two_matches_is_not_applicable():
    context = _context()
    check = check_identification(StarTable.empty(), None, context.camera, context.catalog)
    assert not check.passed and check.n_matched == 0 and check.false_match_prob == 1.0
