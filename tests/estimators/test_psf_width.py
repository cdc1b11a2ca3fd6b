"""The PSF width measured from star pixels rendered here, not by the project's simulator: static
Gaussian spots integrated exactly over each pixel (differences of the error function), on a
sloping background, with Poisson and read noise in integer ADU. A few windows hold two stars (a
blend) or none (a wrong position): the median over the stars must not follow them."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf

from rollingstar.estimators.centroiders.psf_width import measure_psf_sigma

SIZE = 256
READ_NOISE = 4.0


def _render(sigma: float, n: int, rng, blends: int = 0, empty: int = 0):
    """Image (ADU, gain 1) and the positions given to the measurement (n, 4: x, y, vx = vy = 0)."""
    x, y = rng.uniform(12, SIZE - 12, n), rng.uniform(12, SIZE - 12, n)
    flux = rng.uniform(3e3, 3e4, n)
    cols, rows = np.arange(SIZE), np.arange(SIZE)
    img = 20.0 + 0.05 * cols[None, :] + 0.03 * rows[:, None]
    drawn = [(x[k], y[k], flux[k]) for k in range(n) if k >= empty]
    drawn += [(x[k] + 2.5, y[k] - 1.5, 0.7 * flux[k]) for k in range(empty, empty + blends)]
    s2 = np.sqrt(2.0) * sigma
    for cx, cy, f in drawn:
        px = 0.5 * (erf((cols + 0.5 - cx) / s2) - erf((cols - 0.5 - cx) / s2))
        py = 0.5 * (erf((rows + 0.5 - cy) / s2) - erf((rows - 0.5 - cy) / s2))
        img = img + f * np.outer(py, px)
    noisy = rng.poisson(img) + rng.normal(0.0, READ_NOISE, img.shape)
    return np.rint(noisy).astype(np.uint16), np.column_stack([x, y, np.zeros(n), np.zeros(n)])


@pytest.mark.parametrize("sigma", [1.2, 1.8, 2.6])
def test_the_width_of_exactly_integrated_gaussian_spots(sigma):
    rng = np.random.default_rng(int(sigma * 10))
    image, pv = _render(sigma, 25, rng, blends=2, empty=2)
    noise2 = READ_NOISE**2 + 25.0  # read noise and the background's shot noise, about
    got = measure_psf_sigma(image, pv, exposure_s=0.05, line_delay_s=0.0, saturation=65535.0, noise2=noise2,
                            inv_gain=1.0)
    print(f"\nsigma {sigma} px measured as {got:.3f} px")  # pytest -s
    # 25 stars on 256 x 256 px: the windows of the widest PSF take in some of their neighbours' wings
    assert abs(got / sigma - 1) < 0.04, got


def test_too_few_stars_give_no_width():
    rng = np.random.default_rng(0)
    image, pv = _render(1.5, 2, rng)
    assert measure_psf_sigma(image, pv, 0.05, 0.0, 65535.0, 41.0, 1.0) is None
