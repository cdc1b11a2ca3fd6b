"""Attitude and body rate of one rolling-shutter frame fitted to the pixels of its stars.

Star ``j``'s window of pixels is drawn by the rolling-shutter smear model
(:mod:`rollingstar.sensors.streak_model`) from ``p_j = (x_j, y_j, vx_j, vy_j, F_j,
b_j)``: its position at its own row's mid-exposure and image velocity follow from the frame's
attitude ``R`` (at ``t_ref``) and rate ``omega`` (:func:`star_kinematics`), its flux ``F_j`` and
local background ``b_j`` are its own nuisances. Pixel noise (ADU^2): the frame's background
variance, measured from the image (read noise, background shot noise and ADC quantisation
together, whatever the bias), plus the star's own shot noise ``(mu - b) / gain``; saturated
pixels are left out. Each linearisation is one pass of the compiled normal equations the
``streak`` centroider's fit uses (:func:`rollingstar.estimators.centroiders.streak_kernel.normal_equations`),
reading the windows in place. Gauss-Newton on the weighted pixel residuals with the per-star nuisances eliminated
by their Schur complement (each star's ``(F, b)`` couples only to itself):

    S_j = G_j - C_j N_j^-1 C_j^T,  s_j = g_j - C_j N_j^-1 n_j
    (sum A_j^T S_j A_j) theta_step = sum A_j^T s_j

iterated (at most ``pixel_iterations`` times), with ``G, C, N`` the (position-and-velocity,
nuisance) blocks of ``J^T W J``, ``g, n`` those of ``J^T W r``, and ``A_j = d(x_j, y_j, vx_j,
vy_j) / d theta``, until a step under the strict screen moves no parameter by more than
``CONVERGED_SIGMAS`` of its sigma, or is predicted to leave a next step under
``PREDICTED_SIGMAS``. Gauss-Newton converges quadratically: the model is linear to within
``(d / s)^2`` of a step that moves the stars' images by ``d`` px (position, and each streak end:
velocity times half the exposure), ``s`` the PSF's effective sigma, so the next step is about the
step times ``d / s`` (:func:`_contraction`). A step of a few sigmas that moves the stars by
hundredths of a pixel ends the iterations (``tests/estimators/test_rs_bundle.py``: iterating on
from there moves no attitude or rate component by 0.1 of its sigma, at 0 to 10 deg/s). The
information ``sum A_j^T S_j A_j`` is the Fisher information of ``theta`` in the pixels (the
frame-level pixel bound); the one returned, and the screen the outlier count comes from, are the
last linearisation's, a step of a few hundredths of a pixel from the solution (the information
changes over a PSF width).
A window cut by the detector's edge keeps the pixels it has. A star with fewer than
``MIN_LIVE_PIXELS`` live pixels, or one the model does not explain (non-positive flux, or a
reduced chi-square above ``MAX_STAR_CHI2`` at the current step, above ``START_STAR_CHI2`` at the
start: a wrong identification, a blend), is left out of that step; those left out of the last are
counted in the frame flag ``pixel_outliers:N``. When the model explains fewer than
``MIN_EXPLAINED_FRACTION`` of the usable stars (a PSF the Gaussian model does not draw, as on an
undersampled real camera), the frame keeps the position solution, flagged
``pixel_step_skipped:model_misfit(...)``.
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple

import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.frame_fit import apply_step, predicted_directions
from rollingstar.estimators.centroiders.cog import robust_sigma
from rollingstar.estimators.centroiders.psf_width import measure_psf_sigma, star_windows
from rollingstar.estimators.centroiders.streak_kernel import normal_equations, normal_equations_at_fitted_nuisance
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.so3 import skew
from rollingstar.sensors.streak_model import effective_sigma

MAX_STAR_CHI2 = 2.0  # reduced chi-square above which a star's pixels contradict the model (a right one: 1 +- 0.1)
# A step under the strict screen below this fraction of every parameter's sigma ends the
# iterations, or one whose successor is predicted (module docstring) below PREDICTED_SIGMAS
CONVERGED_SIGMAS = 0.5
PREDICTED_SIGMAS = 0.05
MIN_LIVE_PIXELS = 12  # fewest live pixels of a star's window for it to take part
START_STAR_CHI2 = 100.0  # the same at the starting point, where the positions may still be off by a pixel
MIN_EXPLAINED_FRACTION = 0.5  # of the usable stars the model must explain, else the position solution stands
BACKGROUND_STRIDE = 16  # pixel stride of the frame's background-noise sample


def star_kinematics(camera, timing, t0_ns: int, t_ref_ns: int, R: Rotation, omega: np.ndarray, ref: np.ndarray,
                    t_ns: np.ndarray, passes: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each star's position at its own row's mid-exposure, image velocity and ``A_j`` (module docstring).

    Returns ``pv`` (n, 4) = (x, y, vx, vy) px and px/s, ``A`` (n, 4, 6), ``dt`` (n,) s and the own-row
    times (n,) ns. The own-row time is the fixed point ``t = t0 + y ld + E/2``, ``passes``
    iterations from ``t_ns`` (each shrinks a row error ``d`` to ``|v| ld d``: 0.03 d at 10 deg/s on
    he2021a, so two from the stars' measured times leave 0.0006 px of a centroid a 17 px fragment
    off the streak's centre; one from the times of a step before, a few hundredths of a pixel away,
    leaves nothing). ``A``: ``d(x, y)/d(delta, eps) = P [w]x [I, dt I]`` corrected for the own-row time moving
    with ``y`` (``dy = dy0 / (1 - vy ld)``, ``dx = dx0 + vx ld dy``), ``d v / d eps = P [w]x``; the
    velocity's dependence on the attitude (``|omega|`` times smaller) is left out."""
    ld = timing.effective_line_delay_ns * S_PER_NS
    t = np.asarray(t_ns, dtype=np.int64)
    for _ in range(passes):
        dt = (t - np.int64(t_ref_ns)) * S_PER_NS
        w = predicted_directions(R, omega, ref, dt)
        x, y, _ = camera.project(w)
        t = np.asarray(timing.row_mid_exposure_ns(t0_ns, y), dtype=np.int64)
    dt = (t - np.int64(t_ref_ns)) * S_PER_NS
    w = predicted_directions(R, omega, ref, dt)
    x, y, _ = camera.project(w)
    PS = camera.projection_jacobian(w) @ skew(w)  # (n, 2, 3)
    v = PS @ np.asarray(omega, dtype=float)
    shear = np.zeros((len(x), 2, 2))
    shear[:, 1, 1] = 1.0 / (1.0 - v[:, 1] * ld)
    shear[:, 0, 0] = 1.0
    shear[:, 0, 1] = v[:, 0] * ld * shear[:, 1, 1]
    A = np.zeros((len(x), 4, 6))
    A[:, :2, :3] = shear @ PS
    A[:, :2, 3:] = A[:, :2, :3] * dt[:, None, None]
    A[:, 2:, 3:] = PS
    return np.column_stack([x, y, v]), A, dt, t


def background_variance(image: np.ndarray) -> float:
    """The frame's background noise variance (ADU^2): the robust scatter
    (:func:`rollingstar.estimators.centroiders.cog.robust_sigma`, unbiased on integer pixels) of
    every ``BACKGROUND_STRIDE``-th pixel (stars cover a small fraction of them)."""
    sample = np.asarray(image)[::BACKGROUND_STRIDE, ::BACKGROUND_STRIDE]
    return max(robust_sigma(sample) ** 2, 1e-6)


class _Pixels(NamedTuple):
    """The frame's pixels as the compiled normal equations read them (ADU, in place): the image,
    the stars' windows, the saturation level (pixels at or above it are left out), the background
    variance (ADU^2), the shot-noise factor 1 / gain, and the smear model's constants."""

    image: np.ndarray
    row0: np.ndarray
    col0: np.ndarray
    nrows: int
    ncols: int
    saturation: float
    noise2: float
    inv_gain: float
    se: float
    exposure_s: float
    ld_s: float

    def normal_equations(self, pv: np.ndarray, nuis: np.ndarray):
        """Per star ``J^T W J`` (n, 6, 6), ``J^T W r`` (n, 6), chi-square and live pixels at ``(pv, nuis)``
        (:func:`rollingstar.estimators.centroiders.streak_kernel.normal_equations`)."""
        p = np.ascontiguousarray(np.column_stack([pv, nuis]), dtype=float)
        return normal_equations(p, self.row0, self.col0, self.nrows, self.ncols, self.image, self.saturation,
                                self.noise2, self.inv_gain, self.se, self.exposure_s, self.ld_s)

    def at_fitted_nuisance(self, pv: np.ndarray):
        """Each star's flux and background fitted on its predicted profile, and
        :meth:`normal_equations` there: ``(nuis (n, 2), J^T W J, J^T W r, chi-square, live pixels)``
        (:func:`rollingstar.estimators.centroiders.streak_kernel.normal_equations_at_fitted_nuisance`)."""
        return normal_equations_at_fitted_nuisance(
            np.ascontiguousarray(pv[:, :4], dtype=float), self.row0, self.col0, self.nrows, self.ncols, self.image,
            self.saturation, self.noise2, self.inv_gain, self.se, self.exposure_s, self.ld_s)

    def take(self, keep: np.ndarray) -> "_Pixels":
        return self._replace(row0=np.ascontiguousarray(self.row0[keep]), col0=np.ascontiguousarray(self.col0[keep]))


class _Blocks:
    """One Gauss-Newton linearisation of the stars' pixels (module docstring): per star the reduced
    normal ``A^T S A`` and right-hand side ``A^T s`` in ``theta``, the pieces that update the
    nuisances, and the chi-square of its pixels."""

    def __init__(self, M, g, chi2, used, A):
        """From one linearisation's per-star normal equations (:meth:`_Pixels.normal_equations`)."""
        self.chi2 = chi2
        self.dof = np.maximum(used - 6, 1)
        self.C = M[:, :4, 4:]
        self.g_nuis = g[:, 4:]
        self.n_inv, self.normal, self.rhs = _reduced_normal(M, g, np.ascontiguousarray(A, dtype=float))

    def nuisance_step(self, A: np.ndarray, step: np.ndarray) -> np.ndarray:
        """``N^-1 (n - C^T A step)`` per star: the flux and background step that goes with ``step``."""
        k = step.size
        moved = np.einsum("nij,j->ni", A[:, :, :k], step)
        return np.einsum("nij,nj->ni", self.n_inv, self.g_nuis - np.einsum("nji,nj->ni", self.C, moved))


@njit(cache=True, nogil=True)
def _reduced_normal(M, g, A):  # pragma: no cover - compiled
    """Per star the nuisance block's inverse ``N^-1``, ``A^T S A`` and ``A^T s`` (:class:`_Blocks`),
    the 2 x 2 inverse and the Schur complement written out (compiled: a dozen stacked small-matrix
    numpy calls per linearisation cost more than the pixels' sums of a slow frame). Raises
    ``LinAlgError`` when a star's flux and background are not determined (a singular ``N``)."""
    n = M.shape[0]
    n_inv, normal, rhs = np.empty((n, 2, 2)), np.zeros((n, 6, 6)), np.zeros((n, 6))
    CN, S, s, SA = np.empty((4, 2)), np.empty((4, 4)), np.empty(4), np.empty((4, 6))
    for j in range(n):
        a, b, c, d = M[j, 4, 4], M[j, 4, 5], M[j, 5, 4], M[j, 5, 5]
        det = a * d - b * c
        if det == 0.0 or not np.isfinite(det):
            raise np.linalg.LinAlgError("Singular matrix")
        n_inv[j, 0, 0], n_inv[j, 0, 1], n_inv[j, 1, 0], n_inv[j, 1, 1] = d / det, -b / det, -c / det, a / det
        for p in range(4):
            CN[p, 0] = M[j, p, 4] * n_inv[j, 0, 0] + M[j, p, 5] * n_inv[j, 1, 0]
            CN[p, 1] = M[j, p, 4] * n_inv[j, 0, 1] + M[j, p, 5] * n_inv[j, 1, 1]
        for p in range(4):
            s[p] = g[j, p] - (CN[p, 0] * g[j, 4] + CN[p, 1] * g[j, 5])
            for q in range(4):
                S[p, q] = M[j, p, q] - (CN[p, 0] * M[j, q, 4] + CN[p, 1] * M[j, q, 5])
        for p in range(4):
            for v in range(6):
                SA[p, v] = S[p, 0] * A[j, 0, v] + S[p, 1] * A[j, 1, v] + S[p, 2] * A[j, 2, v] + S[p, 3] * A[j, 3, v]
        for u in range(6):
            rhs[j, u] = A[j, 0, u] * s[0] + A[j, 1, u] * s[1] + A[j, 2, u] * s[2] + A[j, 3, u] * s[3]
            for v in range(6):
                normal[j, u, v] = A[j, 0, u] * SA[0, v] + A[j, 1, u] * SA[1, v] + A[j, 2, u] * SA[2, v] + A[j, 3, u] * SA[3, v]
    return n_inv, normal, rhs


def _contraction(A: np.ndarray, step: np.ndarray, pixels: _Pixels) -> float:
    """``d / s``: the largest move ``d`` (px) of a star's image by ``step`` (its position, and its
    streak's ends: the velocity change times half the exposure) over the PSF's effective sigma
    ``s``, the factor by which Gauss-Newton's next step is smaller than this one (module docstring)."""
    move = np.einsum("nij,j->ni", A[:, :, : step.size], step)
    d = max(float(np.max(np.hypot(move[:, 0], move[:, 1]))),
            0.5 * pixels.exposure_s * float(np.max(np.hypot(move[:, 2], move[:, 3]))))
    return d / pixels.se


def _frame_pixels(frame, context, pv: np.ndarray, psf_sigma_px: float, window_sigmas: float) -> _Pixels:
    """The frame's pixels and each star's window
    (:func:`~rollingstar.estimators.centroiders.psf_width.star_windows`) for the pixel model of PSF
    sigma ``psf_sigma_px``."""
    timing = context.timing
    exposure_s, ld_s = timing.exposure_ns * S_PER_NS, timing.effective_line_delay_ns * S_PER_NS
    gain = context.gain_e_per_adu or 1.0
    row0, col0, nr, nc = star_windows(pv, exposure_s, psf_sigma_px, window_sigmas)
    return _Pixels(np.asarray(frame.image), row0, col0, nr, nc, _saturation(context), background_variance(frame.image),
                   1.0 / gain, effective_sigma(psf_sigma_px), exposure_s, ld_s)


def _saturation(context) -> float:
    """The ADC's full scale (ADU): pixels at it carry no information (+inf: unknown)."""
    return float((1 << int(context.bit_depth)) - 1) if context.bit_depth else np.inf


def _kinematics(frame, context, camera, stars, t_ref: int):
    """:func:`star_kinematics` of ``stars`` in ``frame`` as a function of ``(R, omega)``."""
    ref = stars.ref_icrs / np.linalg.norm(stars.ref_icrs, axis=1, keepdims=True)
    return partial(star_kinematics, camera, context.timing, frame.t0_ns, t_ref, ref=ref, t_ns=stars.t_ns)


def measure_psf(frame, context, camera, stars, R: Rotation, omega, t_ref: int, window_sigmas: float) -> float | None:
    """The PSF sigma (px) of the frame's stars at the position solution ``(R, omega)``
    (:func:`rollingstar.estimators.centroiders.psf_width.measure_psf_sigma`), or None."""
    pv = _kinematics(frame, context, camera, stars, t_ref)(R, omega)[0]
    timing = context.timing
    return measure_psf_sigma(np.asarray(frame.image), pv, timing.exposure_ns * S_PER_NS,
                             timing.effective_line_delay_ns * S_PER_NS, _saturation(context),
                             background_variance(frame.image),
                             1.0 / (context.gain_e_per_adu or 1.0), window_sigmas)


def refine_on_pixels(frame, context, camera, stars, R: Rotation, omega, info, fit_rate: bool, t_ref: int, params,
                     psf_sigma_px: float):
    """Attitude, rate, information and flags after the pixel step (module docstring) with the PSF
    sigma ``psf_sigma_px``; the position solution ``(R, omega, info)`` is returned unchanged (and
    flagged) when no star has enough live pixels, or when fewer than two stars pass the screen."""
    kin = _kinematics(frame, context, camera, stars, t_ref)
    pv, A, _, t = kin(R, omega)
    pixels = _frame_pixels(frame, context, pv, psf_sigma_px, params.window_sigmas)
    nuis, *first = pixels.at_fitted_nuisance(pv)  # the start's flux and background, and its linearisation
    usable = first[3] >= MIN_LIVE_PIXELS
    if not usable.any():
        return R, omega, info, frame.flags + ("pixel_step_skipped:no_live_pixels",)
    pixels, nuis, first = pixels.take(usable), nuis[usable], [a[usable] for a in first]
    k = 6 if fit_rate else 3
    start = (R, omega)
    for it in range(params.pixel_iterations + 1):
        if it:  # the first iteration's kinematics are the ones computed above
            pv, A, _, t = kin(R, omega, t_ns=t, passes=1)
        Au = A[usable]
        try:
            b = _Blocks(*(pixels.normal_equations(pv[usable], nuis) if it else first), Au)
        except np.linalg.LinAlgError:  # a star's flux and background not determined by its pixels
            return (*start, info, frame.flags + ("pixel_step_skipped:singular_information",))
        # a loose screen at the start, the strict one after every step (a star the start left out
        # comes back once the fit explains it)
        strict = (nuis[:, 0] > 0) & (b.chi2 / b.dof <= MAX_STAR_CHI2)
        keep = (nuis[:, 0] > 0) & (b.chi2 / b.dof <= START_STAR_CHI2) if it == 0 else strict
        if np.count_nonzero(keep) < max(2, MIN_EXPLAINED_FRACTION * np.count_nonzero(usable)):
            # the model explains too few stars' pixels: a fit to them alone would throw away what
            # the positions of all the others say (a PSF the Gaussian model does not draw)
            return (*start, info, frame.flags + (f"pixel_step_skipped:model_misfit({int(keep.sum())} of "
                                                 f"{int(usable.sum())} stars explained)",))
        normal = np.sum(b.normal[keep][:, :k, :k], axis=0)
        if it == params.pixel_iterations:
            break
        try:
            step = np.linalg.solve(normal, np.sum(b.rhs[keep][:, :k], axis=0))
        except np.linalg.LinAlgError:
            return (*start, info, frame.flags + ("pixel_step_skipped:singular_information",))
        nuis = nuis + b.nuisance_step(Au, step)
        R, omega = apply_step(R, omega, step)
        if np.array_equal(keep, strict):
            in_sigmas = float(np.max(np.abs(step) / np.sqrt(np.diag(np.linalg.inv(normal)))))
            if in_sigmas <= CONVERGED_SIGMAS or in_sigmas * _contraction(Au[keep], step, pixels) <= PREDICTED_SIGMAS:
                break
    dropped = int((~keep).sum()) + int((~usable).sum())
    flags = frame.flags + ((f"pixel_outliers:{dropped}",) if dropped else ())
    return R, np.asarray(omega, dtype=float), 0.5 * (normal + normal.T), flags
