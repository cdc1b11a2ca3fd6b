"""The streak centroider on frames rendered by the image simulator's exact rolling-shutter integral
(not the centroider's closed-form model): its stated covariance against the scatter of its
positions, the pixel-level bound, unbiased velocities, faint streaks the thresholded CoG misses,
and a PSF unlike the model's."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.estimators.centroiders.cog import CogCentroider
from rollingstar.estimators.centroiders.streak import StreakCentroider
from rollingstar.estimators.conformance import check_plugin
from rollingstar.estimators.data import FrameData, GyroSamples, RateEstimate, SensorContext
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.effects.geometry import image_velocity
from rollingstar.sensors.image_sim import ImageModel, digitise, mean_electrons, render_star_electrons
from rollingstar.sensors.pixel_crb import smeared_spot_fisher
from rollingstar.sensors.timing import DetectorTiming

SIZE = 256
EXPOSURE_NS, LINE_DELAY_NS = 44_900_000, 43_900  # he2021a
PX_PER_S_PER_DEG_S = 76.4  # he2021a: 4380 px focal length
BOUND_FRAMES = 8  # frames whose stars' bounds (exact pixel integration, slow) average the bound: random phases


def _context(psf_sigma_px: float = 1.0):
    camera = PinholeCamera(focal_length_m=0.02409, pixel_size_m=5.5e-6, width=SIZE, height=SIZE)
    timing = DetectorTiming(mode="rolling", exposure_ns=EXPOSURE_NS, line_delay_ns=LINE_DELAY_NS, rows=SIZE)
    model = ImageModel(psf_sigma_px=psf_sigma_px)  # he2021a's detector: 12 bits, gain 1, read noise 5 e
    return SensorContext(camera=camera, timing=timing, catalog=None, bit_depth=12, gain_e_per_adu=1.0), model


def _render(ctx, model, x, y, vx, vy, electrons, rng, index=0, gyro_rad_s=None):
    """A frame of stars at ``(x, y)`` at the mid-exposure of their own row, moving at ``(vx, vy)``
    px/s, rendered by the simulator's exact integral over each row's window; with ``gyro_rad_s``
    the frame carries one gyro sample of that body rate."""
    timing = ctx.timing
    t0 = int(timing.frame_start_ns(index))
    t_star = timing.row_mid_exposure_ns(t0, y).astype(float)

    def positions(star, t_ns, rows):
        dt = (t_ns - t_star[star]) * 1e-9
        return x[star] + vx * dt, y[star] + vy * dt

    star_e = render_star_electrons(positions, timing, (SIZE, SIZE), t0, np.zeros((x.size, 3)), electrons, y,
                                   model.psf_sigma_px)
    image = digitise(mean_electrons(star_e, model, EXPOSURE_NS, None), model, rng, rng)
    gyro = GyroSamples.empty() if gyro_rad_s is None else GyroSamples(np.array([t0]), np.reshape(gyro_rad_s, (1, 3)))
    return FrameData(index=index, t0_ns=t0, image=image, gyro=gyro)


def _rate_about_x(ctx, vy: float) -> np.ndarray:
    """The body rate about camera x that moves the image centre at ``vy`` px/s along the columns."""
    c = (SIZE - 1) / 2.0
    per_rad_s = image_velocity(ctx.camera, np.array([c]), np.array([c]), np.array([1.0, 0.0, 0.0]))[1][0]
    return np.array([vy / per_rad_s, 0.0, 0.0])


def _grid_stars(rng, n_cols: int, n_rows: int, margin: float):
    """Stars on a jittered grid (no two streaks overlap), random sub-pixel phases."""
    cols = (np.arange(n_cols) + 0.5) * (SIZE - 2 * margin) / n_cols + margin
    rows = (np.arange(n_rows) + 0.5) * (SIZE - 2 * margin) / n_rows + margin
    gx, gy = np.meshgrid(cols, rows)
    return gx.ravel() + rng.uniform(-3, 3, gx.size), gy.ravel() + rng.uniform(-3, 3, gy.size)


def _matched(stars, x, y, tol):
    d = np.hypot(stars.x[:, None] - x[None, :], stars.y[:, None] - y[None, :])
    j = d.argmin(axis=1)
    ok = d[np.arange(stars.n), j] < tol
    return j[ok], np.flatnonzero(ok)


def test_the_streak_centroider_conforms():
    check_plugin(StreakCentroider)


@pytest.mark.parametrize("rate_deg_s", [0.0, 3.0, 10.0])
def test_positions_scatter_as_stated_at_the_pixel_level_bound(rate_deg_s):
    """30 frames of 9 stars (8000 e, about magnitude 5) moving down the rows at ``rate_deg_s``
    about camera x, with the gyro's rate: the positions' normalised chi-square with the stated 2 x 2 covariance averages
    2 (0.8-1.25 of it: its Monte Carlo error is 5 %), their variance per axis reaches the
    pixel-level bound (smeared_spot_fisher: exact pixel integration, same noise) within 20 % and
    the velocities are unbiased (mean error within 4 standard errors) and, for a star at rest,
    within 5 px/s (0.07 deg/s) of zero."""
    ctx, model = _context()
    rng = np.random.default_rng(7)
    centroider = StreakCentroider(track_windows=False)  # every frame is a new scene: each is searched in full
    centroider.setup(ctx)
    vy = rate_deg_s * PX_PER_S_PER_DEG_S
    err, chi2, crb, dv = [], [], [], []
    background = (model.background_e_per_px_s + model.dark_e_per_px_s) * EXPOSURE_NS * 1e-9
    for k in range(30):
        x, y = _grid_stars(rng, 3, 3, 40.0)
        flux = np.full(x.size, 8000.0)
        stars = centroider.process(_render(ctx, model, x, y, 0.0, vy, flux, rng, k, _rate_about_x(ctx, vy))).stars
        j, i = _matched(stars, x, y, 2.0)
        assert j.size == x.size, f"frame {k}: {j.size} of {x.size} stars found"
        e = np.column_stack([stars.x[i] - x[j], stars.y[i] - y[j]])
        cov = stars.position_covariance(0.05)[i]
        err.append(e)
        chi2.append(np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov), e))
        dv.append(np.column_stack([stars.vx[i], stars.vy[i] - vy]))
        for a, b in zip(x[j], y[j]) if k < BOUND_FRAMES else ():
            info = smeared_spot_fisher(a, b, 0.0, vy, 8000.0, 1.0, EXPOSURE_NS * 1e-9, LINE_DELAY_NS * 1e-9,
                                       background, model.read_noise_e, model.gain_e_per_adu, n_sub=32)
            crb.append(np.diag(np.linalg.inv(info))[:2])
    err, chi2, crb, dv = np.concatenate(err), np.concatenate(chi2), np.array(crb), np.concatenate(dv)
    assert 0.8 < chi2.mean() / 2.0 < 1.25
    efficiency = np.mean(err**2, axis=0) / crb.mean(axis=0)
    assert np.all(efficiency < 1.2) and np.all(efficiency > 0.8), efficiency
    bound = 5.0 if rate_deg_s == 0 else 4.0 * dv.std(axis=0) / np.sqrt(dv.shape[0])
    assert np.all(np.abs(dv.mean(axis=0)) < bound), dv.mean(axis=0)


def test_faint_streaks_at_10_deg_s_are_found_where_the_thresholded_cog_misses_them():
    """20 streaks of 1500 e (about magnitude 6.5) at 10 deg/s, 34 px long: ~40 e per row spread
    over a few pixels, under the CoG's 5-sigma pixel threshold, while the matched filter along the
    streak integrates all of them."""
    ctx, model = _context()
    rng = np.random.default_rng(11)
    vy = 10.0 * PX_PER_S_PER_DEG_S
    found = {"streak": 0, "cog": 0}
    total = 0
    for k in range(3):
        x, y = _grid_stars(rng, 5, 4, 30.0)
        frame = _render(ctx, model, x, y, 0.0, vy, np.full(x.size, 1500.0), rng, k)
        total += x.size
        for name, plugin in (("streak", StreakCentroider()), ("cog", CogCentroider(threshold_sigma=5.0))):
            plugin.setup(ctx)
            stars = plugin.process(frame).stars
            found[name] += np.unique(_matched(stars, x, y, 3.0)[0]).size
    assert found["streak"] >= 0.9 * total
    assert found["cog"] <= 0.5 * total


def test_a_psf_wider_than_the_model_still_finds_the_stars_and_widens_their_covariance():
    """The stars rendered with a 1.3 px PSF, the model's 1.0 px: every star found, and the
    reduced chi-square of the misfit scales the covariance, so that the stated covariance still
    covers the scatter (normalised chi-square at most 1.5 x its nominal 2)."""
    ctx, model = _context(psf_sigma_px=1.3)
    rng = np.random.default_rng(5)
    centroider = StreakCentroider(psf_sigma_px=1.0)  # stated, not measured
    centroider.setup(ctx)
    chi2 = []
    for k in range(10):
        x, y = _grid_stars(rng, 3, 3, 40.0)
        stars = centroider.process(_render(ctx, model, x, y, 0.0, 229.2, np.full(x.size, 3e4), rng, k)).stars
        j, i = _matched(stars, x, y, 2.0)
        assert j.size == x.size
        e = np.column_stack([stars.x[i] - x[j], stars.y[i] - y[j]])
        chi2.append(np.einsum("ni,nij,nj->n", e, np.linalg.inv(stars.position_covariance(0.05)[i]), e))
    assert np.mean(np.concatenate(chi2)) / 2.0 < 1.5


def test_a_rate_estimate_sets_the_expected_motion_and_short_streaks_go_to_cog():
    """update_prior takes a later stage's rate; with every expected streak shorter than
    cog_below_px the frame is the cog centroider's (same stars, same positions), longer ones are fitted."""
    ctx, model = _context()
    rng = np.random.default_rng(11)
    x, y = _grid_stars(rng, 4, 4, 30.0)
    slow, fast = 0.2 * PX_PER_S_PER_DEG_S, 6.0 * PX_PER_S_PER_DEG_S  # 0.7 px and 21 px streaks
    for vy, expect_cog in ((slow, True), (fast, False)):
        frame = _render(ctx, model, x, y, 0.0, vy, np.full(x.size, 3.0e4), rng)
        streak = StreakCentroider(cog_below_px=3.0, background="median")
        streak.setup(ctx)
        rate = RateEstimate(t_ns=frame.t0_ns, omega_rad_s=_rate_about_x(ctx, vy))
        assert streak.update_prior(FrameData(index=0, t0_ns=0, rate=rate))
        out = streak.process(frame).stars
        cog = CogCentroider(background="median")
        cog.setup(ctx)
        ref = cog.process(frame).stars
        same = out.n == ref.n and np.allclose(out.x, ref.x) and np.allclose(out.y, ref.y)
        assert same == expect_cog
        assert np.unique(_matched(out, x, y, 1.0)[0]).size == x.size  # every star, once
        assert np.isfinite(out.vx).all() != expect_cog  # only the streak fit measures velocities


def _moving_sky(rng, vy: float, n_frames: int, jump_at: int | None = None, jump_px: float = 0.0,
                row_offset: float = 0.0, gyro: bool = True, psf_sigma_px: float = 1.0, top_px: float = 6.0):
    """Frames of a sky drifting down the rows at ``vy`` px/s (new stars enter at the top), with its
    true stars per frame; from frame ``jump_at`` on the sky also stands ``jump_px`` to the right
    (an unpredicted jump); ``row_offset`` moves the grid of stars down; without ``gyro`` the frames
    carry no gyro samples; ``psf_sigma_px`` the rendered PSF (the fit's model is 1 px). Stars are
    drawn from ``top_px`` rows down (a negative value: from outside the detector, cut by its edge
    as they enter)."""
    ctx, model = _context(psf_sigma_px)
    cols = (np.arange(5) + 0.5) * (SIZE - 40) / 5 + 20
    t_first = ctx.timing.frame_start_ns(0)
    above = vy * (ctx.timing.frame_start_ns(n_frames) - t_first) * 1e-9 + 50.0  # the sky that enters
    rows = np.arange(-above, SIZE, 44.0) + row_offset
    gx, gy = np.meshgrid(cols, rows)
    gx[1::2] += 0.5 * (SIZE - 40) / 5  # staggered rows: no two streaks collinear and close (a blend)
    x0, y0 = gx.ravel() + rng.uniform(-4, 4, gx.size), gy.ravel() + rng.uniform(-4, 4, gy.size)
    frames, truth = [], []
    for k in range(n_frames):
        y = y0 + vy * (ctx.timing.frame_start_ns(k) - t_first) * 1e-9
        x = x0 + (jump_px if jump_at is not None and k >= jump_at else 0.0)
        on = (y > top_px) & (y < SIZE - 6) & (x > 6) & (x < SIZE - 6)
        frames.append(_render(ctx, model, x[on], y[on], 0.0, vy, np.full(int(on.sum()), 2.0e4), rng, k,
                              _rate_about_x(ctx, vy) if gyro else None))
        truth.append((x[on], y[on]))
    return ctx, frames, truth


@pytest.mark.parametrize("rate_deg_s", [0.5, 3.0, 10.0])
def test_tracked_frames_find_what_a_full_search_finds_including_stars_that_entered(rate_deg_s):
    """A sky drifting down the rows: after the first frame the tracking centroider fits windows
    around its stars moved by the rate and searches only the strip of sky that entered. It finds
    every true star a full search of the same frame finds, stars entering at the top included,
    and gives the same positions (within a fifth of their stated sigma: both fits stop once a
    step is below a tenth of it)."""
    ctx, frames, truth = _moving_sky(np.random.default_rng(3), rate_deg_s * PX_PER_S_PER_DEG_S, 8)
    tracked, full = StreakCentroider(), StreakCentroider(track_windows=False)
    tracked.setup(ctx)
    full.setup(ctx)
    for k, (frame, (x, y)) in enumerate(zip(frames, truth)):
        a, b = tracked.process(frame).stars, full.process(frame).stars
        ja, ia = _matched(a, x, y, 1.5)
        jb, ib = _matched(b, x, y, 1.5)
        assert set(jb) <= set(ja), f"frame {k}: the full search found stars {set(jb) - set(ja)} tracking missed"
        assert ja.size >= 0.8 * x.size
        for j in np.intersect1d(ja, jb):
            sa, sb = ia[ja == j][0], ib[jb == j][0]
            assert abs(a.x[sa] - b.x[sb]) < 0.2 * np.sqrt(a.cov_xx[sa]) + 1e-3
            assert abs(a.y[sa] - b.y[sb]) < 0.2 * np.sqrt(a.cov_yy[sa]) + 1e-3
        if k:
            assert tracked.last_mode == "tracked", f"frame {k}: searched in full"


def test_an_unpredicted_jump_sends_the_tracking_centroider_back_to_a_full_search():
    """The sky jumps 25 px sideways (no rate says so): the windows lose the stars, and the same
    frame is searched in full, so no star is lost."""
    ctx, frames, truth = _moving_sky(np.random.default_rng(4), 3.0 * PX_PER_S_PER_DEG_S, 5, jump_at=3, jump_px=25.0)
    centroider = StreakCentroider()
    centroider.setup(ctx)
    modes = []
    for k, (frame, (x, y)) in enumerate(zip(frames, truth)):
        stars = centroider.process(frame).stars
        modes.append(centroider.last_mode)
        assert np.unique(_matched(stars, x, y, 1.5)[0]).size >= 0.9 * x.size, f"frame {k}"
    assert modes[1:3] == ["tracked", "tracked"] and modes[3] == "full", modes


def test_tracked_round_spots_are_the_cog_centroids_of_the_full_frame():
    """At 0.5 deg/s (2 px streaks, under cog_below_px) a tracked frame takes the cog definition in
    windows around the tracked stars: the same stars as cog on the full frame, at the same
    positions to a quarter of their sigma (the tracked background level comes from a quarter of
    cog's sample: a CoG moves with its background), with the same covariance model."""
    ctx, frames, truth = _moving_sky(np.random.default_rng(6), 0.5 * PX_PER_S_PER_DEG_S, 6)
    tracked = StreakCentroider(cog_below_px=3.0, background="median")
    tracked.setup(ctx)
    cog = CogCentroider(background="median")
    cog.setup(ctx)
    for k, frame in enumerate(frames):
        a = tracked.process(frame).stars
        assert tracked.last_mode == ("cog" if k == 0 else "tracked")
        tracked.update_prior(frame.evolve(rate=RateEstimate(t_ns=frame.t0_ns, omega_rad_s=_rate_about_x(
            ctx, 0.5 * PX_PER_S_PER_DEG_S))))
        b = cog.process(frame).stars
        d = np.hypot(a.x[:, None] - b.x[None, :], a.y[:, None] - b.y[None, :])
        assert a.n == b.n and np.all(d.min(axis=1) < 0.25 * a.sigma_px), (k, a.n, b.n)
        j = d.argmin(axis=1)
        np.testing.assert_allclose(a.cov_xx, b.cov_xx[j], rtol=0.05)
        np.testing.assert_allclose(a.cov_yy, b.cov_yy[j], rtol=0.05)


@pytest.mark.parametrize("cog_below_px", [0.0, 3.0])
def test_a_slow_drift_is_searched_once_enough_sky_has_entered(cog_below_px):
    """0.2 deg/s: under a pixel of sky enters per frame. The strip is searched once the entered sky
    adds up to ``NEW_SKY_PX`` (8 px), so a star that drifts in through the edge is found by
    tracking (no periodic full search here) by the time it is 16 px in, wherever a full search of
    the frame finds it. The stars come in through the edge, cut by it, as a sky does."""
    vy = 0.2 * PX_PER_S_PER_DEG_S
    ctx, frames, truth = _moving_sky(np.random.default_rng(8), vy, 50, row_offset=2.0, top_px=-4.0)
    tracked = StreakCentroider(cog_below_px=cog_below_px, full_search_frames=0)
    full = StreakCentroider(cog_below_px=cog_below_px, track_windows=False)
    tracked.setup(ctx)
    full.setup(ctx)
    entered = set()
    for k, (frame, (x, y)) in enumerate(zip(frames, truth)):
        a, b = tracked.process(frame).stars, full.process(frame).stars
        if k:
            assert tracked.last_mode == "tracked", k
        ja, jb = set(_matched(a, x, y, 1.5)[0]), set(_matched(b, x, y, 1.5)[0])
        missing = {j for j in jb - ja if y[j] > 16.0}  # 8 px of inflow after it shows, and two frames
        assert not missing, f"frame {k}: tracking misses {[(round(x[j]), round(y[j])) for j in missing]}"
        entered |= {(round(x[j]), round(y[j] - vy * (frame.t0_ns - frames[0].t0_ns) * 1e-9)) for j in ja if k
                    and y[j] < 10}
    assert entered, "no star entered the detector in this test's sky"


def test_round_spots_tracked_without_a_gyro_follow_the_rate_from_their_own_moves():
    """No gyro and no later stage's rate after the first frame: the tracked frames of round spots
    start from a rate 30 % slow and correct it from where the stars are found, so the windows stay
    on the stars and the expected rate comes within 2 % of the truth."""
    vy = 0.6 * PX_PER_S_PER_DEG_S
    ctx, frames, truth = _moving_sky(np.random.default_rng(9), vy, 10, gyro=False)
    centroider = StreakCentroider(cog_below_px=3.0, full_search_frames=0)
    centroider.setup(ctx)
    rate = _rate_about_x(ctx, vy)
    centroider.update_prior(frames[0].evolve(rate=RateEstimate(t_ns=frames[0].t0_ns, omega_rad_s=0.7 * rate)))
    for k, (frame, (x, y)) in enumerate(zip(frames, truth)):
        stars = centroider.process(frame).stars
        assert np.unique(_matched(stars, x, y, 1.5)[0]).size >= 0.9 * x.size, k
        assert k == 0 or centroider.last_mode == "tracked"
    assert abs(centroider._omega[0] / rate[0] - 1.0) < 0.02, centroider._omega / rate[0]


@pytest.mark.parametrize("rate_deg_s", [0.5, 6.0])
def test_tracking_a_sky_rendered_with_a_wider_psf_than_the_model_loses_no_star(rate_deg_s):
    """Stars rendered with a 1.4 px PSF (the fit's model: 1 px; cog has no model): tracked frames
    still find every star a full search of the frame finds, and no full search is needed."""
    ctx, frames, truth = _moving_sky(np.random.default_rng(12), rate_deg_s * PX_PER_S_PER_DEG_S, 6, psf_sigma_px=1.4)
    tracked = StreakCentroider(cog_below_px=3.0, psf_sigma_px=1.0)  # stated, not measured
    full = StreakCentroider(cog_below_px=3.0, track_windows=False, psf_sigma_px=1.0)
    tracked.setup(ctx)
    full.setup(ctx)
    for k, (frame, (x, y)) in enumerate(zip(frames, truth)):
        a, b = tracked.process(frame).stars, full.process(frame).stars
        assert k == 0 or tracked.last_mode == "tracked", k
        ja, jb = set(_matched(a, x, y, 1.5)[0]), set(_matched(b, x, y, 1.5)[0])
        assert jb <= ja and len(ja) >= 0.8 * x.size, (k, jb - ja, len(ja), x.size)


@pytest.mark.parametrize("psf_sigma_px", [1.4, 2.2])
def test_the_cold_search_measures_the_psf_and_finds_what_the_stated_width_finds(psf_sigma_px):
    """With no width stated the first cold search measures the camera's PSF from its stars and
    searches again with it: the same stars as a centroider told the true width, at the same
    positions within half their stated sigma (the measured width is off by a per cent or two)."""
    ctx, frames, truth = _moving_sky(np.random.default_rng(21), 6.0 * PX_PER_S_PER_DEG_S, 3, psf_sigma_px=psf_sigma_px)
    measured, stated = StreakCentroider(cog_below_px=3.0), StreakCentroider(cog_below_px=3.0, psf_sigma_px=psf_sigma_px)
    measured.setup(ctx)
    stated.setup(ctx)
    for k, (frame, (x, y)) in enumerate(zip(frames, truth)):
        a, b = measured.process(frame).stars, stated.process(frame).stars
        if k == 0:
            print(f"\nPSF {psf_sigma_px} px measured as {measured._psf:.3f} px")  # pytest -s
            assert abs(measured._psf / psf_sigma_px - 1) < 0.03, measured._psf
        ja, ia = _matched(a, x, y, 1.5)
        jb, ib = _matched(b, x, y, 1.5)
        assert set(ja) == set(jb), (k, set(jb) ^ set(ja))
        order_a, order_b = ia[np.argsort(ja)], ib[np.argsort(jb)]
        moved = np.hypot(a.x[order_a] - b.x[order_b], a.y[order_a] - b.y[order_b])
        assert np.all(moved < 0.5 * b.sigma_px[order_b]), (moved.max(), np.median(b.sigma_px))
