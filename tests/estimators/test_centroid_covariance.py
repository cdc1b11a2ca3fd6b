"""The centroiders' 2 x 2 position covariance (estimators/centroiders/covariance.py) against Monte
Carlo of smeared spots rendered here, independently of the project's simulator: a Gaussian PSF
(pixel-integrated with erf) swept along a straight line, Poisson photon noise and Gaussian read
noise, 12-bit ADC. Each case renders 64 spots per image at random sub-pixel positions (so the
pixel-phase error is part of the scatter, as for real stars) and compares the scatter of the
``cog`` centroids about the truth with the reported covariance, along and across the smear."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtr

from rollingstar.estimators.centroiders.cog import CogCentroider
from rollingstar.estimators.centroiders.covariance import spot_shape
from rollingstar.estimators.centroiders.fragments import fragment_groups
from rollingstar.estimators.centroiders.saturation import clipped_streak_variance
from rollingstar.estimators.data import FrameData, SensorContext
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.timing import DetectorTiming

N = 512  # image side
GRID = 64  # spot spacing
BIAS, BACKGROUND_E, READ_E, GAIN = 100.0, 2.4, 5.0, 1.0  # ADU, e-, e-, e-/ADU (the he2021a detector)


def _render(cx, cy, flux_e, length, theta, psf, rng) -> np.ndarray:
    """uint16 image of straight smears (centre, length, angle per spot): the mean signal is the PSF
    swept along the line (midpoint rule, 10 samples per px), then Poisson, read noise, ADC."""
    mean = np.full((N, N), BACKGROUND_E)
    K = max(8, int(np.ceil(length * 10)) + 1)
    t = (np.arange(K) + 0.5) / K - 0.5
    half = int(np.ceil(length / 2 + 6 * psf + 2))
    for x0, y0, th in zip(cx, cy, theta):
        xs, ys = x0 + t * length * np.cos(th), y0 + t * length * np.sin(th)
        r0, c0 = int(round(y0)) - half, int(round(x0)) - half
        edges = np.arange(-0.5, 2 * half + 1.0)
        py = np.diff(ndtr((r0 + edges[None, :] - ys[:, None]) / psf), axis=1)
        px = np.diff(ndtr((c0 + edges[None, :] - xs[:, None]) / psf), axis=1)
        mean[r0:r0 + 2 * half + 1, c0:c0 + 2 * half + 1] += flux_e / K * py.T @ px
    electrons = rng.poisson(mean) + rng.normal(0.0, READ_E, mean.shape)
    return np.clip(np.rint(electrons / GAIN + BIAS), 0, 4095).astype(np.uint16)


def _cog() -> CogCentroider:
    cam = PinholeCamera(focal_length_m=0.02409, pixel_size_m=5.5e-6, width=N, height=N)
    timing = DetectorTiming(mode="global", exposure_ns=44_900_000, line_delay_ns=0, rows=N)
    cog = CogCentroider()
    cog.setup(SensorContext(camera=cam, timing=timing, catalog=None, bit_depth=12, gain_e_per_adu=GAIN))
    return cog


def _monte_carlo(flux_e, length, theta, psf=1.0, images=10, seed=0):
    """Errors (n, 2) of the centroids about the truth, their reported covariances (n, 2, 2) and
    isotropic sigmas, for spots that were detected as one spot each."""
    rng = np.random.default_rng(seed)
    cog = _cog()
    g = np.arange(GRID // 2, N - GRID // 2 + 1, GRID, dtype=float)
    gx, gy = (a.ravel() for a in np.meshgrid(g, g))
    err, cov, sig = [], [], []
    for _ in range(images):
        cx, cy = gx + rng.uniform(-0.5, 0.5, gx.size), gy + rng.uniform(-0.5, 0.5, gx.size)
        img = _render(cx, cy, flux_e, length, np.full(gx.size, theta), psf, rng)
        st = cog.process(FrameData(index=0, t0_ns=0, image=img)).stars
        j = np.argmin((st.x[:, None] - cx) ** 2 + (st.y[:, None] - cy) ** 2, axis=1)
        one = np.bincount(j, minlength=gx.size)[j] == 1
        err.append(np.column_stack([st.x - cx[j], st.y - cy[j]])[one])
        cov.append(np.stack([np.stack([st.cov_xx, st.cov_xy], -1), np.stack([st.cov_xy, st.cov_yy], -1)], -2)[one])
        sig.append(st.sigma_px[one])
    return np.concatenate(err), np.concatenate(cov), np.concatenate(sig)


# flux (e-): he2021a's magnitude 5 and 6 stars in 44.9 ms; length: 3 and 6 deg/s on that sensor
CASES = {
    "at rest, faint": (3600.0, 0.0, 0.0),
    "diagonal smear": (9000.0, 12.0, np.pi / 4),
    "long faint smear along a pixel axis": (3600.0, 20.0, 0.0),
    "long faint smear, tilted": (3600.0, 20.0, 0.35),
}


@pytest.mark.parametrize("case", list(CASES))
def test_cog_covariance_matches_the_scatter_along_and_across_the_smear(case):
    """chi2/dof of the errors rotated into the smear's frame, with the reported covariance rotated
    the same way, is 1 within 4 standard errors of the mean on both axes (n ~ 640 spots; the
    standard error from the sample, std(z^2) / sqrt(n): about sqrt(2 / n) = 0.056 for Gaussian
    errors, up to 0.07 with the pixel-phase errors of faint smears). Over five seeds the four
    cases measured along / across 0.87-1.09 / 0.94-1.09 (rest and diagonal), 0.93-1.04 / 1.00-1.15
    (faint, along a pixel axis) and 0.80-1.00 / 0.89-1.00 (faint, tilted). The isotropic sigma_px
    cannot do this for a long smear (asserted: its chi2/dof along the smear is over 1.5)."""
    flux, length, theta = CASES[case]
    err, cov, sig = _monte_carlo(flux, length, theta, seed=len(case))
    n = err.shape[0]
    assert n > 600
    u, v = np.array([np.cos(theta), np.sin(theta)]), np.array([-np.sin(theta), np.cos(theta)])
    for name, axis in (("along", u), ("across", v)):
        z2 = (err @ axis) ** 2 / np.einsum("i,nij,j->n", axis, cov, axis)
        chi2, tol = float(np.mean(z2)), 4.0 * float(np.std(z2)) / np.sqrt(n)
        assert tol < 0.35 and abs(chi2 - 1.0) < tol, f"{case}: chi2/dof {name} {chi2:.3f} (n {n}, tolerance {tol:.3f})"
    if length >= 12:
        assert np.mean((err @ u) ** 2 / sig**2) > 1.5


def test_the_correlation_of_a_diagonal_smear_has_the_sign_and_size_of_the_scatter():
    """A smear along (1, 1)/sqrt(2) (down and to the right on the image): both the reported cov_xy
    and the Monte Carlo mean of e_x e_y are positive, and agree within 4 standard errors of the
    sample mean; the mirrored smear gives the opposite sign."""
    for theta, sign in ((np.pi / 4, 1.0), (-np.pi / 4, -1.0)):
        err, cov, _ = _monte_carlo(9000.0, 12.0, theta, seed=5)
        exy = err[:, 0] * err[:, 1]
        reported = cov[:, 0, 1]
        assert np.all(sign * reported > 0)
        se = np.sqrt(np.mean(cov[:, 0, 0] * cov[:, 1, 1] + reported**2) / err.shape[0])
        assert sign * exy.mean() > 4 * se  # the scatter itself is correlated
        assert abs(exy.mean() - reported.mean()) < 4 * se


def test_spot_shape_measures_a_smear():
    """Length, width, axis and brightness of a bright rendered smear from its moments (the
    inputs of the mask term): a line of length L blurred by sigma has variance L^2 / 12 + s^2
    along (+ 1/12 for the pixel) and s^2 (+ 1/12) across."""
    rng = np.random.default_rng(0)
    img = _render([256.3], [255.8], 1e5, 16.0, [0.5], 1.0, rng).astype(float) - BIAS - BACKGROUND_E  # unsaturated
    yy, xx = np.mgrid[0:N, 0:N]
    m = (img > 20) & (np.hypot(xx - 256.3, yy - 255.8) < 20)  # the spot, without noise pixels elsewhere
    w = np.where(m, img, 0.0)
    F = w.sum()
    x0, y0 = (w * xx).sum() / F, (w * yy).sum() / F
    mom = np.array([[(w * (xx - x0) ** 2).sum()], [(w * (xx - x0) * (yy - y0)).sum()], [(w * (yy - y0) ** 2).sum()]]) / F
    shape = spot_shape(mom, np.array([F]), 20.0)
    assert shape.length[0] == pytest.approx(16.0, rel=0.03)
    assert shape.width[0] == pytest.approx(np.sqrt(1.0 + 1 / 12), rel=0.05)
    assert abs(shape.ux[0] * np.sin(0.5) - shape.uy[0] * np.cos(0.5)) < 0.01  # the axis is the smear's
    peak = 1e5 / 16.0 / np.sqrt(2 * np.pi * (1.0 + 1 / 12))
    assert shape.rho[0] == pytest.approx(peak / 20.0, rel=0.05)


@pytest.mark.parametrize("sigma", [1.0, 1.5, 2.0])
def test_clipped_ridge_model_against_noise_free_clipped_profiles(sigma):
    """The 1-D clipped-ridge term (saturation.clipped_streak_variance) against the exact phase RMS
    of the CoG of a clipped, pixel-integrated Gaussian profile (64 phases). The exact RMS swings
    with the peak level (a plateau an integer number of pixels wide has none), which a star's
    measured pixels cannot resolve; the model is its average. Over peaks log-uniform in 1.2-3,
    3-10 and 10-30 x the saturation level, the model's RMS is within 0.7-1.4 x the exact one
    (measured 0.76-1.18 for sigma 1-2 px; 0.63-0.81 for sigma 0.8 px, not asserted). Zero when
    nothing clips."""
    s_d = 4000.0
    phases = (np.arange(64) + 0.5) / 64 - 0.5
    i = np.arange(-14, 15)
    frac = ndtr(0.5 / sigma) - ndtr(-0.5 / sigma)
    for lo, hi in ((1.2, 3.0), (3.0, 10.0), (10.0, 30.0)):
        exact, model = [], []
        for peak_over_s in np.exp(np.linspace(np.log(lo), np.log(hi), 40)):
            v = peak_over_s * s_d / frac * (ndtr((i[None] + 0.5 - phases[:, None]) / sigma)
                                            - ndtr((i[None] - 0.5 - phases[:, None]) / sigma))
            c = np.minimum(v, s_d)
            e = (c * (i[None] - phases[:, None])).sum(1) / c.sum(1)
            exact.append(np.mean(e**2))
            model.append(clipped_streak_variance(np.array([c.sum(1).mean()]), np.array([(v >= s_d).sum(1).mean()]), s_d)[0])
        ratio = np.sqrt(np.mean(model) / np.mean(exact))
        assert 0.7 < ratio < 1.4, (lo, hi, ratio)
    assert clipped_streak_variance(np.array([1e4]), np.array([0.0]), s_d)[0] == 0.0


def test_pieces_of_a_broken_smear_are_grouped_and_widened():
    """A 30 px smear with its middle 4 px below the threshold comes out as two spots: they are
    grouped, each one's covariance along the smear grows by its offset from the pair's centre
    (which is the star's position), and the frame is flagged; two round stars the same distance
    apart are not grouped."""
    rng = np.random.default_rng(3)
    cog = _cog()
    pieces = _render([247.5, 264.5], [200.3, 200.3], 4000.0, 13.0, [0.0, 0.0], 1.0, rng)
    out = cog.process(FrameData(index=0, t0_ns=0, image=pieces))
    assert out.stars.n == 2 and "fragmented_stars:2" in out.flags
    centre = np.average(out.stars.x, weights=out.stars.flux)
    assert abs(centre - 256.0) < 0.3
    assert np.all(np.sqrt(out.stars.cov_xx) > 0.9 * np.abs(out.stars.x - centre))
    assert np.all(out.stars.cov_yy < 0.01)  # across is untouched
    round_stars = _render([247.5, 264.5], [200.3, 200.3], 4000.0, 0.0, [0.0, 0.0], 1.0, rng)
    out = cog.process(FrameData(index=0, t0_ns=0, image=round_stars))
    assert out.stars.n == 2 and not any(f.startswith("fragmented") for f in out.flags)
    assert np.all(out.stars.cov_xx < 0.01)
    shape = spot_shape(np.array([[10.0, 0.1], [0.0, 0.0], [1.0, 1.0]]), np.array([1e3, 1e3]), 10.0)
    assert (fragment_groups(np.array([0.0, 40.0]), np.array([0.0, 0.0]), shape) == -1).all()  # too far apart


@pytest.mark.parametrize("theta", [0.0, 0.3])
def test_saturated_smears_have_a_covariance_of_the_right_size(theta):
    """A magnitude-1.3 star smeared 20 px (peak ~1.3 x the 12-bit saturation level on a ~1.5 px
    wide ridge): the clipped ridge's sampling error across (and its ends' along) the smear are
    phase averages, so the chi2/dof is only asserted within 0.3-2.5 on both axes (measured along
    / across, 256 spots: 0.86 / 1.88 along a pixel axis, 0.91 / 0.42 tilted; the round-plateau term alone gave
    10 across along a pixel axis)."""
    err, cov, _ = _monte_carlo(2.7e5, 20.0, theta, images=4, seed=9)
    u, v = np.array([np.cos(theta), np.sin(theta)]), np.array([-np.sin(theta), np.cos(theta)])
    for axis in (u, v):
        chi2 = np.mean((err @ axis) ** 2 / np.einsum("i,nij,j->n", axis, cov, axis))
        assert 0.3 < chi2 < 2.5, (theta, axis, chi2)
