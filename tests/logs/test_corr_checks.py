"""Corr tables that look valid column by column but are not what they say (logs/importers/corr_checks.py):
each is refused naming the column and what was expected, or read with the damage said, never taken
as physics. Tables are written with astropy in astrometry.net's columns (tests/logs/test_importers.py)."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from rollingstar.logs import LogReader, iter_frames, stars_to_arrays
from rollingstar.logs.importers.corr import find_corr_folders, import_corr
from rollingstar.sensors.conventions import attitude_from_radec_roll
from rollingstar.sensors.scenario import scenario_from_yaml
from tests.logs.test_importers import assert_clean_error, cli, write_corr

R = attitude_from_radec_roll(150.0, -35.0, 20.0)


def _edit(folder: Path, **changes):
    """Rewrite the corr table of ``folder`` with columns changed: name -> function of the table's data."""
    from astropy.io import fits

    path = folder / "corr.fits"
    with fits.open(path) as hdul:
        data = {c.name: np.array(hdul[1].data[c.name]) for c in hdul[1].columns}
        formats = {c.name: c.format for c in hdul[1].columns}
    for name, f in changes.items():
        data[name] = f(data)
    n = len(next(iter(data.values())))
    cols = [fits.Column(name=k, format=formats[k], array=v) for k, v in data.items() if len(v) == n]
    fits.BinTableHDU.from_columns(cols).writeto(path, overwrite=True)


def _stars(rec: Path) -> dict:
    return stars_to_arrays(next(iter(iter_frames(LogReader(rec), "/camera/centroids"))).frame.data)


def test_repeated_rows_are_counted_once_and_ambiguous_matches_dropped(tmp_path):
    table = write_corr(tmp_path / "sky", R, n=20)
    order = np.r_[np.arange(20), np.arange(12)]  # the first 12 rows listed twice

    def moved(d):  # row 19 measured again at another position: one catalogue star, two positions
        x = d["field_x"][order].copy()
        x[-1] += 30.0
        return x

    _edit(tmp_path / "sky", **{k: (lambda d, k=k: d[k][order]) for k in
                               ("field_y", "index_x", "index_y", "index_ra", "index_dec", "index_id", "match_weight",
                                "FLUX")}, field_x=moved)
    with pytest.warns(UserWarning) as caught:
        rec = import_corr(tmp_path / "sky", tmp_path / "r.mcap")
    text = " ".join(str(w.message) for w in caught)
    assert "11 row(s) repeat an earlier row exactly" in text
    assert "2 row(s) match one measured position to two catalogue stars or one catalogue star to two positions" in text
    ids = _stars(rec)["catalog_id"]
    np.testing.assert_array_equal(np.sort(ids), np.delete(table["ids"], 11))  # each star once; star 11's two rows gone


def test_a_shifted_position_column_is_refused(tmp_path):
    write_corr(tmp_path / "sky", R)
    _edit(tmp_path / "sky", field_x=lambda d: d["field_x"] - 1.0)  # written 0-based where FITS is 1-based
    assert_clean_error(cli("import", "corr", tmp_path / "sky", "-o", tmp_path / "r.mcap"),
                       "corr.fits", "field_x - index_x is -1", "shifted", "1-based")


def test_a_constant_or_replaced_position_column_is_refused(tmp_path):
    write_corr(tmp_path / "a", R)
    _edit(tmp_path / "a", field_y=lambda d: np.ones_like(d["field_y"]))
    assert_clean_error(cli("import", "corr", tmp_path / "a", "-o", tmp_path / "r.mcap"), "field_y is 1 for every star")
    write_corr(tmp_path / "b", R)
    _edit(tmp_path / "b", index_x=lambda d: d["index_x"][::-1])  # another column's order
    assert_clean_error(cli("import", "corr", tmp_path / "b", "-o", tmp_path / "r.mcap"),
                       "field_xy - index_xy exceed", "damaged or replaced")


def test_one_damaged_residual_row_is_left_out_of_the_noise_not_the_table(tmp_path):
    write_corr(tmp_path / "sky", R, n=30)
    _edit(tmp_path / "sky", index_y=lambda d: np.where(np.arange(d["index_y"].size) == 4, 9e5, d["index_y"]))
    with pytest.warns(UserWarning, match=r"1 row\(s\) with field_xy - index_xy beyond .* \(rows 4\)"):
        rec = import_corr(tmp_path / "sky", tmp_path / "r.mcap")
    assert _stars(rec)["x"].size == 30
    sigma = scenario_from_yaml(LogReader(rec).metadata()["scenario"]["yaml"]).noise.centroid_sigma_px
    assert 0.05 < sigma < 0.2  # the other rows' 0.1 px per axis


def test_catalogue_angles_in_radians_are_refused(tmp_path):
    write_corr(tmp_path / "sky", R)
    _edit(tmp_path / "sky", index_ra=lambda d: np.radians(d["index_ra"]), index_dec=lambda d: np.radians(d["index_dec"]))
    assert_clean_error(cli("import", "corr", tmp_path / "sky", "-o", tmp_path / "r.mcap"),
                       "index_ra, index_dec", "times those their pixel distances span", "degrees")


def test_a_table_without_its_fit_residual_states_no_noise_and_diagnose_says_it_estimated_one(tmp_path):
    write_corr(tmp_path / "sky", R, n=40)
    _edit(tmp_path / "sky", index_x=lambda d: np.full(d["index_x"].size, np.nan))
    with pytest.warns(UserWarning, match="states no fit residual"):
        rec = import_corr(tmp_path / "sky", tmp_path / "r.mcap")
    assert scenario_from_yaml(LogReader(rec).metadata()["scenario"]["yaml"]).noise.centroid_sigma_px == 0.0
    proc = cli("diagnose", "--recording", rec, "-o", tmp_path / "d", "--json", "-q")
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert result["noise"]["source"].startswith("estimated")
    assert result["summary"].startswith("The recording states no centroid noise")
    assert "RuntimeWarning" not in proc.stderr and "invalid value" not in proc.stderr


def test_a_pointing_centre_far_from_the_stars_is_said(tmp_path):
    write_corr(tmp_path / "sky", R, centre=(330.0, 35.0))
    with pytest.warns(UserWarning, match=r"log.json's centre .* deg from the mean direction of the table's stars"):
        import_corr(tmp_path / "sky", tmp_path / "r.mcap")


def test_one_image_in_two_folders_is_said(tmp_path):
    write_corr(tmp_path / "sky" / "a", R)
    write_corr(tmp_path / "sky" / "b", R)  # the same seed: the same stars at the same positions
    with pytest.warns(UserWarning, match="one image imported twice"):
        import_corr(tmp_path / "sky", tmp_path / "r.mcap")


def test_a_solve_field_output_folder_and_linked_folders_are_read(tmp_path):
    """astrometry.net's solve-field writes ``<image>.corr`` beside wcs, rdls and axy FITS files; the
    table is the one with the corr columns. A folder linked into the tree is read like any other."""
    from astropy.io import fits

    write_corr(tmp_path / "solve", R)
    (tmp_path / "solve" / "corr.fits").rename(tmp_path / "solve" / "image.corr")
    fits.PrimaryHDU(np.zeros((4, 4))).writeto(tmp_path / "solve" / "image.wcs.fits")
    fits.BinTableHDU.from_columns([fits.Column(name="RA", format="D", array=[1.0]),
                                   fits.Column(name="DEC", format="D", array=[2.0])]).writeto(tmp_path / "solve" / "image.rdls.fits")
    rec = import_corr(tmp_path / "solve", tmp_path / "r.mcap")
    assert _stars(rec)["x"].size == 30
    tree = tmp_path / "tree"
    write_corr(tree / "own", R, seed=1)
    os.symlink(tmp_path / "solve", tree / "linked")
    os.symlink(tree, tree / "own" / "loop")  # a link back up the tree is not followed twice
    assert [p.name for p in find_corr_folders(tree)] == ["linked", "own"]


def test_an_existing_file_that_is_not_a_recording_is_never_replaced(tmp_path):
    write_corr(tmp_path / "sky", R)
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes")
    assert_clean_error(cli("import", "corr", tmp_path / "sky", "-o", notes), "notes.txt", "is not an MCAP recording")
    assert notes.read_text() == "my notes"
    rec = tmp_path / "r.mcap"
    import_corr(tmp_path / "sky", rec)
    with pytest.warns(UserWarning, match="replaced"):  # a recording is replaced by a recording, with a warning
        import_corr(tmp_path / "sky", rec)


@pytest.mark.parametrize("value", ["inf", "1e300"])
def test_an_impossible_reference_accuracy_is_refused(tmp_path, value):
    write_corr(tmp_path / "sky", R)
    rec = import_corr(tmp_path / "sky", tmp_path / "r.mcap")
    assert_clean_error(cli("diagnose", "--recording", rec, "-o", tmp_path / "d", "--reference-attitude-arcsec", value),
                       "--reference-attitude-arcsec", "finite number from 0 to 648000")


def test_the_real_creusot_tables_pass_every_check(tmp_path):
    """The checks' limits against astrometry.net's own output: none of the 31 real tables is refused or warned about."""
    root = Path(os.environ.get("ROLLINGSTAR_REAL_DATA", Path(__file__).resolve().parents[3] / "shared" / "data" / "real"))
    if not (root / "creusot").is_dir():
        pytest.skip(f"real data not found at {root} (set ROLLINGSTAR_REAL_DATA)")
    from rollingstar.logs.importers.common import WarningLog
    from rollingstar.logs.importers.corr import _read_frame

    log = WarningLog()
    frames = [_read_frame(f, log) for f in find_corr_folders(root / "creusot")]
    assert len(frames) == 31
    assert [m for m in log.messages if "not valid JSON" not in m] == []  # Nunki's log.json lacks a comma (repaired)


def test_a_log_json_key_given_twice_is_said_and_an_unread_timestamp_of_any_form_is_kept(tmp_path):
    write_corr(tmp_path / "sky", R)
    text = (tmp_path / "sky" / "log.json").read_text()
    data = json.loads(text)
    body = json.dumps({**data, "timestamp": "2023-09-07T21:26:00Z"})
    (tmp_path / "sky" / "log.json").write_text(body[:-1] + ', "fov_deg": ' + str(data["fov_deg"]) + "}")
    with pytest.warns(UserWarning, match="'fov_deg' given more than once"):
        rec = import_corr(tmp_path / "sky", tmp_path / "r.mcap")
    details = json.loads(LogReader(rec).metadata()["import"]["details"])
    assert details["frames"][0]["timestamp"] == "2023-09-07T21:26:00Z"


def test_a_stated_noise_larger_than_the_residuals_is_said(tmp_path):
    """write_corr's measured positions are exact and its index positions 0.1 px off: the table states
    0.1 px, the single image's fit leaves far less, and the report says the tests are conservative."""
    write_corr(tmp_path / "sky", R, n=40)
    rec = import_corr(tmp_path / "sky", tmp_path / "r.mcap")
    proc = cli("diagnose", "--recording", rec, "-o", tmp_path / "d", "--json", "-q")
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    over = result["noise_overstated"]
    assert over is not None and over["factor"] < 0.2 and over["p"] < 1e-3
    assert "The stated noise is larger than this recording's residuals" in result["summary"]
