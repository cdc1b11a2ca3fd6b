"""JSON records: strict validation, NaN <-> null, array round trips."""
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from pydantic import ValidationError

from rollingstar.logs.records import (
    RECORD_TYPES,
    AttitudeEstimateRecord,
    AttitudeSamplesRecord,
    GyroSamplesRecord,
    RateEstimateRecord,
    StarsRecord,
    arrays_to_stars,
    attitude_samples_from_arrays,
    attitude_samples_to_arrays,
    gyro_samples_from_arrays,
    gyro_samples_to_arrays,
    stars_to_arrays,
)

floats = st.floats(allow_nan=True, allow_infinity=False, width=64)


@st.composite
def star_columns(draw):
    n = draw(st.integers(0, 8))
    col = lambda: draw(hnp.arrays(float, n, elements=floats))  # noqa: E731
    ref = draw(hnp.arrays(float, (n, 3), elements=st.floats(-1, 1)))
    norm = np.linalg.norm(ref, axis=1, keepdims=True)
    ref = np.where(norm > 1e-3, ref / np.maximum(norm, 1e-3), [0.0, 0.0, 1.0])  # directions are unit vectors
    unidentified = draw(hnp.arrays(bool, n))
    ref[unidentified] = np.nan
    return dict(
        x=col(), y=col(), t_ns=draw(hnp.arrays(np.int64, n, elements=st.integers(0, 2**62))),
        row_time_ns=draw(hnp.arrays(np.int64, n, elements=st.integers(0, 2**62))),
        flux=col(), sigma_px=col(), vx=col(), saturated=draw(hnp.arrays(bool, n)),
        npix=draw(hnp.arrays(np.int64, n, elements=st.integers(0, 1000))),
        catalog_id=draw(hnp.arrays(np.int64, n, elements=st.integers(-1, 10**6))),
        ref_icrs=ref, magnitude=col(),
    )


@settings(max_examples=60, deadline=None)
@given(columns=star_columns(), frame=st.integers(0, 10**6), t0=st.integers(0, 2**62))
def test_stars_round_trip_through_json_keeps_nan_and_ints(columns, frame, t0):
    record = arrays_to_stars(frame, t0, **columns)
    text = record.model_dump_json()
    assert "NaN" not in text
    back_record = StarsRecord.model_validate_json(text)
    assert back_record.frame == frame and back_record.t0_ns == t0
    back = stars_to_arrays(json.loads(text))
    assert set(back) == set(columns)
    for name, value in columns.items():
        np.testing.assert_array_equal(back[name], value, err_msg=name)
        assert back[name].dtype == np.asarray(value).dtype, name


def test_omitted_columns_are_absent_and_scalar_t_ns_broadcasts():
    rec = arrays_to_stars(0, 5, x=[1.0, 2.0], y=[3.0, 4.0], t_ns=7, flux=None)
    arrays = stars_to_arrays(rec)
    assert set(arrays) == {"x", "y", "t_ns"}
    assert arrays["t_ns"].tolist() == [7, 7]


def test_column_length_mismatch_names_the_field():
    with pytest.raises(ValidationError, match="column 'flux' has length 1, expected 2"):
        StarsRecord(frame=0, t0_ns=0, x=[1.0, 2.0], y=[1.0, 2.0], t_ns=[0, 0], flux=[1.0])
    with pytest.raises(ValueError, match="'y'.*expected shape"):
        arrays_to_stars(0, 0, x=[1.0, 2.0], y=[1.0], t_ns=0)


def test_strict_types_reject_float_times_unknown_fields_and_nan():
    good = {"frame": 0, "t0_ns": 0, "x": [1.0], "y": [2.0], "t_ns": [0]}
    StarsRecord.model_validate(good)
    with pytest.raises(ValidationError, match="t0_ns"):
        StarsRecord.model_validate({**good, "t0_ns": 1.5e18})
    with pytest.raises(ValidationError, match="extra"):
        StarsRecord.model_validate({**good, "colour": [1]})
    with pytest.raises(ValidationError):
        StarsRecord.model_validate({**good, "x": [float("nan")]})
    with pytest.raises(ValidationError):
        StarsRecord.model_validate({**good, "ref_icrs": [[1.0, 0.0]]})


@settings(max_examples=30, deadline=None)
@given(n=st.integers(1, 6), data=st.data())
def test_attitude_and_gyro_samples_round_trip(n, data):
    t = np.sort(data.draw(hnp.arrays(np.int64, n, elements=st.integers(0, 2**62))))
    q = data.draw(hnp.arrays(float, (n, 4), elements=st.floats(-1, 1)))
    q[:, 3] += 2.0  # keep away from zero before normalising
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w = data.draw(hnp.arrays(float, (n, 3), elements=st.floats(-1, 1)))
    rec = AttitudeSamplesRecord.model_validate_json(attitude_samples_from_arrays(t, q, w).model_dump_json())
    arrays = attitude_samples_to_arrays(rec)
    np.testing.assert_array_equal(arrays["t_ns"], t)
    np.testing.assert_array_equal(arrays["q_xyzw"], q)
    np.testing.assert_array_equal(arrays["omega_rad_s"], w)
    gyro = gyro_samples_to_arrays(GyroSamplesRecord.model_validate_json(gyro_samples_from_arrays(t, w).model_dump_json()))
    np.testing.assert_array_equal(gyro["omega_rad_s"], w)
    assert rec.default_log_time_ns() == t[0]
    assert gyro_samples_from_arrays(t, w).default_log_time_ns() == t[-1]


def test_attitude_samples_without_rates_give_nan_and_bad_quaternions_fail():
    arrays = attitude_samples_to_arrays(attitude_samples_from_arrays([1], [[0, 0, 0, 1]]))
    assert np.isnan(arrays["omega_rad_s"]).all()
    with pytest.raises(ValidationError, match="not unit"):
        attitude_samples_from_arrays([1], [[0, 0, 0, 2]])
    with pytest.raises(ValidationError, match="non-decreasing"):
        gyro_samples_from_arrays([2, 1], np.zeros((2, 3)))


def test_estimates_invalid_give_null_and_valid_need_values():
    rec = AttitudeEstimateRecord.from_values(3, 10, np.full(4, np.nan), n_stars=1, valid=False, reason="too_few_stars")
    assert json.loads(rec.model_dump_json())["q"] is None
    assert np.isnan(rec.q_xyzw()).all()
    with pytest.raises(ValidationError, match="valid estimate needs q"):
        AttitudeEstimateRecord.from_values(3, 10, None, n_stars=5, valid=True)
    cov = np.eye(3) * 1e-10
    rec = AttitudeEstimateRecord.from_values(3, 10, [0, 0, 0, 1], n_stars=5, covariance_rad2=cov)
    assert rec.covariance_rad2 == cov.reshape(-1).tolist()
    rate = RateEstimateRecord.from_values(3, 10, [0.1, 0.2, 0.3], iterations=4)
    assert rate.omega.z == 0.3 and rate.iterations == 4


def test_every_record_has_a_json_schema_named_after_it():
    for name, cls in RECORD_TYPES.items():
        schema = cls.model_json_schema()
        assert schema["title"] == name
        assert schema["additionalProperties"] is False


def test_directions_are_unit_and_integers_fit_int64():
    good = {"frame": 0, "t0_ns": 0, "x": [1.0, 2.0], "y": [2.0, 3.0], "t_ns": [0, 0], "catalog_id": [5, -1],
            "ref_icrs": [[0.0, 0.6, 0.8], None]}
    StarsRecord.model_validate(good)
    for ref, norm in (([0.0, 0.0, 0.0], "0"), ([0.0, 1.2, 1.6], "2")):
        with pytest.raises(ValidationError, match=rf"ref_icrs of star 0 is not a unit vector \(\|v\| = {norm}\)"):
            StarsRecord.model_validate({**good, "ref_icrs": [ref, None]})
    with pytest.raises(ValidationError, match="t0_ns"):
        StarsRecord.model_validate({**good, "t0_ns": -1})
    with pytest.raises(ValidationError, match="catalog_id.0"):
        StarsRecord.model_validate({**good, "catalog_id": [2**63, -1]})
    with pytest.raises(ValidationError, match="t_ns.0"):
        GyroSamplesRecord.model_validate({"t_ns": [-(2**63) - 1], "x": [0.0], "y": [0.0], "z": [0.0]})
