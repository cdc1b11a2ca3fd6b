"""Tracking identifier: prediction from the prior attitude and mutual-nearest matching in a gate."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from rollingstar.estimators.conformance.scenes import detections, make_scene
from rollingstar.estimators.data import AttitudeEstimate, FrameData, StarTable
from rollingstar.estimators.identifiers.tracking import TrackingIdentifier
from rollingstar.sensors.conventions import radec_roll_from_attitude


def _ident(scene, **params):
    t = TrackingIdentifier(**params)
    t.setup(scene.context)
    return t


def _truth_ids(scene):
    return scene.context.catalog.ids[scene.catalog_index]


def test_all_stars_matched_with_right_ids():
    scene = make_scene(seed=21)
    det = detections(scene, 0, np.random.default_rng(0), sigma_px=0.2)
    out = _ident(scene).process(FrameData(index=0, t0_ns=0, stars=det))
    assert out.stars.n == scene.x.size and out.unmatched.n == 0
    np.testing.assert_array_equal(out.stars.catalog_id, _truth_ids(scene))  # input order kept
    cat = scene.context.catalog
    np.testing.assert_array_equal(out.stars.ref_icrs, cat.unit_icrs[cat.index_of(out.stars.catalog_id)])
    np.testing.assert_array_equal(out.stars.x, det.x)


def test_prediction_is_the_projection_of_the_catalogue():
    """With the prior equal to the truth, predictions land on the true positions (1e-9 px)."""
    scene = make_scene(seed=22, prior_error_arcsec=0.0)
    t = _ident(scene)
    idx, x, y = t.predict(scene.truth)
    order = np.argsort(idx)
    np.testing.assert_array_equal(idx[order], scene.catalog_index)
    np.testing.assert_allclose(x[order], scene.x, atol=1e-9)
    np.testing.assert_allclose(y[order], scene.y, atol=1e-9)


def test_spurious_spots_unmatched_and_gate():
    scene = make_scene(seed=23, min_sep_px=40.0)
    rng = np.random.default_rng(0)
    det = detections(scene, 0, rng)
    # two spurious spots far (> 15 px) from every star, and star 0 displaced by 12 px (> gate 10)
    spur_x = np.array([3.0, 300.0])
    spur_y = np.array([250.0, 4.0])
    far = np.min(np.hypot(spur_x[:, None] - scene.x[None], spur_y[:, None] - scene.y[None]), axis=1)
    assert np.all(far > 15)
    x = np.concatenate([det.x + np.where(np.arange(det.n) == 0, 12.0, 0.0), spur_x])
    y = np.concatenate([det.y, spur_y])
    table = StarTable.build(x, y, t_ns=np.zeros(x.size, dtype=np.int64))
    out = _ident(scene, gate_px=10.0).process(FrameData(index=0, t0_ns=0, stars=table))
    ids = _truth_ids(scene)
    assert set(out.stars.catalog_id) == set(ids[1:])
    assert out.unmatched.n == 3
    np.testing.assert_array_equal(np.sort(out.unmatched.x), np.sort(np.concatenate([[x[0]], spur_x])))
    # without verification a wider gate takes the displaced star back ...
    wide = _ident(scene, gate_px=15.0, refine=False).process(FrameData(index=0, t0_ns=0, stars=table))
    assert set(wide.stars.catalog_id) == set(ids)
    # ... with verification it is rejected: 12 px off the attitude fitted to the other stars
    verified = _ident(scene, gate_px=15.0).process(FrameData(index=0, t0_ns=0, stars=table))
    assert set(verified.stars.catalog_id) == set(ids[1:])


def test_one_spot_per_star():
    """Two detections near one star: only the nearer is matched (mutual nearest neighbours)."""
    scene = make_scene(seed=24, prior_error_arcsec=0.0)
    x = np.array([scene.x[0] + 1.0, scene.x[0] - 3.0])
    y = np.array([scene.y[0], scene.y[0]])
    table = StarTable.build(x, y, t_ns=np.zeros(2, dtype=np.int64))
    out = _ident(scene).process(FrameData(index=0, t0_ns=0, stars=table))
    assert out.stars.n == 1 and out.stars.x[0] == x[0]
    assert out.unmatched.n == 1 and out.unmatched.x[0] == x[1]


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_permutation_invariance(seed):
    scene = make_scene(seed=25)
    rng = np.random.default_rng(seed)
    det = detections(scene, 0, rng, sigma_px=0.5)
    extra = StarTable.build(rng.uniform(0, 319, 5), rng.uniform(0, 255, 5), t_ns=np.zeros(5, dtype=np.int64))
    full = StarTable.concat(det, extra)
    perm = rng.permutation(full.n)
    t = _ident(scene)
    a = t.process(FrameData(index=0, t0_ns=0, stars=full))
    b = t.process(FrameData(index=0, t0_ns=0, stars=full.take(perm)))
    pairs_a = sorted(zip(a.stars.catalog_id.tolist(), a.stars.x.tolist()))
    pairs_b = sorted(zip(b.stars.catalog_id.tolist(), b.stars.x.tolist()))
    assert pairs_a == pairs_b
    assert sorted(a.unmatched.x.tolist()) == sorted(b.unmatched.x.tolist())


def test_prior_update_and_sources():
    scene = make_scene(seed=26)
    t = _ident(scene)
    assert t.prior.approx_equal(scene.context.initial_attitude)
    new = scene.truth * Rotation.from_rotvec([0.0, 0.01, 0.0])
    frame = FrameData(index=0, t0_ns=0, attitudes=(AttitudeEstimate(0, new.as_quat(), 5),
                                                    AttitudeEstimate.invalid(1, 1, "x")))
    assert t.update_prior(frame)
    assert t.prior.approx_equal(new)
    assert not t.update_prior(FrameData(index=1, t0_ns=0, attitudes=(AttitudeEstimate.invalid(1, 1, "x"),)))
    assert t.prior.approx_equal(new)
    # params override the context; without either setup fails with a helpful message
    ra, dec, roll = radec_roll_from_attitude(scene.truth)
    p = _ident(scene, initial_attitude={"ra_deg": ra, "dec_deg": dec, "roll_deg": roll})
    assert (p.prior.inv() * scene.truth).magnitude() < 1e-9
    bare = make_scene(seed=26, initial_attitude=False)
    with pytest.raises(ValueError, match="prior attitude.*initial_attitude.*lost-in-space"):
        _ident(bare)


def test_empty_and_missing_detections():
    scene = make_scene(seed=27)
    t = _ident(scene)
    out = t.process(FrameData(index=0, t0_ns=0, stars=StarTable.empty()))
    assert out.stars.n == 0 and out.unmatched.n == 0
    with pytest.raises(ValueError, match="frame 4.*centroider"):
        t.process(FrameData(index=4, t0_ns=0))


def test_magnitude_limit_drops_faint_predictions():
    scene = make_scene(seed=28)
    det = detections(scene, 0, np.random.default_rng(0))
    mag = scene.context.catalog.magnitude[scene.catalog_index]
    out = _ident(scene, magnitude_limit=4.0).process(FrameData(index=0, t0_ns=0, stars=det))
    assert set(out.stars.catalog_id) == set(_truth_ids(scene)[mag <= 4.0])


def test_verification_drops_a_detection_matched_to_the_wrong_star():
    """A detection placed on a neighbour-like position 4 px from its star, with a 3 px prior error:
    the first pass may accept it, the verified pass keeps only detections consistent with one attitude."""
    scene = make_scene(seed=31, min_sep_px=40.0)
    rng = np.random.default_rng(3)
    det = detections(scene, 0, rng)
    x = det.x + np.where(np.arange(det.n) == 2, 4.0, 0.0)
    table = StarTable.build(x, det.y, t_ns=np.zeros(det.n, dtype=np.int64))
    ids = _truth_ids(scene)
    out = _ident(scene, gate_px=10.0).process(FrameData(index=0, t0_ns=0, stars=table))
    assert set(out.stars.catalog_id) == set(ids) - {ids[2]}
    plain = _ident(scene, gate_px=10.0, refine=False).process(FrameData(index=0, t0_ns=0, stars=table))
    assert ids[2] in set(plain.stars.catalog_id)


def test_detections_no_direction_images_are_left_unmatched():
    """An orthographic lens whose image circle (radius f) ends inside the detector. A star imaged
    near the rim is detected just beyond it (where a distortion the camera does not model can
    put it), and spots sit in the corners: none of them has a direction. They stay unmatched
    instead of breaking the attitude refit, and every other star is identified."""
    from dataclasses import replace

    from rollingstar.sensors.camera import PinholeCamera

    scene = make_scene(seed=21)
    cam = scene.context.camera
    ortho = PinholeCamera(focal_length_m=120 * cam.pixel_size_m, pixel_size_m=cam.pixel_size_m, width=cam.width,
                          height=cam.height, projection="orthographic")
    ctx = replace(scene.context, camera=ortho)
    tracker = TrackingIdentifier()
    tracker.setup(ctx)
    idx, px, py, _, _ = tracker.predict_frame(0)
    r = np.hypot(px - ortho.cx, py - ortho.cy)
    edge = int(np.argmax(r))
    assert idx.size >= 5 and r[edge] > ortho.focal_px - 5.0  # a star within 5 px of the rim
    x, y = px.copy(), py.copy()
    x[edge], y[edge] = ortho.cx + (px[edge] - ortho.cx) * (ortho.focal_px + 1.0) / r[edge], \
        ortho.cy + (py[edge] - ortho.cy) * (ortho.focal_px + 1.0) / r[edge]  # 1 px beyond the rim
    corners = np.array([[1.0, 1.0], [cam.width - 2.0, 1.0], [1.0, cam.height - 2.0]])
    assert np.isnan(ortho.unproject(np.r_[x[edge], corners[:, 0]], np.r_[y[edge], corners[:, 1]])).all()
    det = StarTable.build(np.r_[x, corners[:, 0]], np.r_[y, corners[:, 1]], t_ns=0, sigma_px=0.1)
    out = tracker.process(FrameData(index=0, t0_ns=0, stars=det))
    assert out.stars.n == idx.size - 1 and out.unmatched.n == 4
    np.testing.assert_array_equal(np.sort(out.stars.catalog_id), np.sort(ctx.catalog.ids[np.delete(idx, edge)]))
