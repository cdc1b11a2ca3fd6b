"""Attitude and body rate of one rolling-shutter frame fitted to the pixels of its stars.

Star ``j``'s window of pixels is drawn by the rolling-shutter smear model
(:func:`rollingstar.sensors.streak_model.streak_mu_jac`) from ``p_j = (x_j, y_j, vx_j, vy_j, F_j,
b_j)``: its position at its own row's mid-exposure and image velocity follow from the frame's
attitude ``R`` (at ``t_ref``) and rate ``omega`` (:func:`star_kinematics`), its flux ``F_j`` and
local background ``b_j`` are its own nuisances. Pixel noise (electrons): the frame's background
variance, measured from the image (read noise, background shot noise and ADC quantisation
together, whatever the bias), plus the star's own shot noise ``mu - b``; saturated pixels are
left out. Gauss-Newton on the weighted pixel residuals with the per-star nuisances eliminated
by their Schur complement (each star's ``(F, b)`` couples only to itself):

    S_j = G_j - C_j N_j^-1 C_j^T,  s_j = g_j - C_j N_j^-1 n_j
    (sum A_j^T S_j A_j) theta_step = sum A_j^T s_j

iterated until a step moves no parameter by more than ``CONVERGED_SIGMAS`` of its sigma (at
least two steps, at most ``pixel_iterations``), with ``G, C, N`` the (position-and-velocity, nuisance) blocks of ``J^T W J``, ``g, n`` those of
``J^T W r``, and ``A_j = d(x_j, y_j, vx_j, vy_j) / d theta``. The information ``sum A_j^T S_j A_j``
at the solution is the Fisher information of ``theta`` in the pixels (the frame-level pixel bound).
A window cut by the detector's edge keeps the pixels it has. A star with fewer than
``MIN_LIVE_PIXELS`` live pixels, or one the model does not explain (non-positive flux, or a
reduced chi-square above ``MAX_STAR_CHI2`` at the current step, above ``START_STAR_CHI2`` at the
start: a wrong identification, a blend), is left out of that step; those left out of the last are
counted in the frame flag ``pixel_outliers:N``.
"""
from __future__ import annotations

from functools import partial

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.frame_fit import apply_step, predicted_directions
from rollingstar.estimators.centroiders.cog import robust_sigma
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.so3 import skew
from rollingstar.sensors.streak_model import streak_mu_jac

MAX_STAR_CHI2 = 2.0  # reduced chi-square above which a star's pixels contradict the model (a right one: 1 +- 0.1)
CONVERGED_SIGMAS = 0.05  # a step below this fraction of every parameter's sigma ends the iterations
MIN_LIVE_PIXELS = 12  # fewest live pixels of a star's window for it to take part
START_STAR_CHI2 = 100.0  # the same at the starting point, where the positions may still be off by a pixel
BACKGROUND_STRIDE = 8  # pixel stride of the frame's background-noise sample


def star_kinematics(camera, timing, t0_ns: int, t_ref_ns: int, R: Rotation, omega: np.ndarray, ref: np.ndarray,
                    t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each star's position at its own row's mid-exposure, image velocity and ``A_j`` (module docstring).

    Returns ``pv`` (n, 4) = (x, y, vx, vy) px and px/s, ``A`` (n, 4, 6) and ``dt`` (n,) s. The own-row
    time is the fixed point ``t = t0 + y ld + E/2`` (two iterations from the stars' measured
    times). ``A``: ``d(x, y)/d(delta, eps) = P [w]x [I, dt I]`` corrected for the own-row time moving
    with ``y`` (``dy = dy0 / (1 - vy ld)``, ``dx = dx0 + vx ld dy``), ``d v / d eps = P [w]x``; the
    velocity's dependence on the attitude (``|omega|`` times smaller) is left out."""
    ld = timing.effective_line_delay_ns * S_PER_NS
    t = np.asarray(t_ns, dtype=np.int64)
    for _ in range(2):
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
    return np.column_stack([x, y, v]), A, dt


def background_variance(image: np.ndarray, gain_e_per_adu: float) -> float:
    """The frame's background noise variance (e^2): the robust scatter
    (:func:`rollingstar.estimators.centroiders.cog.robust_sigma`, unbiased on integer pixels) of
    every ``BACKGROUND_STRIDE``-th pixel (stars cover a small fraction of them)."""
    sample = np.asarray(image)[::BACKGROUND_STRIDE, ::BACKGROUND_STRIDE]
    return max((robust_sigma(sample) * gain_e_per_adu) ** 2, 1e-6)


def _windows(pv: np.ndarray, exposure_s: float, params):
    """Equal-size windows covering every star's streak: ``row0, col0, nrows, ncols``."""
    half = params.window_sigmas * params.psf_sigma_px + 1.0
    ext_x = 0.5 * np.abs(pv[:, 2]) * exposure_s * 1.1 + half
    ext_y = 0.5 * np.abs(pv[:, 3]) * exposure_s * 1.1 + half
    nr = 2 * int(np.ceil(ext_y.max())) + 1
    nc = 2 * int(np.ceil(ext_x.max())) + 1
    row0 = np.rint(pv[:, 1]).astype(np.int64) - nr // 2
    col0 = np.rint(pv[:, 0]).astype(np.int64) - nc // 2
    return row0, col0, nr, nc


def _cut(image: np.ndarray, gain_e_per_adu: float, bit_depth: int | None, row0, col0, nr: int, nc: int):
    """The stars' windows (n, nr, nc) in electrons (bias included: each star's background absorbs
    it) and the masks of their live pixels: on the detector and not saturated (a window cut by the
    detector's edge keeps the pixels it has, so an edge star is fitted without the bias a
    truncated centroid has)."""
    img = np.asarray(image)
    rr = row0[:, None, None] + np.arange(nr)[None, :, None]
    cc = col0[:, None, None] + np.arange(nc)[None, None, :]
    on = (rr >= 0) & (rr < img.shape[0]) & (cc >= 0) & (cc < img.shape[1])
    adu = img[np.clip(rr, 0, img.shape[0] - 1), np.clip(cc, 0, img.shape[1] - 1)]
    live = on & (adu < ((1 << int(bit_depth)) - 1) if bit_depth else on)
    return adu.astype(np.float64) * gain_e_per_adu, live


class _Blocks:
    """One Gauss-Newton linearisation of the stars' pixels (module docstring): per star the reduced
    normal ``A^T S A`` and right-hand side ``A^T s`` in ``theta``, the pieces that update the
    nuisances, and the chi-square of its pixels."""

    def __init__(self, pv, A, nuis, data, live, bg_var, row0, col0, nr, nc, params, exposure_s, ld_s):
        n = pv.shape[0]
        mu, jac = streak_mu_jac(np.column_stack([pv, nuis]), row0, col0, nr, nc, params.psf_sigma_px,
                                exposure_s, ld_s)
        var = bg_var + np.maximum(mu - nuis[:, 1, None, None], 0.0)
        wt = (live / var).reshape(n, -1)
        r = (data - mu).reshape(n, -1)
        J = jac.reshape(n, 6, -1)
        JW = J * wt[:, None, :]
        M = JW @ np.swapaxes(J, 1, 2)
        g = np.einsum("nkp,np->nk", JW, r)
        self.chi2 = np.sum(wt * r * r, axis=1)
        self.dof = np.maximum(np.count_nonzero(wt, axis=1) - 6, 1)
        self.n_inv = np.linalg.inv(M[:, 4:, 4:])
        self.C = M[:, :4, 4:]
        self.g_nuis = g[:, 4:]
        CN = self.C @ self.n_inv
        S = M[:, :4, :4] - CN @ np.swapaxes(self.C, 1, 2)
        s = g[:, :4] - np.einsum("nij,nj->ni", CN, self.g_nuis)
        At = np.swapaxes(A, 1, 2)
        self.normal = At @ S @ A
        self.rhs = np.einsum("nij,nj->ni", At, s)

    def nuisance_step(self, A: np.ndarray, step: np.ndarray) -> np.ndarray:
        """``N^-1 (n - C^T A step)`` per star: the flux and background step that goes with ``step``."""
        k = step.size
        moved = np.einsum("nij,j->ni", A[:, :, :k], step)
        return np.einsum("nij,nj->ni", self.n_inv, self.g_nuis - np.einsum("nji,nj->ni", self.C, moved))


def _initial_nuisance(pv, data, live, bg_var, row0, col0, nr, nc, params, exposure_s, ld_s) -> np.ndarray:
    """Per-star flux and background by weighted linear least squares on the predicted spot shape."""
    n = pv.shape[0]
    unit = np.column_stack([pv, np.ones(n), np.zeros(n)])
    shape, _ = streak_mu_jac(unit, row0, col0, nr, nc, params.psf_sigma_px, exposure_s, ld_s)
    g, d, w = shape.reshape(n, -1), data.reshape(n, -1), live.reshape(n, -1) / bg_var
    sgg, sg, s1 = np.sum(w * g * g, 1), np.sum(w * g, 1), np.sum(w, 1)
    sgd, sd = np.sum(w * g * d, 1), np.sum(w * d, 1)
    det = sgg * s1 - sg * sg
    flux = (s1 * sgd - sg * sd) / det
    background = (sgg * sd - sg * sgd) / det
    return np.column_stack([flux, background])


def refine_on_pixels(frame, context, camera, stars, R: Rotation, omega, info, fit_rate: bool, t_ref: int, params):
    """Attitude, rate, information and flags after the pixel step (module docstring); the position
    solution ``(R, omega, info)`` is returned unchanged when no star has enough live pixels."""
    timing = context.timing
    exposure_s, ld_s = timing.exposure_ns * S_PER_NS, timing.effective_line_delay_ns * S_PER_NS
    gain = context.gain_e_per_adu or 1.0
    bg_var = background_variance(frame.image, gain)
    ref = stars.ref_icrs / np.linalg.norm(stars.ref_icrs, axis=1, keepdims=True)
    kin = partial(star_kinematics, camera, timing, frame.t0_ns, t_ref, ref=ref, t_ns=stars.t_ns)
    pv, A, _ = kin(R, omega)
    row0, col0, nr, nc = _windows(pv, exposure_s, params)
    data, live = _cut(frame.image, gain, context.bit_depth, row0, col0, nr, nc)
    usable = np.count_nonzero(live.reshape(len(pv), -1), axis=1) >= MIN_LIVE_PIXELS
    if not usable.any():
        return R, omega, info, frame.flags + ("pixel_step_skipped:no_live_pixels",)
    data, live = data[usable], live[usable]
    win = (row0[usable], col0[usable], nr, nc, params, exposure_s, ld_s)
    nuis = _initial_nuisance(pv[usable], data, live, bg_var, *win)
    k = 6 if fit_rate else 3
    converged = False
    for it in range(params.pixel_iterations + 1):
        pv, A, _ = kin(R, omega)
        b = _Blocks(pv[usable], A[usable], nuis, data, live, bg_var, *win)
        # a loose screen at the start, the strict one after every step (a star the start left out
        # comes back once the fit explains it)
        keep = (nuis[:, 0] > 0) & (b.chi2 / b.dof <= (START_STAR_CHI2 if it == 0 else MAX_STAR_CHI2))
        normal = np.sum(b.normal[keep][:, :k, :k], axis=0)
        if it == params.pixel_iterations or (it >= 2 and converged):
            break
        step = np.linalg.solve(normal, np.sum(b.rhs[keep][:, :k], axis=0))
        converged = bool(np.all(np.abs(step) <= CONVERGED_SIGMAS * np.sqrt(np.diag(np.linalg.inv(normal)))))
        nuis = nuis + b.nuisance_step(A[usable], step)
        R, omega = apply_step(R, omega, step)
    dropped = int((~keep).sum()) + int((~usable).sum())
    flags = frame.flags + ((f"pixel_outliers:{dropped}",) if dropped else ())
    return R, np.asarray(omega, dtype=float), 0.5 * (normal + normal.T), flags
