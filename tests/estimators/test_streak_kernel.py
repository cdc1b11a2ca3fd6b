"""The compiled normal equations of the streak fit against sums written out from the smear model, the
flux-and-background kernel against their block, and the fused kernel (flux and background fitted,
then the normal equations there) against the two run one after the other."""
import numpy as np
import pytest

from rollingstar.estimators.centroiders.streak_kernel import (
    normal_equations,
    normal_equations_at_fitted_nuisance,
    nuisance_equations,
)
from rollingstar.sensors.streak_model import effective_sigma, streak_mu_jac

PSF, EXPOSURE, LD = 1.0, 0.0449, 43.9e-6
NOISE2, INV_GAIN, SAT = 25.0, 0.5, 1000.0


@pytest.fixture(scope="module")
def case():
    """Two stars (a 30 px streak, a round spot), one near saturation, on a noisy frame."""
    rng = np.random.default_rng(4)
    p = np.array([[60.3, 70.7, 400.0, -600.0, 30000.0, 100.0], [150.2, 40.6, 0.0, 0.0, 9000.0, 102.0]])
    row0, col0, nr, nc = np.array([45, 28]), np.array([45, 138]), 50, 26
    image = rng.normal(100.0, 5.0, (200, 200))
    mu, _ = streak_mu_jac(p, row0, col0, nr, nc, PSF, EXPOSURE, LD)
    for k in range(2):
        image[row0[k]:row0[k] + nr, col0[k]:col0[k] + nc] += mu[k] - p[k, 5]
    image = np.clip(np.rint(image), 0, SAT).astype(np.uint16)
    return p * np.array([1.0, 1.0, 1.0, 1.0, 0.97, 1.0]), row0, col0, nr, nc, image  # evaluated a little off


def _written_out(p, row0, col0, nr, nc, image):
    """``J^T W J``, ``J^T W r``, chi-square and pixels used from the model's Jacobian, pixel by pixel."""
    mu, jac = streak_mu_jac(p, row0, col0, nr, nc, PSF, EXPOSURE, LD)
    out = []
    for k in range(p.shape[0]):
        data = image[row0[k]:row0[k] + nr, col0[k]:col0[k] + nc].astype(float).reshape(-1)
        m, J = mu[k].reshape(-1), jac[k].reshape(6, -1)
        live = data < SAT
        w = 1.0 / (NOISE2 + np.maximum(m - p[k, 5], 0.0) * INV_GAIN)
        r = data - m
        W = np.where(live, w, 0.0)
        out.append(((J * W) @ J.T, (J * W) @ r, np.sum(W * r * r), int(live.sum())))
    return out


def test_the_normal_equations_are_the_models_sums(case):
    p, row0, col0, nr, nc, image = case
    H, g, chi2, used = normal_equations(p, row0, col0, nr, nc, image, SAT, NOISE2, INV_GAIN, effective_sigma(PSF),
                                        EXPOSURE, LD)
    for k, (Hk, gk, ck, uk) in enumerate(_written_out(p, row0, col0, nr, nc, image)):
        scale = np.sqrt(np.outer(np.diag(Hk), np.diag(Hk)))
        np.testing.assert_allclose(H[k] / scale, Hk / scale, atol=1e-6)
        np.testing.assert_allclose(g[k], gk, rtol=1e-6, atol=1e-6 * np.abs(gk).max())
        assert chi2[k] == pytest.approx(ck, rel=1e-6) and used[k] == uk
    assert used[1] < nr * nc == used[0]  # the round star's saturated core is left out, the streak has none


def test_the_nuisance_kernel_is_the_flux_and_background_block(case):
    p, row0, col0, nr, nc, image = case
    args = (p, row0, col0, nr, nc, image, SAT, NOISE2, INV_GAIN, effective_sigma(PSF), EXPOSURE, LD)
    H, g, _, used = normal_equations(*args)
    N, h, used_n = nuisance_equations(*args)
    np.testing.assert_allclose(N, H[:, 4:, 4:], rtol=1e-9)
    np.testing.assert_allclose(h, g[:, 4:], rtol=1e-9, atol=1e-9 * np.abs(h).max())
    assert np.array_equal(used, used_n)


def test_the_fused_kernel_fits_flux_and_background_then_sums_there(case):
    p, row0, col0, nr, nc, image = case
    tail = (row0, col0, nr, nc, image, SAT, NOISE2, INV_GAIN, effective_sigma(PSF), EXPOSURE, LD)
    start = np.column_stack([p[:, :4], np.ones(len(p)), np.zeros(len(p))])
    N, h, used = nuisance_equations(start, *tail)
    nuis = start[:, 4:] + np.linalg.solve(N + 1e-12 * np.eye(2), h[..., None])[..., 0]
    H, g, chi2, used_h = normal_equations(np.column_stack([p[:, :4], nuis]), *tail)
    got = normal_equations_at_fitted_nuisance(np.ascontiguousarray(p[:, :4]), *tail)
    np.testing.assert_allclose(got[0], nuis, rtol=1e-10)
    np.testing.assert_allclose(got[0][:, 0], p[:, 4] / 0.97, rtol=0.02)  # the flux the image was drawn with
    np.testing.assert_allclose(got[1], H, rtol=1e-9, atol=1e-9 * np.abs(H).max())
    np.testing.assert_allclose(got[2], g, rtol=1e-9, atol=1e-9 * np.abs(g).max())
    np.testing.assert_allclose(got[3], chi2, rtol=1e-9)
    assert np.array_equal(got[4], used) and np.array_equal(used, used_h)
