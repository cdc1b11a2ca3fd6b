"""``rollingstar import corr --centroids image``: the table's stars measured again on the image beside it.

The corr table is written with astropy in astrometry.net's columns, its positions 0.3 px off the
stars; the image (an 8-bit PNG, as the creusot folders hold) is drawn here with pixel-integrated
Gaussian stars and Poisson noise (``tests/estimators/test_remeasure.py``), not by the simulator.
"""
from __future__ import annotations

import json

import numpy as np
from astropy.io import fits
from PIL import Image
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from rollingstar.cli import app
from rollingstar.logs import LogReader, iter_frames, stars_to_arrays
from rollingstar.logs.importers.corr import pointing_centres
from tests.logs.test_importers import H, W, write_corr


def _image(x, y, rng, flux=1200.0, sigma=1.2) -> np.ndarray:
    from scipy.special import erf

    mean = np.full((H, W), 12.0)
    ex, ey = np.arange(W + 1) - 0.5, np.arange(H + 1) - 0.5
    for xi, yi in zip(x, y):
        cx = np.diff(0.5 * (1 + erf((ex - xi) / (np.sqrt(2) * sigma))))
        cy = np.diff(0.5 * (1 + erf((ey - yi) / (np.sqrt(2) * sigma))))
        mean += flux * np.outer(cy, cx)
    return np.clip(np.rint(rng.poisson(mean) + rng.normal(0, 1.5, mean.shape)), 0, 255).astype(np.uint8)


def _scene(tmp_path, images: dict[str, str]):
    """A corr folder of 30 stars listed 0.3 px off; ``images``: file name -> "stars" or "dark"."""
    rng = np.random.default_rng(4)
    folder = tmp_path / "scene"
    truth = write_corr(folder, Rotation.from_euler("xyz", [20, -35, 60], degrees=True), seed=4)
    with fits.open(folder / "corr.fits", mode="update") as hdul:
        d = hdul[1].data
        d["field_x"] += rng.normal(0, 0.3, d["field_x"].size)
        d["field_y"] += rng.normal(0, 0.3, d["field_y"].size)
        listed = np.column_stack([d["field_x"] - 1, d["field_y"] - 1])
    for name, kind in images.items():
        img = _image(truth["x"], truth["y"], rng) if kind == "stars" else _image([], [], rng)
        Image.fromarray(img).save(folder / name)
    return folder, truth, listed


def _import(tmp_path, folder, *extra):
    out = tmp_path / "rec.mcap"
    res = CliRunner().invoke(app, ["import", "corr", str(folder), "-o", str(out), *extra])
    return res, out


def test_the_solved_image_is_found_beside_a_dark_frame_and_its_stars_measured_again(tmp_path):
    folder, truth, listed = _scene(tmp_path, {"black.png": "dark", "sky.png": "stars"})
    res, out = _import(tmp_path, folder, "--centroids", "image")
    assert res.exit_code == 0, res.output
    s = stars_to_arrays(next(iter_frames(LogReader(out), "/camera/centroids")).frame.data)
    err = np.hypot(s["x"] - truth["x"], s["y"] - truth["y"])
    before = np.hypot(listed[:, 0] - truth["x"], listed[:, 1] - truth["y"])
    done = pointing_centres(out)[0]["remeasured"]
    assert done["image"] == "sky.png" and done["measured"] >= 27
    measured = np.isfinite(s["cov_xx"])
    assert measured.sum() == done["measured"]
    assert np.sqrt(np.mean(err[measured] ** 2)) < 0.3 * np.sqrt(np.mean(before[measured] ** 2))
    np.testing.assert_allclose(s["x"][~measured], listed[~measured, 0])  # the others keep the table's position
    details = json.loads(LogReader(out).metadata()["import"]["details"])
    table = np.column_stack([listed[:, 0] - truth["x"], listed[:, 1] - truth["y"]])  # index_xy: the truth + 0.1 px
    assert details["centroid_sigma_px"] > 0.8 * np.sqrt(np.mean(table**2))  # the table's accuracy, for the others


def test_without_a_solved_image_the_table_positions_are_kept_with_a_warning(tmp_path):
    folder, _, listed = _scene(tmp_path, {"black.png": "dark"})
    res, out = _import(tmp_path, folder, "--centroids", "image")
    assert res.exit_code == 0, res.output
    assert "no image shows stars at the table's positions" in res.output
    s = stars_to_arrays(next(iter_frames(LogReader(out), "/camera/centroids")).frame.data)
    np.testing.assert_allclose(np.column_stack([s["x"], s["y"]]), listed)
    assert "cov_xx" not in s or np.isnan(s["cov_xx"]).all()


def test_the_default_keeps_the_table_and_a_wrong_choice_is_refused(tmp_path):
    folder, _, listed = _scene(tmp_path, {"sky.png": "stars"})
    res, out = _import(tmp_path, folder)
    assert res.exit_code == 0, res.output
    s = stars_to_arrays(next(iter_frames(LogReader(out), "/camera/centroids")).frame.data)
    np.testing.assert_allclose(np.column_stack([s["x"], s["y"]]), listed)
    res, _ = _import(tmp_path, folder, "--centroids", "pixels")
    assert res.exit_code == 2 and "--centroids 'pixels'" in res.output and "Traceback" not in res.output


def test_an_unreadable_or_dark_file_beside_the_solved_image_is_passed_over(tmp_path):
    """A corrupt PNG, and a dark frame named the way the creusot solved images are named, sit
    beside the image with the stars: each is passed over with a warning naming it, and the stars
    are measured on the right one."""
    folder, truth, _ = _scene(tmp_path, {"scene_700000e_11.3g.png": "dark", "sky.png": "stars"})
    (folder / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    res, out = _import(tmp_path, folder, "--centroids", "image")
    assert res.exit_code == 0, res.output
    assert "broken.png" in res.output and "Traceback" not in res.output
    done = pointing_centres(out)[0]
    assert done["remeasured"]["image"] == "sky.png" == done["image"] and done["remeasured"]["measured"] >= 27
