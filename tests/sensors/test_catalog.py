"""Star catalogue: real-star positions, proper motion, cone search, look-ups, caching."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from rollingstar.sensors import catalog as catmod
from rollingstar.sensors.catalog import (
    StarCatalog,
    load_hipparcos_columns,
    propagate_proper_motion,
)
from rollingstar.sensors.conventions import RAD_TO_ARCSEC, radec_to_unit, unit_to_radec


def _angle(a, b):
    """Angle between unit vectors (robust at small angles)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


@pytest.fixture(scope="module")
def hip65():
    return StarCatalog.from_hipparcos(2000.0, 6.5)


def test_sirius_j2000_position(hip65):
    # SIMBAD ICRS J2000 (from the same Hipparcos-2 solution): 06 45 08.91728 -16 42 58.0171
    i = hip65.index_of([32349])[0]
    assert i >= 0
    ra, dec = unit_to_radec(hip65.unit_icrs[i])
    truth = radec_to_unit(np.radians(101.28715533), np.radians(-16.71611586))
    assert abs(np.degrees(ra) - 101.287) < 0.01 and abs(np.degrees(dec) + 16.716) < 0.01
    assert _angle(hip65.unit_icrs[i], truth) * RAD_TO_ARCSEC < 0.01  # 10 mas
    # Sirius is the brightest star in the sky
    assert hip65.ids[np.argmin(hip65.magnitude)] == 32349


def test_barnards_star_proper_motion():
    a = StarCatalog.from_hipparcos(1991.25, 10.0)
    b = StarCatalog.from_hipparcos(2025.0, 10.0)
    ia, ib = a.index_of([87937])[0], b.index_of([87937])[0]
    moved = _angle(a.unit_icrs[ia], b.unit_icrs[ib]) * RAD_TO_ARCSEC
    mu = np.hypot(-798.58, 10328.12) / 1000.0  # arcsec/yr, from hip2.dat
    assert mu == pytest.approx(10.36, abs=0.05)
    assert moved == pytest.approx(mu * (2025.0 - 1991.25), rel=0.01)
    # moves north (pmDE > 0)
    assert b.unit_icrs[ib, 2] > a.unit_icrs[ia, 2]


def test_epoch_1991_25_is_catalogue_position():
    cols = load_hipparcos_columns()
    cat = StarCatalog.from_hipparcos(1991.25, 4.0)
    i = np.searchsorted(cols["hip"], cat.ids)
    expected = radec_to_unit(cols["ra_rad"][i], cols["dec_rad"][i])
    np.testing.assert_allclose(cat.unit_icrs, expected, atol=1e-15)


def test_proper_motion_is_tangent_and_linear():
    rng = np.random.default_rng(1)
    ra, dec = rng.uniform(0, 2 * np.pi, 50), rng.uniform(-1.5, 1.5, 50)
    pmra, pmde = rng.normal(0, 500, 50), rng.normal(0, 500, 50)
    u0 = propagate_proper_motion(ra, dec, pmra, pmde, 0.0)
    u1 = propagate_proper_motion(ra, dec, pmra, pmde, 10.0)
    mu_rad = np.hypot(pmra, pmde) * catmod.MAS_TO_RAD
    np.testing.assert_allclose(_angle(u0, u1), np.arctan(10.0 * mu_rad), rtol=1e-6)
    # pure pmRA moves along a parallel: declination unchanged to first order (at the equator, exactly)
    u = propagate_proper_motion(np.array([1.0]), np.array([0.0]), np.array([1000.0]), np.array([0.0]), 100.0)
    assert unit_to_radec(u)[1][0] == pytest.approx(0.0, abs=1e-15)


def test_unit_norms_and_types(hip65):
    np.testing.assert_allclose(np.linalg.norm(hip65.unit_icrs, axis=1), 1.0, atol=1e-14)
    assert hip65.ids.dtype == np.int64 and hip65.unit_icrs.shape == (len(hip65), 3)
    assert np.all(hip65.magnitude <= 6.5)
    assert hip65.epoch_year == 2000.0
    # usable directly with scipy rotations (which reject read-only arrays)
    assert Rotation.from_rotvec([0.1, 0.2, 0.3]).inv().apply(hip65.unit_icrs[:3]).shape == (3, 3)


def test_counts_monotone_in_magnitude_limit():
    counts = [len(StarCatalog.from_hipparcos(2000.0, m)) for m in (2.0, 4.0, 6.0, 6.5, 8.0)]
    assert all(a < b for a, b in zip(counts, counts[1:]))
    # naked-eye sky: thousands of stars brighter than Hp 6.5, a few tens brighter than 2
    assert 20 < counts[0] < 100 and 5000 < counts[3] < 12000


def test_memoised():
    assert StarCatalog.from_hipparcos(2000.0, 5.0) is StarCatalog.from_hipparcos(2000, 5)


def test_cache_written_and_reused(tmp_path):
    fresh = load_hipparcos_columns(tmp_path)
    files = list(tmp_path.glob("hip2_*.npz"))
    assert len(files) == 1
    again = load_hipparcos_columns(tmp_path)
    for name in fresh:
        np.testing.assert_array_equal(fresh[name], again[name])
    assert len(fresh["hip"]) > 100_000


def test_cache_unwritable_falls_back(tmp_path):
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    cols = load_hipparcos_columns(blocker / "sub")
    assert len(cols["hip"]) > 100_000


def test_corrupt_cache_is_reparsed(tmp_path):
    load_hipparcos_columns(tmp_path)
    (path,) = tmp_path.glob("hip2_*.npz")
    path.write_bytes(b"garbage")
    cols = load_hipparcos_columns(tmp_path)
    assert len(cols["hip"]) > 100_000


@settings(max_examples=60, deadline=None)
@given(
    ra=st.floats(0, 2 * np.pi),
    dec=st.floats(-np.pi / 2, np.pi / 2),
    radius=st.floats(0.0, 3.5),
)
def test_cone_matches_brute_force(hip65, ra, dec, radius):
    center = radec_to_unit(ra, dec)
    got = hip65.cone(center * 3.0, radius)  # any non-zero length centre
    ang = _angle(hip65.unit_icrs, center)
    expected = np.flatnonzero(ang <= radius)
    assert np.all(np.diff(got) > 0)
    boundary = np.abs(ang - radius) < 1e-9
    assert set(got) ^ set(expected) <= set(np.flatnonzero(boundary))


def test_index_of_and_subset():
    cat = StarCatalog.synthetic(np.eye(3), magnitude=[1.0, 2.0, 3.0], ids=[30, 10, 20])
    np.testing.assert_array_equal(cat.index_of([10, 20, 30, 99]), [1, 2, 0, -1])
    assert cat.index_of(20) == 2
    sub = cat.subset([2, 0])
    np.testing.assert_array_equal(sub.ids, [20, 30])
    np.testing.assert_array_equal(sub.magnitude, [3.0, 1.0])
    np.testing.assert_array_equal(sub.unit_icrs, [[0, 0, 1], [1, 0, 0]])
    masked = cat.subset(cat.magnitude < 2.5)
    np.testing.assert_array_equal(masked.ids, [30, 10])
    assert len(cat.subset([])) == 0 and cat.subset([]).index_of([10])[0] == -1


def test_synthetic_normalises_and_defaults():
    cat = StarCatalog.synthetic([[2.0, 0, 0], [0, 0, -5.0]])
    np.testing.assert_array_equal(cat.unit_icrs, [[1, 0, 0], [0, 0, -1]])
    np.testing.assert_array_equal(cat.ids, [1, 2])
    np.testing.assert_array_equal(cat.magnitude, [5.0, 5.0])
    np.testing.assert_array_equal(cat.cone([1, 0, 0], np.radians(1)), [0])
    np.testing.assert_array_equal(cat.cone([0, 1, 0], np.pi / 2), [0, 1])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(unit_icrs=[[0, 0, 0]]), "unit_icrs"),
        (dict(unit_icrs=[1, 0, 0]), "unit_icrs"),
        (dict(unit_icrs=np.eye(2)), "ids|unit_icrs"),
        (dict(unit_icrs=np.eye(3), ids=[1, 1, 2]), "ids"),
        (dict(unit_icrs=np.eye(3), magnitude=[1.0, 2.0]), "magnitude|broadcast"),
    ],
)
def test_synthetic_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        StarCatalog.synthetic(**kwargs)


def test_cone_validation():
    cat = StarCatalog.synthetic(np.eye(3))
    with pytest.raises(ValueError, match="center_unit"):
        cat.cone([0, 0, 0], 0.1)
    with pytest.raises(ValueError, match="radius_rad"):
        cat.cone([0, 0, 1], -0.1)


def test_without_close_pairs_drops_both_stars_of_close_pairs_only():
    from rollingstar.sensors.catalog import StarCatalog
    from rollingstar.sensors.conventions import radec_to_unit

    arcsec = np.pi / 180 / 3600
    ra = np.array([0.0, 30.0, 0.0, 100.0]) * arcsec  # stars 0-1 are 30" apart, 2 duplicates 0
    dec = np.array([0.0, 0.0, 0.0, 0.0])
    cat = StarCatalog.synthetic(radec_to_unit(ra, dec), ids=[1, 2, 3, 4])
    kept = cat.without_close_pairs(20 * arcsec)
    assert kept.ids.tolist() == [2, 4]  # 1 and 3 coincide; 2 is 30" from both (kept at 20")
    assert cat.without_close_pairs(40 * arcsec).ids.tolist() == [4]
    assert len(cat.without_close_pairs(0.0)) == 4
