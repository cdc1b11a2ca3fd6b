"""Centroid CSVs as new users write them: benign variants import, mistakes fail with a message
naming the file, line and column (exit 2 from the CLI), never a silently wrong recording."""
import warnings

import pytest

from rollingstar.logs import LogReader
from rollingstar.logs.importers import CameraSpec, ImportDataError, ImportDataWarning, import_centroids
from tests.logs.test_importers import assert_clean_error, cli

# a rolling shutter reading out its 1024 rows in 1023 x 20 us = 20.46 ms; frames 100 ms apart
CAMERA = CameraSpec(width_px=1024, height_px=1024, focal_length_mm=50.0, pixel_size_um=5.5,
                    shutter={"mode": "rolling", "exposure_ms": 10.0, "line_delay_us": 20.0})
HEADER = "frame,t_ns,x,y,flux"
ROWS = ["0,1000000000,101.5,40.25,5200", "0,1000000000,512.75,300.5,830",
        "1,1100000000,102.0,41.0,5150", "1,1100000000,513.5,301.25,820"]


def _import(tmp_path, text, camera=CAMERA, encoding="utf-8"):
    csv = tmp_path / "c.csv"
    csv.write_bytes(text.encode(encoding) if isinstance(text, str) else text)
    return csv, import_centroids(csv, tmp_path / "r.mcap", camera)


def _fails(tmp_path, text, *needles, camera=CAMERA):
    with pytest.raises(ImportDataError) as err:
        _import(tmp_path, text, camera)
    msg = str(err.value)
    assert str(tmp_path / "c.csv") in msg and all(n in msg for n in needles), msg


@pytest.mark.parametrize("text", [
    "\ufeff" + "\r\n".join([HEADER, *ROWS]) + "\r\n\r\n",                        # BOM, CRLF, trailing blank line
    "\n".join(['"frame","t_ns","x","y","flux"', *(",".join(f'"{c}"' for c in r.split(",")) for r in ROWS)]),
    "\n".join([" flux , y , x , t_ns , frame ", *(" , ".join(r.split(",")[::-1]) for r in ROWS)]),
])
def test_benign_variants_import_the_same_stars(tmp_path, text):
    _, rec = _import(tmp_path, text)
    frames = [m.data for m in LogReader(rec).messages("/camera/centroids")]
    assert [f["t0_ns"] for f in frames] == [1_000_000_000, 1_100_000_000]
    assert frames[0]["x"] == [101.5, 512.75] and frames[1]["y"] == [41.0, 301.25]


@pytest.mark.parametrize("scale,unit", [(1_000, "microseconds"), (1_000_000, "milliseconds")])
def test_times_in_another_unit_than_ns_are_refused_before_the_sensor_model(tmp_path, scale, unit):
    rows = [",".join([f, str(int(t) // scale), *rest]) for f, t, *rest in (r.split(",") for r in ROWS)]
    _fails(tmp_path, "\n".join([HEADER, *rows]), "line 4, column 't_ns'", "frame 1 is", "after frame 0 (line 2)",
           "readout", "read as integer nanoseconds")


def test_microseconds_in_t_ns_without_a_shutter_are_warned_about(tmp_path):
    """A camera file without a shutter states no minimum frame spacing: times in microseconds
    (frames 0.1 ms apart as nanoseconds) import, with a warning that names the column and the unit
    it is read in; frames 100 ms apart import without one."""
    bare = CameraSpec(width_px=1024, height_px=1024, focal_length_mm=50.0, pixel_size_um=5.5)
    rows = [",".join([f, str(int(t) // 1_000), *rest]) for f, t, *rest in (r.split(",") for r in ROWS)]
    with pytest.warns(ImportDataWarning, match=r"line 4, column 't_ns'.*0\.1 ms apart.*states no shutter.*"
                                               r"read as integer nanoseconds"):
        _import(tmp_path, "\n".join([HEADER, *rows]), camera=bare)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _import(tmp_path, "\n".join([HEADER, *ROWS]), camera=bare)
    assert not any("ms apart" in str(w.message) for w in caught)


def test_frames_closer_than_the_declared_exposure_are_refused(tmp_path):
    cam = CAMERA.model_copy(update={"shutter": CAMERA.shutter.model_copy(update={"exposure_ms": 150.0})})
    _fails(tmp_path, "\n".join([HEADER, *ROWS]), "line 4, column 't_ns'", "exposure (shutter.exposure_ms 150)",
           camera=cam)


def test_one_jittery_frame_spacing_is_accepted_but_not_a_fraction_of_the_readout(tmp_path):
    times = [0, 100, 200, 280, 400]  # ms: 80 ms is jitter, above the 20.46 ms readout anyway
    rows = [f"{k},{t * 1_000_000},10,10,1\n{k},{t * 1_000_000},20,20,1" for k, t in enumerate(times)]
    _import(tmp_path, "\n".join([HEADER, *rows]))
    times[3] = 205  # 5 ms after the previous frame: less than half the readout
    rows = [f"{k},{t * 1_000_000},10,10,1\n{k},{t * 1_000_000},20,20,1" for k, t in enumerate(times)]
    _fails(tmp_path, "\n".join([HEADER, *rows]), "line 8, column 't_ns'", "frame 3 is 5 ms after frame 2 (line 6)")


def test_nanoseconds_in_time_s_are_refused_naming_the_column(tmp_path):
    rows = ["0,1000000000,1,2,3", "0,1000000000,5,2,3", "1,1100000000,1,2,3", "1,1100000000,5,2,3"]
    _fails(tmp_path, "\n".join(["frame,time_s,x,y,flux", *rows]), "line 4, column 'time_s'", "more than",
           "read as seconds")


def test_seconds_in_t_ns_say_which_column_holds_seconds(tmp_path):
    _fails(tmp_path, "frame,t_ns,x,y,flux\n0,1.5,1,2,3\n", "line 2, column 't_ns'", "not an integer",
           "a time_s column")


@pytest.mark.parametrize("rows,needle", [
    ([ROWS[0], ROWS[0], *ROWS[1:]], "line 3, column 'x': the star at (101.5, 40.25) repeats line 2 of the same frame 0"),
    ([*ROWS, ROWS[3]], "line 6, column 'x': the star at (513.5, 301.25) repeats line 5 of the same frame 1"),
])
def test_a_repeated_star_row_is_refused(tmp_path, rows, needle):
    _fails(tmp_path, "\n".join([HEADER, *rows]), needle)


def test_the_same_position_in_two_frames_is_not_a_repeat(tmp_path):
    _import(tmp_path, "\n".join([HEADER, ROWS[0], ROWS[1], "1,1100000000,101.5,40.25,5200", ROWS[3]]))


def test_frames_with_a_single_star_are_imported_with_a_warning(tmp_path):
    with pytest.warns(ImportDataWarning, match=r"1 of 2 frames hold a single star \(the first: frame 1, line 4\)"):
        _import(tmp_path, "\n".join([HEADER, ROWS[0], ROWS[1], ROWS[2]]))


@pytest.mark.parametrize("text,needles", [
    ("\n".join(ROWS), ("line 1:", "holds numbers, not column names", "required: frame, x, y, flux")),
    ("\n".join(r.replace(",", ";") for r in [HEADER, *ROWS]), ("missing column(s)", "';'-separated")),
    ("\n".join(r.replace(",", "\t") for r in [HEADER, *ROWS]), ("missing column(s)", "'\\t'-separated")),
    ("frame,t_ns,x,y,flux,note\n0,0,1,2,3,caf\xe9\n".encode("latin-1"), ("line 2: byte 0xe9 is not UTF-8 text",)),
    (b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe", ("line 1: byte 0x89 is not UTF-8 text",)),
    ("frame,t_ns,x,y,flux\n0,0,1,2," + "9" * 200_000 + "\n", ("line 2: not readable as CSV",)),
])
def test_unreadable_files_name_the_file_and_line(tmp_path, text, needles):
    _fails(tmp_path, text, *needles)


def test_cli_exits_2_on_a_unit_mistake_and_on_binary_garbage(tmp_path):
    cam = tmp_path / "camera.yaml"
    cam.write_text("width_px: 1024\nheight_px: 1024\nfov_deg: 10\n"
                   "shutter: {mode: rolling, exposure_ms: 10.0, line_delay_us: 20.0}\n")
    csv = tmp_path / "c.csv"
    csv.write_text("\n".join([HEADER, *(r.replace("00000000,", "00000,") for r in ROWS)]))
    assert_clean_error(cli("import", "centroids", csv, "-o", tmp_path / "r.mcap", "--camera", cam),
                       str(csv), "line 4", "column 't_ns'", "read as integer nanoseconds")
    csv.write_bytes(bytes(range(256)) * 4)
    assert_clean_error(cli("import", "centroids", csv, "-o", tmp_path / "r.mcap", "--camera", cam),
                       str(csv), "line 2", "byte 0x80 is not UTF-8 text")
