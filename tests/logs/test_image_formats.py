"""`rollingstar import images` on the files cameras and astronomy software write: FITS, floating-point
pixels, counts left-justified in 16-bit words, frame numbers without leading zeros, and files that
are not images. Each test writes its own input; the real-data test skips when the data is absent."""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from astropy.io import fits
from PIL import Image

from rollingstar.config import ConfigError
from rollingstar.logs import LogReader, image_from_raw, iter_frames
from rollingstar.logs.importers import ImportDataError, ImportDataWarning, import_images, load_camera, read_image
from rollingstar.sensors.scenario import scenario_from_yaml
from tests.logs.test_importers import TETRA3_SIDECAR, assert_clean_error, cli, small_camera

H, W = 30, 40


def sky(seed: int = 0, top: int = 65535) -> np.ndarray:
    """A (H, W) uint16 frame whose rows all differ, so that a flip or transpose shows."""
    img = np.random.default_rng(seed).integers(0, top, (H, W), endpoint=True).astype(np.uint16)
    img[0, 0], img[-1, -1] = 0, top
    return img


def frames(rec) -> list[np.ndarray]:
    return [image_from_raw(f.frame) for f in iter_frames(LogReader(rec), "/camera/image")]


def details(rec) -> dict:
    return json.loads(LogReader(rec).metadata()["import"]["details"])


def import_quietly(folder, out, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ImportDataWarning)  # default frame rate and epoch
        return import_images(folder, out, **kw)


def write_bzero_int16(img: np.ndarray, path) -> None:
    """Unsigned 16-bit pixels as cameras write them in FITS: int16 with BZERO = 32768."""
    hdu = fits.PrimaryHDU((img.astype(np.int32) - 32768).astype(np.int16))
    hdu.header["BZERO"], hdu.header["BSCALE"] = 32768, 1
    hdu.writeto(path)


# --- FITS -----------------------------------------------------------------------------------------
def test_fits_images_keep_their_pixels_and_row_order(tmp_path):
    """BZERO applied, float32 counts, a cube of one plane, an image behind an empty primary HDU: each
    reads as the uint16 frame written (row 0 first), beside a corr table that is left out."""
    folder = tmp_path / "imgs"
    folder.mkdir()
    imgs = [sky(k) for k in range(5)]
    write_bzero_int16(imgs[0], folder / "f0.fits")
    fits.PrimaryHDU(imgs[1].astype(np.float32)).writeto(folder / "f1.fits")
    fits.PrimaryHDU(imgs[2][None]).writeto(folder / "f2.fit")
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(imgs[3])]).writeto(folder / "f3.fts")
    Image.fromarray(imgs[4]).save(folder / "f4.png")
    fits.BinTableHDU.from_columns([fits.Column(name="x", format="D", array=np.ones(3))]).writeto(folder / "corr.fits")
    with pytest.warns(ImportDataWarning, match=r"corr\.fits: FITS file\(s\) holding no image"):
        rec = import_images(folder, tmp_path / "r.mcap", camera=small_camera(bit_depth=16))
    got = frames(rec)
    assert details(rec)["files"] == ["f0.fits", "f1.fits", "f2.fit", "f3.fts", "f4.png"]
    assert all(g.dtype == np.uint16 and np.array_equal(g, i) for g, i in zip(got, imgs))


@pytest.mark.parametrize("case,needle", [
    ("empty", r"b\.fits: cannot read FITS file \(empty file \(0 bytes\)\); expected a FITS image"),
    ("text", r"b\.fits: cannot read FITS file \(.*SIMPLE.*\); expected a FITS image"),
    ("cube", r"b\.fits: HDU 0 holds 3 planes .*one image per file is expected"),
    ("table", r"b\.fits: holds no image .*expected a FITS image"),
    ("huge", r"b\.fits: truncated: the header declares a 30000x30000 px image .* but the file holds 5760 bytes"),
    ("negative", r"b\.fits: pixel values -100\.\.\d+ do not fit 16 bits \(expected 0\.\.65535\)"),
])
def test_unusable_fits_files_are_named(tmp_path, case, needle):
    folder = tmp_path / "imgs"
    folder.mkdir()
    path = folder / "b.fits"
    if case == "empty":
        path.touch()
    elif case == "text":
        path.write_text("not a FITS file\n")
    elif case == "cube":
        fits.PrimaryHDU(np.stack([sky()] * 3)).writeto(path)
    elif case == "table":
        fits.BinTableHDU.from_columns([fits.Column(name="x", format="D", array=np.ones(3))]).writeto(path)
    elif case == "huge":  # a header declaring 30000 x 30000 px over one block of data: refused before reading it
        header = fits.Header([("SIMPLE", True), ("BITPIX", 16), ("NAXIS", 2), ("NAXIS1", 30000), ("NAXIS2", 30000)])
        path.write_bytes(header.tostring().encode() + bytes(2880))
    else:
        fits.PrimaryHDU(sky(top=1000).astype(np.int16) - 100).writeto(path)
    (folder / "recording.yaml").write_text(f"camera: {{width_px: {W}, height_px: {H}, fov_deg: 10}}\n"
                                           "files: [b.fits]\n")
    camera = small_camera(width_px=30000, height_px=30000) if case == "huge" else None
    with pytest.raises(ImportDataError, match=needle):
        import_quietly(folder, tmp_path / "r.mcap", camera=camera)


# --- floating-point pixels ------------------------------------------------------------------------
def test_float_tiffs_become_16_bit_counts(tmp_path):
    """Normalised (0..1) and count-valued (0..65535) float32 TIFFs read as the uint16 frame, and are
    declared 16-bit (a camera stating bit_depth 16 is accepted)."""
    folder = tmp_path / "imgs"
    folder.mkdir()
    imgs = [sky(1), sky(2)]
    Image.fromarray(imgs[0].astype(np.float32) / 65535).save(folder / "f0.tiff")
    Image.fromarray(imgs[1].astype(np.float32)).save(folder / "f1.tiff")
    rec = import_quietly(folder, tmp_path / "r.mcap", camera=small_camera(bit_depth=16))
    assert all(g.dtype == np.uint16 and np.array_equal(g, i) for g, i in zip(frames(rec), imgs))
    assert details(rec)["container_bits"] == 16


@pytest.mark.parametrize("value,needle", [
    (np.nan, r"f\.tiff: 1 pixels are NaN or infinite \(the first at row 3, column 4\); expected finite values"),
    (np.inf, r"f\.tiff: 1 pixels are NaN or infinite"),
    (-5.0, r"f\.tiff: floating-point pixel values -5\.\.\d+; expected 0\.\.1 \(normalised\) or 0\.\.65535"),
    (1e6, r"f\.tiff: floating-point pixel values 0\.\.1e\+06; expected 0\.\.1 \(normalised\) or 0\.\.65535"),
])
def test_float_pixels_that_are_no_counts_are_refused(tmp_path, value, needle):
    img = sky().astype(np.float32)
    img[3, 4] = value
    Image.fromarray(img).save(tmp_path / "f.tiff")
    with pytest.raises(ImportDataError, match=needle):
        read_image(tmp_path / "f.tiff")


def test_float_fits_with_nan_is_refused_through_the_cli(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    img = sky().astype(np.float32)
    img[7, 2] = np.nan
    fits.PrimaryHDU(img).writeto(folder / "f.fits")
    (folder / "recording.yaml").write_text(f"camera: {{width_px: {W}, height_px: {H}, fov_deg: 10}}\n")
    assert_clean_error(cli("import", "images", folder, "-o", tmp_path / "r.mcap"),
                       str(folder / "f.fits"), "NaN or infinite (the first at row 7, column 2)")


# --- bit depth ------------------------------------------------------------------------------------
def write_left_justified(folder, counts: list[np.ndarray]) -> None:
    """12-bit counts in the top bits of 16-bit TIFF words; a saturated pixel written as 65535."""
    folder.mkdir()
    for k, c in enumerate(counts):
        words = (c << 4).astype(np.uint16)
        words[c == 4095] = 65535
        Image.fromarray(words).save(folder / f"f{k}.tiff")


def test_left_justified_counts_are_shifted_to_the_camera_bit_depth(tmp_path):
    counts = [sky(k, top=4095) for k in range(3)]
    write_left_justified(tmp_path / "imgs", counts)
    rec = import_quietly(tmp_path / "imgs", tmp_path / "r.mcap", camera=small_camera(bit_depth=12))
    assert all(np.array_equal(g, c) for g, c in zip(frames(rec), counts))  # 65535 read as 4095: saturated
    assert details(rec)["value_shift_bits"] == 4
    assert scenario_from_yaml(LogReader(rec).metadata()["scenario"]["yaml"]).image.bit_depth == 12


def test_values_inconsistent_with_the_bit_depth_are_named(tmp_path):
    counts = [sky(k, top=4095) for k in range(2)]
    write_left_justified(tmp_path / "lj", counts)
    Image.fromarray(counts[1] * 16 + 3).save(tmp_path / "lj" / "f1.tiff")  # not a multiple of 16
    with pytest.raises(ImportDataError, match=r"f1\.tiff: pixel value \d+ at row \d+, column \d+ is not a multiple "
                                              r"of 16; the counts of the camera's bit_depth 12 were judged left-justified .*f0\.tiff: values up to 65535 exceed 4095"):
        import_quietly(tmp_path / "lj", tmp_path / "r.mcap", camera=small_camera(bit_depth=12))
    folder = tmp_path / "rj"
    folder.mkdir()
    Image.fromarray(sky(0, top=4095)).save(folder / "f0.tiff")
    Image.fromarray(sky(1, top=5000)).save(folder / "f1.tiff")  # right-justified, then beyond 12 bits
    with pytest.raises(ImportDataError, match=r"f1\.tiff: pixel values up to 5000 exceed 4095, the largest count "
                                              r"of the camera's bit_depth 12; the counts were judged right-justified \(f0\.tiff: values up to 4095, not all multiples of 16\)"):
        import_quietly(folder, tmp_path / "r.mcap", camera=small_camera(bit_depth=12))


@pytest.mark.parametrize("dark", ["dim", "zero"])
def test_a_dark_first_image_of_left_justified_counts_is_judged_from_its_low_bits(tmp_path, dark):
    """A first frame taken in the dark (counts far below 4095, left-justified: multiples of 16)
    cannot show the shift by its maximum; its low bits show it. An all-zero first frame tells
    nothing: the next image decides."""
    rng = np.random.default_rng(3)
    first = rng.integers(0, 40, (H, W)).astype(np.uint16) if dark == "dim" else np.zeros((H, W), np.uint16)
    counts = [first, sky(1, top=4095), sky(2, top=4095)]
    write_left_justified(tmp_path / "imgs", counts)
    rec = import_quietly(tmp_path / "imgs", tmp_path / "r.mcap", camera=small_camera(bit_depth=12))
    assert all(np.array_equal(g, c) for g, c in zip(frames(rec), counts))
    assert details(rec)["value_shift_bits"] == 4
    assert details(rec)["value_shift_reason"].startswith("f0.tiff: all" if dark == "dim" else "f1.tiff: values up to")


def test_dim_right_justified_counts_stay_as_they_are(tmp_path):
    """Dim right-justified 12-bit counts (values far below 4095, low bits set by noise) are not
    shifted, and a frame of the same camera that later reaches 4095 is read as it is."""
    folder = tmp_path / "imgs"
    folder.mkdir()
    counts = [np.random.default_rng(4).integers(0, 40, (H, W)).astype(np.uint16), sky(1, top=4095)]
    for k, c in enumerate(counts):
        Image.fromarray(c).save(folder / f"f{k}.tiff")
    rec = import_quietly(folder, tmp_path / "r.mcap", camera=small_camera(bit_depth=12))
    assert all(np.array_equal(g, c) for g, c in zip(frames(rec), counts))
    assert details(rec)["value_shift_bits"] == 0 and "not all multiples of 16" in details(rec)["value_shift_reason"]


def test_left_justified_counts_without_a_bit_depth_are_warned_about(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    Image.fromarray((sky(0, top=4095) << 4).astype(np.uint16)).save(folder / "f0.tiff")
    with pytest.warns(ImportDataWarning, match=r"f0\.tiff: every pixel value is a multiple of 16, as when a 12-bit "
                                               r"camera's counts .* state bit_depth: 12"):
        rec = import_images(folder, tmp_path / "r.mcap", camera=small_camera())
    assert details(rec)["bit_depth"] == 16 and details(rec)["value_shift_bits"] == 0


# --- file names and unreadable files --------------------------------------------------------------
def test_frame_numbers_without_leading_zeros_keep_their_order(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for k in (1, 2, 9, 10, 11, 100):
        Image.fromarray(np.full((H, W), k, np.uint8)).save(folder / f"frame_{k}.png")
    rec = import_quietly(folder, tmp_path / "r.mcap", camera=small_camera())
    assert [int(f[0, 0]) for f in frames(rec)] == [1, 2, 9, 10, 11, 100]


@pytest.mark.parametrize("content,needle", [
    (b"", r"b\.png: cannot read image \(empty file \(0 bytes\)\); expected a TIFF, PNG, JPEG or FITS image"),
    (b"hello\n", r"b\.png: cannot read image \(UnidentifiedImageError: .*\); expected a TIFF, PNG, JPEG or FITS"),
])
def test_files_that_are_not_images_say_what_was_expected(tmp_path, content, needle):
    folder = tmp_path / "imgs"
    folder.mkdir()
    Image.fromarray(sky()).save(folder / "a.png")
    (folder / "b.png").write_bytes(content)
    with pytest.raises(ImportDataError, match=needle):
        import_quietly(folder, tmp_path / "r.mcap", camera=small_camera())


def test_a_sidecar_given_as_the_camera_is_named(tmp_path):
    side = tmp_path / "recording.yaml"
    side.write_text("camera_file: camera.yaml\nfiles: '*.tiff'\ntimestamps: {frame_rate_hz: 2.0}\n")
    with pytest.raises(ConfigError, match=r"recording\.yaml: a recording sidecar \(it has camera_file, files, "
                                          r"timestamps\), not a camera file .* give a sidecar with --sidecar"):
        load_camera(side)
    folder = tmp_path / "imgs"
    folder.mkdir()
    Image.fromarray(sky()).save(folder / "a.png")
    assert_clean_error(cli("import", "images", folder, "-o", tmp_path / "r.mcap", "--camera", "tetra3_recording"),
                       "tetra3_recording.yaml: a recording sidecar", "--sidecar")


# --- real data ------------------------------------------------------------------------------------
def test_real_tetra3_frames_as_fits_and_as_12_bit_counts(real_data_dir, tmp_path):
    """The tetra3 TIFFs rewritten as FITS (int16 + BZERO) import to the same pixels; read with the
    camera's 12-bit depth, they become its counts (the TIFFs' values / 16, saturated 65535 -> 4095)."""
    tiffs = sorted((real_data_dir / "tetra3").glob("*.tiff"))
    folder = tmp_path / "fits"
    folder.mkdir()
    for path in tiffs[:2]:
        write_bzero_int16(read_image(path), folder / f"{path.stem}.fits")
    camera = load_camera(TETRA3_SIDECAR.parent / "tetra3_blackfly_s.yaml")
    rec = import_quietly(folder, tmp_path / "f.mcap", camera=camera)
    assert all(np.array_equal(g, read_image(p)) for g, p in zip(frames(rec), tiffs))
    twelve = camera.model_copy(update={"bit_depth": 12})
    rec = import_quietly(real_data_dir / "tetra3", tmp_path / "t.mcap", camera=twelve)
    got = frames(rec)
    assert len(got) == 8 and max(int(g.max()) for g in got) == 4095
    assert all(np.array_equal(g, read_image(p) >> 4) for g, p in zip(got, tiffs))
