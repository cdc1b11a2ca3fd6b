"""`rollingstar import`: images, astrometry.net corr tables and centroid CSVs into rollingstar logs."""
from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from rollingstar.logs import LogReader, image_from_raw, iter_frames, stars_to_arrays
from rollingstar.logs.importers import (
    CameraSpec,
    ImportDataError,
    ImportDataWarning,
    boresight_offsets,
    import_centroids,
    import_corr,
    import_images,
    import_warnings,
    pointing_centres,
    read_image,
)
from rollingstar.logs.importers.corr import (
    focal_px_from_fov,
    read_corr_table,
    read_log_json,
)
from rollingstar.logs.importers.images import batches_by_frame
from rollingstar.pipelines.config import PipelineConfig, load_pipeline
from rollingstar.pipelines.runner import run_pipeline
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.conventions import (
    attitude_from_radec_roll,
    radec_to_unit,
    unit_to_radec,
)
from rollingstar.sensors.scenario import scenario_from_yaml

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "log-format.md"
BASELINE = ROOT / "configs" / "pipelines" / "baseline.yaml"
TETRA3_CAMERA = ROOT / "configs" / "cameras" / "tetra3_blackfly_s.yaml"
TETRA3_SIDECAR = ROOT / "configs" / "cameras" / "tetra3_recording.yaml"
QUEST_ONLY = PipelineConfig.model_validate({"name": "quest-only", "stages": [{"kind": "quest"}]})


def cli(*args):
    return subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, timeout=300)


def assert_clean_error(proc, *needles):
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    text = " ".join(proc.stderr.split())  # rich wraps long lines
    for needle in needles:
        assert needle in text, (needle, proc.stderr)


def small_camera(**kw) -> CameraSpec:
    base = dict(width_px=40, height_px=30, focal_length_mm=10.0, pixel_size_um=5.0)
    base.update(kw)
    return CameraSpec(**base)


# --- images ------------------------------------------------------------------------------------
@pytest.mark.parametrize("suffix,dtype", [(".png", np.uint8), (".png", np.uint16), (".tiff", np.uint8),
                                          (".tiff", np.uint16)])
def test_image_round_trip_pixels_and_times(tmp_path, suffix, dtype):
    rng = np.random.default_rng(3)
    top = np.iinfo(dtype).max
    folder = tmp_path / "imgs"
    folder.mkdir()
    images = []
    for k in range(3):
        img = rng.integers(0, top, (30, 40), endpoint=True).astype(dtype)
        img[0, 0], img[-1, -1] = 0, top  # the extremes survive unchanged
        Image.fromarray(img).save(folder / f"f{k:02d}{suffix}")
        images.append(img)
    t0 = [5_000_000_123, 5_033_333_456, 5_066_666_789]
    (folder / "recording.yaml").write_text(
        "camera: {width_px: 40, height_px: 30, focal_length_mm: 10.0, pixel_size_um: 5.0,\n"
        "         shutter: {mode: rolling, exposure_ms: 2.0, line_delay_us: 20.0}}\n"
        f"timestamps: {{t0_ns: {t0}}}\n")
    out = import_images(folder, tmp_path / "r.mcap")
    reader = LogReader(out)
    frames = list(iter_frames(reader, "/camera/image"))
    assert [f.t0_ns for f in frames] == t0
    for f, img in zip(frames, images):
        got = image_from_raw(f.frame)
        assert got.dtype == dtype and np.array_equal(got, img)
        stamp = f.frame.data.timestamp
        assert stamp.seconds * 1_000_000_000 + stamp.nanos == f.t0_ns
    meta = reader.metadata()
    assert meta["rollingstar"]["kind"] == "import" and meta["import"]["format"] == "images"
    scenario = scenario_from_yaml(meta["scenario"]["yaml"])
    assert scenario.level == "image" and scenario.image.bit_depth == 8 * np.dtype(dtype).itemsize
    assert scenario.shutter.mode == "rolling" and scenario.shutter.line_delay_us == 20.0
    assert scenario.motion.initial_attitude is None  # no prior invented
    assert json.loads(meta["import"]["details"])["t0_ns"] == t0


def test_jpeg_and_colour_images_are_luminance(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    rgb = np.zeros((30, 40, 3), dtype=np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 100, 50
    Image.fromarray(rgb).save(folder / "a.png")
    Image.fromarray(rgb).save(folder / "b.png")
    with pytest.warns(ImportDataWarning, match="2 of the 2 images are colour") as caught:
        out = import_images(folder, tmp_path / "r.mcap", camera=small_camera())
    assert sum("converted to 8-bit luminance" in str(w.message) for w in caught) == 1  # once, not per frame
    img = image_from_raw(next(LogReader(out).messages("/camera/image")))
    # ITU-R 601-2 luma, as Pillow: L = R * 299/1000 + G * 587/1000 + B * 114/1000
    assert img.dtype == np.uint8 and np.all(img == round(200 * 0.299 + 100 * 0.587 + 50 * 0.114))
    kept = json.loads(LogReader(out).metadata()["import"]["warnings"])
    assert any("are colour (the first a.png, mode RGB)" in w for w in kept), kept


def test_a_16_bit_colour_png_says_what_pillow_drops(tmp_path):
    """Pillow decodes a PNG of 16 bits per RGB channel to 8 bits per channel: the import says so.
    The file is written by hand from the PNG specification (signature, IHDR, IDAT, IEND), as Pillow
    cannot write one."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    folder = tmp_path / "imgs"
    folder.mkdir()
    rgb = np.full((30, 40, 3), 40000, dtype=">u2")
    rows = b"".join(b"\x00" + row.tobytes() for row in rgb)  # filter type 0 before each row
    (folder / "a.png").write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 40, 30, 16, 2, 0, 0, 0))
                                   + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))
    with pytest.warns(ImportDataWarning, match=r"1 of them hold 16 bits per channel, of which Pillow keeps the top 8"):
        out = import_images(folder, tmp_path / "r.mcap", camera=small_camera())
    assert np.all(image_from_raw(next(LogReader(out).messages("/camera/image"))) == 40000 >> 8)


def test_image_sidecar_frame_rate_default_and_camera_file(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for k in range(4):
        Image.fromarray(np.full((30, 40), k, dtype=np.uint8)).save(folder / f"{k}.png")
    cam = tmp_path / "camera.yaml"
    cam.write_text("width_px: 40\nheight_px: 30\nfov_deg: 10.0\n")
    with pytest.warns(ImportDataWarning, match="assuming 1 Hz"):
        out = import_images(folder, tmp_path / "r.mcap", camera=cam)
    reader = LogReader(out)
    assert [f.t0_ns for f in iter_frames(reader, "/camera/image")] == [0, 1_000_000_000, 2_000_000_000, 3_000_000_000]
    scenario = scenario_from_yaml(reader.metadata()["scenario"]["yaml"])
    fpx = scenario.sensor.focal_length_mm * 1e3 / scenario.sensor.pixel_size_um
    assert fpx == pytest.approx(20.0 / math.tan(math.radians(5.0)), rel=1e-12)  # (W/2) / tan(fov/2)
    assert scenario.shutter.mode == "global" and scenario.shutter.exposure_ms == 100.0  # stated defaults
    assert "assuming 1 Hz" in json.loads(reader.metadata()["import"]["warnings"])[0]


def test_gyro_and_truth_csv_belong_to_the_frame_they_lead_up_to(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for k in range(3):
        Image.fromarray(np.zeros((30, 40), dtype=np.uint16)).save(folder / f"{k}.tiff")
    tg = np.arange(0, 260_000_000, 10_000_000)  # 0..250 ms, frames at 50, 150, 200 ms
    w = np.column_stack([tg * 1e-9, -tg * 1e-9, np.full(tg.size, 0.5)])
    (folder / "gyro.csv").write_text("t_ns,wx,wy,wz\n" + "\n".join(f"{t},{a:.17g},{b:.17g},{c:.17g}" for t, (a, b, c) in zip(tg, w)))
    q = Rotation.from_rotvec(np.outer(tg * 1e-9, [0.0, 0.0, 0.3])).as_quat()
    (folder / "truth.csv").write_text("time_s,qx,qy,qz,qw\n" + "\n".join(
        f"{t * 1e-9:.17g},{a:.17g},{b:.17g},{c:.17g},{d:.17g}" for t, (a, b, c, d) in zip(tg, q)))
    (folder / "recording.yaml").write_text(
        "camera: {width_px: 40, height_px: 30, fov_deg: 10}\n"
        "timestamps: {t0_ns: [50000000, 150000000, 200000000]}\ngyro_csv: gyro.csv\ntruth_csv: truth.csv\n")
    out = import_images(folder, tmp_path / "r.mcap")
    frames = list(iter_frames(LogReader(out), "/camera/image", ["/gyro", "/truth/attitude"]))
    t0 = [f.t0_ns for f in frames]
    seen_gyro, seen_truth = [], []
    for k, f in enumerate(frames):
        lo = -1 if k == 0 else t0[k - 1]
        for m in f.side["/gyro"]:
            t = np.asarray(m.data["t_ns"])
            assert np.all((t > lo) & (t <= t0[k])) and m.log_time_ns == t[-1]
            seen_gyro.append(t)
            np.testing.assert_array_equal(m.data["x"], t * 1e-9)
        for m in f.side["/truth/attitude"]:
            seen_truth.append(np.asarray(m.data["t_ns"]))
            assert m.log_time_ns == m.data["t_ns"][0] and lo < m.log_time_ns <= t0[k]
    # gyro samples after the last frame belong to no frame; truth after it joins the last batch
    np.testing.assert_array_equal(np.concatenate(seen_gyro), tg[tg <= t0[-1]])
    np.testing.assert_array_equal(np.concatenate(seen_truth), tg)


def test_batches_by_frame_partition():
    rng = np.random.default_rng(5)
    for _ in range(50):
        t = np.sort(rng.integers(0, 1000, rng.integers(0, 40)))
        t0 = np.unique(rng.integers(0, 1000, rng.integers(1, 6)))
        batches = batches_by_frame(t, t0)
        assert np.array_equal(np.concatenate(batches) if batches else np.zeros(0, int), np.arange(t.size))
        for b in batches:  # every batch is logged at its first sample and that lands in one frame interval
            k = np.searchsorted(t0, t[b[0]], side="left")
            assert k == 0 or t[b[0]] > t0[k - 1]
            if k < t0.size - 1:
                assert np.all(t[b] <= t0[k])


# --- bad image input ----------------------------------------------------------------------------
def test_image_errors_name_file_and_field(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    Image.fromarray(np.zeros((30, 40), dtype=np.uint8)).save(folder / "a.png")
    Image.fromarray(np.zeros((31, 40), dtype=np.uint8)).save(folder / "b.png")
    with pytest.raises(ImportDataError, match=r"b\.png: image is 40x31 px but the camera says width_px 40, height_px 30"):
        import_images(folder, tmp_path / "r.mcap", camera=small_camera())
    (folder / "b.png").unlink()
    Image.fromarray(np.zeros((30, 40), dtype=np.uint16)).save(folder / "c.png")
    with pytest.raises(ImportDataError, match="mixes 8-bit .a.png. and 16-bit .c.png."):
        import_images(folder, tmp_path / "r.mcap", camera=small_camera())
    (folder / "c.png").unlink()
    with pytest.raises(ImportDataError, match="no recording.yaml.*--camera"):
        import_images(folder, tmp_path / "r.mcap")
    (folder / "recording.yaml").write_text("camera: {width_px: 40, height_px: 30, fov_deg: 10}\n"
                                           "timestamps: {t0_ns: [5, 3]}\n")
    with pytest.raises(ImportDataError, match="t0_ns has 2 entries for 1 image"):
        import_images(folder, tmp_path / "r.mcap")


def test_cli_images_bad_sidecar_exits_2(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    Image.fromarray(np.zeros((30, 40), dtype=np.uint8)).save(folder / "a.png")
    side = folder / "recording.yaml"
    side.write_text("camera: {width_px: 40, height_px: 30, fov_deg: 10, shutter: {mode: rolling}}\n")
    assert_clean_error(cli("import", "images", folder, "-o", tmp_path / "r.mcap"), str(side), "camera.shutter",
                       "line_delay_us > 0")
    side.write_text("camera: {width_px: 40, height_px: 30, fov_deg: 10}\nframe_rate: 3\n")
    assert_clean_error(cli("import", "images", folder, "-o", tmp_path / "r.mcap"), str(side), "frame_rate",
                       "unknown key")


# --- corr tables ----------------------------------------------------------------------------------
W, H, FOV = 808, 608, 17.9


def write_corr(folder: Path, R: Rotation, n: int = 30, seed: int = 0, log_json: str | None = None,
               centre: tuple[float, float] | None = None) -> dict:
    """An astrometry.net-style corr table of ``n`` stars seen by the log.json camera at attitude ``R``."""
    from astropy.io import fits

    rng = np.random.default_rng(seed)
    cam = PinholeCamera(focal_px_from_fov(FOV, W, H) * 1e-6, 1e-6, W, H)
    x, y = rng.uniform(5, W - 5, n), rng.uniform(5, H - 5, n)
    ref = R.apply(cam.unproject(x, y))
    ra, dec = (np.degrees(a) for a in unit_to_radec(ref))
    folder.mkdir(parents=True, exist_ok=True)
    cols = [fits.Column(name="field_x", format="D", array=x + 1), fits.Column(name="field_y", format="D", array=y + 1),
            fits.Column(name="index_x", format="D", array=x + 1 + rng.normal(0, 0.1, n)),
            fits.Column(name="index_y", format="D", array=y + 1 + rng.normal(0, 0.1, n)),
            fits.Column(name="index_ra", format="D", array=ra), fits.Column(name="index_dec", format="D", array=dec),
            fits.Column(name="index_id", format="J", array=np.arange(n) + 100),
            fits.Column(name="match_weight", format="D", array=np.ones(n)),
            fits.Column(name="FLUX", format="E", array=rng.uniform(10, 100, n))]
    fits.BinTableHDU.from_columns(cols).writeto(folder / "corr.fits")
    if centre is None:
        c_ra, c_dec = (float(np.degrees(a)) for a in unit_to_radec(R.apply([0.0, 0.0, 1.0])))
    else:
        c_ra, c_dec = centre
    (folder / "log.json").write_text(log_json if log_json is not None else json.dumps(
        {"fov_deg": FOV, "image_size": {"x": W, "y": H}, "center": {"ra_degrees": c_ra, "dec_degrees": c_dec},
         "timestamp": {"date": "7/09/2023", "time": "9:30 PM"}}))
    return {"x": x, "y": y, "ref": ref, "ids": np.arange(n) + 100}


def test_corr_round_trip_quest_recovers_the_attitude(tmp_path):
    truths = [attitude_from_radec_roll(40.0 + 30 * k, -60.0 + 35 * k, 25.0 * k) for k in range(3)]
    tables = [write_corr(tmp_path / "sky" / f"scene{k}", R, seed=k) for k, R in enumerate(truths)]
    rec = import_corr(tmp_path / "sky", tmp_path / "rec.mcap")
    reader = LogReader(rec)
    frames = list(iter_frames(reader, "/camera/centroids"))
    assert len(frames) == 3 and [f.t0_ns for f in frames] == [0, 1_000_000_000, 2_000_000_000]
    s = stars_to_arrays(frames[1].frame.data)
    np.testing.assert_allclose(s["x"], tables[1]["x"], atol=1e-9)  # FITS 1-based -> 0-based
    np.testing.assert_array_equal(s["catalog_id"], tables[1]["ids"])
    np.testing.assert_allclose(s["ref_icrs"], tables[1]["ref"], atol=1e-12)
    # The baseline pipeline's tracking identifier is skipped (the stars are identified already; the
    # synthetic stars are not in Hipparcos, so tracking would have dropped them) and QUEST solves.
    out = run_pipeline(rec, load_pipeline(BASELINE), tmp_path / "out.mcap", show_progress=False)
    assert out.valid_estimates == 3
    est = [m.data for m in LogReader(tmp_path / "out.mcap").messages("/estimate/attitude")]
    for e, R in zip(est, truths):
        q = np.array([e["q"][k] for k in "xyzw"])
        assert (R.inv() * Rotation.from_quat(q)).magnitude() < 1e-6
    offsets = boresight_offsets(rec, tmp_path / "out.mcap")
    assert [o["folder"] for o in offsets] == ["scene0", "scene1", "scene2"]
    # each table's own residual RMS per axis, pooled over the tables: the recording's centroid sigma
    frames = pointing_centres(rec).values()
    pooled = np.sqrt(sum(f["n_stars"] * f["residual_rms_px"] ** 2 for f in frames) / sum(f["n_stars"] for f in frames))
    scenario = scenario_from_yaml(reader.metadata()["scenario"]["yaml"])
    assert pooled == pytest.approx(scenario.noise.centroid_sigma_px, rel=1e-12)
    assert len({f["residual_rms_px"] for f in frames}) == 3
    assert max(o["offset_deg"] for o in offsets) < 1e-6


def test_corr_damaged_rows_dropped_and_overflowing_residuals_not_taken_as_noise(tmp_path):
    """Found by fuzzing (tests/reliability/test_fuzz.py): a star outside the image and an index_x of 1e300
    (residual overflow: the RMS was inf and the sensor model invalid, a raw pydantic error)."""
    from astropy.io import fits

    R = attitude_from_radec_roll(10.0, 20.0, 30.0)
    table = write_corr(tmp_path / "sky" / "scene", R, n=12)
    path = tmp_path / "sky" / "scene" / "corr.fits"
    with fits.open(path, mode="update") as hdul:
        hdul[1].data["field_x"][3] = 5.0 * W  # outside the 808 px wide image
        hdul[1].data["index_x"][5] = 1e300
    with pytest.warns(UserWarning) as caught:
        rec = import_corr(tmp_path / "sky", tmp_path / "rec.mcap")
    text = " ".join(str(w.message) for w in caught)
    assert "1 star(s) outside the 808x608 image of log.json dropped (rows 3)" in text
    assert "1 row(s) with field_xy - index_xy beyond" in text and "left out of the centroid noise" in text
    s = stars_to_arrays(next(iter(iter_frames(LogReader(rec), "/camera/centroids"))).frame.data)
    np.testing.assert_array_equal(s["catalog_id"], np.delete(table["ids"], 3))  # the star itself is kept
    scenario = scenario_from_yaml(LogReader(rec).metadata()["scenario"]["yaml"])
    with fits.open(path) as hdul:
        d = hdul[1].data
        keep = np.setdiff1d(np.arange(len(d)), [3, 5])
        r = np.concatenate([d["field_x"][keep] - d["index_x"][keep], d["field_y"][keep] - d["index_y"][keep]])
    assert scenario.noise.centroid_sigma_px == pytest.approx(np.sqrt(np.mean(r**2)))  # the other rows' residual


def test_corr_log_json_missing_comma_is_recovered_with_a_warning(tmp_path):
    R = attitude_from_radec_roll(284.811, -28.299, 10.0)
    text = ('{\n "fov_deg": 17.9,\n "image_size": {"x": 808, "y": 608},\n'
            ' "center": {"ra_degrees": 284.811, "dec_degrees": -28.299}\n'
            ' "timestamp": {"date": "7/09/2023", "time": "9:24 PM"}\n}')
    write_corr(tmp_path / "nunki", R, log_json=text)
    with pytest.warns(ImportDataWarning, match=r"line 5, column 2: missing ',' inserted"):
        rec = import_corr(tmp_path / "nunki", tmp_path / "r.mcap")
    frame = pointing_centres(rec)[0]
    assert (frame["ra_deg"], frame["dec_deg"], frame["fov_deg"]) == (284.811, -28.299, 17.9)
    assert "missing ','" in import_warnings(rec)[0]


def test_corr_log_json_field_by_field_recovery_and_failure(tmp_path):
    ok = tmp_path / "ok.json"
    ok.write_text('{"fov_deg": 17.9; "image_size": {"x": 808, "y": 608}, '
                  '"center": {"ra_degrees": 1.5, "dec_degrees": -2.5}}')
    with pytest.warns(ImportDataWarning, match="recovered field by field"):
        meta = read_log_json(ok)
    assert (meta.fov_deg, meta.image_size.x, meta.center.dec_degrees) == (17.9, 808, -2.5)
    bad = tmp_path / "bad.json"
    bad.write_text('{"fov_deg": 17.9; "image_size": {"x": 808, "y": 608}, "center": {"ra_degrees": 1.5}}')
    with pytest.raises(ImportDataError, match=r"bad\.json.*cannot be recovered: center\.dec_degrees: not found"):
        read_log_json(bad)
    twice = tmp_path / "twice.json"
    twice.write_text('{"fov_deg": 17.9 "fov_deg": 18, "image_size": {"x": 808, "y": 608}, '
                     '"center": {"ra_degrees": 1.5, "dec_degrees": 2}')
    with pytest.raises(ImportDataError, match="fov_deg: found 2 times"):
        read_log_json(twice)
    wrong = tmp_path / "wrong.json"
    wrong.write_text('{"fov_deg": -3, "image_size": {"x": 808, "y": 608}, "center": {"ra_degrees": 1, "dec_degrees": 2}}')
    with pytest.raises(ImportDataError, match=r"wrong\.json: fov_deg: Input should be greater than 0"):
        read_log_json(wrong)


def test_corr_cli_errors_exit_2(tmp_path):
    R = attitude_from_radec_roll(10, 20, 0)
    write_corr(tmp_path / "a", R, log_json='{"fov_deg": 17.9, "image_size": {"x": 808}, '
                                           '"center": {"ra_degrees": 1, "dec_degrees": 2}}')
    assert_clean_error(cli("import", "corr", tmp_path / "a", "-o", tmp_path / "r.mcap"),
                       str(tmp_path / "a" / "log.json"), "image_size.y", "Field required")
    write_corr(tmp_path / "b" / "one", R)
    write_corr(tmp_path / "b" / "two", R, log_json=json.dumps(
        {"fov_deg": 18.5, "image_size": {"x": W, "y": H}, "center": {"ra_degrees": 1, "dec_degrees": 2}}))
    assert_clean_error(cli("import", "corr", tmp_path / "b", "-o", tmp_path / "r.mcap"),
                       "fields of view differ", "one/log.json", "two/log.json", "import the sub-folders separately")
    from astropy.io import fits

    (tmp_path / "c").mkdir()
    fits.BinTableHDU.from_columns([fits.Column(name="field_x", format="D", array=[1.0])]).writeto(tmp_path / "c" / "t.fits")
    (tmp_path / "c" / "log.json").write_text((tmp_path / "b" / "one" / "log.json").read_text())
    assert_clean_error(cli("import", "corr", tmp_path / "c", "-o", tmp_path / "r.mcap"),
                       "t.fits: missing column(s) field_y, index_ra, index_dec")


# --- centroid CSV ---------------------------------------------------------------------------------
CSV_CAMERA = CameraSpec(width_px=1024, height_px=1024, focal_length_mm=50.0, pixel_size_um=5.5,
                        shutter={"mode": "rolling", "exposure_ms": 10.0, "line_delay_us": 20.0})


def test_centroid_csv_round_trip(tmp_path):
    csv = tmp_path / "c.csv"
    csv.write_text("frame,time_s,x,y,flux,sigma_px,saturated,extra\n"
                   "# a comment\n"
                   "3,1.5,101.25,40.5,5200,0.05,1,a\n"
                   "3,1.5,512.75,300.25,,,0,b\n"
                   "\n"
                   "4,1.6,102.0,41.0,5150.5,0.06,false,c\n")
    with pytest.warns(ImportDataWarning, match="extra not used by rollingstar"):
        rec = import_centroids(csv, tmp_path / "r.mcap", CSV_CAMERA)
    frames = list(iter_frames(LogReader(rec), "/camera/centroids"))
    assert [f.t0_ns for f in frames] == [1_500_000_000, 1_600_000_000]
    s = stars_to_arrays(frames[0].frame.data)
    assert frames[0].frame.data["frame"] == 3
    np.testing.assert_array_equal(s["x"], [101.25, 512.75])
    assert s["flux"][0] == 5200 and np.isnan(s["flux"][1]) and np.isnan(s["sigma_px"][1])
    np.testing.assert_array_equal(s["saturated"], [True, False])
    # rolling shutter: row y starts at t0 + y * 20 us, the centroid refers to its mid-exposure (+5 ms)
    np.testing.assert_array_equal(s["row_time_ns"], 1_500_000_000 + np.rint(np.array([40.5, 300.25]) * 20_000))
    np.testing.assert_array_equal(s["t_ns"], s["row_time_ns"] + 5_000_000)


def test_centroid_csv_with_catalogue_ids_is_solved_without_identifier(tmp_path):
    R = attitude_from_radec_roll(120.0, 33.0, -70.0)
    cam = PinholeCamera(50e-3, 5.5e-6, 1024, 1024)
    rng = np.random.default_rng(2)
    x, y = rng.uniform(0, 1023, 12), rng.uniform(0, 1023, 12)
    ra, dec = (np.degrees(a) for a in unit_to_radec(R.apply(cam.unproject(x, y))))
    rows = "\n".join(f"0,0,{a:.17g},{b:.17g},1,{i},{r:.17g},{d:.17g}" for i, (a, b, r, d) in enumerate(zip(x, y, ra, dec)))
    (tmp_path / "c.csv").write_text("frame,t_ns,x,y,flux,catalog_id,ra_deg,dec_deg\n" + rows)
    global_cam = CameraSpec(width_px=1024, height_px=1024, focal_length_mm=50.0, pixel_size_um=5.5)
    rec = import_centroids(tmp_path / "c.csv", tmp_path / "r.mcap", global_cam)
    run_pipeline(rec, QUEST_ONLY, tmp_path / "o.mcap", show_progress=False)
    e = next(LogReader(tmp_path / "o.mcap").messages("/estimate/attitude")).data
    assert e["valid"] and (R.inv() * Rotation.from_quat([e["q"][k] for k in "xyzw"])).magnitude() < 1e-6


@pytest.mark.parametrize("body,needle", [
    ("frame,t_ns,x,y\n0,0,1,2\n", "line 1: missing column(s) flux"),
    ("frame,x,y,flux\n0,1,2,3\n", "needs exactly one of the columns t_ns or time_s or t_unix_ns or time_unix_s (found none)"),
    ("frame,t_ns,time_s,x,y,flux\n0,0,0,1,2,3\n", "found t_ns and time_s"),
    ("frame,t_ns,x,y,flux\n0,0,1,2,3\n0,0,nan,2,3\n", "line 3, column 'x': 'nan' is not a finite number"),
    ("frame,t_ns,x,y,flux\n0,0,1,2,3\n0,0,1,,3\n", "line 3, column 'y': empty; a number is required"),
    ("frame,t_ns,x,y,flux\n0,0,1,2,abc\n", "line 2, column 'flux': 'abc' is not a number"),
    ("frame,t_ns,x,y,flux\n0,0,1,2,inf\n", "leave the cell empty for 'unknown'"),
    ("frame,t_ns,x,y,flux\n0,100,1,2,3\n1,50,1,2,3\n", "line 3, column 't_ns': frame 1 at 50 ns is not after frame 0"),
    ("frame,t_ns,x,y,flux\n0,100,1,2,3\n0,200,1,2,3\n", "line 3, column 't_ns': 200 differs from 100"),
    ("frame,t_ns,x,y,flux\n1,100,1,2,3\n0,200,1,2,3\n", "line 3, column 'frame': 0 after 1"),
    ("frame,t_ns,x,y,flux\n0,-5,1,2,3\n", "line 2, column 't_ns': negative time"),
    ("frame,t_ns,x,y,flux\n0,1.5,1,2,3\n", "line 2, column 't_ns': '1.5' is not an integer"),
    ("frame,t_ns,x,y,flux\n0,0,1,2\n", "line 2: 4 fields, the header has 5"),
    ("frame,t_ns,x,y,flux\n0,0,2000,2,3\n", "line 2, column 'x': 2000.0 is outside the detector"),
    ("frame,t_ns,x,y,flux,catalog_id\n0,0,1,2,3,7\n", "catalog_id given without ra_deg, dec_deg"),
    ("", "empty CSV file"),
    ("frame,time_s,x,y,flux\n0,9.3e9,1,2,3\n", "line 2, column 'time_s': 9.3e+09 s is beyond the nanosecond clock"),
    ("frame,time_unix_s,x,y,flux\n0,1700000000000,1,2,3\n", "1.7e+09 s if it is milliseconds: time_unix_s holds seconds"),
    ("frame,t_ns,x,y,flux\n0,99999999999999999999,1,2,3\n", "line 2, column 't_ns': '99999999999999999999' is beyond a 64-bit integer"),
    ("frame,t_ns,x,y,flux,sigma_px\n0,0,1,2,3,0\n", "line 2, column 'sigma_px': 0.0; a position uncertainty is > 0"),
    ("frame,t_ns,x,y,flux,sigma_px\n0,0,1,2,3,\n0,0,5,2,3,-0.1\n", "line 3, column 'sigma_px': -0.1"),
])
def test_centroid_csv_bad_rows(tmp_path, body, needle):
    csv = tmp_path / "bad.csv"
    csv.write_text(body)
    with pytest.raises(ImportDataError) as err:
        import_centroids(csv, tmp_path / "r.mcap", CSV_CAMERA)
    assert str(csv) in str(err.value) and needle in str(err.value), str(err.value)


def test_cli_centroids_bad_row_exits_2(tmp_path):
    csv = tmp_path / "bad.csv"
    csv.write_text("frame,t_ns,x,y,flux\n0,0,1,2,3\n0,0,NaN,2,3\n")
    cam = tmp_path / "camera.yaml"
    cam.write_text("width_px: 100\nheight_px: 100\nfov_deg: 10\n")
    assert_clean_error(cli("import", "centroids", csv, "-o", tmp_path / "r.mcap", "--camera", cam),
                       str(csv), "line 3", "column 'x'", "not a finite number")
    cam.write_text("width_px: 100\nheight_px: 100\nfov_deg: 10\nfocal_length_mm: 5\n")
    assert_clean_error(cli("import", "centroids", csv, "-o", tmp_path / "r.mcap", "--camera", cam),
                       str(cam), "not both")


# --- the documented examples ----------------------------------------------------------------------
def _doc_block(name: str, lang: str) -> str:
    match = re.search(rf"<!-- example: {name} -->\s*```{lang}\n(.*?)```", DOC.read_text(), re.S)
    assert match, f"example {name} missing from docs/log-format.md"
    return match.group(1)


def test_documented_import_examples(tmp_path):
    folder = tmp_path / "rec"
    folder.mkdir()
    (folder / "camera.yaml").write_text(_doc_block("camera-yaml", "yaml"))
    (folder / "recording.yaml").write_text(_doc_block("recording-yaml", "yaml"))
    (folder / "gyro.csv").write_text(_doc_block("gyro-csv", "csv"))
    (folder / "truth.csv").write_text(_doc_block("truth-csv", "csv"))
    cam = CameraSpec.model_validate(__import__("yaml").safe_load((folder / "camera.yaml").read_text()))
    rng = np.random.default_rng(0)
    for k in range(3):
        Image.fromarray(rng.integers(0, 4096, (cam.height_px, cam.width_px)).astype(np.uint16)).save(folder / f"{k}.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rec = import_images(folder, tmp_path / "r.mcap")
    reader = LogReader(rec)
    frames = list(iter_frames(reader, "/camera/image", ["/gyro", "/truth/attitude"]))
    assert [f.t0_ns for f in frames] == [1_000_000_000, 1_100_000_000, 1_200_000_000]
    assert sum(len(m.data["t_ns"]) for f in frames for m in f.side["/gyro"]) == 6
    scenario = scenario_from_yaml(reader.metadata()["scenario"]["yaml"])
    assert scenario.image.bit_depth == 12 and scenario.shutter.line_delay_us == 15.0
    (tmp_path / "c.csv").write_text(_doc_block("centroids-csv", "csv"))
    rec = import_centroids(tmp_path / "c.csv", tmp_path / "c.mcap", folder / "camera.yaml")
    frames = list(iter_frames(LogReader(rec), "/camera/centroids"))
    assert len(frames) == 2 and np.isnan(stars_to_arrays(frames[1].frame.data)["flux"][1])


# --- real data ------------------------------------------------------------------------------------
def test_real_tetra3_images_import_unchanged(real_data_dir, tmp_path):
    folder = real_data_dir / "tetra3"
    files = sorted(folder.glob("*.tiff"))
    assert len(files) == 8
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the sidecar states every choice: nothing to warn about
        rec = import_images(folder, tmp_path / "t.mcap", sidecar=TETRA3_SIDECAR)
    frames = list(iter_frames(LogReader(rec), "/camera/image"))
    assert [f.t0_ns for f in frames] == [k * 1_000_000_000 for k in range(8)]
    for f, path in zip(frames, files):
        img = image_from_raw(f.frame)
        assert img.shape == (768, 1024) and img.dtype == np.uint16
        # independent decode: these TIFFs are one uncompressed little-endian strip (tile offset from the header)
        with Image.open(path) as im:
            (tile,) = im.tile
            assert im.info["compression"] == "raw" and tile.args[0] == "I;16"
        raw = np.fromfile(path, dtype="<u2", count=1024 * 768, offset=tile.offset).reshape(768, 1024)
        assert np.array_equal(img, raw)
    with pytest.warns(ImportDataWarning, match="assuming 1 Hz"):  # --camera alone: same sensor, default times
        same = import_images(folder, tmp_path / "t2.mcap", camera=TETRA3_CAMERA)
    a, b = (scenario_from_yaml(LogReader(r).metadata()["scenario"]["yaml"]) for r in (same, rec))
    # the same sensor; only the sidecar states the observation time, hence the catalogue epoch
    assert a.model_copy(update={"catalog": b.catalog}) == b and a.catalog.epoch_year == 2025.0
    scenario = scenario_from_yaml(LogReader(rec).metadata()["scenario"]["yaml"])
    # 1024 px * 6.9 um behind a 35 mm lens: 11.53 deg across (the data's README: "about 11.4")
    hfov = 2 * math.degrees(math.atan(1024 * scenario.sensor.pixel_size_um * 1e-3 / 2 / scenario.sensor.focal_length_mm))
    assert 11.3 < hfov < 11.6


def test_real_creusot_png_imports_with_a_camera_from_log_json(real_data_dir, tmp_path):
    folder = real_data_dir / "creusot" / "16mm_checker_2" / "Albaldah"
    meta = read_log_json(folder / "log.json")
    cam = CameraSpec(width_px=meta.image_size.x, height_px=meta.image_size.y, pixel_size_um=1.0,
                     focal_length_mm=focal_px_from_fov(meta.fov_deg, meta.image_size.x, meta.image_size.y) * 1e-3)
    rec = import_images(folder, tmp_path / "a.mcap", camera=cam)
    img = image_from_raw(next(LogReader(rec).messages("/camera/image")))
    assert img.shape == (608, 808) and img.dtype == np.uint8
    assert np.array_equal(img, read_image(next(folder.glob("*.png"))))


def test_creusot_fov_is_the_linear_diagonal_scale(real_data_dir):
    """log.json's fov_deg = diagonal px * central scale: the focal length fitted to star-pair angles agrees within 0.3 %."""
    from scipy.optimize import least_squares

    for folder in sorted((real_data_dir / "creusot" / "16mm_checker_2").iterdir()):
        cols = read_corr_table(next(folder.glob("*.fits")))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ImportDataWarning)  # Nunki's malformed log.json
            meta = read_log_json(next(folder.glob("*.json")))
        x, y = cols["field_x"] - 1, cols["field_y"] - 1
        ref = radec_to_unit(np.radians(cols["index_ra"]), np.radians(cols["index_dec"]))
        i, j = np.triu_indices(x.size, 1)
        ang = np.arccos(np.clip(np.sum(ref[i] * ref[j], axis=1), -1, 1))

        def resid(p):
            w = PinholeCamera(p[0] * 1e-6, 1e-6, W, H).unproject(x, y)
            return np.arccos(np.clip(np.sum(w[i] * w[j], axis=1), -1, 1)) - ang

        fitted = least_squares(resid, [3000.0]).x[0]
        linear = focal_px_from_fov(meta.fov_deg, W, H)
        atan_rule = math.hypot(W, H) / 2 / math.tan(math.radians(meta.fov_deg) / 2)
        assert abs(fitted / linear - 1) < 3e-3, (folder.name, fitted, linear)  # measured at most 0.24 %
        assert abs(fitted / atan_rule - 1) > 2 * abs(fitted / linear - 1)  # the 2 atan reading is worse


def test_real_creusot_corr_end_to_end(real_data_dir, tmp_path):
    """`import corr` + `run` (baseline: tracking skipped, QUEST) -> one attitude per image, near log.json's centre."""
    folder = real_data_dir / "creusot" / "16mm_checker_2"
    rec, out = tmp_path / "c.mcap", tmp_path / "c.out.mcap"
    proc = cli("import", "corr", folder, "-o", rec)
    assert proc.returncode == 0, proc.stderr
    assert "nunki.json" in proc.stderr and "missing ',' inserted" in " ".join(proc.stderr.split())
    proc = cli("run", BASELINE, rec, "-o", out, "-q")
    assert proc.returncode == 0, proc.stderr
    assert "11 frames: 11 valid, 0 invalid" in proc.stdout
    rows = boresight_offsets(rec, out)
    assert len(rows) == 11 and all(r["offset_deg"] is not None for r in rows)
    # log.json centres are rounded to 1e-3 deg and come from astrometry.net's distorted (SIP) fit,
    # ours from a pinhole: measured offsets are 0.0008..0.0121 deg (13" at most, 0.2 px).
    assert max(r["offset_deg"] for r in rows) < 0.03
    nunki = next(r for r in rows if r["folder"] == "Nunki")
    assert (nunki["ra_deg"], nunki["dec_deg"]) == (284.811, -28.299)


def test_run_on_imported_images_without_prior(tmp_path):
    """No prior attitude is invented for real images: the baseline starts lost in space (an empty
    frame is rejected with its reason, no valid attitude), and a pipeline whose identifier can
    only track refuses clearly (exit 2), naming the stage."""
    folder = tmp_path / "imgs"
    folder.mkdir()
    Image.fromarray(np.zeros((30, 40), dtype=np.uint8)).save(folder / "a.png")
    rec = import_images(folder, tmp_path / "r.mcap", camera=small_camera())
    proc = cli("run", BASELINE, rec, "-o", tmp_path / "o.mcap", "-q")
    assert proc.returncode == 0, proc.stderr
    status = [m.data for m in LogReader(tmp_path / "o.mcap").messages(["/estimate/frame"])]
    assert any(f.startswith("lost_in_space_rejected:") for f in status[0]["flags"])
    assert not any(m.data["valid"] for m in LogReader(tmp_path / "o.mcap").messages(["/estimate/attitude"]))
    tracking_only = tmp_path / "tracking.yaml"
    tracking_only.write_text("stages:\n  - {kind: cog}\n  - {kind: tracking}\n  - {kind: quest}\n")
    assert_clean_error(cli("run", tracking_only, rec, "-o", tmp_path / "o2.mcap", "-q"),
                       "stages[1] ('tracking')", "prior attitude", "lost-in-space")


def test_imports_never_write_over_their_inputs(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    img = np.zeros((30, 40), np.uint16)
    Image.fromarray(img).save(folder / "f00.png")
    (folder / "recording.yaml").write_text(
        "camera: {width_px: 40, height_px: 30, focal_length_mm: 10.0, pixel_size_um: 5.0}\n")
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    assert_clean_error(cli("import", "images", folder, "-o", folder / "f00.png"), "destroy the input")
    assert_clean_error(cli("import", "images", folder, "-o", folder / "rec.mcap"), "inside the input folder")
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    csv = tmp_path / "c.csv"
    csv.write_text("frame,time_s,x,y,flux\n0,1.0,10.0,10.0,100\n")
    (tmp_path / "link.mcap").symlink_to(csv)
    camera = tmp_path / "camera.yaml"
    camera.write_text("width_px: 1024\nheight_px: 1024\nfocal_length_mm: 50.0\npixel_size_um: 5.5\n")
    for out in (csv, tmp_path / "link.mcap", camera):
        assert_clean_error(cli("import", "centroids", csv, "-o", out, "--camera", camera), "destroy the input")
    assert camera.read_text().startswith("width_px")
    assert csv.read_text().startswith("frame,time_s")


@pytest.mark.parametrize("make", ["loop", "dangling", "fifo"])
def test_image_folder_entries_that_are_not_files_are_named(tmp_path, make):
    folder = tmp_path / "imgs"
    folder.mkdir()
    Image.fromarray(np.zeros((30, 40), np.uint16)).save(folder / "f00.png")
    odd = folder / "f01.png"
    if make == "loop":
        odd.symlink_to(odd)
    elif make == "dangling":
        odd.symlink_to(folder / "gone.png")
    else:
        os.mkfifo(odd)
    (folder / "recording.yaml").write_text(
        "camera: {width_px: 40, height_px: 30, focal_length_mm: 10.0, pixel_size_um: 5.0}\n")
    with pytest.raises(ImportDataError, match="f01.png match the image files but are not readable regular files"):
        import_images(folder, tmp_path / "r.mcap")


def test_the_camera_gain_reaches_the_centroiders(tmp_path):
    """camera.yaml's gain_e_per_adu is the sensor context's, which sizes the centroid covariance's
    shot-noise term; without it the declared default is 1 e-/ADU."""
    from rollingstar.pipelines.source import open_recording

    folder = tmp_path / "imgs"
    folder.mkdir()
    Image.fromarray(np.zeros((30, 40), dtype=np.uint8)).save(folder / "a.png")
    stated = import_images(folder, tmp_path / "g.mcap", camera=small_camera(gain_e_per_adu=8.0))
    default = import_images(folder, tmp_path / "d.mcap", camera=small_camera())
    assert open_recording(stated).context.gain_e_per_adu == 8.0
    assert open_recording(default).context.gain_e_per_adu == 1.0


def test_centroid_csv_covariance_columns_state_each_stars_sigma(tmp_path):
    """An isotropic covariance (cov_xx = cov_yy, cov_xy = 0) states the star's accuracy as much as
    sigma_px does: the star carries sigma_px = sqrt(trace / 2), which the estimators weight by."""
    rows = ["frame,t_ns,x,y,flux,cov_xx,cov_xy,cov_yy"]
    rows += [f"0,0,{100 + 50 * i},{200 + 30 * i},100,0.09,0,0.09" for i in range(5)]
    (tmp_path / "c.csv").write_text("\n".join(rows) + "\n")
    rec = import_centroids(tmp_path / "c.csv", tmp_path / "r.mcap", CSV_CAMERA)
    s = stars_to_arrays(next(iter(iter_frames(LogReader(rec), "/camera/centroids"))).frame.data)
    np.testing.assert_allclose(s["sigma_px"], 0.3)


def test_a_camera_whose_pinhole_field_passes_170_degrees_is_refused(tmp_path):
    """focal_length_mm written in metres (0.025 for 25 mm): a 4.7 px focal length, a 179 deg pinhole."""
    cam = tmp_path / "cam.yaml"
    cam.write_text("width_px: 1280\nheight_px: 1024\nfocal_length_mm: 0.025\npixel_size_um: 5.3\n")
    (tmp_path / "c.csv").write_text("frame,t_ns,x,y\n0,0,10,10\n0,0,20,30\n")
    assert_clean_error(cli("import", "centroids", tmp_path / "c.csv", "--camera", cam, "-o", tmp_path / "r.mcap"),
                       "cam.yaml", "focal length of 4.72 px", "179.3 deg", "millimetres")


def test_centroid_csv_with_no_positive_flux_is_said(tmp_path):
    (tmp_path / "c.csv").write_text("frame,t_ns,x,y,flux\n0,0,10,10,-5\n0,0,20,30,0\n")
    with pytest.warns(UserWarning, match="column 'flux' holds no positive value"):
        import_centroids(tmp_path / "c.csv", tmp_path / "r.mcap", CSV_CAMERA)


@pytest.mark.parametrize("times", ["[1.0, 2.0, 3.0]", "[1000, 2000, 3000]"])
def test_sidecar_frame_times_in_seconds_or_milliseconds_are_refused_naming_the_unit(tmp_path, times):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for k in range(3):
        Image.fromarray(np.zeros((30, 40), dtype=np.uint8)).save(folder / f"f{k}.png")
    (folder / "recording.yaml").write_text(f"camera: {{width_px: 40, height_px: 30, fov_deg: 10}}\ntimestamps: {{t0_ns: {times}}}\n")
    from rollingstar.errors import ConfigError

    with pytest.raises(ConfigError, match=r"recording.yaml: timestamps: t0_ns: frames .* ns apart \(median\): t0_ns holds integer"):
        import_images(folder, tmp_path / "r.mcap")
