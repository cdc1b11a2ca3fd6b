"""The fast forms in QUEST, the star-motion KF and the centroid covariance compute the same mathematics as
the textbook forms.

- QUEST's degeneracy test (Sylvester's criterion on ``info - t I``) decides as the smallest
  eigenvalue of ``info`` against ``t`` does, on frames spanning the threshold;
- QUEST's written-out quaternion product and canonical sign equal scipy's ``Rotation`` composition
  and ``as_quat(canonical=True)``, including the ``w = 0`` cases;
- the KF predict/update equal the matrix forms ``F X``, ``F P F^T + q G G^T`` and the Joseph form
  ``(I - K H) P (I - K H)^T + r K K^T`` with ``K = P H^T (H P H^T + r I)^-1``;
- the compiled edge-bias fixed point equals its vectorised numpy form, and the clipped-spot
  sigma with its per-count cache equals the Bessel sums evaluated spot by spot;
- the compiled rotations of ``sensors/so3.py`` equal scipy's ``Rotation`` on every broadcast
  shape, and the compiled robust noise sigma equals its definition written with numpy.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.wahba import (
    _FLIP_QUATS,
    _canonical,
    _quat_product,
    quest,
)
from rollingstar.estimators.filters.kf_cv import (
    H,
    cv_process_noise,
    cv_transition,
    kf_cv_predict,
    kf_cv_update,
)
from rollingstar.estimators.filters.kf_cv_kernel import kf_cv_step_kernel


@pytest.mark.parametrize("tol", [1e-10, 1e-6, 1e-2])
def test_degeneracy_matches_smallest_eigenvalue(tol):
    rng = np.random.default_rng(5)
    F, N = 4000, 4
    base = rng.normal(size=(F, 1, 3)) + [0.0, 0.0, 20.0]
    spread = 10 ** rng.uniform(-9, 1.5, F)[:, None, None]
    obs = base + spread * rng.normal(size=(F, N, 3))
    obs[:50] = base[:50]  # exactly parallel
    obs[50:100, 1] = -base[50:100, 0]  # anti-parallel
    obs /= np.linalg.norm(obs, axis=-1, keepdims=True)
    res = quest(obs, obs, degenerate_tol=tol)
    info = np.eye(3) - np.einsum("fni,fnj->fij", obs, obs) / N  # normalised weights (1/N each)
    expected_degenerate = np.linalg.eigvalsh(info)[:, 0] <= tol * np.trace(info, axis1=1, axis2=2)
    assert 100 < expected_degenerate.sum() < F - 100  # the threshold is straddled
    np.testing.assert_array_equal(~res.valid, expected_degenerate)


def test_quaternion_product_matches_scipy():
    q = Rotation.random(500, random_state=2).as_quat()
    q[:20, 3] = 0.0  # w = 0: the canonical sign falls to x, then y, then z
    q[:20] /= np.linalg.norm(q[:20], axis=1, keepdims=True)
    q[5] = [0.0, 0.0, -1.0, 0.0]
    q[6] = [0.0, -1.0, 0.0, 0.0]
    for flip in _FLIP_QUATS:
        p = np.tile(flip, (len(q), 1))
        ours = _canonical(_quat_product(p, q))
        ref = (Rotation.from_quat(p) * Rotation.from_quat(q)).as_quat(canonical=True)
        np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-15)


def _kf_inputs(seed: int, n: int):
    """Random states, symmetric positive-definite covariances, steps and measurements of ``n`` tracks."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, 4)) * 100
    M = rng.normal(size=(n, 4, 4))
    P = M @ np.swapaxes(M, 1, 2) + np.eye(4)
    return X, P, rng.uniform(0.01, 1.0, n), rng.normal(size=(n, 2)) * 100


def test_kf_predict_update_match_matrix_forms():
    q, r = 0.3, 0.05
    X, P, dt, z = _kf_inputs(seed=0, n=30)
    F, _ = cv_transition(dt)
    Xp, Pp = kf_cv_predict(X, P, dt, q)
    np.testing.assert_allclose(Xp, np.einsum("nij,nj->ni", F, X), rtol=1e-14, atol=1e-12)
    np.testing.assert_allclose(Pp, F @ P @ np.swapaxes(F, 1, 2) + cv_process_noise(dt, q), rtol=1e-13)
    Xu, Pu = kf_cv_update(X, P, z, r)
    S = H @ P @ H.T + r * np.eye(2)
    K = P @ H.T @ np.linalg.inv(S)
    IKH = np.eye(4) - K @ H
    np.testing.assert_allclose(Xu, X + np.einsum("nij,nj->ni", K, z - X @ H.T), rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(Pu, IKH @ P @ np.swapaxes(IKH, 1, 2) + r * K @ np.swapaxes(K, 1, 2), rtol=1e-10, atol=1e-12)
    assert np.array_equal(P, _kf_inputs(seed=0, n=30)[1])  # inputs not mutated


def test_kf_kernel_step_matches_numpy_reference():
    """The compiled predict + update equals kf_cv_predict then kf_cv_update (the filter's path)."""
    q, r = 0.7, 0.02
    X, P, dt, z = _kf_inputs(seed=3, n=25)
    Xr, Pr = kf_cv_update(*kf_cv_predict(X, P, dt, q), z, r)
    Xk, Pk = np.empty_like(X), np.empty_like(P)
    kf_cv_step_kernel(X, P, z, dt, q, r, Xk, Pk)
    np.testing.assert_allclose(Xk, Xr, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(Pk, Pr, rtol=1e-11, atol=1e-12)
    kf_cv_step_kernel(X, P, z, dt, q, r, X, P)  # in place (aliased output) gives the same
    np.testing.assert_array_equal(X, Xk)
    np.testing.assert_array_equal(P, Pk)


def test_flip_gammas_equal_each_variants_own_gamma():
    """The four sequential-rotation gammas computed from variant 0 (adjugate diagonal) equal each
    variant's own ``(lambda + sigma) alpha - Delta``, on random attitudes including ones near
    180 degrees about each axis (where variant 0's gamma vanishes)."""
    from rollingstar.estimators.attitude.wahba import _FLIPS, _flip_gammas, _quest_terms

    rng = np.random.default_rng(8)
    F, N = 400, 6
    rots = Rotation.random(F, random_state=3)
    rots = Rotation.from_rotvec(np.concatenate([rots.as_rotvec()[:100],
                                                np.pi * np.eye(3)[rng.integers(0, 3, 300)] + rng.normal(0, 1e-3, (300, 3))]))
    obs = rng.normal(size=(F, N, 3)) + [0.0, 0.0, 5.0]
    obs /= np.linalg.norm(obs, axis=-1, keepdims=True)
    ref = np.einsum("fij,fnj->fni", rots.as_matrix(), obs)
    B0 = np.einsum("fni,fnj->fij", obs, ref) / N
    lam = np.ones(F)  # noise-free: lambda_max = sum a_i = 1
    S0, Z0, s0, d0, k0, _, _ = _quest_terms(B0)
    g = _flip_gammas(S0, Z0, s0, d0, k0, lam)
    for v in range(4):
        _, _, sv, dv, kv, _, _ = _quest_terms(B0 * _FLIPS[v])
        own = (lam + sv) * (lam**2 - sv**2 + kv) - dv
        np.testing.assert_allclose(g[:, v], own, rtol=1e-9, atol=1e-12)
    assert (np.argmax(np.abs(g), axis=1) != 0).sum() >= 250  # the near-180 frames pick another variant


def _edge_bias_numpy(x, y, flux, peak, shape, iterations):
    """The edge-bias fixed point of :mod:`rollingstar.estimators.centroiders.edge` written as its
    module docstring states it, vectorised over the spots, every spot iterated (no margin test)."""
    from scipy.special import ndtr

    H, W = shape
    n = np.concatenate([np.full(x.size, float(W)), np.full(y.size, float(H))])
    meas = np.concatenate([x, y])
    width_sq = np.tile(flux / (2.0 * np.pi * peak), 2)

    def shift(mu, s):
        a, b = (-0.5 - mu) / s, (n - 0.5 - mu) / s
        T = ndtr(b) - ndtr(a)
        return s * (np.exp(-0.5 * a * a) - np.exp(-0.5 * b * b)) / (np.sqrt(2.0 * np.pi) * T), T

    s = np.sqrt(width_sq)
    mu = np.clip(meas, -0.5, n - 0.5)
    k = x.size
    for _ in range(iterations):
        d, T = shift(mu, s)
        mu = np.clip(meas - d, -0.5, n - 0.5)
        s = np.sqrt(width_sq / np.tile(T[:k] * T[k:], 2))
    return shift(mu, s)


@pytest.mark.parametrize("iterations", [0, 1, 20, 200])
def test_compiled_edge_fixed_point_matches_the_numpy_form(iterations):
    from rollingstar.estimators.centroiders.edge import _fixed_point

    rng = np.random.default_rng(iterations)
    k = 300
    x, y = rng.uniform(-1.0, 12.0, k), rng.uniform(-1.0, 1030.0, k)
    flux = rng.uniform(100.0, 1e5, k)
    peak = flux / (2.0 * np.pi * rng.uniform(0.5, 3.0, k) ** 2)
    d, T = _fixed_point(np.concatenate([x, y]), flux / (2.0 * np.pi * peak), 1024.0, 1024.0, iterations)
    d_ref, T_ref = _edge_bias_numpy(x, y, flux, peak, (1024, 1024), iterations)
    np.testing.assert_allclose(d, d_ref, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(T, T_ref, rtol=1e-12)


def test_cached_plateau_sums_match_the_bessel_sums_spot_by_spot():
    """:func:`clipped_cog_sigma_px` with its per-count cache equals the module docstring's sum
    evaluated for every spot (including counts that are not whole numbers)."""
    from scipy.special import j0, j1

    from rollingstar.estimators.centroiders import saturation as sat

    rng = np.random.default_rng(3)
    F, n_sat, S = rng.uniform(1e3, 1e6, 400), rng.integers(0, 300, 400).astype(float), rng.uniform(100.0, 4000.0, 400)
    n_sat[:20] += rng.uniform(0.1, 0.9, 20)
    got = sat.clipped_cog_sigma_px(F, n_sat, S)
    ok = n_sat > 0
    Fs, n, Ss = F[ok], n_sat[ok], S[ok]
    r0 = np.sqrt(n / np.pi)
    slope = 2.0 * (n * Ss / np.maximum(Fs - n * Ss, Ss)) * Ss / r0
    r = np.maximum(r0[:, None] + sat._RADIUS_OFFSETS[None], 0.05)[:, :, None]
    kk = 2.0 * np.pi * sat._RHO[None, None]
    z = kk * r
    dC = 4.0 * np.pi**2 * slope[:, None, None] * r * (r * j1(z) / kk**2 - 4.0 * (2.0 * j1(z) / z - j0(z)) / kk**3)
    ref = np.sqrt(np.mean(np.sum(sat._AXIS_WEIGHT * dC**2, axis=2), axis=1)) / (2.0 * np.pi * Fs)
    np.testing.assert_allclose(got[ok], ref, rtol=1e-12)
    assert np.all(got[~ok] == 0.0)


def test_wahba_by_svd_matches_scipy_align_vectors():
    """:func:`rollingstar.sensors.so3.wahba` equals ``Rotation.align_vectors`` (weighted), for
    noisy pairs and for pairs whose best orthogonal fit is a reflection (the sign correction)."""
    from rollingstar.sensors.so3 import wahba

    rng = np.random.default_rng(7)
    for k in range(50):
        n = int(rng.integers(3, 60))
        body = rng.normal(size=(n, 3))
        body /= np.linalg.norm(body, axis=1, keepdims=True)
        R = Rotation.random(random_state=k)
        ref = R.apply(body) + 10 ** rng.uniform(-8, -1) * rng.normal(size=(n, 3))
        if k % 5 == 0:
            ref[:, 2] *= -1.0  # a mirrored sky: no rotation maps it, the fit must stay a rotation
        w = rng.uniform(0.1, 5.0, n)
        expected, _ = Rotation.align_vectors(ref, body, weights=w)
        got = wahba(ref, body, w)
        np.testing.assert_allclose(got, expected.as_matrix(), atol=1e-10)
        assert np.isclose(np.linalg.det(got), 1.0)


@pytest.mark.parametrize("shapes", [((40, 3), (40, 3)), ((3,), (40, 3)), ((40, 3), (3,)), ((5, 7, 3), (7, 3)),
                                    ((3,), (3,)), ((0, 3), (0, 3))])
def test_compiled_rotations_match_scipy_on_every_broadcast_shape(shapes):
    from rollingstar.sensors.so3 import rotate_at_rate, rotate_by_rotvec

    rng = np.random.default_rng(11)
    rotvec = rng.normal(size=shapes[0]) * rng.choice([0.0, 1e-12, 1e-5, 1.0, 3.0], size=shapes[0][:-1] + (1,))
    v = rng.normal(size=shapes[1])
    out = rotate_by_rotvec(rotvec, v)
    shape = np.broadcast_shapes(*shapes)
    r, w = (np.array(np.broadcast_to(a, shape)).reshape(-1, 3) for a in (rotvec, v))  # scipy wants writable arrays
    expected = Rotation.from_rotvec(r).apply(w) if len(r) else w
    assert out.shape == shape
    np.testing.assert_allclose(out.reshape(-1, 3), expected, rtol=0, atol=1e-14)
    if shapes[1] == (40, 3):
        omega, dt = rng.normal(size=3), rng.normal(size=40)
        np.testing.assert_allclose(rotate_at_rate(omega, v, dt), Rotation.from_rotvec(omega * dt[:, None]).apply(v),
                                   rtol=0, atol=1e-14)
        np.testing.assert_allclose(rotate_at_rate(omega, v, 0.3), Rotation.from_rotvec(0.3 * omega).apply(v),
                                   rtol=0, atol=1e-14)
        assert rotate_at_rate(np.zeros(3), v, dt) is v


def _robust_sigma_numpy(r):
    """The definition of ``cog.robust_sigma`` (its docstring) written with numpy."""
    med = np.median(r)
    dev = np.abs(r - med)
    s0 = 1.482602218505602 * np.median(dev)
    if s0 <= 0:
        return max(0.0, np.percentile(r, 84.134) - med)
    s1 = np.std(r[dev < 5.0 * s0])
    if s1 <= 0:
        return s0
    return np.sqrt(np.mean((r[dev < 3.0 * s1] - med) ** 2)) / 0.98658


def test_compiled_robust_sigma_matches_its_definition():
    from rollingstar.estimators.centroiders.cog import robust_sigma

    rng = np.random.default_rng(4)
    for k in range(120):
        n = int(rng.integers(1, 9000))
        r = rng.poisson(rng.uniform(0.05, 300), n).astype(float) + (rng.normal(0, 2, n) if k % 2 else 0.0)
        if k % 5 == 0:
            r[: n // 2 + 1] = 0.0  # more than half one value: the one-sided branch
        if k % 7 == 0:
            r[0] = np.inf  # a hot pixel read as infinity stays out of the clipped moments
        assert robust_sigma(r) == pytest.approx(_robust_sigma_numpy(r), rel=1e-12, abs=1e-300)
    assert np.isnan(robust_sigma(np.array([1.0, np.nan, 2.0]))) and np.isnan(robust_sigma(np.zeros(0)))


def test_compiled_check_rate_fit_matches_least_squares_on_the_stacked_rows():
    from rollingstar.estimators.identifiers.integrity import fit_rate
    from rollingstar.sensors.so3 import skew

    rng = np.random.default_rng(9)
    n = 30
    body = np.column_stack([rng.normal(0, 0.1, (n, 2)), np.ones(n)])
    body /= np.linalg.norm(body, axis=1, keepdims=True)
    dt, omega, R = rng.uniform(-0.03, 0.03, n), np.radians([4.0, -7.0, 2.0]), Rotation.random(random_state=9)
    ref = R.apply(Rotation.from_rotvec(omega * dt[:, None]).apply(body)) + rng.normal(0, 1e-5, (n, 3))
    rw = rng.uniform(0.5, 2.0, n)
    start = (R * Rotation.from_rotvec([1e-3, -2e-3, 5e-4])).as_matrix()
    phi = np.zeros((n, 3))
    total = np.zeros(3)
    for _ in range(2):  # the two linearised steps, each by least squares on the stacked rows
        w = Rotation.from_rotvec(phi).inv().apply(ref @ start)
        S = skew(w)
        A = np.concatenate([S, S * dt[:, None, None]], axis=2).reshape(-1, 6) * np.repeat(rw, 3)[:, None]
        sol = np.linalg.lstsq(A, (body - w).reshape(-1) * np.repeat(rw, 3), rcond=None)[0]
        phi, total = phi + sol[:3] + dt[:, None] * sol[3:], total + sol[3:]
    got_phi, got_omega = fit_rate(start, body, ref, dt, rw)
    np.testing.assert_allclose(got_phi, phi, rtol=0, atol=1e-13)
    np.testing.assert_allclose(got_omega, total, rtol=0, atol=1e-11)
    np.testing.assert_allclose(got_omega, omega, rtol=0, atol=2e-3)  # and it finds the rate


def test_compiled_check_rate_fit_is_the_minimum_norm_solution_when_the_stars_leave_it_undetermined():
    from rollingstar.estimators.identifiers.integrity import fit_rate
    from rollingstar.sensors.so3 import skew

    rng = np.random.default_rng(9)
    n = 5
    body = np.column_stack([rng.normal(0, 0.1, (n, 2)), np.ones(n)])
    body /= np.linalg.norm(body, axis=1, keepdims=True)
    dt = np.array([-0.01, -0.01, -0.01, -0.01, 0.02])
    R = Rotation.random(random_state=9)
    ref = R.apply(Rotation.from_rotvec(np.radians([4.0, -7.0, 2.0]) * dt[:, None]).apply(body))
    rw = np.r_[np.ones(4), 0.0]  # the one star at its own time weighs nothing: the rate is undetermined
    w = ref @ R.as_matrix()
    S = skew(w)
    A = np.concatenate([S, S * dt[:, None, None]], axis=2).reshape(-1, 6) * np.repeat(rw, 3)[:, None]
    sol = np.linalg.lstsq(A, (body - w).reshape(-1) * np.repeat(rw, 3), rcond=None)[0]
    _, got = fit_rate(R.as_matrix(), body, ref, dt, rw, steps=1)
    np.testing.assert_allclose(got, sol[3:], rtol=0, atol=1e-9)


def test_compiled_tangent_covariance_matches_the_matrix_forms():
    from rollingstar.estimators.attitude.star_covariance import direction_covariance, direction_jacobian, tangent_basis
    from rollingstar.sensors.camera import PinholeCamera

    rng = np.random.default_rng(12)
    cam = PinholeCamera(focal_length_m=0.012, pixel_size_m=4e-6, width=1280, height=960, k1=-0.15, k2=0.02)
    n = 40
    x, y = rng.uniform(0, 1279, n), rng.uniform(0, 959, n)
    a = rng.normal(0, 0.2, (n, 2, 2))
    cov_px = a @ np.swapaxes(a, 1, 2) + 1e-3 * np.eye(2)
    d = direction_covariance(cam, x, y, cov_px)
    body, J = direction_jacobian(cam, x, y)
    E = tangent_basis(body)
    M = np.swapaxes(E, 1, 2) @ J
    sigma = M @ cov_px @ np.swapaxes(M, 1, 2)
    np.testing.assert_allclose(d.cov, 0.5 * (sigma + np.swapaxes(sigma, 1, 2)), rtol=1e-12, atol=0)
    for got, expected in ((d.info, np.linalg.inv(d.cov)), (d.whiten, np.linalg.inv(np.linalg.cholesky(d.cov)))):
        scale = np.abs(expected).max(axis=(1, 2), keepdims=True)  # LAPACK leaves ~1e-16 where 0 is exact
        np.testing.assert_allclose(got / scale, expected / scale, rtol=0, atol=1e-12)
    bad = cov_px.copy()
    bad[7] = [[1.0, 2.0], [2.0, 1.0]]  # indefinite: refused as numpy's Cholesky refuses it
    with pytest.raises(np.linalg.LinAlgError):
        direction_covariance(cam, x, y, bad)


def test_compiled_schur_complement_matches_the_matrix_forms():
    from rollingstar.estimators.attitude.pixel_bundle import _reduced_normal

    rng = np.random.default_rng(13)
    n = 25
    J = rng.normal(size=(n, 40, 6))
    M = np.swapaxes(J, 1, 2) @ J  # per star J^T W J of (x, y, vx, vy, F, b)
    g = rng.normal(size=(n, 6))
    A = rng.normal(size=(n, 4, 6))
    n_inv, normal, rhs = _reduced_normal(M, g, A)
    N_inv = np.linalg.inv(M[:, 4:, 4:])
    CN = M[:, :4, 4:] @ N_inv
    S = M[:, :4, :4] - CN @ np.swapaxes(M[:, :4, 4:], 1, 2)
    s = g[:, :4] - np.einsum("nij,nj->ni", CN, g[:, 4:])
    np.testing.assert_allclose(n_inv, N_inv, rtol=1e-10)
    np.testing.assert_allclose(normal, np.swapaxes(A, 1, 2) @ S @ A, rtol=1e-9, atol=1e-9 * np.abs(normal).max())
    np.testing.assert_allclose(rhs, np.einsum("nji,nj->ni", A, s), rtol=1e-9, atol=1e-9 * np.abs(rhs).max())
    M[3, 4:, 4:] = 0.0  # a star whose flux and background its pixels do not determine
    with pytest.raises(np.linalg.LinAlgError):
        _reduced_normal(M, g, A)


def test_compiled_robust_rate_step_matches_least_squares_without_outliers():
    from rollingstar.estimators.centroiders.streak import _robust_rate_step

    rng = np.random.default_rng(14)
    A = rng.normal(size=(30, 2, 3))
    r = A @ np.array([1e-3, -2e-3, 5e-4]) + rng.normal(0, 0.02, (30, 2))
    r[[4, 9]] += 3.0  # two stars that moved by themselves
    keep = np.ones(30, dtype=bool)
    for _ in range(2):
        d = np.linalg.lstsq(A[keep].reshape(-1, 3), r[keep].reshape(-1), rcond=None)[0]
        miss = np.hypot(*(r - A @ d).T)
        keep = miss <= 3.0 * max(1.4826 * np.median(miss), 0.05)
    assert not keep[4] and not keep[9]
    np.testing.assert_allclose(_robust_rate_step(A, r), d, rtol=1e-10, atol=1e-15)


def test_compiled_quaternion_from_matrix_matches_scipy_near_every_branch():
    from rollingstar.sensors.so3 import quat_from_matrix

    rotations = list(Rotation.random(500, random_state=21))
    rotations += [Rotation.from_rotvec(v) for v in ([np.pi, 0, 0], [0, np.pi, 0], [0, 0, np.pi],
                                                     [0, np.pi - 1e-9, 0], [0, 0, 0], [1e-12, 0, 0])]
    for r in rotations:
        q, expected = quat_from_matrix(r.as_matrix()), r.as_quat()
        assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-14  # q and -q: one rotation


def test_compiled_forms_keep_numpys_answers_on_degenerate_input():
    from rollingstar.estimators.attitude.star_covariance import direction_covariance
    from rollingstar.estimators.centroiders.cog import robust_sigma
    from rollingstar.sensors.camera import PinholeCamera
    from rollingstar.sensors.so3 import rotate_at_rate, wahba

    w = np.random.default_rng(3).normal(size=(4, 3))
    omega = np.array([0.3, -0.2, 0.1])
    expected = Rotation.from_rotvec(omega * 0.5).apply(w)
    np.testing.assert_allclose(rotate_at_rate(omega, w, np.array([0.5])), expected, atol=1e-14)  # times broadcast
    np.testing.assert_allclose(rotate_at_rate(omega, w[:1], np.array([0.5, 0.5])), expected[[0, 0]], atol=1e-14)
    np.testing.assert_array_equal(rotate_at_rate(np.array([1e-170, 0.0, 0.0]), w, np.ones(4)), w)  # rate underflows
    with pytest.raises(ValueError):
        wahba(w[:3], w[:2])
    assert np.isnan(robust_sigma(np.array([np.inf, np.inf])))
    cam = PinholeCamera(focal_length_m=0.025, pixel_size_m=5.5e-6, width=1024, height=1024)
    x, y = np.array([100.0, 500.0, 900.0]), np.array([200.0, 600.0, 300.0])
    np.testing.assert_allclose(direction_covariance(cam, x, y, 0.04 * np.eye(2)).cov,  # one covariance for all
                               direction_covariance(cam, x, y, np.tile(0.04 * np.eye(2), (3, 1, 1))).cov)
    for singular in (np.zeros((2, 2)), np.diag([0.04, 0.0])):  # refused, as numpy's Cholesky refuses them
        cov = np.tile(0.04 * np.eye(2), (3, 1, 1))
        cov[1] = singular
        with pytest.raises(np.linalg.LinAlgError):
            direction_covariance(cam, x, y, cov)


def _mutual_nearest_numpy(dpos, dcov, ppos, pcov, chi2_gate, gate_px):
    """Every pair's Mahalanobis distance, gated, and the mutual nearest neighbours (numpy form)."""
    r = dpos[:, None, :] - ppos[None, :, :]
    s = dcov[:, None] + pcov[None]
    det = s[..., 0, 0] * s[..., 1, 1] - s[..., 0, 1] * s[..., 1, 0]
    d2 = (s[..., 1, 1] * r[..., 0] ** 2 - 2.0 * s[..., 0, 1] * r[..., 0] * r[..., 1] + s[..., 0, 0] * r[..., 1] ** 2) / det
    d2[(d2 > chi2_gate) | (r[..., 0] ** 2 + r[..., 1] ** 2 > gate_px * gate_px)] = np.inf
    rows = np.arange(len(dpos))
    j = np.argmin(d2, axis=1)
    both = np.isfinite(d2[rows, j]) & (np.argmin(d2, axis=0)[j] == rows)
    return rows[both], j[both]


def test_compiled_mutual_nearest_matches_the_pairwise_numpy_form():
    from rollingstar.estimators.identifiers.tracking import match_mahalanobis

    rng = np.random.default_rng(15)
    for k in range(200):
        n, m = int(rng.integers(1, 40)), int(rng.integers(1, 50))
        ppos = rng.uniform(0, 200, (m, 2))
        dpos = np.concatenate([ppos[: min(n, m)] + rng.normal(0, 1, (min(n, m), 2)), rng.uniform(0, 200, (max(n - m, 0), 2))])
        if k % 5 == 0 and n > 2:
            dpos[2] = dpos[1]  # a tie: the first index wins, as numpy.argmin
        a, b = rng.normal(0, 0.5, (n, 2, 2)), rng.normal(0, 0.5, (m, 2, 2))
        dcov, pcov = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(2), b @ np.swapaxes(b, 1, 2) + 0.1 * np.eye(2)
        got = match_mahalanobis(dpos, dcov, ppos, pcov, 9.21, 5.0)
        expected = _mutual_nearest_numpy(dpos, dcov, ppos, pcov, 9.21, 5.0)
        assert np.array_equal(got[0], expected[0]) and np.array_equal(got[1], expected[1]), k


def test_compiled_quaternion_step_and_matrix_match_scipy():
    from rollingstar.sensors.so3 import quat_times_exp, quat_to_matrix

    rng = np.random.default_rng(22)
    for r in Rotation.random(200, random_state=22):
        delta = rng.normal(size=3) * rng.choice([0.0, 1e-9, 1e-4, 0.5, 3.0])
        got, expected = quat_times_exp(r.as_quat(), delta), (r * Rotation.from_rotvec(delta)).as_quat()
        assert min(np.abs(got - expected).max(), np.abs(got + expected).max()) < 1e-14
        np.testing.assert_allclose(quat_to_matrix(r.as_quat()), r.as_matrix(), rtol=0, atol=1e-15)


@pytest.mark.parametrize("stars, trailing", [(0, (3, 3)), (1, (3, 1)), (40, (3, 3)), (3000, (3, 7)), (500, (3, 0))])
def test_the_diagnosis_frame_sums_are_numpys_add_at_to_the_bit(stars, trailing):
    """``frame_sums`` (one ``bincount``) and ``frame_normal`` (its products written out) against
    ``np.add.at`` and ``einsum``, the forms they replace: equal bit for bit, frames in any order,
    empty frames included."""
    from rollingstar.estimators.diagnosis.observations import frame_normal, frame_sums

    rng = np.random.default_rng(stars)
    frames = 9
    frame = rng.integers(0, frames - 2, stars)  # the last two frames have no stars
    values = rng.normal(size=(stars,) + trailing) * 10.0 ** rng.integers(-8, 8, (stars,) + trailing)
    expect = np.zeros((frames,) + trailing)
    np.add.at(expect, frame, values)
    got = frame_sums(frame, frames, values)
    assert got.dtype == expect.dtype and got.shape == expect.shape
    np.testing.assert_array_equal(got, expect)
    jac, rhs = rng.normal(size=(stars, 2, 3)) * 1e3, rng.normal(size=(stars, 2) + trailing[1:])
    for wts in (rng.random(stars), rng.random((stars, 2, 2))):
        jw = jac * wts[:, None, None] if wts.ndim == 1 else wts @ jac
        a, b = np.zeros((frames, 3, 3)), np.zeros((frames, 3) + trailing[1:])
        np.add.at(a, frame, np.einsum("nki,nkj->nij", jw, jac))
        np.add.at(b, frame, np.einsum("nki,nkm->nim", jw, rhs))
        got = frame_normal(frame, frames, jac, wts, rhs)
        np.testing.assert_array_equal(got[0], a)
        np.testing.assert_array_equal(got[1], b)


def test_the_diagnosis_frame_solves_are_each_frame_solved_alone():
    """``solve_frames`` solves all frames in one call when every one is well conditioned, and only
    those that are otherwise (zeros for the rest): both must be each frame's own ``solve``."""
    from rollingstar.estimators.diagnosis.observations import solve_frames

    rng = np.random.default_rng(11)
    m = rng.normal(size=(12, 3, 3))
    a, b = m @ np.swapaxes(m, 1, 2) + 0.1 * np.eye(3), rng.normal(size=(12, 3, 2))
    each = np.stack([np.linalg.solve(a[k], b[k]) for k in range(12)])
    np.testing.assert_array_equal(solve_frames(a, b), each)
    a[[2, 7]] = np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])  # rank one: a frame with one star
    got = solve_frames(a, b)
    np.testing.assert_array_equal(got[[2, 7]], 0.0)
    keep = np.setdiff1d(np.arange(12), [2, 7])
    np.testing.assert_array_equal(got[keep], each[keep])
    assert solve_frames(np.zeros((0, 3, 3)), np.zeros((0, 3, 1))).shape == (0, 3, 1)


def test_the_camera_unit_vectors_are_normalised_as_numpys_norm_does():
    """``unproject`` divides by the square root of the sum of squares written out: the same
    numbers as ``np.linalg.norm``, to the bit."""
    from rollingstar.sensors.camera import PinholeCamera

    cam = PinholeCamera(width=808, height=608, focal_length_m=0.016, pixel_size_m=8e-6)
    rng = np.random.default_rng(2)
    x, y = rng.uniform(-2000, 3000, 5000), rng.uniform(-2000, 3000, 5000)
    w = np.stack([-(x - cam.cx), -(y - cam.cy), np.full(x.shape, cam.focal_px)], axis=-1)
    np.testing.assert_array_equal(cam.unproject(x, y), w / np.linalg.norm(w, axis=-1, keepdims=True))
