"""Windowed centroider: gyro window prediction, equality with full-frame CoG, lost-star fallback."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rollingstar.estimators.centroiders.cog import CogCentroider
from rollingstar.estimators.centroiders.windowed import WindowedCentroider
from rollingstar.estimators.conformance.scenes import make_scene, render
from rollingstar.estimators.data import FrameData, GyroSamples
from rollingstar.estimators.filters.gyro_kf import star_motion_jacobian


def _image(scene, x, y, flux=None, noise=0.0, seed=0):
    cam = scene.context.camera
    rng = np.random.default_rng(seed) if noise else None
    flux = scene.flux if flux is None else flux
    return render(x, y, flux, (cam.height, cam.width), noise_sigma=noise, rng=rng)


def test_jacobian_matches_exact_rotation():
    """eq (8) in our convention equals the finite-difference image motion of a body rotation."""
    scene = make_scene(seed=3)
    cam = scene.context.camera
    x, y = scene.x, scene.y
    dtheta = np.array([2e-5, -3e-5, 4e-5])
    w = cam.unproject(x, y)
    w2 = Rotation.from_rotvec(dtheta).inv().apply(w)  # R(t+dt) = R Exp(dtheta): w' = Exp(-dtheta) w
    x2, y2, _ = cam.project(w2)
    d = np.einsum("nij,j->ni", star_motion_jacobian(x, y, cam), dtheta)
    np.testing.assert_allclose(d[:, 0], x2 - x, atol=2e-3)
    np.testing.assert_allclose(d[:, 1], y2 - y, atol=2e-3)


def test_window_prediction_from_gyro_within_predicted_error():
    scene = make_scene(seed=5)
    ctx = scene.context
    cam = ctx.camera
    period = int(ctx.timing.frame_period_ns)
    omega = np.array([0.1, -0.15, 0.2])  # rad/s, constant
    plugin = WindowedCentroider(window_px=32, n_guide_stars=5, exposure_mean=False)
    plugin.setup(ctx)
    t0 = 0
    plugin.process(FrameData(index=0, t0_ns=t0, image=_image(scene, scene.x, scene.y)))
    tracks = plugin._tracks
    t1 = period
    t_g = np.arange(1, 11, dtype=np.int64) * (period // 10)
    plugin._gyro.add(GyroSamples(np.concatenate([[-period // 10 * 2, -period // 10], t_g]), np.tile(omega, (12, 1))))
    px, py, sig = plugin.predict(t1)
    # truth: rotate each spot's direction by omega over its own time difference
    t_old = tracks.t_ns
    t_new = ctx.timing.row_mid_exposure_ns(t1, py)
    dt = (t_new - t_old) * 1e-9
    w = cam.unproject(tracks.x, tracks.y)
    w2 = np.stack([Rotation.from_rotvec(omega * d).inv().apply(wi) for d, wi in zip(dt, w)])
    xt, yt, _ = cam.project(w2)
    err = np.hypot(px - xt, py - yt)
    assert np.all(np.hypot(xt - tracks.x, yt - tracks.y) > 3.0)  # the stars really moved
    assert np.all(err <= 3 * np.hypot(sig, 0.01) + 0.02), (err, sig)


def test_windowed_equals_full_frame_cog():
    scene = make_scene(seed=7)
    ctx = scene.context
    img = _image(scene, scene.x, scene.y)  # noise-free: same background / threshold in window and frame
    plugin = WindowedCentroider(window_px=40)
    plugin.setup(ctx)
    first = plugin.process(FrameData(index=0, t0_ns=0, image=img))
    assert plugin.last_mode == "full"
    second = plugin.process(FrameData(index=1, t0_ns=int(ctx.timing.frame_period_ns), image=img))
    assert plugin.last_mode == "window"
    cog = CogCentroider()
    cog.setup(ctx)
    ref = cog.process(FrameData(index=1, t0_ns=int(ctx.timing.frame_period_ns), image=img)).stars
    assert second.stars.n == first.stars.n == ref.n
    for i in range(second.stars.n):
        j = np.argmin(np.hypot(ref.x - second.stars.x[i], ref.y - second.stars.y[i]))
        assert abs(ref.x[j] - second.stars.x[i]) < 1e-9 and abs(ref.y[j] - second.stars.y[i]) < 1e-9
        assert abs(ref.flux[j] - second.stars.flux[i]) < 1e-6 * ref.flux[j]
        assert ref.t_ns[j] == second.stars.t_ns[i] and ref.row_time_ns[j] == second.stars.row_time_ns[i]
    assert not second.stars.identified.any()


def test_lost_star_falls_back_to_full_frame():
    scene = make_scene(seed=9)
    ctx = scene.context
    plugin = WindowedCentroider(window_px=24, n_guide_stars=3)
    plugin.setup(ctx)
    plugin.process(FrameData(index=0, t0_ns=0, image=_image(scene, scene.x, scene.y)))
    guide = plugin._tracks
    # the first guide star disappears (occulted): its window is empty -> full-frame detection
    keep = np.hypot(scene.x - guide.x[0], scene.y - guide.y[0]) > 2.0
    img = _image(scene, scene.x[keep], scene.y[keep], scene.flux[keep])
    out = plugin.process(FrameData(index=1, t0_ns=int(ctx.timing.frame_period_ns), image=img))
    assert plugin.last_mode == "full"
    assert out.stars.n == 3
    assert np.all(np.hypot(out.stars.x - guide.x[0], out.stars.y - guide.y[0]) > 2.0)
    # and the next frame is windowed again around the re-acquired guide stars
    plugin.process(FrameData(index=2, t0_ns=2 * int(ctx.timing.frame_period_ns), image=img))
    assert plugin.last_mode == "window"


@pytest.mark.parametrize("kernel", ["compiled", "numpy"])
@pytest.mark.parametrize("dtype", [float, np.uint16])
def test_batched_windows_equal_the_per_window_cog_loop(kernel, dtype):
    """The one-pass window centroiding (compiled kernel or vectorised numpy, with each window's own
    background) gives the same spots as one cog call per window (batch=False, the original path)
    on noisy frames, float and integer, every column, over 6 frames."""
    scene = make_scene(seed=11)
    ctx = scene.context
    period = int(ctx.timing.frame_period_ns)
    fast = WindowedCentroider(window_px=32, n_guide_stars=6, kernel=kernel, background="window")
    slow = WindowedCentroider(window_px=32, n_guide_stars=6, batch=False)
    for p in (fast, slow):
        p.setup(ctx)
    rng = np.random.default_rng(4)
    windowed = 0
    for k in range(6):
        dx, dy = rng.normal(0, 0.8, 2)  # small drift between frames, inside the windows
        img = _image(scene, scene.x + dx, scene.y + dy, noise=3.0, seed=k) + 100.0
        if dtype is not float:
            img = np.rint(img).astype(dtype)
        a = fast.process(FrameData(index=k, t0_ns=k * period, image=img))
        b = slow.process(FrameData(index=k, t0_ns=k * period, image=img))
        assert fast.last_mode == slow.last_mode
        windowed += fast.last_mode == "window"
        assert a.stars.n == b.stars.n
        for col in ("x", "y", "flux", "peak", "snr", "sigma_px", "cov_xx", "cov_xy", "cov_yy"):
            np.testing.assert_allclose(getattr(a.stars, col), getattr(b.stars, col), rtol=1e-9, atol=1e-9, err_msg=col)
        assert np.all(np.isfinite(a.stars.cov_xx)) and np.all(a.stars.cov_xx * a.stars.cov_yy > a.stars.cov_xy**2)
        for col in ("npix", "saturated", "t_ns", "row_time_ns"):
            np.testing.assert_array_equal(getattr(a.stars, col), getattr(b.stars, col), err_msg=col)
    assert windowed == 5


def test_window_cog_known_answer_and_windows_do_not_join():
    """A symmetric spot centred at (12.5, 9.5) has its CoG exactly there; two windows stacked with
    spots on their touching edges are labelled separately (no component crosses windows)."""
    from rollingstar.estimators.centroiders.window_cog import centroid_windows

    yy, xx = np.mgrid[0:24, 0:24].astype(float)
    spot = 1000.0 * np.exp(-((xx - 12.5) ** 2 + (yy - 9.5) ** 2) / (2 * 1.2**2))
    a = 50.0 + spot
    b = 50.0 + 1000.0 * np.exp(-((xx - 5.0) ** 2 + (yy - 0.0) ** 2) / (2 * 1.2**2))  # spot on the top edge
    c = 50.0 + 1000.0 * np.exp(-((xx - 5.0) ** 2 + (yy - 23.0) ** 2) / (2 * 1.2**2))  # ... and the bottom edge
    kw = dict(threshold_sigma=5.0, min_pixels=3, max_pixels=None, connectivity=8, grow_px=1,
              noise_floor_adu=1 / np.sqrt(12), saturation_adu=np.inf)
    out = centroid_windows(np.stack([a, c, b]), np.array([12.0, 5.0, 5.0]), np.array([9.0, 23.0, 0.0]), **kw)
    assert out.found.all()
    assert abs(out.x[0] - 12.5) < 1e-9 and abs(out.y[0] - 9.5) < 1e-9
    assert out.y[1] > 21.0 and out.y[2] < 2.0  # each window keeps its own edge spot
    # one window alone gives the same answer as in the stack
    alone = centroid_windows(c[None], np.array([5.0]), np.array([23.0]), **kw)
    assert alone.x[0] == out.x[1] and alone.y[0] == out.y[1]


def test_compiled_kernel_equals_numpy_window_pass_on_many_windows():
    """centroid_windows_at (compiled, in place in the frame) equals centroid_windows (numpy, stacked
    windows) given the same per-window background and noise: every column, 40 random windows with
    0-3 noisy spots each (edges, blends, hot pixels, saturated spots: their covariance carries the
    clipped-spot term), 4- and 8-connectivity, grow 0-2 rings, with and without the shot term."""
    from rollingstar.estimators.centroiders.window_cog import (
        centroid_windows,
        cut_windows,
        median_rows,
        robust_sigma_rows,
    )
    from rollingstar.estimators.centroiders.window_kernel import centroid_windows_at

    rng = np.random.default_rng(21)
    H = W = 200
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    img = 80.0 + rng.normal(0, 4.0, (H, W))
    for _ in range(60):
        cx, cy, a, s = rng.uniform(0, W), rng.uniform(0, H), rng.uniform(50, 3000), rng.uniform(0.6, 2.0)
        img += a * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
    img[rng.integers(0, H, 30), rng.integers(0, W, 30)] += 500.0  # hot pixels
    img = np.rint(img).astype(np.uint16)
    n, h, w = 40, 24, 24
    r0, c0 = rng.integers(0, H - h + 1, n), rng.integers(0, W - w + 1, n)
    px, py = c0 + rng.uniform(0, w, n), r0 + rng.uniform(0, h, n)
    stack = cut_windows(img, r0, c0, h, w).astype(float).reshape(n, -1)
    bg = median_rows(stack)
    noise = np.maximum(robust_sigma_rows(stack - bg[:, None], np.zeros(n)), 0.3)
    for connectivity in (4, 8):
        for grow in (0, 1, 2):
            kw = dict(threshold_sigma=4.0, min_pixels=2, max_pixels=40, connectivity=connectivity, grow_px=grow,
                      saturation_adu=1500.0, reject_border=grow == 1, gain_e_per_adu=2.0 if grow == 2 else None,
                      cov_gain_e_per_adu=2.0 if grow != 1 else None)
            ref = centroid_windows(cut_windows(img, r0, c0, h, w), px - c0, py - r0, noise_floor_adu=0.3, **kw)
            got, bgsum = centroid_windows_at(img, r0, c0, h, w, px, py, bg, noise, **kw)
            assert 3 < ref.found.sum() < n  # found and empty windows both occur
            assert 0 < (ref.found & ref.saturated).sum() < ref.found.sum()  # with and without the clipped-spot sigma
            np.testing.assert_array_equal(got.found, ref.found)
            np.testing.assert_allclose(got.x, ref.x + c0, rtol=1e-12, equal_nan=True)
            np.testing.assert_allclose(got.y, ref.y + r0, rtol=1e-12, equal_nan=True)
            for col in ("flux", "peak", "snr", "sigma_px"):
                np.testing.assert_allclose(getattr(got, col), getattr(ref, col), rtol=1e-10, equal_nan=True, err_msg=col)
            np.testing.assert_allclose(got.cov, ref.cov, rtol=1e-9, atol=1e-15, equal_nan=True)
            for col in ("npix", "saturated"):
                np.testing.assert_array_equal(getattr(got, col), getattr(ref, col), err_msg=col)
    # background sums (every 4th row, |d| < 3 s, outside spots): exact where no pixel is above threshold
    d = cut_windows(img, r0, c0, h, w).astype(float) - bg[:, None, None]
    empty = ~np.any(d > 4.0 * noise[:, None, None], axis=(1, 2))
    assert empty.sum() >= 3
    sub = d[:, ::4, :]
    m = np.abs(sub) < 3.0 * noise[:, None, None]
    np.testing.assert_allclose(bgsum[empty, 0], m.sum(axis=(1, 2))[empty])
    np.testing.assert_allclose(bgsum[empty, 1], (sub * m).sum(axis=(1, 2))[empty], rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(bgsum[empty, 2], (sub**2 * m).sum(axis=(1, 2))[empty], rtol=1e-9)


def test_compiled_prediction_and_gyro_increment_equal_the_reference_helpers():
    """predict_windows applies star_motion_jacobian (eq 8-10), gyro_increment equals
    GyroIntegrator.increment (instants and exposure means), predict_step's row times equal
    DetectorTiming's, and FastGyroIntegrator keeps GyroIntegrator's knots, on random stars and
    gyro histories."""
    from rollingstar.estimators.centroiders.window_gyro import (
        FastGyroIntegrator,
        gyro_increment,
    )
    from rollingstar.estimators.centroiders.window_kernel import (
        predict_step,
        predict_windows,
    )
    from rollingstar.sensors.gyro import GyroIntegrator
    from rollingstar.sensors.timing import DetectorTiming

    scene = make_scene(seed=13)
    cam = scene.context.camera
    rng = np.random.default_rng(3)
    dtheta = rng.normal(0, 3e-4, (scene.x.size, 3))
    px, py, r0, c0 = predict_windows(scene.x, scene.y, dtheta, cam.cx, cam.cy, cam.focal_px, cam.height, cam.width, 32, 32)
    d = np.einsum("nij,nj->ni", star_motion_jacobian(scene.x, scene.y, cam), dtheta)
    np.testing.assert_allclose(px, scene.x + d[:, 0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(py, scene.y + d[:, 1], rtol=0, atol=1e-9)
    assert np.all((c0 >= 0) & (c0 <= cam.width - 32) & (r0 >= 0) & (r0 <= cam.height - 32))
    inside = (px > 16) & (px < cam.width - 16) & (py > 16) & (py < cam.height - 16)
    np.testing.assert_array_equal(c0[inside], np.rint(px[inside]).astype(int) - 16)
    g = GyroIntegrator(bias_rad_s=(1e-4, -2e-4, 0.0))
    t = np.cumsum(rng.integers(8_000_000, 12_000_000, 60))
    g.add(GyroSamples(t[:30], rng.normal(0, 0.01, (30, 3))))
    g.add(GyroSamples(t[30:], rng.normal(0, 0.01, (30, 3))))
    a = rng.integers(t[0] - 20_000_000, t[-1], 25)
    b = a + rng.integers(0, 30_000_000, 25)  # some beyond the last sample: extrapolated
    for exposure_mean in (True, False):
        ref = g.increment(a, b, 1_000_000 if exposure_mean else None)
        got = gyro_increment(g.tau, g.psi, g.theta, g.rate, g.origin_ns, a, b, 1_000_000, exposure_mean)
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-18)
    # rolling shutter: the second pass predicts at the row the first pass predicted
    timing = DetectorTiming(mode="rolling", exposure_ns=2_000_000, line_delay_ns=30_000, rows=cam.height)
    t0 = int(t[40])
    row_prev = timing.row_start_ns(int(t[38]), scene.y)
    for exposure_mean in (True, False):
        t_prev = row_prev if exposure_mean else row_prev + timing.exposure_ns // 2
        px, py, _, _, dth, t_new = predict_step(scene.x, scene.y, t_prev, g.tau, g.psi, g.theta, g.rate, g.origin_ns,
                                                exposure_mean, t0, timing.line_delay_ns, timing.exposure_ns,
                                                cam.cx, cam.cy, cam.focal_px, cam.height, cam.width, 32, 32)
        y1 = scene.y + np.einsum("nij,nj->ni", star_motion_jacobian(scene.x, scene.y, cam), g.increment(
            t_prev, (timing.row_start_ns if exposure_mean else timing.row_mid_exposure_ns)(t0, scene.y),
            timing.exposure_ns if exposure_mean else None))[:, 1]
        ref_t = (timing.row_start_ns if exposure_mean else timing.row_mid_exposure_ns)(t0, y1)
        np.testing.assert_array_equal(t_new, ref_t)
        np.testing.assert_allclose(dth, g.increment(t_prev, ref_t, timing.exposure_ns if exposure_mean else None),
                                   rtol=1e-12, atol=1e-18)
    # the compiled add / trim keep the same knots as GyroIntegrator's, through buffer growth and
    # compaction, with repeated (ignored) samples and 1-3 samples per call
    ref, fast = GyroIntegrator((1e-4, 0, -1e-4), keep_s=0.3), FastGyroIntegrator((1e-4, 0, -1e-4), keep_s=0.3)
    t = np.cumsum(rng.integers(1_000_000, 3_000_000, 1500))
    i = 0
    while i < t.size:
        k = int(rng.integers(1, 4))
        s = GyroSamples(t[max(0, i - 1):i + k], rng.normal(0, 0.02, (len(t[max(0, i - 1):i + k]), 3)))
        ref.add(s)
        fast.add(s)
        if i > 800 and rng.random() < 0.05:  # first past the initial buffer capacity (256), then trimmed
            ref.trim(int(t[i]))
            fast.trim(int(t[i]))
        i += k
        for name in ("tau", "rate", "theta", "psi"):
            np.testing.assert_array_equal(getattr(fast, name), getattr(ref, name), err_msg=name)
    assert ref.rate.shape[0] < 400  # trimmed


def _flat_frames(scene, levels, sigma, seed):
    """uint16 frames of the scene's stars on a background ``level`` with Gaussian pixel noise ``sigma``."""
    rng = np.random.default_rng(seed)
    cam = scene.context.camera
    stars = render(scene.x, scene.y, scene.flux, (cam.height, cam.width), background=0.0, noise_sigma=0.0, dtype=float)
    for level in levels:
        yield np.rint(stars + level + rng.normal(0, sigma, stars.shape)).astype(np.uint16)


def test_tracked_background_converges_and_follows_a_drift_with_the_running_mean_lag():
    """background='tracked': on a constant background B with pixel noise sigma the tracked level and
    noise converge to B and sigma (within their standard errors: a running mean over ~100 frames of
    ~1000 pixels, ~0.01 sigma); on a background rising by r ADU per frame the running mean lags by
    r (1 - a) / a (a = 1 / background_frames), the steady-state lag of an exponential mean."""
    scene = make_scene(seed=17)
    ctx = scene.context
    period = int(ctx.timing.frame_period_ns)
    B, sigma, frames = 200.0, 6.0, 300
    plugin = WindowedCentroider(window_px=32, n_guide_stars=3, background_frames=50)
    plugin.setup(ctx)
    for k, img in enumerate(_flat_frames(scene, [B] * frames, sigma, 1)):
        plugin.process(FrameData(index=k, t0_ns=k * period, image=img))
        assert plugin.last_mode == ("full" if k == 0 else "window")
    # pixel values are rounded: variance sigma^2 + 1/12. Margins: seeds 1-3 gave |bg - B| <= 0.085 ADU,
    # |noise / truth - 1| <= 0.012 and |lag error| <= 0.15 ADU (the spots' faint wings bias the level a little)
    np.testing.assert_allclose(plugin._bg, B, atol=0.05 * sigma)
    np.testing.assert_allclose(plugin._noise, np.sqrt(sigma**2 + 1 / 12), rtol=0.02)
    rate = 0.05  # ADU per frame
    plugin = WindowedCentroider(window_px=32, n_guide_stars=3, background_frames=50)
    plugin.setup(ctx)
    levels = B + rate * np.arange(frames)
    for k, img in enumerate(_flat_frames(scene, levels, sigma, 2)):
        plugin.process(FrameData(index=k, t0_ns=k * period, image=img))
    lag = rate * (1 - 1 / 50) / (1 / 50)
    np.testing.assert_allclose(levels[-1] - plugin._bg, lag, atol=0.05 * sigma)


def test_tracked_background_spots_match_the_per_window_background():
    """The default (tracked background) and background='window' find the same spots to within the
    noise of the per-frame window median (positions <= 0.02 px here, all flags equal)."""
    scene = make_scene(seed=19)
    ctx = scene.context
    period = int(ctx.timing.frame_period_ns)
    a = WindowedCentroider(window_px=32, n_guide_stars=5)
    b = WindowedCentroider(window_px=32, n_guide_stars=5, background="window")
    for p in (a, b):
        p.setup(ctx)
    diffs = []
    for k, img in enumerate(_flat_frames(scene, [150.0] * 30, 4.0, 5)):
        sa = a.process(FrameData(index=k, t0_ns=k * period, image=img)).stars
        sb = b.process(FrameData(index=k, t0_ns=k * period, image=img)).stars
        assert a.last_mode == b.last_mode and sa.n == sb.n == 5
        np.testing.assert_array_equal(sa.saturated, sb.saturated)
        diffs.append(np.hypot(sa.x - sb.x, sa.y - sb.y))
    assert np.max(diffs) < 0.02, np.max(diffs)
    assert np.max(diffs) > 0  # the two backgrounds do differ


def test_windowed_params_that_do_not_fit_are_refused():
    scene = make_scene(seed=1)
    for bad in (dict(kernel="numpy", background="tracked"), dict(batch=False, background="tracked")):
        with pytest.raises(ValueError, match="tracked"):
            WindowedCentroider(**bad).setup(scene.context)
