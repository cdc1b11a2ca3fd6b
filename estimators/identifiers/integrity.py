"""Identification integrity: how likely a frame's matches are chance coincidences, for any identifier.

A frame's identified stars are checked against the catalogue with no knowledge of how they were
found (pattern search, tracking from a prior, a third-party identifier):

1. Fit. The attitude that best fits the ``k`` identified stars, each weighted by its own
   covariance (Wahba's problem, :func:`rollingstar.sensors.so3.wahba`); with at least
   :data:`RATE_FIT_MIN_MATCHES` stars whose times differ (raw rolling-shutter centroids, each at
   its own row time) also a constant body rate, ``R(t) = R0 Exp(omega (t - t_mid))``, by two
   linearised weighted least-squares steps (the rolling shutter's row-to-row motion would
   otherwise read as residual). With fewer stars the rate is the frame's gyro rate when it has gyro
   samples, else zero (a static frame, as the pattern search assumes).
2. Gate. ``g`` = the largest pixel residual of the ``k`` stars under that fit, at least
   ``max(min_gate_px, 3 * median star sigma)``: the distance within which every match was found.
3. Chance. With ``N`` catalogue stars predicted on the ``W x H`` detector by the fit, one random
   detection falls within ``g`` of one of them with probability ``p = min(1, N pi g^2 / (W H))``
   (overlapping discs make the true ``p`` smaller: conservative). The fit's attitude (3
   parameters; 6 with the rate) could have been chosen to make any ``a`` = 2 (3) detections match,
   so those *anchor* stars are not evidence: the probability that the matches are chance is the
   binomial tail over the others, ``P = binom.sf(k - 1 - a, n - a, p)`` (``n`` detections), the
   verification tetra3 applies to the stars beyond its pattern, here independent of the
   identifier. A tracker whose prior points at an unrelated part of the sky, a mirrored or
   shuffled field, random spots: all leave large residuals or few matches, hence a large ``P``.
   The frame passes when ``P <= bound`` (default :data:`DEFAULT_MAX_FALSE_MATCH_PROB`). When even
   the tail over all ``k`` stars, ``binom.sf(k - 1, n, p)``, exceeds the bound the matches are
   likely chance (``false_match_probability``: the stage mechanics withdraw them); when only
   ``P`` does they are ``unverifiable``: the stars keep their identities for per-star stages (a
   filter tracking guide stars) but no attitude made from them is valid. Two stars (three with a
   rate) can never be verified; with fewer than two the check does not apply (``P = 1``,
   ``passed`` False, no flag).
4. Consistency. The same fit's ``chi^2 = sum_i r_i^T C_i^-1 r_i`` with each star's stated 2 x 2
   position covariance ``C_i`` (``StarTable.position_covariance``), over ``2 k - 3`` degrees of
   freedom (``2 k - 6`` with the rate). A chance-free identification whose positions scatter far
   more than their covariances say (a displaced or blended star, an unmodelled lens) makes every
   covariance computed from those stars too small: with fewer than :data:`MIN_REDUNDANT_MATCHES`
   stars the identification is rejected (``inconsistent_residuals``: too few stars to tell the
   displaced one). With more, the majority decides: when the stars' typical scatter (the median
   normalised residual, robust to a few blends or misplaced spots) exceeds their covariances by
   :data:`SCALE_THRESHOLD` or more, the stage mechanics scale the frame's attitude covariances by
   that factor; a few stars beyond 5 sigma with an honest majority are only counted
   (``outlier_stars:N``: a robust attitude gate, ``robust: ransac``, removes them).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation
from scipy.special import bdtrc, chdtrc

from rollingstar.estimators.centroiders.cog import median
from rollingstar.estimators.data import DEFAULT_CENTROID_SIGMA_PX, FrameData, IdentificationCheck, StarTable
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.so3 import rotate_by_rotvec, rotate_rows, wahba

#: Largest accepted chance probability of a frame's matches (one frame's hypothesis; a pattern
#: search that tests ~1e4 hypotheses still leaves ~1e-5 per frame).
DEFAULT_MAX_FALSE_MATCH_PROB = 1e-9
#: Fewest identified stars (with distinct times) a body rate is fitted with.
RATE_FIT_MIN_MATCHES = 5
#: Smallest gate (px) the chance probability is computed with.
MIN_GATE_PX = 0.5
#: Chi-square tail probability below which a fit's residuals contradict the stated covariances.
INCONSISTENT_P = 1e-6
#: A star further than 5 sigma of its own covariance from the fit is an outlier.
OUTLIER_Z2 = 25.0
#: Majority scatter factor above which the frame's attitude covariances are scaled by it.
SCALE_THRESHOLD = 2.0
#: Fewest matches whose inconsistent residuals still leave a usable attitude (with fewer, the
#: displaced star cannot be told from the others: the identification is rejected).
MIN_REDUNDANT_MATCHES = 5


def check_identification(stars: StarTable | None, unmatched: StarTable | None, camera, catalog,
                         bound: float = DEFAULT_MAX_FALSE_MATCH_PROB, min_gate_px: float = MIN_GATE_PX,
                         omega_rad_s=None) -> IdentificationCheck:
    """The integrity check of one frame's identification (module docstring).

    ``stars`` holds the identified stars (unidentified rows are counted as detections), ``unmatched``
    the other detections; ``camera`` the frame's camera model; ``catalog`` the catalogue the
    identifications refer to; ``omega_rad_s`` the body rate (camera frame) when a gyro measured it.
    """
    stars = stars if stars is not None else StarTable.empty()
    n = _finite_count(stars) + (_finite_count(unmatched) if unmatched is not None else 0)
    ident = stars.take(stars.identified & np.isfinite(stars.x) & np.isfinite(stars.y)
                       & np.isfinite(stars.ref_icrs).all(axis=1))
    k = ident.n
    if k < 2:
        return IdentificationCheck(1.0, n, k, 0, float("nan"), float(bound), False, f"too_few_matches({k}<2)")
    stated = ident.sigma_px[ident.sigma_px > 0]  # the stars' own sigmas (NaN: none stated)
    sigma = median(stated) if stated.size and np.isfinite(stated).any() else np.nan
    cov = ident.position_covariance(sigma if np.isfinite(sigma) else DEFAULT_CENTROID_SIGMA_PX)
    resid, attitude, dx = fit_residuals(ident, camera, omega_rad_s, cov)
    floor = max(min_gate_px, 3.0 * (sigma if np.isfinite(sigma) else DEFAULT_CENTROID_SIGMA_PX))
    gate = max(float(np.max(resid)), floor) if np.all(np.isfinite(resid)) else float("inf")
    n_pred = predicted_count(attitude, camera, catalog)
    p = min(1.0, max(n_pred, k) * np.pi * gate**2 / (camera.width * camera.height))
    fitted = 6 if rate_fitted(ident) else 3
    anchors = (fitted + 1) // 2  # stars the fit could have made match whatever they were
    n = max(n, k)
    # binomial and chi-square tails by scipy.special's functions: scipy.stats' distribution objects
    # return the same values (tested against them) at ~40x the cost, a tenth of a tracked frame
    chance = float(bdtrc(k - 1, n, p))
    prob = float(bdtrc(k - 1 - anchors, n - anchors, p)) if k > anchors else 1.0
    dof = 2 * k - fitted
    info = np.linalg.inv(cov)
    z2 = np.einsum("ni,nij,nj->n", dx, info, dx) if np.all(np.isfinite(dx)) else np.full(k, np.nan)
    chi2_dof = float(z2.sum() / dof) if dof > 0 else float("nan")
    # the majority's scale: a star's z^2 has ~2 (1 - fitted / 2k) degrees of freedom; the median of
    # chi^2 with 2 degrees of freedom is 2 ln 2
    scale = float(median(z2) / (2.0 * np.log(2.0) * max(dof, 1) / (2.0 * k)))
    check = IdentificationCheck(prob, n, k, n_pred, gate, float(bound), True, "", chi2_dof, max(dof, 0), scale,
                                int(np.count_nonzero(z2 > OUTLIER_Z2)))
    if chance > bound:
        return replace(check, passed=False, reason=f"false_match_probability({chance:.1e}>{bound:.0e})")
    if prob > bound:
        return replace(check, passed=False, reason=f"unverifiable({prob:.1e}>{bound:.0e},{k} stars)")
    if k < MIN_REDUNDANT_MATCHES and inconsistent(check):
        return replace(check, passed=False, reason=f"inconsistent_residuals(chi2/dof={chi2_dof:.3g},{k}<{MIN_REDUNDANT_MATCHES} stars)")
    return check


def check_frame(frame: FrameData, camera, catalog, bound: float = DEFAULT_MAX_FALSE_MATCH_PROB) -> IdentificationCheck:
    """:func:`check_identification` of ``frame``'s stars, with its gyro samples' mean rate when it has any."""
    gyro = frame.gyro.omega_rad_s
    return check_identification(frame.stars, frame.unmatched, camera, catalog, bound,
                                omega_rad_s=gyro.mean(axis=0) if len(gyro) else None)


def inconsistent(check: IdentificationCheck) -> bool:
    """True when the fit's chi-square contradicts the stars' stated covariances (``p < INCONSISTENT_P``)."""
    return check.dof > 0 and np.isfinite(check.chi2_dof) and chdtrc(check.dof, check.chi2_dof * check.dof) < INCONSISTENT_P


def rate_fitted(ident: StarTable) -> bool:
    """True when the fit includes a body rate (enough stars at distinct times)."""
    return ident.n >= RATE_FIT_MIN_MATCHES and np.ptp(ident.t_ns) > 0


def fit_residuals(ident: StarTable, camera, omega_rad_s=None, cov=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel residual distances of the identified stars under the best-fit attitude (and body rate,
    see the module docstring), the attitude at the stars' middle time (camera -> ICRS rotation
    matrix: no scipy ``Rotation`` is built in the check), and the residual vectors (n, 2).
    ``cov``: the stars' position covariances (n, 2, 2) the fit is weighted by (default: their own)."""
    body = camera.unproject(ident.x, ident.y)
    ref = ident.ref_icrs / np.linalg.norm(ident.ref_icrs, axis=1, keepdims=True)
    t = ident.t_ns.astype(np.int64)
    dt = (t - int(np.median(t))) * S_PER_NS
    phi = np.zeros((ident.n, 3))
    if omega_rad_s is not None and not rate_fitted(ident):
        phi = dt[:, None] * np.asarray(omega_rad_s, dtype=float)[None, :]
    # weights 1 / sigma^2 (the isotropic part of each star's covariance): the maximum-likelihood
    # fit, so that well-measured stars are not judged against a fit the noisy ones pulled
    cov = ident.position_covariance(DEFAULT_CENTROID_SIGMA_PX) if cov is None else cov
    weights = 2.0 / np.trace(cov, axis1=1, axis2=2) if ident.n else np.zeros(0)
    # R^T r_i = Exp(phi_i) b_i: the stars referred to the middle time, then Wahba's problem
    R = wahba(ref, rotate_by_rotvec(phi, body), weights)
    if rate_fitted(ident):
        phi, _ = fit_rate(R, body, ref, dt, np.sqrt(weights))
    # predicted camera vectors: w_i = (R Exp(phi_i))^T r_i
    w = _predicted(R, phi, ref) if ident.n else np.zeros((0, 3))
    px, py, front = camera.project(w)
    dx = np.column_stack([ident.x - px, ident.y - py])
    resid = np.where(front, np.hypot(dx[:, 0], dx[:, 1]), np.inf)
    return resid, R, dx


def fit_rate(R: Rotation | np.ndarray, body: np.ndarray, ref: np.ndarray, dt: np.ndarray, root_weights: np.ndarray,
             steps: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The attitude-and-rate fit ``R(t_i) = R Exp(delta + omega dt_i)`` to camera directions
    ``body`` of catalogue vectors ``ref`` seen ``dt`` seconds from the reference time, from ``R``:
    ``steps`` linearised weighted least-squares steps (the second removes the first's
    linearisation error). Each step solves ``b_i - w_i = [w_i]x (d delta + d omega dt_i)``, with
    ``w_i = (R Exp(phi_i))^T r_i`` and each star's rows scaled by ``root_weights``, by its normal
    equations. Returns the per-star rotation vectors ``phi_i = delta + omega dt_i`` (n, 3) and the
    body rate ``omega`` (3,), rad/s in the camera frame."""
    v = np.ascontiguousarray(np.asarray(ref, dtype=float) @ _matrix(R))
    n = (len(v),)
    return _fit_rate(v, np.ascontiguousarray(np.broadcast_to(np.asarray(body, dtype=float), v.shape)),
                     np.ascontiguousarray(np.broadcast_to(np.asarray(dt, dtype=float), n)),
                     np.ascontiguousarray(np.broadcast_to(np.asarray(root_weights, dtype=float), n)), int(steps))


def _fit_rate(v, body, dt, root_weights, steps):
    """:func:`fit_rate` from ``v_i = R^T r_i``: each step the least-squares solution (minimum norm
    when the stars leave it undetermined) of the stacked rows :func:`_rate_rows` writes."""
    phi, omega = np.zeros((len(v), 3)), np.zeros(3)
    for _ in range(steps):
        A, b = _rate_rows(v, body, dt, root_weights, phi)
        sol = np.linalg.lstsq(A, b, rcond=None)[0]
        phi = phi + sol[:3][None, :] + dt[:, None] * sol[3:][None, :]
        omega = omega + sol[3:]
    return phi, omega


@njit(cache=True, nogil=True)
def _rate_rows(v, body, dt, root_weights, phi):  # pragma: no cover - compiled
    """The rows ``[w_i]x [I, dt_i I]`` and right-hand sides ``b_i - w_i`` of :func:`fit_rate`'s step
    at ``phi``, ``w_i = Exp(-phi_i) v_i``, each star's scaled by its root weight. Compiled: a check
    runs on every tracked frame, and the numpy form's skew matrices and stacking cost several times
    their arithmetic (the least squares stay numpy's)."""
    n = v.shape[0]
    w = rotate_rows(-phi, v)
    A, b = np.zeros((3 * n, 6)), np.zeros(3 * n)
    for i in range(n):
        q = root_weights[i]
        rows = ((0.0, -w[i, 2], w[i, 1]), (w[i, 2], 0.0, -w[i, 0]), (-w[i, 1], w[i, 0], 0.0))  # [w]x
        for r in range(3):
            for c in range(3):
                A[3 * i + r, c] = q * rows[r][c]
                A[3 * i + r, 3 + c] = q * rows[r][c] * dt[i]
            b[3 * i + r] = q * (body[i, r] - w[i, r])
    return A, b


def _matrix(R: Rotation | np.ndarray) -> np.ndarray:
    """The rotation matrix of a scipy ``Rotation`` or of a 3 x 3 matrix (itself)."""
    return R.as_matrix() if isinstance(R, Rotation) else np.asarray(R, dtype=float)


def _predicted(R: Rotation | np.ndarray, phi: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``w_i = (R Exp(phi_i))^T r_i = Exp(-phi_i) R^T r_i``, written with the rotation matrix and
    Rodrigues' formula (scipy's per-star ``Rotation`` compositions cost more than the rest of the
    check on a tracked frame)."""
    return rotate_by_rotvec(-phi, ref @ _matrix(R))


def predicted_count(attitude: Rotation | np.ndarray, camera, catalog) -> int:
    """Catalogue stars the camera sees on its detector at ``attitude`` (camera -> ICRS)."""
    m = _matrix(attitude)
    idx = np.asarray(catalog.cone(m[:, 2], camera.half_diagonal_rad), dtype=np.intp)
    if idx.size == 0:
        return 0
    x, y, front = camera.project(catalog.unit_icrs[idx] @ m)
    return int(np.count_nonzero(front & camera.contains(x, y)))


def _finite_count(table: StarTable) -> int:
    return int(np.count_nonzero(np.isfinite(table.x) & np.isfinite(table.y)))
