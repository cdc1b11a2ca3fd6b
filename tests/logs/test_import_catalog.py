"""Imported recordings declare their catalogue: epoch from the observation time, depth from the camera's field."""
from __future__ import annotations

import json
import math
import warnings
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from rollingstar.logs import LogReader
from rollingstar.logs.importers import ImportDataError, ImportDataWarning, import_centroids, import_images
from rollingstar.pipelines.source import open_recording
from rollingstar.sensors.catalog import julian_year, magnitude_limit_for_field
from rollingstar.sensors.scenario import scenario_from_yaml

from .test_importers import TETRA3_SIDECAR, assert_clean_error, cli

# 400 px wide: the catalogue drops pairs closer than 8 px, which must stay small against the field
CAMERA_6DEG = "camera: {width_px: 400, height_px: 300, fov_deg: 6.0}\n"
CAMERA_50DEG = "camera: {width_px: 400, height_px: 300, fov_deg: 50.0}\n"
OBSERVED = datetime(2019, 7, 29, 20, 47, 26, tzinfo=timezone.utc)


def _folder(tmp_path: Path, sidecar: str, n: int = 2, suffix: str = ".png", exif=None) -> Path:
    folder = tmp_path / "imgs"
    folder.mkdir(exist_ok=True)
    for k in range(n):
        Image.fromarray(np.zeros((300, 400), np.uint8)).save(folder / f"f{k}{suffix}", **({"exif": exif} if exif else {}))
    (folder / "recording.yaml").write_text(sidecar)
    return folder


def _imported(path: Path) -> tuple:
    """(scenario, import.details.catalog, import warnings) of an imported recording."""
    meta = LogReader(path).metadata()
    return (scenario_from_yaml(meta["scenario"]["yaml"]), json.loads(meta["import"]["details"])["catalog"],
            json.loads(meta["import"]["warnings"]))


def _quiet_import(folder: Path, out: Path) -> Path:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every choice is stated: nothing to warn about
        return import_images(folder, out)


# --- epoch ------------------------------------------------------------------------------------------
def test_observation_time_sets_the_epoch(tmp_path):
    folder = _folder(tmp_path, CAMERA_6DEG + "timestamps: {frame_rate_hz: 2.0}\n"
                     "observation_time: 2019-07-29T22:47:26+02:00\n")  # an offset: the same instant as ...26Z
    scenario, cat, _ = _imported(_quiet_import(folder, tmp_path / "r.mcap"))
    assert cat["epoch_source"] == "observation_time" and cat["observation_time_utc"] == "2019-07-29T20:47:26Z"
    assert scenario.catalog.epoch_year == round(julian_year(OBSERVED), 4) == 2019.5739
    assert "observation_time" in cat["epoch_reason"] and str(folder / "recording.yaml") in cat["epoch_reason"]


def test_sidecar_epoch_wins_over_the_observation_time(tmp_path):
    folder = _folder(tmp_path, CAMERA_6DEG + "timestamps: {frame_rate_hz: 2.0}\n"
                     "observation_time: 2019-07-29T20:47:26Z\ncatalog: {epoch_year: 2000.0}\n")
    scenario, cat, _ = _imported(_quiet_import(folder, tmp_path / "r.mcap"))
    assert scenario.catalog.epoch_year == 2000.0 and cat["epoch_source"] == "sidecar"
    assert cat["observation_time_utc"] == "2019-07-29T20:47:26Z"  # still recorded
    # `rollingstar run` builds its catalogue from the declared scenario: positions at J2000.0
    assert open_recording(tmp_path / "r.mcap").context.catalog.epoch_year == 2000.0


def test_unix_time_frame_times_give_the_observation_time(tmp_path):
    t0 = int(OBSERVED.timestamp()) * 1_000_000_000
    folder = _folder(tmp_path, CAMERA_6DEG + "timestamps: {csv: times.csv}\n")
    (folder / "times.csv").write_text(f"file,t_unix_ns\nf0.png,{t0}\nf1.png,{t0 + 100_000_000}\n")
    scenario, cat, _ = _imported(_quiet_import(folder, tmp_path / "r.mcap"))
    assert cat["epoch_source"] == "timestamps" and cat["observation_time_source"] == "t_unix_ns"
    assert cat["observation_time_utc"] == "2019-07-29T20:47:26Z" and scenario.catalog.epoch_year == 2019.5739


def test_unix_looking_times_on_the_recording_clock_are_not_read_as_dates(tmp_path):
    t0 = int(OBSERVED.timestamp()) * 1_000_000_000
    folder = _folder(tmp_path, CAMERA_6DEG + f"timestamps: {{t0_ns: [{t0}, {t0 + 100_000_000}]}}\n")
    with pytest.warns(ImportDataWarning, match=r"would be 2019-07-29T20:47:26Z read as Unix time.*t_unix_ns"):
        rec = import_images(folder, tmp_path / "r.mcap")
    scenario, cat, warned = _imported(rec)
    assert cat["epoch_source"] == "default" and scenario.catalog.epoch_year == 2025.0
    assert any("no observation time" in w for w in warned)


def test_exif_time_with_its_offset(tmp_path):
    exif = Image.Exif()
    exif[0x0132] = "2019:07:30 10:00:00"  # DateTime (of the file's last change): DateTimeOriginal comes first
    sub = exif.get_ifd(0x8769)
    sub[0x9003], sub[0x9011] = "2019:07:29 22:47:26", "+02:00"  # DateTimeOriginal, OffsetTimeOriginal
    folder = _folder(tmp_path, CAMERA_6DEG + "timestamps: {frame_rate_hz: 2.0}\n", exif=exif)
    scenario, cat, _ = _imported(_quiet_import(folder, tmp_path / "r.mcap"))
    assert cat["epoch_source"] == "exif" and cat["observation_time_utc"] == "2019-07-29T20:47:26Z"
    assert scenario.catalog.epoch_year == 2019.5739


def _fits_folder(tmp_path: Path, sidecar: str, cards: dict, extension: bool = False) -> Path:
    """Two FITS frames with ``cards`` in the header of the HDU that holds the image (or, with
    ``extension``, in an empty primary HDU before an image extension)."""
    from astropy.io import fits

    folder = tmp_path / "fits"
    folder.mkdir()
    for k in range(2):
        image = fits.ImageHDU if extension else fits.PrimaryHDU
        hdu = image(np.zeros((300, 400), np.uint16))
        target = fits.PrimaryHDU() if extension else hdu
        target.header.update(cards)
        (fits.HDUList([target, hdu]) if extension else fits.HDUList([hdu])).writeto(folder / f"f{k}.fits")
    (folder / "recording.yaml").write_text(sidecar)
    return folder


@pytest.mark.parametrize("cards,extension", [
    ({"DATE-OBS": "2019-07-29T20:47:26"}, False),  # UTC by the standard's default
    ({"DATE-OBS": "2019-07-29T20:48:35.184", "TIMESYS": "TT"}, True),  # TT = UTC + 37 s + 32.184 s in 2019
    ({"DATE-OBS": "2019-07-29", "TIME-OBS": "20:47:26"}, False),  # the older split form
    ({"DATE-OBS": "2019-07-29 22:47:26.25+02:00"}, False),  # a space, a fraction and a zone
    ({"DATE-OBS": "2019-07-29", "MJD-OBS": 58693.86627315}, False),  # the time of day from MJD-OBS
    ({"MJD-OBS": 58693.86627315}, True),  # MJD-OBS alone
])
def test_fits_date_obs_sets_the_epoch(tmp_path, cards, extension):
    folder = _fits_folder(tmp_path, CAMERA_6DEG + "timestamps: {frame_rate_hz: 2.0}\n", cards, extension)
    scenario, cat, _ = _imported(_quiet_import(folder, tmp_path / "r.mcap"))
    assert cat["epoch_source"] == "fits" and cat["observation_time_source"] == "fits"
    when = datetime.fromisoformat(cat["observation_time_utc"].replace("Z", "+00:00"))
    assert abs((when - OBSERVED).total_seconds()) < 1.0, cat["observation_time_utc"]
    assert scenario.catalog.epoch_year == 2019.5739 and "FITS header" in cat["epoch_reason"]


def test_fits_header_times_are_the_frame_times(tmp_path):
    """FITS frames with a full DATE-OBS each and no frame times in the sidecar: the headers give the
    frame times (to the microsecond) instead of an assumed frame rate; one file without a time and
    the rate is assumed again, with the warning."""
    from astropy.io import fits

    folder = tmp_path / "fits"
    folder.mkdir()
    for k, stamp in enumerate(["20:47:26.000", "20:47:26.250", "20:47:26.500125"]):
        hdu = fits.PrimaryHDU(np.zeros((300, 400), np.uint16))
        hdu.header["DATE-OBS"] = f"2019-07-29T{stamp}"
        hdu.writeto(folder / f"f{k}.fits")
    (folder / "recording.yaml").write_text(CAMERA_6DEG)
    rec = _quiet_import(folder, tmp_path / "r.mcap")
    details = json.loads(LogReader(rec).metadata()["import"]["details"])
    t0 = np.array(details["t0_ns"])
    assert details["timestamps"] == {"source": "fits_headers"}
    assert t0[0] == int(OBSERVED.timestamp()) * 1_000_000_000 and list(np.diff(t0)) == [250_000_000, 250_125_000]
    fits.PrimaryHDU(np.zeros((300, 400), np.uint16)).writeto(folder / "f3.fits")
    with pytest.warns(ImportDataWarning, match="a time in every FITS header.*assuming"):
        rec = import_images(folder, tmp_path / "r2.mcap")
    assert json.loads(LogReader(rec).metadata()["import"]["details"])["timestamps"]["source"] == "frame_rate_hz"
    # whole seconds for a faster camera: two frames at one time, said and not used
    (folder / "f3.fits").unlink()
    with fits.open(folder / "f2.fits", mode="update") as hdul:
        hdul[0].header["DATE-OBS"] = "2019-07-29T20:47:26.250"
    with pytest.warns(ImportDataWarning, match=r"do not increase strictly in file order \(f2\.fits is 0 s after f1\.fits\)"):
        rec = import_images(folder, tmp_path / "r3.mcap")
    assert json.loads(LogReader(rec).metadata()["import"]["details"])["timestamps"]["source"] == "frame_rate_hz"


@pytest.mark.parametrize("cards,expect", [
    ({"DATE-OBS": "29/07/99"}, r"DATE-OBS 29/07/99 states no time of day"),  # the pre-2000 form: 1999-07-29
    ({"DATE-OBS": "1850-07-29T20:47:26"}, r"outside the years 1900-2100; not used"),
    ({"DATE-OBS": "2019-07-29"}, r"no time of day.*read as 00:00"),
    ({"DATE-OBS": "yesterday"}, r"DATE-OBS 'yesterday' is not a date and time"),
    ({"DATE-OBS": "2019-07-29", "MJD-OBS": "soon"}, r"MJD-OBS 'soon' is not a modified Julian date"),
    ({"DATE-OBS": "2019-07-29T20:47:26", "TIMESYS": "LOCAL"}, r"TIMESYS LOCAL.*time read as UTC"),
])
def test_a_fits_date_obs_that_is_not_a_full_time_is_said(tmp_path, cards, expect):
    folder = _fits_folder(tmp_path, CAMERA_6DEG + "timestamps: {frame_rate_hz: 2.0}\n", cards)
    with pytest.warns(ImportDataWarning, match=expect):
        rec = import_images(folder, tmp_path / "r.mcap")
    _, cat, _ = _imported(rec)
    if cards["DATE-OBS"] in ("2019-07-29", "2019-07-29T20:47:26", "29/07/99"):
        assert cat["epoch_source"] == "fits"
        assert cat["observation_time_utc"].startswith("1999-07-29T00:00:00" if "/" in cards["DATE-OBS"] else "2019-07-29T")
    else:
        assert cat["epoch_source"] == "default" and cat["observation_time_utc"] is None


def test_tiff_datetime_without_zone_is_read_as_utc_with_a_warning(tmp_path):
    exif = Image.Exif()
    exif[0x0132] = "2019:07:29 20:47:26"  # TIFF DateTime: local time of an unknown zone
    folder = _folder(tmp_path, CAMERA_6DEG + "timestamps: {frame_rate_hz: 2.0}\n", suffix=".tiff", exif=exif)
    with pytest.warns(ImportDataWarning, match="states no time zone; read as UTC"):
        rec = import_images(folder, tmp_path / "r.mcap")
    _, cat, _ = _imported(rec)
    assert cat["epoch_source"] == "exif" and cat["observation_time_utc"] == "2019-07-29T20:47:26Z"


def test_no_time_keeps_the_default_epoch_and_says_so(tmp_path):
    folder = _folder(tmp_path, CAMERA_6DEG + "timestamps: {frame_rate_hz: 2.0}\n")
    with pytest.warns(ImportDataWarning, match="no observation time.*default epoch 2025"):
        rec = import_images(folder, tmp_path / "r.mcap")
    scenario, cat, warned = _imported(rec)
    assert scenario.catalog.epoch_year == 2025.0 and cat["epoch_source"] == "default"
    assert cat["observation_time_utc"] is None and len(warned) == 1


# --- depth ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("camera,deeper", [(CAMERA_6DEG, True), (CAMERA_50DEG, False)])
def test_the_camera_field_sets_the_depth(tmp_path, camera, deeper):
    folder = _folder(tmp_path, camera + "timestamps: {frame_rate_hz: 2.0}\nobservation_time: 2019-07-29T20:47:26Z\n")
    rec = _quiet_import(folder, tmp_path / "r.mcap")
    scenario, cat, _ = _imported(rec)
    limit = scenario.catalog.magnitude_limit
    hfov, vfov = cat["field"]["hfov_deg"], cat["field"]["vfov_deg"]
    assert hfov == pytest.approx(6.0 if deeper else 50.0) and vfov < hfov
    assert cat["magnitude_source"] == "field" and limit == magnitude_limit_for_field(hfov, vfov).magnitude_limit
    assert (limit > 6.0) == deeper and limit >= 6.0
    assert cat["field"]["stars_per_field"] >= 20
    catalog = open_recording(rec).context.catalog  # what `rollingstar run` identifies against
    assert catalog.magnitude.max() <= limit and (catalog.magnitude.max() > 6.0) == deeper


def test_sidecar_magnitude_limit_wins(tmp_path):
    folder = _folder(tmp_path, CAMERA_50DEG + "timestamps: {frame_rate_hz: 2.0}\n"
                     "observation_time: 2019-07-29T20:47:26Z\ncatalog: {magnitude_limit: 7.5}\n")
    scenario, cat, _ = _imported(_quiet_import(folder, tmp_path / "r.mcap"))
    assert scenario.catalog.magnitude_limit == 7.5 and cat["magnitude_source"] == "sidecar"
    assert cat["field"]["rule_magnitude_limit"] == 6.0  # what the field alone would have chosen


def test_centroid_tables_cap_the_depth_at_their_detections_and_read_unix_times(tmp_path):
    t0 = int(OBSERVED.timestamp()) * 1_000_000_000
    rows = [f"{k},{t0 + k * 100_000_000},{10 + i},{12 + i},100" for k in range(2) for i in range(3)]
    csv = tmp_path / "c.csv"
    csv.write_text("frame,t_unix_ns,x,y,flux\n" + "\n".join(rows) + "\n")
    camera = tmp_path / "camera.yaml"
    camera.write_text("width_px: 400\nheight_px: 300\nfov_deg: 6.0\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rec = import_centroids(csv, tmp_path / "c.mcap", camera)
    scenario, cat, _ = _imported(rec)
    assert cat["field"]["detections_per_frame"] == 3.0 and cat["field"]["target_per_field"] == 3.0
    hfov, vfov = cat["field"]["hfov_deg"], cat["field"]["vfov_deg"]
    assert scenario.catalog.magnitude_limit == magnitude_limit_for_field(hfov, vfov, detections_per_frame=3).magnitude_limit
    assert scenario.catalog.magnitude_limit < magnitude_limit_for_field(hfov, vfov).magnitude_limit
    assert cat["epoch_source"] == "timestamps" and scenario.catalog.epoch_year == 2019.5739
    # the Python arguments play the sidecar's part
    rec = import_centroids(csv, tmp_path / "d.mcap", camera, catalog={"epoch_year": 2000.0, "magnitude_limit": 8.0})
    scenario, cat, _ = _imported(rec)
    assert (scenario.catalog.epoch_year, scenario.catalog.magnitude_limit) == (2000.0, 8.0)
    with pytest.raises(ImportDataError, match="import_centroids: catalog.epoch_year"):
        import_centroids(csv, tmp_path / "e.mcap", camera, catalog={"epoch_year": 3000.0})


# --- errors -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("line,needles", [
    ("catalog: {epoch_year: 3000.0}", ["catalog.epoch_year", "less than or equal to 2100"]),
    ("catalog: {magnitude_limit: 25}", ["catalog.magnitude_limit", "less than or equal to 12"]),
    ("observation_time: '29/07/2019 20:47'", ["observation_time", "not an ISO 8601 time"]),
    ("observation_time: 2019-07-29T20:47:26", ["observation_time", "no time zone"]),
    ("observation_time: 1564433246", ["observation_time", "a number"]),
    ("observation_time: 2019-02-30T10:00:00Z", ["line 2", "2019-02-30T10:00:00Z", "not a valid date or time"]),
])
def test_bad_sidecar_values_name_the_file_and_key(tmp_path, line, needles):
    folder = _folder(tmp_path, CAMERA_6DEG + line + "\n")
    assert_clean_error(cli("import", "images", folder, "-o", tmp_path / "r.mcap"),
                       str(folder / "recording.yaml"), *needles)


def test_unix_frame_times_outside_the_accepted_years_are_an_error(tmp_path):
    folder = _folder(tmp_path, CAMERA_6DEG + "timestamps: {csv: times.csv}\n")
    (folder / "times.csv").write_text("file,t_unix_ns\nf0.png,5000000000000000000\nf1.png,5000000000100000000\n")
    with pytest.raises(ImportDataError, match=r"times.csv: t_unix_ns 5000000000000000000 is 2128-06-11 as Unix time"):
        import_images(folder, tmp_path / "r.mcap")


# --- real data --------------------------------------------------------------------------------------
def test_real_tetra3_recording_declares_its_observation_epoch_and_depth(real_data_dir, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rec = import_images(real_data_dir / "tetra3", tmp_path / "t.mcap", sidecar=TETRA3_SIDECAR)
    scenario, cat, _ = _imported(rec)
    assert cat["observation_time_utc"] == "2019-07-29T20:47:26Z" and cat["epoch_source"] == "observation_time"
    assert scenario.catalog.epoch_year == 2019.5739
    # 11.5 x 8.7 deg: Hp 6.5 holds 19.3 stars per field on average, Hp 7.0 33.7
    assert scenario.catalog.magnitude_limit == 7.0 and cat["magnitude_source"] == "field"
    assert math.isclose(cat["field"]["stars_per_field"], 33.65, abs_tol=0.05)
