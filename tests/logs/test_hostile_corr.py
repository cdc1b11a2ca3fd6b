"""``rollingstar import corr`` on tables and log.json files nobody here made.

A corr row whose catalogue direction is no direction on the sky is dropped with a warning, like a
star outside the image; a log.json value of the wrong kind is refused (exit 2) naming the file and
the field.
"""
from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from rollingstar.logs import LogReader, iter_frames, stars_to_arrays
from rollingstar.sensors.conventions import attitude_from_radec_roll

from .test_importers import FOV, H, W, write_corr


def import_corr(tmp_path, folder) -> tuple[int, str]:
    """``rollingstar import corr FOLDER -o rec.mcap`` in-process: (exit code, stderr on one line)."""
    from rollingstar.cli import app

    res = CliRunner().invoke(app, ["import", "corr", str(folder), "-o", str(tmp_path / "rec.mcap")])
    return res.exit_code, " ".join(res.stderr.split())


@pytest.mark.parametrize("column, value", [("index_dec", 500.0), ("index_dec", -90.5), ("index_ra", 1e300)])
def test_rows_whose_catalogue_direction_is_off_the_sky_are_dropped_with_a_warning(tmp_path, column, value):
    from astropy.io import fits

    table = write_corr(tmp_path / "scene", attitude_from_radec_roll(10.0, 20.0, 30.0), n=12)
    with fits.open(tmp_path / "scene" / "corr.fits", mode="update") as hdul:
        hdul[1].data[column][[2, 7]] = value
    code, err = import_corr(tmp_path, tmp_path / "scene")
    assert code == 0, err
    expected = "corr.fits: 2 row(s) with index_ra outside [-360, 360] deg or index_dec outside [-90, 90] deg " \
               "dropped (rows 2, 7)"
    assert "".join(expected.split()) in "".join(err.split()), err  # the console may wrap inside the long path
    frame = next(iter(iter_frames(LogReader(tmp_path / "rec.mcap"), "/camera/centroids"))).frame
    assert list(stars_to_arrays(frame.data)["catalog_id"]) == [i for k, i in enumerate(table["ids"]) if k not in (2, 7)]


@pytest.mark.parametrize("field, log_json", [
    ("image_size.x", {"fov_deg": FOV, "image_size": {"x": True, "y": H}, "center": {"ra_degrees": 1, "dec_degrees": 2}}),
    ("fov_deg", {"fov_deg": True, "image_size": {"x": W, "y": H}, "center": {"ra_degrees": 1, "dec_degrees": 2}}),
    ("center.dec_degrees", {"fov_deg": FOV, "image_size": {"x": W, "y": H},
                            "center": {"ra_degrees": 1, "dec_degrees": False}}),
])
def test_a_boolean_where_log_json_has_a_number_is_refused(tmp_path, field, log_json):
    write_corr(tmp_path / "scene", attitude_from_radec_roll(10.0, 20.0, 30.0), log_json=json.dumps(log_json))
    code, err = import_corr(tmp_path, tmp_path / "scene")
    assert code == 2, err
    expected = f"scene/log.json: {field}: expected a number, got a boolean"
    assert "".join(expected.split()) in "".join(err.split()), err  # the console may wrap inside the long path
    assert not (tmp_path / "rec.mcap").exists()
