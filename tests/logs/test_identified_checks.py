"""Stars that arrive identified must be the stars at their positions (logs/importers/identified.py):
a mirror image, angles in radians, shuffled rows are refused at import, while a lens that is no
pinhole and wrong identifications short of half are not."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.logs.importers.common import ImportDataError
from rollingstar.logs.importers.identified import check_identified
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.conventions import attitude_from_radec_roll, radec_to_unit, unit_to_radec

W, H, PIXEL_MM = 808, 608, 4.94e-3


def _stars(lens_mm: float, k: tuple, n: int = 40, wrong: int = 0, seed: int = 0):
    """Positions on the 808 x 608 creusot camera through a lens of radial distortion ``k1``, and the
    catalogue directions of the stars there (``wrong`` of them those of other places); ``k``: k1, k2, k3."""
    rng = np.random.default_rng(seed)
    cam = PinholeCamera(lens_mm * 1e-3, PIXEL_MM * 1e-3, W, H, k1=k[0], k2=k[1], k3=k[2])
    x, y = rng.uniform(3, W - 3, n), rng.uniform(3, H - 3, n)
    R = attitude_from_radec_roll(120.0, -30.0, 20.0)
    ref = R.apply(cam.unproject(x, y))
    ref[:wrong] = R.apply(cam.unproject(rng.uniform(3, W - 3, wrong), rng.uniform(3, H - 3, wrong)))
    return x, y, ref, lens_mm / PIXEL_MM


@pytest.mark.parametrize("lens_mm, k, wrong", [(16.0, (0, 0, 0), 0), (3.6, (-0.35, 0.12, -0.02), 0),
                                               (3.6, (-0.38, 0.15, -0.03), 4), (6.0, (-0.12, 0, 0), 2)])
def test_a_distorted_lens_and_a_few_wrong_identifications_pass(lens_mm, k, wrong):
    x, y, ref, f = _stars(lens_mm, k, wrong=wrong)
    check_identified(x, y, ref, f, (W - 1) / 2, (H - 1) / 2, "table")
    check_identified(x, y, ref, f * 0.9, (W - 1) / 2, (H - 1) / 2, "table")  # a nominal field 11 % off


@pytest.mark.parametrize("projection", ["equidistant", "equisolid", "stereographic", "orthographic"])
def test_a_fisheye_of_160_degrees_read_as_a_pinhole_passes(projection):
    """A fisheye table imported as the pinhole of its field (astrometry.net's linear scale)."""
    import math

    half = math.radians(80.0)
    rho = {"equidistant": half, "equisolid": 2 * math.sin(half / 2), "stereographic": 2 * math.tan(half / 2),
           "orthographic": math.sin(half)}[projection]
    f = math.hypot(W, H) / 2 / rho
    cam = PinholeCamera(f * 1e-6, 1e-6, W, H, projection=projection)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(3, W - 3, 60), rng.uniform(3, H - 3, 60)
    ref = attitude_from_radec_roll(10.0, 20.0, 0.0).apply(cam.unproject(x, y))
    check_identified(x, y, ref, f, (W - 1) / 2, (H - 1) / 2, "fisheye")


def test_a_mirror_image_is_refused_as_such():
    x, y, ref, f = _stars(16.0, (0, 0, 0))
    for mx, my in ((W - 1 - x, y), (x, H - 1 - y)):
        with pytest.raises(ImportDataError, match="frame 3: the stars' positions are a mirror image"):
            check_identified(mx, my, ref, f, (W - 1) / 2, (H - 1) / 2, "frame 3")


def test_directions_that_are_not_the_stars_are_refused():
    x, y, ref, f = _stars(16.0, (0, 0, 0))
    ra, dec = (np.degrees(a) for a in unit_to_radec(ref))
    others = {"shuffled": ref[np.random.default_rng(1).permutation(len(ref))],
              "angles in radians read as degrees": np.asarray(radec_to_unit(ra * np.pi / 180 ** 2, dec * np.pi / 180 ** 2)
                                                             ).reshape(-1, 3)}
    for what, bad in others.items():
        with pytest.raises(ImportDataError, match="the catalogue directions are not these stars'"):
            check_identified(x, y, bad, f, (W - 1) / 2, (H - 1) / 2, what)


def test_a_centroid_table_with_angles_in_radians_is_refused_at_import(tmp_path):
    from tests.logs.test_importers import assert_clean_error, cli

    x, y, ref, f = _stars(16.0, (0, 0, 0), n=12)
    ra, dec = unit_to_radec(ref)
    rows = ["frame,t_ns,x,y,flux,catalog_id,ra_deg,dec_deg"]
    rows += [f"0,1000000000,{x[i]:.4f},{y[i]:.4f},100,{i + 1},{ra[i]:.8f},{dec[i]:.8f}" for i in range(12)]
    (tmp_path / "c.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "cam.yaml").write_text(f"width_px: {W}\nheight_px: {H}\nfocal_length_mm: 16.0\npixel_size_um: {PIXEL_MM * 1e3}\n")
    assert_clean_error(cli("import", "centroids", tmp_path / "c.csv", "--camera", tmp_path / "cam.yaml", "-o",
                           tmp_path / "r.mcap"), "c.csv: frame 0 (line 2)", "not these stars'", "radians")
