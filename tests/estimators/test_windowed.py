"""Windowed centroider: gyro window prediction, equality with full-frame CoG, lost-star fallback."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from estimators.centroiders.cog import CogCentroider
from estimators.centroiders.windowed import WindowedCentroider
from estimators.data import FrameData, GyroSamples
from estimators.filters.gyro_kf import star_motion_jacobian
from tests.conformance.scene import make_scene, render


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


def test_batched_windows_equal_the_per_window_cog_loop():
    """The one-pass window centroiding (batch=True, the default) gives the same spots as one cog
    call per window (batch=False, the original path) on noisy frames, every column, over 6 frames."""
    scene = make_scene(seed=11)
    ctx = scene.context
    period = int(ctx.timing.frame_period_ns)
    fast = WindowedCentroider(window_px=32, n_guide_stars=6)
    slow = WindowedCentroider(window_px=32, n_guide_stars=6, batch=False)
    for p in (fast, slow):
        p.setup(ctx)
    rng = np.random.default_rng(4)
    windowed = 0
    for k in range(6):
        dx, dy = rng.normal(0, 0.8, 2)  # small drift between frames, inside the windows
        img = _image(scene, scene.x + dx, scene.y + dy, noise=3.0, seed=k) + 100.0
        a = fast.process(FrameData(index=k, t0_ns=k * period, image=img))
        b = slow.process(FrameData(index=k, t0_ns=k * period, image=img))
        assert fast.last_mode == slow.last_mode
        windowed += fast.last_mode == "window"
        assert a.stars.n == b.stars.n
        for col in ("x", "y", "flux", "peak", "snr", "sigma_px"):
            np.testing.assert_allclose(getattr(a.stars, col), getattr(b.stars, col), rtol=1e-9, atol=1e-9, err_msg=col)
        for col in ("npix", "saturated", "t_ns", "row_time_ns"):
            np.testing.assert_array_equal(getattr(a.stars, col), getattr(b.stars, col), err_msg=col)
    assert windowed == 5


def test_window_cog_known_answer_and_windows_do_not_join():
    """A symmetric spot centred at (12.5, 9.5) has its CoG exactly there; two windows stacked with
    spots on their touching edges are labelled separately (no component crosses windows)."""
    from estimators.centroiders.window_cog import centroid_windows

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
