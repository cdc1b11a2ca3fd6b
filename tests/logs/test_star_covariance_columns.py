"""The stars' 2 x 2 position covariance in the log: the ``rollingstar.Stars`` columns
``cov_xx, cov_xy, cov_yy``, written by the run's sink, read back, NaN from records without them,
and accepted by the centroid CSV importer."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.estimators.data import FrameData, StarTable
from rollingstar.logs import LogReader, iter_frames, stars_to_arrays
from rollingstar.logs.importers import CameraSpec, ImportDataError, import_centroids
from rollingstar.logs.records import arrays_to_stars
from rollingstar.logs.topics import TOPIC_EST_STARS
from rollingstar.logs.writer import LogWriter
from rollingstar.pipelines.sink import write_frame
from rollingstar.pipelines.source import stars_from_record

CAMERA = CameraSpec(width_px=1024, height_px=1024, focal_length_mm=50.0, pixel_size_um=5.5)


def _table() -> StarTable:
    return StarTable.build([10.0, 20.0, 30.0], [5.0, 6.0, 7.0], 1000, sigma_px=[0.1, 0.2, np.nan],
                           cov_xx=[0.04, 0.01, np.nan], cov_xy=[0.006, -0.002, np.nan], cov_yy=[0.0025, 0.07, np.nan])


def test_record_round_trip_and_null_for_unknown():
    t = _table()
    rec = arrays_to_stars(0, 0, x=t.x, y=t.y, t_ns=t.t_ns, cov_xx=t.cov_xx, cov_xy=t.cov_xy, cov_yy=t.cov_yy)
    data = rec.model_dump(mode="json")
    assert data["cov_xy"] == [0.006, -0.002, None]
    back = stars_to_arrays(data)
    for col in ("cov_xx", "cov_xy", "cov_yy"):
        np.testing.assert_array_equal(back[col], getattr(t, col))


def test_a_record_without_the_columns_reads_as_nan_and_falls_back_to_sigma():
    """A record written before the covariance columns existed: the record has no such columns, the
    star table read from it a NaN covariance, so its position_covariance falls back to
    sigma_px^2 I (then the default)."""
    old = {"frame": 2, "t0_ns": 0, "x": [1.0, 2.0], "y": [3.0, 4.0], "t_ns": [0, 0], "sigma_px": [0.1, None]}
    assert not {"cov_xx", "cov_xy", "cov_yy"} & set(stars_to_arrays(old))
    table, dropped = stars_from_record(old)
    assert dropped == 0
    for col in ("cov_xx", "cov_xy", "cov_yy"):
        assert np.isnan(getattr(table, col)).all()
    np.testing.assert_allclose(table.position_covariance(0.05), [np.diag([0.01, 0.01]), np.diag([0.0025, 0.0025])])


def test_the_sink_writes_the_covariance_and_the_source_reads_it(tmp_path):
    t = _table()
    path = tmp_path / "out.mcap"
    with LogWriter(path, kind="run") as writer:
        write_frame(writer, FrameData(index=0, t0_ns=1000, stars=t))
    stars = LogReader(path).stars(TOPIC_EST_STARS)[0]
    for col in ("cov_xx", "cov_xy", "cov_yy", "sigma_px"):
        np.testing.assert_array_equal(stars[col], getattr(t, col))
    msg = next(LogReader(path).messages(TOPIC_EST_STARS))
    table, _ = stars_from_record(msg.data)
    np.testing.assert_array_equal(table.position_covariance(0.05)[0], [[0.04, 0.006], [0.006, 0.0025]])


def test_centroid_csv_with_a_covariance(tmp_path):
    csv = tmp_path / "c.csv"
    csv.write_text("frame,t_ns,x,y,flux,cov_xx,cov_xy,cov_yy\n"
                   "0,1000,101.5,40.5,5200,0.04,0.006,0.0025\n"
                   "0,1000,512.0,300.0,830,,,\n")
    rec = import_centroids(csv, tmp_path / "r.mcap", CAMERA)
    s = stars_to_arrays(next(iter(iter_frames(LogReader(rec), "/camera/centroids"))).frame.data)
    np.testing.assert_array_equal(s["cov_xx"], [0.04, np.nan])
    np.testing.assert_array_equal(s["cov_xy"], [0.006, np.nan])
    np.testing.assert_array_equal(s["cov_yy"], [0.0025, np.nan])


@pytest.mark.parametrize("header,row,needle", [
    ("cov_xx,cov_yy", "0.04,0.01", "cov_xx, cov_yy without cov_xy"),
    ("cov_xx,cov_xy,cov_yy", "0.04,,0.01", "line 2, column 'cov_xy': empty while the row's other covariance cells"),
    ("cov_xx,cov_xy,cov_yy", "0.04,0.05,0.01", "line 2, column 'cov_xx': [[0.04, 0.05], [0.05, 0.01]] is not a position"),
    ("cov_xx,cov_xy,cov_yy", "-0.04,0,0.01", "is not a position covariance"),
])
def test_centroid_csv_bad_covariance(tmp_path, header, row, needle):
    csv = tmp_path / "bad.csv"
    csv.write_text(f"frame,t_ns,x,y,flux,{header}\n0,0,1,2,3,{row}\n")
    with pytest.raises(ImportDataError) as err:
        import_centroids(csv, tmp_path / "r.mcap", CAMERA)
    assert str(csv) in str(err.value) and needle in str(err.value), str(err.value)
