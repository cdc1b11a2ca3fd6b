"""The camera's wide-angle projections against their textbook radius laws, written out here
independently of the camera code: where a direction lands, the way back, the Jacobian, and what
each projection cannot image."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.sensors.camera import PROJECTIONS, PinholeCamera

# r / f as a function of the angle from the boresight (Kannala & Brandt 2006, table 1)
RADIUS = {
    "perspective": np.tan,
    "equidistant": lambda t: t,
    "equisolid": lambda t: 2.0 * np.sin(t / 2.0),
    "stereographic": lambda t: 2.0 * np.tan(t / 2.0),
    "orthographic": np.sin,
}
# the widest angle tested (rad): short of where each law stops imaging or the image blows up
WIDEST = {"perspective": np.radians(80.0), "equidistant": np.radians(170.0), "equisolid": np.radians(170.0),
          "stereographic": np.radians(160.0), "orthographic": np.radians(85.0)}


def _camera(projection: str, **kw) -> PinholeCamera:
    return PinholeCamera(focal_length_m=0.004, pixel_size_m=5e-6, width=808, height=608, projection=projection, **kw)


def _directions(rng, n: int, widest: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit directions up to ``widest`` from the boresight, with their angle and azimuth."""
    theta = rng.uniform(0.0, widest, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    w = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    return w, theta, phi


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_a_direction_lands_at_the_radius_its_law_gives_along_the_pinhole_azimuth(projection):
    """``r = f rho(theta)`` from the principal point, on the side the pinhole puts it (camera +x
    towards decreasing column, +y towards decreasing row), whatever the projection."""
    cam = _camera(projection)
    w, theta, phi = _directions(np.random.default_rng(1), 500, WIDEST[projection])
    x, y, front = cam.project(w)
    assert front.all()
    r = cam.focal_px * RADIUS[projection](theta)
    np.testing.assert_allclose(x, cam.cx - r * np.cos(phi), atol=1e-9 * cam.focal_px)
    np.testing.assert_allclose(y, cam.cy - r * np.sin(phi), atol=1e-9 * cam.focal_px)


@pytest.mark.parametrize("projection", PROJECTIONS)
@pytest.mark.parametrize("k", [(0.0, 0.0, 0.0), (-0.05, 0.004, -0.0002)])
def test_unproject_inverts_project_with_and_without_distortion(projection, k):
    """Out to 75 deg from the boresight (45 deg for the pinhole, whose tan grows past where the
    distortion polynomial stays monotonic)."""
    cam = _camera(projection, k1=k[0], k2=k[1], k3=k[2])
    widest = np.radians(45.0 if projection == "perspective" and any(k) else 75.0)
    w, _, _ = _directions(np.random.default_rng(2), 500, widest)
    x, y, front = cam.project(w)
    assert front.all()
    np.testing.assert_allclose(cam.unproject(x, y), w, atol=1e-10)


@pytest.mark.parametrize("projection", PROJECTIONS)
@pytest.mark.parametrize("k", [(0.0, 0.0, 0.0), (-0.05, 0.004, -0.0002)])
def test_the_jacobian_matches_finite_differences(projection, k):
    """d(x, y)/dw of unnormalised directions, the boresight included (its own limit)."""
    cam = _camera(projection, k1=k[0], k2=k[1], k3=k[2])
    w, _, _ = _directions(np.random.default_rng(3), 200, min(WIDEST[projection], np.radians(75.0)))
    w = np.vstack([w * np.random.default_rng(4).uniform(0.5, 2.0, (len(w), 1)), [0.0, 0.0, 1.0], [0.0, 0.0, 3.0]])
    jac = cam.projection_jacobian(w)
    h = 1e-6
    for i in range(3):
        step = np.zeros(3)
        step[i] = h
        xp, yp, _ = cam.project(w + step)
        xm, ym, _ = cam.project(w - step)
        numeric = np.column_stack([xp - xm, yp - ym]) / (2 * h)
        np.testing.assert_allclose(jac[:, :, i], numeric, atol=1e-5 * cam.focal_px, rtol=1e-6)


@pytest.mark.parametrize("projection", ["equidistant", "equisolid", "stereographic"])
def test_the_fisheye_projections_image_directions_behind_the_detector_plane(projection):
    """Beyond 90 deg from the boresight a fisheye still images (the pinhole and the orthographic
    projection do not): a direction at 120 deg lands at its law's radius, and comes back."""
    cam = _camera(projection)
    theta = np.radians(120.0)
    w = np.array([[np.sin(theta), 0.0, np.cos(theta)]])
    x, y, front = cam.project(w)
    assert front.all() and np.isclose(x[0], cam.cx - cam.focal_px * RADIUS[projection](theta))
    np.testing.assert_allclose(cam.unproject(x, y), w, atol=1e-12)
    for hemispheric in ("perspective", "orthographic"):
        assert not _camera(hemispheric).project(w)[2].any()


def test_pixels_beyond_the_image_rim_have_no_direction():
    """An equisolid-angle image ends at r = 2 f, an orthographic one at r = f: beyond, NaN."""
    for projection, rim in (("equisolid", 2.0), ("orthographic", 1.0)):
        cam = _camera(projection)
        x = cam.cx - np.array([0.99, 1.01]) * rim * cam.focal_px
        w = cam.unproject(x, np.full(2, cam.cy))
        assert np.all(np.isfinite(w[0])) and np.all(np.isnan(w[1]))


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_field_of_view_and_corner_angle_follow_the_law(projection):
    cam = _camera(projection)
    half_w = cam.width * cam.pixel_size_m / 2 / cam.focal_length_m
    inverse = {"perspective": np.arctan(half_w), "equidistant": half_w, "equisolid": 2 * np.arcsin(half_w / 2),
               "stereographic": 2 * np.arctan(half_w / 2), "orthographic": np.arcsin(min(half_w, 1.0))}
    assert np.isclose(cam.fov_deg[0], np.degrees(2 * inverse[projection]))
    corner = cam.unproject(-0.5, -0.5)
    assert np.isclose(cam.half_diagonal_rad, np.arccos(corner[2]), rtol=1e-9) or projection == "orthographic"


def test_an_unknown_projection_is_refused():
    with pytest.raises(ValueError, match="unknown projection 'fisheye'"):
        _camera("fisheye")


@pytest.mark.parametrize("projection", ["equidistant", "stereographic"])
def test_the_simulator_images_a_wide_field_through_the_lens_projection(projection):
    """A 120 deg fisheye over Hipparcos to magnitude 4.5, simulated at rest with a rolling shutter:
    every true star lands where the camera projects its catalogue direction at its own row's time,
    and the field holds the stars a 120 deg field should (the corners reach 72 deg off-axis)."""
    from scipy.spatial.transform import Rotation

    from rollingstar.sensors.catalog import StarCatalog
    from rollingstar.sensors.motion import PiecewiseMotion, Segment
    from rollingstar.sensors.simulate import StarTrackerSimulator
    from rollingstar.sensors.timing import DetectorTiming

    width, height = 1024, 768
    f_px = (width / 2) / float(RADIUS[projection](np.radians(60.0)))
    cam = PinholeCamera(focal_length_m=f_px * 5e-6, pixel_size_m=5e-6, width=width, height=height, projection=projection)
    assert np.isclose(cam.fov_deg[0], 120.0)
    timing = DetectorTiming(mode="rolling", exposure_ns=20_000_000, line_delay_ns=30_000, rows=height)
    catalog = StarCatalog.from_hipparcos(2025.0, 4.5)
    attitude = Rotation.from_euler("xyz", [0.3, -0.8, 1.2])
    motion = PiecewiseMotion(attitude, [Segment(10**12, np.zeros(3), np.zeros(3))])
    truth = StarTrackerSimulator(cam, timing, catalog, motion, centroid_sigma_px=0.0, seed=1).frame(0).truth
    idx = np.searchsorted(catalog.ids, truth.catalog_id, sorter=np.argsort(catalog.ids))
    idx = np.argsort(catalog.ids)[idx]
    x, y, front = cam.project(attitude.inv().apply(catalog.unit_icrs[idx]))
    assert front.all()
    np.testing.assert_allclose(np.column_stack([truth.x, truth.y]), np.column_stack([x, y]), atol=1e-6)
    # Hp <= 4.5 holds ~900 stars over the sky; a 120 x 98 deg field sees ~1/6 of it
    assert 60 < truth.x.size < 300, truth.x.size


@pytest.mark.parametrize("projection, rim_deg", [("orthographic", 90.0), ("equisolid", 180.0), ("equidistant", 180.0)])
def test_a_detector_wider_than_the_image_circle_sees_the_whole_circle(projection, rim_deg):
    """A circular fisheye: the detector's corners (and, here, its sides) lie beyond the image
    circle, where no direction images; the field is the circle's, not a pinhole's formula."""
    rim_rho = {"orthographic": 1.0, "equisolid": 2.0, "equidistant": np.pi}[projection]
    f_px = 0.4 * 808 / rim_rho  # the circle's radius is 0.4 of the width: narrower than the detector
    cam = PinholeCamera(focal_length_m=f_px * 5e-6, pixel_size_m=5e-6, width=808, height=608, projection=projection)
    assert np.isnan(cam.unproject(-0.5, -0.5)).all()
    assert np.isclose(cam.half_diagonal_rad, np.radians(rim_deg))
    assert np.isclose(cam.fov_deg[0], 2 * rim_deg)


def test_lost_in_space_does_not_pattern_search_a_camera_it_would_treat_as_a_pinhole():
    """A fisheye can be tracked from a prior (the tracker projects through the camera), but the
    pattern search and the camera fit are a pinhole's: the fit is refused when configured, and a
    frame that would need a pattern search is rejected with that reason, not identified wrongly."""
    from rollingstar.estimators.data import FrameData, SensorContext, StarTable
    from rollingstar.estimators.identifiers.lost_in_space import LostInSpaceIdentifier
    from rollingstar.sensors.catalog import StarCatalog
    from rollingstar.sensors.timing import DetectorTiming

    ctx = SensorContext(camera=_camera("equidistant"), timing=DetectorTiming(mode="global", exposure_ns=10**7,
                                                                             line_delay_ns=0, rows=608),
                        catalog=StarCatalog.from_hipparcos(2025.0, 3.0))
    with pytest.raises(ValueError, match="projection 'equidistant'"):
        LostInSpaceIdentifier(fit_distortion="radial").setup(ctx)
    lis = LostInSpaceIdentifier()
    lis.setup(ctx)
    rng = np.random.default_rng(0)
    stars = StarTable.build(rng.uniform(0, 807, 20), rng.uniform(0, 607, 20), t_ns=0)
    out = lis.process(FrameData(index=0, t0_ns=0, stars=stars))
    assert out.stars.n == 0 and "lost_in_space_rejected:pattern_search_needs_a_pinhole(equidistant)" in out.flags
