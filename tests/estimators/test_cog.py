"""Centre-of-gravity centroider on rendered (erf-integrated Gaussian PSF) images."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from rollingstar.estimators.centroiders.cog import CogCentroider
from rollingstar.estimators.conformance.scenes import make_scene, render
from rollingstar.estimators.data import FrameData

NOISE = 5.0  # ADU, Gaussian read noise of the rendered images
PSF = 1.2  # px


def _run(scene, image, index=0, t0=0, **params):
    c = CogCentroider(**params)
    c.setup(scene.context)
    return c.process(FrameData(index=index, t0_ns=t0, image=image)).stars


def _match(stars, x, y):
    d, j = cKDTree(np.column_stack([x, y])).query(np.column_stack([stars.x, stars.y]))
    return d, j


@pytest.mark.parametrize("background", ["median", "tiles"])
def test_subpixel_positions_flux_and_sigma(background):
    """Errors follow the CoG noise propagation: sigma = s sqrt(sum r^2 / 2) / F (background noise).

    For the bright stars (F >= 5000 ADU, sigma ~ 0.01 px) the error must be below 0.05 px (noise
    plus the residual truncation bias of a 1-ring-grown thresholded CoG); for every star the
    normalised errors err / sigma_px must have an RMS of order 1 (0.6 .. 1.6), i.e. sigma_px is an
    honest estimate, and the flux is recovered within 5 % (bright) / 15 % (all).
    """
    scene = make_scene(seed=11)
    cam = scene.context.camera
    rng = np.random.default_rng(2)
    chis, bright_err, ratio, ratio_bright = [], [], [], []
    for _ in range(8):
        x = scene.x + rng.uniform(-0.5, 0.5, scene.x.shape)
        y = scene.y + rng.uniform(-0.5, 0.5, scene.y.shape)
        bg = 100.0
        img = render(x, y, scene.flux, (cam.height, cam.width), psf_sigma_px=PSF, background=bg, noise_sigma=NOISE, rng=rng)
        stars = _run(scene, img, background=background)
        assert stars.n == scene.x.size
        d, j = _match(stars, x, y)
        assert np.unique(j).size == stars.n
        ex, ey = stars.x - x[j], stars.y - y[j]
        chis.append(np.concatenate([ex, ey]) / np.concatenate([stars.sigma_px] * 2))
        bright = scene.flux[j] >= 5000
        bright_err.append(d[bright])
        ratio.append(stars.flux / scene.flux[j])
        ratio_bright.append(stars.flux[bright] / scene.flux[j][bright])
        assert np.all(stars.catalog_id == -1)
        assert np.all(stars.npix >= 3) and not stars.saturated.any()
    chi = np.concatenate(chis)
    assert 0.6 < np.sqrt(np.mean(chi**2)) < 1.6
    assert np.concatenate(bright_err).max() < 0.05
    assert np.all(np.abs(np.concatenate(ratio) - 1) < 0.15)
    assert np.all(np.abs(np.concatenate(ratio_bright) - 1) < 0.05)


def test_times_follow_the_rolling_shutter_row():
    scene = make_scene(seed=12)
    cam, timing = scene.context.camera, scene.context.timing
    img = render(scene.x, scene.y, scene.flux, (cam.height, cam.width), rng=np.random.default_rng(0))
    t0 = 5_000_000_000
    stars = _run(scene, img, t0=t0)
    assert stars.t_ns.dtype == np.int64 and stars.row_time_ns.dtype == np.int64
    # row r starts at t0 + r * line_delay (20 us); the centroid time is mid-exposure of that row
    np.testing.assert_array_equal(stars.row_time_ns, t0 + np.rint(stars.y * 20_000).astype(np.int64))
    np.testing.assert_array_equal(stars.t_ns, stars.row_time_ns + timing.exposure_ns // 2)


def test_snr_and_flux_order():
    scene = make_scene(seed=13)
    cam = scene.context.camera
    img = render(scene.x, scene.y, scene.flux, (cam.height, cam.width), rng=np.random.default_rng(0))
    stars = _run(scene, img)
    assert np.all(np.diff(stars.flux) <= 0)
    # snr = flux / (noise sqrt(npix)) with the noise measured ~ NOISE
    np.testing.assert_allclose(stars.snr, stars.flux / (NOISE * np.sqrt(stars.npix)), rtol=0.1)


def test_saturation_flag():
    scene = make_scene(seed=14)
    cam = scene.context.camera
    flux = scene.flux.copy()
    flux[0] = 200_000.0  # peak ~ 200000 / (2 pi 1.44) >> 4095
    img = render(scene.x, scene.y, flux, (cam.height, cam.width), rng=np.random.default_rng(0))
    stars = _run(scene, img)  # saturation from the context's bit depth (12 -> 4095)
    d, j = _match(stars, scene.x, scene.y)
    assert stars.saturated[j == 0].all()
    assert not stars.saturated[j != 0].any()
    # an explicit lower level flags more
    stars2 = _run(scene, img, saturation_adu=float(img.max() - 1))
    assert stars2.saturated.sum() >= 1


def test_border_spots():
    """A spot centred on the first row is truncated: its row is biased inwards but its column
    (along the border) keeps the symmetric-PSF accuracy; reject_border drops it."""
    scene = make_scene(seed=15, n_field=3)
    cam = scene.context.camera
    x = np.array([100.3, 200.0, cam.width - 1.0])
    y = np.array([0.0, 120.4, 60.7])
    img = render(x, y, 20000.0, (cam.height, cam.width), rng=np.random.default_rng(0))
    stars = _run(scene, img)
    d, j = _match(stars, x, y)
    assert stars.n == 3
    assert np.all(cam.contains(stars.x, stars.y))
    top = j == 0
    assert abs(stars.x[top][0] - 100.3) < 0.05
    assert 0.0 < stars.y[top][0] < 1.5  # the missing half of the PSF pulls the CoG inside
    right = j == 2
    assert abs(stars.y[right][0] - 60.7) < 0.05 and stars.x[right][0] < cam.width - 1
    kept = _run(scene, img, reject_border=True)
    assert kept.n == 1 and abs(kept.x[0] - 200.0) < 0.05


def test_tiled_background_removes_a_gradient():
    scene = make_scene(seed=16)
    cam = scene.context.camera
    rng = np.random.default_rng(0)
    img = render(scene.x, scene.y, scene.flux, (cam.height, cam.width), background=0.0, noise_sigma=NOISE, rng=rng,
                 dtype=float)
    gradient = 100.0 + 1.0 * np.arange(cam.width)[None, :] + 0.5 * np.arange(cam.height)[:, None]  # 100..520 ADU
    img = img + gradient
    tiled = _run(scene, img, background="tiles", tile_px=32)
    assert tiled.n == scene.x.size  # the global median would cut half the image into one blob or miss faint stars
    d, _ = _match(tiled, scene.x, scene.y)
    assert d.max() < 0.25
    median = _run(scene, img, background="median")
    assert median.n != scene.x.size


def test_no_stars_gives_empty_table():
    scene = make_scene(seed=17)
    cam = scene.context.camera
    img = render([], [], [], (cam.height, cam.width), rng=np.random.default_rng(0))
    stars = _run(scene, img)
    assert stars.n == 0 and stars.t_ns.dtype == np.int64
    const = np.full((cam.height, cam.width), 100, dtype=np.uint16)
    assert _run(scene, const).n == 0


def test_errors_name_the_frame():
    scene = make_scene(seed=18)
    cam = scene.context.camera
    c = CogCentroider()
    c.setup(scene.context)
    img = np.full((cam.height, cam.width), 100.0)
    img[3, 4] = np.nan
    with pytest.raises(ValueError, match="frame 7.*non-finite"):
        c.process(FrameData(index=7, t0_ns=0, image=img))
    with pytest.raises(ValueError, match="frame 8.*no image"):
        c.process(FrameData(index=8, t0_ns=0))
    with pytest.raises(ValueError, match="frame 9.*shape"):
        c.process(FrameData(index=9, t0_ns=0, image=np.zeros((10, 10))))
