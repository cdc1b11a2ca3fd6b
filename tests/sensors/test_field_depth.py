"""Catalogue epoch from a date (Julian year) and catalogue depth from a camera's field."""
from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from rollingstar.sensors.catalog import (
    HIPPARCOS_EPOCH_YEAR,
    StarCatalog,
    field_solid_angle_sr,
    hipparcos_stars_per_sr,
    julian_year,
    magnitude_limit_for_field,
)

UTC = timezone.utc


def test_julian_year_known_answers():
    assert julian_year(datetime(2000, 1, 1, 12, tzinfo=UTC)) == pytest.approx(2000.0, abs=1e-4)
    # the Hipparcos epoch J1991.25 is JD 2448349.0625 (TT) = 1991-04-02 13:30 (UTC within a minute)
    assert julian_year(datetime(1991, 4, 2, 13, 30, tzinfo=UTC)) == pytest.approx(HIPPARCOS_EPOCH_YEAR, abs=1e-5)
    # 36525 days after J2000 is J2100 exactly (a Julian century), though 2100 is no Gregorian leap year
    assert julian_year(datetime(2000, 1, 1, 12, tzinfo=UTC) + timedelta(days=36525)) == pytest.approx(2100.0, abs=1e-12)
    # the same instant in another zone is the same year
    cest = timezone(timedelta(hours=2))
    assert julian_year(datetime(2019, 7, 29, 22, 47, 26, tzinfo=cest)) == julian_year(
        datetime(2019, 7, 29, 20, 47, 26, tzinfo=UTC))
    with pytest.raises(ValueError, match="zone"):
        julian_year(datetime(2019, 7, 29, 20, 47, 26))


def test_field_solid_angle_against_the_corner_formula_and_monte_carlo():
    assert field_solid_angle_sr(180.0, 180.0) == pytest.approx(2 * math.pi, rel=1e-12)  # a hemisphere
    for h, v in [(6.0, 6.0), (11.53, 8.66), (50.0, 30.0)]:
        # independent form: a rectangle of half-sides X, Y at unit distance subtends 4 atan(XY / sqrt(1 + X^2 + Y^2))
        x, y = math.tan(math.radians(h) / 2), math.tan(math.radians(v) / 2)
        assert field_solid_angle_sr(h, v) == pytest.approx(4 * math.atan(x * y / math.sqrt(1 + x * x + y * y)), rel=1e-12)
    # Monte Carlo: the fraction of uniform directions inside a 50 x 30 deg pyramid, times 4 pi
    rng = np.random.default_rng(0)
    u = rng.normal(size=(400_000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    inside = (u[:, 2] > 0) & (np.abs(u[:, 0] / u[:, 2]) < math.tan(math.radians(25))) & \
             (np.abs(u[:, 1] / u[:, 2]) < math.tan(math.radians(15)))
    p = inside.mean()
    sigma = 4 * math.pi * math.sqrt(p * (1 - p) / u.shape[0])
    assert abs(4 * math.pi * p - field_solid_angle_sr(50.0, 30.0)) < 4 * sigma


def test_narrow_fields_get_a_deeper_catalogue_wide_ones_stay_at_hp6():
    six = magnitude_limit_for_field(6.0, 6.0)
    assert six.magnitude_limit > 6.0 and six.reached
    assert six.stars_per_field >= 20 and hipparcos_stars_per_sr(six.magnitude_limit - 0.5) * six.solid_angle_sr < 20
    assert magnitude_limit_for_field(6.0, 4.5).magnitude_limit >= six.magnitude_limit  # smaller field, deeper
    wide = magnitude_limit_for_field(50.0, 50.0)
    assert wide.magnitude_limit == 6.0 and wide.stars_per_field > 100
    tetra3 = magnitude_limit_for_field(11.53, 8.66)  # the 35 mm Blackfly S of the tetra3 images
    assert tetra3.magnitude_limit == 7.0
    narrow = magnitude_limit_for_field(1.0, 1.0)  # not even Hp 9 fills it: the completeness limit, flagged
    assert narrow.magnitude_limit == 9.0 and not narrow.reached and narrow.stars_per_field < 20


def test_detections_cap_the_target():
    """A camera that detects 5 stars a frame needs no more than 5 references per field."""
    capped = magnitude_limit_for_field(6.0, 6.0, detections_per_frame=5.0)
    assert capped.target_per_field == 5.0
    assert capped.stars_per_field >= 5.0 and capped.magnitude_limit < magnitude_limit_for_field(6.0, 6.0).magnitude_limit
    assert magnitude_limit_for_field(6.0, 6.0, detections_per_frame=500.0).target_per_field == 20.0


def test_stars_per_field_is_the_mean_count_of_random_fields():
    """density x solid angle = the mean number of catalogue stars in fields pointed at random."""
    limit = 7.0
    catalog = StarCatalog.from_hipparcos(epoch_year=2000.0, magnitude_limit=limit)
    radius = math.radians(8.0)
    omega = 2 * math.pi * (1 - math.cos(radius))  # a circular field of the same kind of size
    rng = np.random.default_rng(1)
    centres = rng.normal(size=(3000, 3))
    counts = np.array([catalog.cone(c, radius).size for c in centres])
    expected = hipparcos_stars_per_sr(limit) * omega
    assert abs(counts.mean() - expected) < 4 * counts.std() / math.sqrt(counts.size)
