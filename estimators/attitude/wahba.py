"""Batched solutions of Wahba's problem: QUEST (Shuster & Oh 1981) and its measurement covariance.

Wahba's problem: find the attitude matrix ``A`` (reference frame -> body frame) minimising::

    L(A) = 1/2 sum_i a_i |b_i - A r_i|^2,

with ``b_i`` unit observation vectors in the body (camera) frame, ``r_i`` the matching unit
reference vectors (ICRS) and weights ``a_i > 0``. With ``B = sum_i a_i b_i r_i^T``,
``L(A) = sum a_i - tr(A B^T)``.

Project convention: an *attitude* is the camera-to-ICRS rotation ``R`` (``r = R b``), so the
QUEST attitude matrix is ``A = R^T``. Shuster's quaternion ``q = [X; gamma]`` parametrises
``A(q) = (q4^2 - |q|^2) I + 2 q q^T - 2 q4 [q x]``, which is the *transpose* of scipy's matrix of
the same quaternion: scipy ``Rotation.from_quat([X, gamma])`` is therefore exactly the
camera-to-ICRS rotation ``R``; no conjugation is needed.

Everything here is vectorised over frames ``F`` (leading axis) and stars ``N``; a ``mask`` selects
the stars of each frame that take part (padding for ragged batches).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.sensors.so3 import skew

__all__ = ["QuestResult", "quest", "quest_covariance", "wahba_loss", "refine_attitude"]


class QuestResult(NamedTuple):
    """Output of :func:`quest`, one row per frame.

    - ``q_xyzw`` (F, 4): camera-to-ICRS quaternion, scalar last, ``w >= 0``; NaN where invalid.
    - ``loss`` (F,): Wahba loss ``1/2 sum a_i |b_i - A r_i|^2 = sum a_i - lambda_max`` at the
      solution, for the weights as given (so with
      ``a_i = 1 / sigma_i^2`` in rad^-2, ``2 * loss`` is approximately chi-square with ``2N - 3``
      degrees of freedom); NaN where invalid.
    - ``valid`` (F,): False for fewer than two usable stars, non-finite input or collinear
      observations (rotation about their common axis unobservable).
    """

    q_xyzw: np.ndarray
    loss: np.ndarray
    valid: np.ndarray


# 180-degree rotations about x, y, z applied to the reference vectors (Shuster & Oh's method of
# sequential rotations). Index 0 is the identity (no rotation).
_FLIPS = np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]])
# Quaternions (xyzw) of those rotations, for undoing them: R = R_flip * R'.
_FLIP_QUATS = np.array([[0.0, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])


def _quat_product(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p q`` of scalar-last quaternions (F, 4): the rotation ``R_p * R_q`` (scipy).

    Written out (16 products) because building two scipy ``Rotation`` objects and composing them
    costs more than the rest of QUEST for 10k frames (``rollingstar bench perf --only quest``).
    """
    px, py, pz, pw = p[:, 0], p[:, 1], p[:, 2], p[:, 3]
    qx, qy, qz, qw = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    out = np.stack([pw * qx + px * qw + py * qz - pz * qy,
                    pw * qy - px * qz + py * qw + pz * qx,
                    pw * qz + px * qy - py * qx + pz * qw,
                    pw * qw - px * qx - py * qy - pz * qz], axis=-1)
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def _canonical(q: np.ndarray) -> np.ndarray:
    """scipy's canonical sign: ``w >= 0``; for ``w == 0`` the first non-zero of x, y, z positive."""
    lead = np.where(q[:, 3] != 0, q[:, 3], np.where(q[:, 0] != 0, q[:, 0], np.where(q[:, 1] != 0, q[:, 1], q[:, 2])))
    return np.where((lead < 0)[:, None], -q, q)


def _prepare(ref_icrs, obs_cam, weights, mask):
    ref = np.asarray(ref_icrs, dtype=float)
    obs = np.asarray(obs_cam, dtype=float)
    if ref.ndim == 2:
        ref, obs = ref[None], obs[None]
    if ref.shape != obs.shape or ref.ndim != 3 or ref.shape[-1] != 3:
        raise ValueError(f"ref_icrs and obs_cam must both have shape (F, N, 3); got {ref.shape} and {obs.shape}")
    F, N, _ = ref.shape
    w = np.ones((F, N)) if weights is None else np.broadcast_to(np.asarray(weights, dtype=float), (F, N)).copy()
    m = np.ones((F, N), dtype=bool) if mask is None else np.broadcast_to(np.asarray(mask, dtype=bool), (F, N)).copy()
    fr, fo = np.isfinite(ref), np.isfinite(obs)  # (and over the 3 components: faster than .all(-1))
    finite = fr[..., 0] & fr[..., 1] & fr[..., 2] & fo[..., 0] & fo[..., 1] & fo[..., 2] & np.isfinite(w)
    if np.any(m & (w <= 0) & finite):
        raise ValueError("weights of the stars in use must be > 0")
    # A frame with non-finite data among its used stars is invalid (never silently dropped).
    bad_frame = np.any(m & ~finite, axis=1)
    m = m & finite
    # Zero the unused entries so that sums ignore them without NaN propagation.
    if not m.all():  # (all in use, the common case: nothing to zero)
        ref = np.where(m[..., None], ref, 0.0)
        obs = np.where(m[..., None], obs, 0.0)
        w = np.where(m, w, 0.0)
    return ref, obs, w, m, bad_frame


def _quest_terms(B: np.ndarray):
    """QUEST's quantities of attitude profile matrices ``B`` (..., 3, 3): ``S = B + B^T``, ``Z``,
    ``sigma = tr B``, ``Delta = det S``, ``kappa = tr adj S`` (closed-form cofactors), ``S Z``, ``S^2 Z``."""
    S = B + np.swapaxes(B, -1, -2)
    Z = np.stack([B[..., 1, 2] - B[..., 2, 1], B[..., 2, 0] - B[..., 0, 2], B[..., 0, 1] - B[..., 1, 0]], axis=-1)
    sigma = B[..., 0, 0] + B[..., 1, 1] + B[..., 2, 2]
    delta = (S[..., 0, 0] * (S[..., 1, 1] * S[..., 2, 2] - S[..., 1, 2] * S[..., 2, 1])
             - S[..., 0, 1] * (S[..., 1, 0] * S[..., 2, 2] - S[..., 1, 2] * S[..., 2, 0])
             + S[..., 0, 2] * (S[..., 1, 0] * S[..., 2, 1] - S[..., 1, 1] * S[..., 2, 0]))
    kappa = (S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
             + S[..., 0, 0] * S[..., 2, 2] - S[..., 0, 2] * S[..., 2, 0]
             + S[..., 1, 1] * S[..., 2, 2] - S[..., 1, 2] * S[..., 2, 1])
    SZ = (S @ Z[..., None])[..., 0]
    return S, Z, sigma, delta, kappa, SZ, (S @ SZ[..., None])[..., 0]


def _flip_gammas(S, Z, sigma, delta, kappa, lam) -> np.ndarray:
    """``gamma`` of the four sequential-rotation variants (none, x, y, z), (F, 4), from variant 0.

    ``gamma`` of the variant flipped by 180 degrees about axis i is the i-th diagonal entry of
    ``adj(lambda I - K)`` of variant 0 (the flip is a signed permutation of K's rows and columns):
    [w] ``det((lambda + sigma) I - S) = (lambda + sigma) alpha - Delta``; [x, y, z] the 3 x 3
    principal minor without row/column i, ``(lambda - sigma) det(A') - z'^T adj(A') z'`` with
    ``A = (lambda + sigma) I - S`` and ``A'``, ``z'`` ``A`` and ``Z`` without index i. Building only
    the chosen variant instead of all four saves a quarter of QUEST's time (``bench perf --only quest``).
    """
    A = (lam + sigma)[:, None, None] * np.eye(3) - S
    dl = lam - sigma
    out = np.empty((lam.shape[0], 4))
    out[:, 0] = (lam + sigma) * (lam**2 - sigma**2 + kappa) - delta
    for col, (p, r) in enumerate(((1, 2), (0, 2), (0, 1)), start=1):
        app, arr, apr, zp, zr = A[:, p, p], A[:, r, r], A[:, p, r], Z[:, p], Z[:, r]
        out[:, col] = dl * (app * arr - apr**2) - (arr * zp**2 - 2.0 * apr * zp * zr + app * zr**2)
    return out


def quest(ref_icrs, obs_cam, weights=None, mask=None, *, newton_tol: float = 1e-15, max_newton: int = 50,
          degenerate_tol: float = 1e-10, refine: bool = True) -> QuestResult:
    """QUEST (Shuster & Oh 1981, J. Guidance Control 4(1):70-77), batched over frames.

    Parameters: ``ref_icrs`` and ``obs_cam`` (F, N, 3) or (N, 3) unit vectors; ``weights`` (F, N)
    positive (default equal; only their ratios change the attitude; the usual choice is
    ``1 / sigma_i^2``); ``mask`` (F, N) bool of the stars in use.

    Algorithm (weights normalised to ``sum a_i = 1`` internally for conditioning)::

        B = sum a_i b_i r_i^T,  S = B + B^T,  Z = sum a_i b_i x r_i,  sigma = tr B,
        kappa = tr adj S,  Delta = det S,
        a = sigma^2 - kappa,  b = sigma^2 + Z.Z,  c = Delta + Z.S Z,  d = Z.S^2 Z,
        lambda^4 - (a + b) lambda^2 - c lambda + (a b + c sigma - d) = 0   (characteristic eq.)

    solved for ``lambda_max`` by Newton-Raphson from ``lambda_0 = sum a_i = 1`` (iterated for all
    frames until every frame has converged to ``newton_tol``); then::

        alpha = lambda^2 - sigma^2 + kappa,  beta = lambda - sigma,
        gamma = (lambda + sigma) alpha - Delta,  X = (alpha I + beta S + S^2) Z,
        q = [X; gamma] / |[X; gamma]|.

    ``[X; gamma]`` is the last column of ``adj(lambda_max I - K)``, proportional to ``q4 q``; it
    vanishes as the rotation approaches 180 degrees (Gibbs vector singular). Method of sequential
    rotations: the problem is also solved with the reference vectors rotated by 180 degrees about
    x, y and z (``lambda_max`` is unchanged; ``gamma`` of each variant is proportional to the
    square of a different quaternion component), each frame keeps the variant with the largest
    ``|gamma|`` (the best-conditioned one; all four gammas from variant 0, :func:`_flip_gammas`)
    and the rotation is undone: ``R = R_flip R'``.

    With ``refine`` (default) the QUEST quaternion is polished by one step of inverse iteration on
    Davenport's ``K = [[S - sigma I, Z], [Z^T, sigma]]`` shifted by ``lambda_max`` (the eigenvalue
    QUEST just found), which brings it to the accuracy of an SVD solution for closely spaced stars.

    Degenerate geometry (all observation vectors parallel or anti-parallel): the smallest
    eigenvalue of ``sum a_i (I - b_i b_i^T)`` relative to its trace is below ``degenerate_tol``.
    """
    ref, obs, w, m, bad_frame = _prepare(ref_icrs, obs_cam, weights, mask)
    n_used = m.sum(axis=1)
    wsum = w.sum(axis=1)
    safe_wsum = np.where(wsum > 0, wsum, 1.0)
    a = w / safe_wsum[:, None]  # normalised weights, sum 1 per usable frame
    a_obs_t = np.swapaxes(a[..., None] * obs, 1, 2)  # (F, 3, N): a_i b_i
    degenerate = _degenerate(a, a_obs_t, obs, degenerate_tol)

    B0 = a_obs_t @ ref  # (F, 3, 3): sum a_i b_i r_i^T
    S0, Z0, s0, d0, k0, SZ0, S2Z0 = _quest_terms(B0)
    lam = _lambda_max(Z0, s0, d0, k0, SZ0, S2Z0, newton_tol, max_newton)

    # The variant to solve: the one with the largest |gamma| (_flip_gammas); only it is built.
    with np.errstate(invalid="ignore"):
        g = _flip_gammas(S0, Z0, s0, d0, k0, lam)
        best = np.argmax(np.where(np.isfinite(g), np.abs(g), -1.0), axis=1)  # (F,)
    S, Z, sigma, delta, kappa, SZ, S2Z = _quest_terms(B0 * _FLIPS[best][:, None, :])
    alpha = lam**2 - sigma**2 + kappa
    beta = lam - sigma
    gamma = (lam + sigma) * alpha - delta  # (F,)
    X = alpha[:, None] * Z + beta[:, None] * SZ + S2Z  # (F, 3)
    q_prime = np.concatenate([X, gamma[:, None]], axis=-1)
    norm = np.linalg.norm(q_prime, axis=-1)
    ok = np.isfinite(norm) & (norm > 0)
    q_prime = q_prime / np.where(ok, norm, 1.0)[:, None]
    q_prime[~ok] = [0.0, 0.0, 0.0, 1.0]
    if refine:
        q_prime = _inverse_iteration(q_prime, ok, S, Z, sigma, lam)
    q = _canonical(_quat_product(_FLIP_QUATS[best], q_prime))  # = (R_flip * R').as_quat(canonical=True)

    valid = ok & ~bad_frame & (n_used >= 2) & ~degenerate & np.isfinite(lam)
    # Wahba loss at the solution, 1/2 sum a_i |b_i - A r_i|^2 (= sum a_i - lambda_max, but without
    # the cancellation of that difference for small residuals).
    Rm = Rotation.from_quat(q).as_matrix()
    resid = obs - ref @ Rm  # b - R^T r (row n: r_n^T R = (R^T r_n)^T)
    loss = np.where(valid, 0.5 * np.einsum("fn,fn->f", w, np.sum(resid**2, axis=-1)), np.nan)
    q[~valid] = np.nan
    return QuestResult(q_xyzw=q, loss=loss, valid=valid)


def _degenerate(a: np.ndarray, a_obs_t: np.ndarray, obs: np.ndarray, degenerate_tol: float) -> np.ndarray:
    """Frames whose observations do not fix all three axes: the smallest eigenvalue of the
    information matrix ``sum a_i (I - b_i b_i^T)`` (normalised weights) is below ``degenerate_tol``
    times its trace. ``a_obs_t`` (F, 3, N): the products ``a_i b_i``.

    (Batched matmul rather than a 3-operand einsum: the same sums, ~10x faster for 10k frames.)
    smallest eigenvalue <= t  <=>  info - t I is not positive definite  <=>  (Sylvester's
    criterion) one of its leading principal minors is <= 0: three closed-form minors instead of
    a batched eigvalsh (a sixth of QUEST's time for 10k frames, ``rollingstar bench perf --only quest``).
    """
    info = a.sum(axis=1)[:, None, None] * np.eye(3) - a_obs_t @ obs
    trace = np.trace(info, axis1=1, axis2=2)
    M = info - (degenerate_tol * np.where(trace > 0, trace, 1.0))[:, None, None] * np.eye(3)
    minor2 = M[:, 0, 0] * M[:, 1, 1] - M[:, 0, 1] * M[:, 1, 0]
    minor3 = (M[:, 0, 0] * (M[:, 1, 1] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 1])
              - M[:, 0, 1] * (M[:, 1, 0] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 0])
              + M[:, 0, 2] * (M[:, 1, 0] * M[:, 2, 1] - M[:, 1, 1] * M[:, 2, 0]))
    return (M[:, 0, 0] <= 0) | (minor2 <= 0) | (minor3 <= 0)


def _lambda_max(Z, sigma, delta, kappa, SZ, S2Z, newton_tol: float, max_newton: int) -> np.ndarray:
    """Largest root of QUEST's characteristic equation (:func:`quest`) per frame, by Newton-Raphson
    from ``lambda_0 = 1`` for all frames at once. ``lambda_max`` is invariant under the sequential
    rotations, so it is solved once, for variant 0."""
    ca = sigma**2 - kappa
    cb = sigma**2 + np.einsum("fi,fi->f", Z, Z)
    cc = delta + np.einsum("fi,fi->f", Z, SZ)
    cd = np.einsum("fi,fi->f", Z, S2Z)
    c2 = -(ca + cb)
    c0 = ca * cb + cc * sigma - cd
    F = sigma.shape[0]
    lam = np.ones(F)
    active = np.ones(F, dtype=bool)
    prev = np.full(F, np.inf)
    for _ in range(max_newton):
        f = ((lam**2 + c2) * lam - cc) * lam + c0
        fp = (4 * lam**2 + 2 * c2) * lam - cc
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(active & (fp != 0), f / fp, 0.0)
        lam = lam - step
        # Newton from lambda_0 = 1 >= lambda_max decreases monotonically with shrinking steps; a
        # step that no longer shrinks is rounding noise (close eigenvalues make f' small), so that
        # frame has converged too (else it would iterate to max_newton; refine polishes the result).
        size = np.abs(step)
        active = active & (size > newton_tol) & (size < prev)
        prev = size
        if not active.any():
            break
    return lam


def _inverse_iteration(q_prime, ok, S, Z, sigma, lam) -> np.ndarray:
    """One step of inverse iteration on Davenport's K of the chosen variant, shifted just above
    lambda_max: ``(lambda' I - K) q_new = q``. It removes the error QUEST inherits from solving the
    characteristic equation in floating point (relative error ~ eps / gap^2 for close stars),
    leaving the eigenvector's own conditioning ~ eps / gap, as an SVD solution. Frames not ``ok``
    (and a step that fails) keep ``q_prime``."""
    F = q_prime.shape[0]
    K = np.empty((F, 4, 4))
    K[:, :3, :3] = S - sigma[:, None, None] * np.eye(3)
    K[:, :3, 3] = Z
    K[:, 3, :3] = Z
    K[:, 3, 3] = sigma
    shift = np.where(np.isfinite(lam), lam, 1.0) + 1e-12
    M = shift[:, None, None] * np.eye(4) - K
    M[~ok] = np.eye(4)
    try:
        q_new = np.linalg.solve(M, q_prime[..., None])[..., 0]
    except np.linalg.LinAlgError:  # exactly singular somewhere: keep the QUEST answer
        q_new = q_prime
    n_new = np.linalg.norm(q_new, axis=-1)
    use = ok & np.isfinite(n_new) & (n_new > 0)
    q_new = q_new / np.where(use, n_new, 1.0)[:, None]
    return np.where(use[:, None], np.where(np.sum(q_new * q_prime, axis=-1, keepdims=True) < 0, -q_new, q_new), q_prime)


def quest_covariance(obs_cam, weights_rad2, mask=None) -> np.ndarray:
    """QUEST measurement-model attitude-error covariance (Shuster & Oh 1981), camera frame, rad^2.

    ``P = (sum_i a_i (I - b_i b_i^T))^-1`` with ``a_i = 1 / sigma_i^2`` (``sigma_i`` the 1-sigma
    angular error of observation ``i`` in rad). Shape (F, 3, 3); NaN for frames whose information
    matrix is singular (fewer than two non-parallel observations).
    """
    obs = np.asarray(obs_cam, dtype=float)
    if obs.ndim == 2:
        obs = obs[None]
    F, N, _ = obs.shape
    w = np.broadcast_to(np.asarray(weights_rad2, dtype=float), (F, N))
    m = np.ones((F, N), dtype=bool) if mask is None else np.broadcast_to(np.asarray(mask, dtype=bool), (F, N))
    m = m & np.isfinite(obs).all(-1) & np.isfinite(w)
    w = np.where(m, w, 0.0)
    obs = np.where(m[..., None], obs, 0.0)
    info = np.einsum("fn,ij->fij", w, np.eye(3)) - np.einsum("fn,fni,fnj->fij", w, obs, obs)
    eig = np.linalg.eigvalsh(info)
    good = eig[:, 0] > 1e-10 * np.maximum(eig[:, -1], np.finfo(float).tiny)
    out = np.full((F, 3, 3), np.nan)
    if good.any():
        inv = np.linalg.inv(info[good])
        out[good] = 0.5 * (inv + np.swapaxes(inv, -1, -2))
    return out


def wahba_loss(q_xyzw, ref_icrs, obs_cam, weights=None) -> np.ndarray:
    """Wahba loss ``1/2 sum a_i |b_i - R^T r_i|^2`` of camera-to-ICRS quaternions, (F,)."""
    ref = np.asarray(ref_icrs, dtype=float)
    obs = np.asarray(obs_cam, dtype=float)
    if ref.ndim == 2:
        ref, obs = ref[None], obs[None]
    F, N, _ = ref.shape
    w = np.ones((F, N)) if weights is None else np.broadcast_to(np.asarray(weights, dtype=float), (F, N))
    R = Rotation.from_quat(np.asarray(q_xyzw, dtype=float).reshape(F, 4)).as_matrix()
    pred = np.einsum("fji,fnj->fni", R, ref)  # R^T r
    return 0.5 * np.einsum("fn,fn->f", w, np.sum((obs - pred) ** 2, axis=-1))


def refine_attitude(q_xyzw, ref_icrs, obs_cam, basis, info, iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton refinement of one camera-to-ICRS attitude with a full 2 x 2 weight per star.

    QUEST accepts one scalar weight per star; a star whose direction is better known across one
    axis than along the other (a smeared spot) needs its 2 x 2 tangent-plane information ``W_i``
    (rad^-2, in the orthonormal basis ``E_i`` (3 x 2) perpendicular to the measured ``b_i``, see
    :mod:`rollingstar.estimators.attitude.star_covariance`). With ``R = R0 Exp(delta)`` the predicted
    direction is ``R^T r_i ~ p_i + [p_i x] delta`` (``p_i = R0^T r_i``), so the residual
    ``e_i = E_i^T (b_i - R^T r_i)`` is linear in ``delta`` with ``H_i = E_i^T [p_i x]``; each iteration solves

        (sum H_i^T W_i H_i) delta = sum H_i^T W_i E_i^T (b_i - p_i),     R0 <- R0 Exp(delta),

    starting from ``q_xyzw`` (the QUEST solution: one or two iterations converge, the model is linear
    to the arcsecond). Returns the refined quaternion (scalar last, ``w >= 0``) and the covariance of
    its error ``(sum H_i^T W_i H_i)^-1`` (rad^2, camera frame, ``R_true = R Exp(d)``), evaluated at the
    solution. With ``W_i = a_i I`` the minimiser is QUEST's (Wahba's loss and this one differ by terms
    of fourth order in the residuals) and the covariance Shuster's ``(sum a_i (I - b_i b_i^T))^-1``.
    Arrays: ``ref_icrs``, ``obs_cam`` (n, 3) unit vectors, ``basis`` (n, 3, 2), ``info`` (n, 2, 2).
    """
    ref = np.asarray(ref_icrs, dtype=float).reshape(-1, 3)
    obs = np.asarray(obs_cam, dtype=float).reshape(-1, 3)
    E = np.asarray(basis, dtype=float)
    W = np.asarray(info, dtype=float)
    Et = np.swapaxes(E, -1, -2)
    R = Rotation.from_quat(q_xyzw)
    for step in range(iterations + 1):
        p = R.inv().apply(ref)  # R^T r
        H = Et @ skew(p)  # (n, 2, 3)
        HtW = np.swapaxes(H, -1, -2) @ W  # (n, 3, 2)
        normal = np.sum(HtW @ H, axis=0)
        if step == iterations:
            break
        e = np.einsum("nki,ni->nk", Et, obs - p)
        delta = np.linalg.solve(normal, np.einsum("nik,nk->i", HtW, e))
        R = R * Rotation.from_rotvec(delta)
    cov = np.linalg.inv(normal)
    return R.as_quat(canonical=True), 0.5 * (cov + cov.T)
