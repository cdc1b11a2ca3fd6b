"""The width of a camera's point-spread function, measured from the pixels of its stars.

The smear model of :mod:`rollingstar.sensors.streak_model` draws a star as a Gaussian PSF of
sigma ``s`` swept along its image velocity over each row's exposure. ``s`` belongs to the camera
(focus, optics, pixel response), not to the simulator: a star tracker is often defocused on
purpose to 1.5-3 px, and a model 1 px wide against 2 px stars puts every star beyond a
chi-square screen (and the streak detector's matched filter then misses the faint ones).

:func:`measure_psf_sigma` tries widths in two passes, each on one set of windows (sized for the
widest width of the pass): a coarse grid from 0.4 to 5 px, then a fine one around the coarse
winner, on windows that fit it (the coarse windows, sized for 5 px, take in the light of
neighbouring stars, which widens the fit). For each width: every star's flux and background
exactly (the model is linear in both), then ``FIT_STEPS`` Gauss-Newton steps of its position,
flux and background (velocity held), and its reduced chi-square. The width with the lowest median
over the stars wins (robust to a blend or a wrong identification); in the fine pass a parabola in
``log s`` through the summed chi-square of the stars consistent there (reduced chi-square at most
``CONSISTENT_CHI2``) at it and its two neighbours refines it. A coarse winner at either end of
the grid is no measurement (the width lies beyond it). The sums are the compiled normal
equations the fits use (:mod:`rollingstar.estimators.centroiders.streak_kernel`).
"""
from __future__ import annotations

import numpy as np

from rollingstar.estimators.centroiders.streak_kernel import normal_equations, nuisance_equations
from rollingstar.sensors.streak_model import effective_sigma

COARSE_GRID = np.exp(np.linspace(np.log(0.4), np.log(5.0), 15))  # px, 20 % apart
FINE_STEPS = np.exp(np.linspace(np.log(0.75), np.log(1.3), 11))  # times the coarse width, 5.6 % apart
FIT_STEPS = 3  # Gauss-Newton steps of each star's position, flux and background per sigma
MIN_STARS = 3  # fewest usable stars a sigma is measured from
MIN_PIXELS = 12  # fewest live pixels of a star's window for it to count
CONSISTENT_CHI2 = 2.0  # reduced chi-square of the stars the parabola is fitted to
_FREE = [0, 1, 4, 5]  # of a star's (x, y, vx, vy, F, b): position, flux and background


def star_windows(pv: np.ndarray, exposure_s: float, psf_sigma_px: float, window_sigmas: float):
    """Equal-size windows covering every star's streak (``pv`` (n, >= 4): x, y, vx, vy at the
    star's own row's mid-exposure, px and px/s): ``row0, col0, nrows, ncols``."""
    half = window_sigmas * psf_sigma_px + 1.0
    ext_x = 0.5 * np.abs(pv[:, 2]) * exposure_s * 1.1 + half
    ext_y = 0.5 * np.abs(pv[:, 3]) * exposure_s * 1.1 + half
    nr = 2 * int(np.ceil(ext_y.max())) + 1
    nc = 2 * int(np.ceil(ext_x.max())) + 1
    row0 = np.rint(pv[:, 1]).astype(np.int64) - nr // 2
    col0 = np.rint(pv[:, 0]).astype(np.int64) - nc // 2
    return row0, col0, nr, nc


def measure_psf_sigma(image: np.ndarray, pv: np.ndarray, exposure_s: float, line_delay_s: float,
                      saturation: float, noise2: float, inv_gain: float, window_sigmas: float = 3.0,
                      narrow_end: bool = False) -> float | None:
    """The Gaussian PSF sigma (px) that explains the stars ``pv`` (module docstring), or None with
    fewer than ``MIN_STARS`` usable stars or a best width at an end of the coarse grid. ``noise2``:
    the background noise variance and ``inv_gain`` the shot-noise factor, in the image's units;
    pixels at ``saturation`` are left out. ``narrow_end``: a coarse winner at the grid's narrow end
    (an undersampled PSF, most of a star's light in one pixel) is refined like any other, down to
    ``0.75`` of it: the best model width for a fit, not a measurement of the PSF."""
    pv = np.ascontiguousarray(np.asarray(pv, dtype=float)[:, :4])
    if len(pv) < MIN_STARS:
        return None
    frame = (np.asarray(image), float(saturation), float(noise2), float(inv_gain), float(exposure_s),
             float(line_delay_s))
    coarse = _best_width(frame, pv, COARSE_GRID, window_sigmas, refine=False)
    if coarse is None or coarse == COARSE_GRID[-1] or (coarse == COARSE_GRID[0] and not narrow_end):
        return None
    return _best_width(frame, pv, coarse * FINE_STEPS, window_sigmas, refine=True)


def _best_width(frame, pv: np.ndarray, grid: np.ndarray, window_sigmas: float, refine: bool) -> float | None:
    """The width of ``grid`` whose reduced chi-square has the lowest median over the stars, on
    windows sized for the widest (refined by the parabola of the module docstring when ``refine``);
    None with fewer than ``MIN_STARS`` usable stars."""
    image, saturation, noise2, inv_gain, exposure_s, line_delay_s = frame
    row0, col0, nr, nc = star_windows(pv, exposure_s, float(grid[-1]), window_sigmas)
    args = (row0, col0, nr, nc, image, saturation, noise2, inv_gain)
    chi2 = np.full((grid.size, len(pv)), np.nan)
    used = np.zeros(len(pv))  # live pixels per window: the windows are the same for every width
    for i, sigma in enumerate(grid):
        tail = (effective_sigma(float(sigma)), exposure_s, line_delay_s)
        p = np.column_stack([pv, np.ones(len(pv)), np.zeros(len(pv))])
        N, h, _ = nuisance_equations(p, *args, *tail)
        with np.errstate(invalid="ignore", divide="ignore"):
            p[:, 4:] += np.linalg.solve(N + 1e-12 * np.eye(2), h[..., None])[..., 0]
        for _ in range(FIT_STEPS):
            M, g, _, _ = normal_equations(p, *args, *tail)
            with np.errstate(invalid="ignore", divide="ignore"):
                step = np.linalg.solve(M[:, _FREE][:, :, _FREE] + 1e-9 * np.eye(4), g[:, _FREE, None])[..., 0]
            p[:, _FREE] += np.where(np.isfinite(step), step, 0.0)
        _, _, c, used = normal_equations(p, *args, *tail)
        chi2[i] = np.where((used >= MIN_PIXELS) & (p[:, 4] > 0), c, np.nan)
    reduced = chi2 / np.maximum(used - len(_FREE), 1)
    usable = np.all(np.isfinite(reduced), axis=0)
    if np.count_nonzero(usable) < MIN_STARS:
        return None
    best = int(np.argmin(np.median(reduced[:, usable], axis=1)))
    consistent = usable & (reduced[best] <= CONSISTENT_CHI2)
    if not refine or best in (0, grid.size - 1) or np.count_nonzero(consistent) < MIN_STARS:
        return float(grid[best])
    u = np.log(grid[best - 1: best + 2])
    total = chi2[best - 1: best + 2][:, consistent].sum(axis=1)
    a, b, _ = np.polyfit(u - u[1], total, 2)
    if a <= 0:
        return float(grid[best])
    return float(np.exp(u[1] + np.clip(-b / (2.0 * a), u[0] - u[1], u[2] - u[1])))
