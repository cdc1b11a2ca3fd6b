"""Pixel-level Cramér–Rao bound of one star's position: the Fisher information of its pixels.

The centroid-level bound the evaluation quotes takes a centroid sigma as given; this one derives
it from the pixels. Model of one spot on a pixel grid: the expected signal of pixel ``j`` (column
``u_j``, row ``v_j``, electrons) is

    mu_j = F * g(u_j - x) * g(v_j - y) + b,   g(d) = Phi((d + 1/2) / s) - Phi((d - 1/2) / s)

(a Gaussian PSF of width ``s`` integrated over the square pixel, ``F`` the star's electrons, ``b``
the background electrons per pixel); each pixel's noise is Poisson (shot noise of star and
background) plus Gaussian read noise ``r``. The Fisher information for parameters ``theta`` is

    I = sum_j (d mu_j / d theta)(d mu_j / d theta)^T / (mu_j + r^2)

exact for Poisson pixels (``r = 0``) and the usual approximation with read noise (Mortensen et
al. 2010, Nat. Methods 7:377, for the same model). Parameters: ``x, y`` and the nuisances ``F``
and ``b``; the bound on the position is the ``(x, y)`` block of ``I^-1``. Known answer: a
well-sampled spot without background or read noise gives ``var(x) = (s^2 + 1/12) / F`` (the PSF
variance plus the pixel's).

A moving star (:func:`smeared_spot_fisher`) is the same PSF swept along its image velocity
``(vx, vy)`` (px/s) over each row's own exposure window: row ``v`` starts ``(v - y) * line_delay``
after the star's own row, so its segment is ``x + vx (tau + (v - y) ld)``, ``tau`` over the exposure
``E``, and the pixel's expectation is the average of the PSF over that segment (``n_sub`` points).
Parameters ``(x, y, vx, vy, F, b)``: the position at the star's own row's mid-exposure (the time
a raw centroid refers to), its velocity, flux and background; derivatives by central differences.
ADC quantisation adds ``gain^2 / 12`` e^2 to each pixel's variance, and a pixel whose expectation
reaches the full well carries no information (it reads the saturation level whatever the
parameters).
Written by hand: the sum is a dozen numpy lines, and no maintained package computes it.

Frame bound on attitude and body rate (:func:`frame_crb`): the stars of one frame share the
attitude and the rate. With constant rate over the frame the attitude is
``R(t) = R_ref Exp(delta) Exp((omega + eps)(t - t_ref))`` (camera to ICRS, ``delta`` a body-frame
perturbation at ``t_ref``, ``eps`` one of the rate; the convention of
:func:`rollingstar.pipelines.truth.rate_crb_rad2`, which is this model linearised at ``omega = 0``),
so a star of catalogue direction ``s`` has the camera vector ``w(t) = R(t)^T s`` and its smear
parameters ``(x, y, vx, vy)`` (:func:`track_parameters`) are functions of ``theta = (delta, eps)``:
``(x, y)`` the projection at its own row's mid-exposure ``t = t0 + y ld + E/2`` (a fixed point in
``y``, solved by iteration: it contracts by ``|vy ld|`` per step), ``(vx, vy) = P(w) (w x omega)``
(``P`` the projection Jacobian). With ``A_j = d(x, y, vx, vy)/d theta`` (central differences,
:func:`track_jacobian`) and ``S_j`` the star's smear Fisher information (:func:`star_fisher`) with
its flux and the background eliminated (the Schur complement onto ``(x, y, vx, vy)``), the frame's
information is
``F = sum_j A_j^T S_j A_j`` and its inverse the joint bound on ``(delta, eps)``: the attitude at
``t_ref`` with the rate unknown, and the rate. The rate block does not depend on ``t_ref``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import ndtr

from rollingstar.sensors.so3 import cross
from rollingstar.sensors.streak_model import streak_fisher

_SQRT_2PI = np.sqrt(2.0 * np.pi)


def _pixel_profile(d: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """The PSF integrated over pixels at offsets ``d`` from the centre, and its derivative in the centre."""
    hi, lo = (d + 0.5) / s, (d - 0.5) / s
    g = ndtr(hi) - ndtr(lo)
    # d g / d centre = -d g / d d = -(phi(hi) - phi(lo)) / s
    dg = -(np.exp(-0.5 * hi**2) - np.exp(-0.5 * lo**2)) / (_SQRT_2PI * s)
    return g, dg


def spot_fisher(x: float, y: float, flux_e: float, psf_sigma_px: float, background_e: float = 0.0,
                read_noise_e: float = 0.0, half_width_px: int | None = None) -> np.ndarray:
    """Fisher information (4 x 4) of ``(x, y, flux, background)`` from the pixels around the spot
    (module docstring); ``half_width_px`` the window's half width (default ``ceil(6 s) + 1``)."""
    s = float(psf_sigma_px)
    h = int(np.ceil(6.0 * s)) + 1 if half_width_px is None else int(half_width_px)
    cols = np.arange(np.floor(x) - h, np.floor(x) + h + 1)
    rows = np.arange(np.floor(y) - h, np.floor(y) + h + 1)
    gx, dgx = _pixel_profile(cols - x, s)
    gy, dgy = _pixel_profile(rows - y, s)
    shape = np.outer(gy, gx)  # rows x columns
    mu = flux_e * shape + background_e
    grads = np.stack([flux_e * np.outer(gy, dgx), flux_e * np.outer(dgy, gx), shape,
                      np.ones_like(shape)]).reshape(4, -1)
    var = mu.reshape(-1) + float(read_noise_e) ** 2
    return (grads / var) @ grads.T


def position_crb_px(x: float, y: float, flux_e: float, psf_sigma_px: float, background_e: float = 0.0,
                    read_noise_e: float = 0.0) -> np.ndarray:
    """The Cramér–Rao bound (2 x 2 covariance, px^2) of the spot's ``(x, y)`` with its flux and the
    background unknown too."""
    info = spot_fisher(x, y, flux_e, psf_sigma_px, background_e, read_noise_e)
    return np.linalg.inv(info)[:2, :2]


def _smeared_mu(p: np.ndarray, cols: np.ndarray, rows: np.ndarray, s: float, exposure_s: float,
                line_delay_s: float, n_sub: int) -> np.ndarray:
    """Expected electrons (rows x columns) of a swept spot, ``p = (x, y, vx, vy, F, b)``."""
    x, y, vx, vy, flux, b = p
    tau = (np.arange(n_sub) + 0.5) / n_sub * exposure_s - 0.5 * exposure_s  # about mid-exposure
    shift = tau[:, None] + (rows[None, :] - y) * line_delay_s  # (n_sub, rows): time from the reference
    cx = x + vx * shift  # (n_sub, rows)
    cy = y + vy * shift
    hi_x = (cols[None, None, :] - cx[:, :, None] + 0.5) / s
    lo_x = (cols[None, None, :] - cx[:, :, None] - 0.5) / s
    hi_y = (rows[None, :] - cy + 0.5) / s
    lo_y = (rows[None, :] - cy - 0.5) / s
    gx = ndtr(hi_x) - ndtr(lo_x)  # (n_sub, rows, cols)
    gy = (ndtr(hi_y) - ndtr(lo_y))[:, :, None]
    return flux * np.mean(gx * gy, axis=0) + b


def smeared_spot_fisher(x: float, y: float, vx: float, vy: float, flux_e: float, psf_sigma_px: float,
                        exposure_s: float, line_delay_s: float = 0.0, background_e: float = 0.0,
                        read_noise_e: float = 0.0, gain_e_per_adu: float = 0.0, full_well_e: float = np.inf,
                        n_sub: int = 64) -> np.ndarray:
    """Fisher information (6 x 6) of ``(x, y, vx, vy, flux, background)`` of a star moving during
    its rolling-shutter exposure (module docstring); ``gain_e_per_adu`` 0: no quantisation."""
    s = float(psf_sigma_px)
    reach = abs(vx) + abs(vy)
    h = int(np.ceil(6.0 * s + 0.5 * reach * (exposure_s + 12.0 * s * line_delay_s))) + 1
    cols = np.arange(np.floor(x) - h, np.floor(x) + h + 1)
    rows = np.arange(np.floor(y) - h, np.floor(y) + h + 1)
    p = np.array([x, y, vx, vy, flux_e, background_e], dtype=float)
    steps = np.array([1e-4, 1e-4, 1e-2, 1e-2, 1e-3 * max(flux_e, 1.0), 1e-3 * max(background_e, 1.0)])
    mu = _smeared_mu(p, cols, rows, s, exposure_s, line_delay_s, n_sub)
    grads = np.empty((6, mu.size))
    for k in range(6):
        dp = np.zeros(6)
        dp[k] = steps[k]
        grads[k] = ((_smeared_mu(p + dp, cols, rows, s, exposure_s, line_delay_s, n_sub)
                     - _smeared_mu(p - dp, cols, rows, s, exposure_s, line_delay_s, n_sub)) / (2.0 * steps[k])).ravel()
    var = mu.ravel() + float(read_noise_e) ** 2 + float(gain_e_per_adu) ** 2 / 12.0
    live = mu.ravel() < full_well_e
    return (grads[:, live] / var[live]) @ grads[:, live].T


_ROW_TOLERANCE_PX = 1e-11  # the own-row fixed point is iterated to this
_MAX_ROW_ITERATIONS = 60
_DELTA_STEP_RAD = 1e-6  # central-difference steps of the attitude and of the rate
_EPS_STEP_RAD_S = 1e-6


@dataclass(frozen=True)
class FrameDetector:
    """The detector of one frame as the pixel bound sees it.

    ``background_e``: expected background electrons per pixel over the exposure (sky plus dark
    current); ``saturation_e``: the signal at which a pixel stops carrying information (the full
    well, or the ADC's top code if it comes first); ``gain_e_per_adu`` 0: no quantisation.
    """

    psf_sigma_px: float
    exposure_s: float
    line_delay_s: float = 0.0
    background_e: float = 0.0
    read_noise_e: float = 0.0
    gain_e_per_adu: float = 0.0
    saturation_e: float = np.inf

    @classmethod
    def from_image_model(cls, model, exposure_ns: int, line_delay_ns: int) -> FrameDetector:
        """From a :class:`rollingstar.sensors.image_sim.ImageModel` (hot pixels left out) and the timing."""
        exposure_s = exposure_ns * 1e-9
        adc_top_e = (model.max_adu - model.bias_adu) * model.gain_e_per_adu
        return cls(psf_sigma_px=float(model.psf_sigma_px), exposure_s=exposure_s, line_delay_s=line_delay_ns * 1e-9,
                   background_e=(model.background_e_per_px_s + model.dark_e_per_px_s) * exposure_s,
                   read_noise_e=float(model.read_noise_e), gain_e_per_adu=float(model.gain_e_per_adu),
                   saturation_e=float(min(model.full_well_e, adc_top_e)))


def star_fisher(p: np.ndarray, det: FrameDetector) -> np.ndarray:
    """Fisher information (6 x 6) of one star's ``p = (x, y, vx, vy, flux_e, background_e)``: the one
    per-star call of the frame bound. It is :func:`rollingstar.sensors.streak_model.streak_fisher`,
    the definition of :func:`smeared_spot_fisher` with the pixel-integrated PSF replaced by a
    Gaussian of the same second moment and the time integral in closed form (within 0.5 % of it on
    he2021a's stars from 0 to 10 deg/s, and hundreds of times faster on long smears)."""
    return streak_fisher(np.asarray(p, dtype=float), det.psf_sigma_px, det.exposure_s, det.line_delay_s,
                         det.read_noise_e, det.gain_e_per_adu, det.saturation_e)


def schur_information(info: np.ndarray, keep) -> np.ndarray:
    """Information on the parameters ``keep`` with every other one unknown: the Schur complement
    ``I_kk - I_kn I_nn^-1 I_nk``."""
    keep = np.asarray(keep)
    rest = np.setdiff1d(np.arange(info.shape[0]), keep)
    if rest.size == 0:
        return info[np.ix_(keep, keep)]
    kn = info[np.ix_(keep, rest)]
    return info[np.ix_(keep, keep)] - kn @ np.linalg.solve(info[np.ix_(rest, rest)], kn.T)


def _rotate(rotvec: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``Exp(rotvec) v`` element by element over matching leading shapes (..., 3)."""
    shape = np.broadcast_shapes(rotvec.shape, v.shape)
    rv = np.array(np.broadcast_to(rotvec, shape)).reshape(-1, 3)
    vv = np.array(np.broadcast_to(v, shape)).reshape(-1, 3)
    return Rotation.from_rotvec(rv).apply(vv).reshape(shape)


def _tracks(camera, attitude_ref, omega_rad_s, unit_icrs, t0_s: float, det: FrameDetector,
            thetas: np.ndarray) -> np.ndarray:
    """:func:`track_parameters` for each of the perturbations ``thetas`` (m, 6): (m, n, 4)."""
    omega = np.asarray(omega_rad_s, dtype=float)[None, :] + thetas[:, 3:]  # (m, 3)
    w0 = attitude_ref.inv().apply(np.asarray(unit_icrs, dtype=float).reshape(-1, 3))
    w_ref = _rotate(-thetas[:, None, :3], w0[None, :, :])  # (m, n, 3)
    mid0 = t0_s + 0.5 * det.exposure_s
    y = camera.project(w_ref)[1]
    for _ in range(_MAX_ROW_ITERATIONS):
        w = _rotate(-omega[:, None, :] * (mid0 + y * det.line_delay_s)[..., None], w_ref)
        y_next = camera.project(w)[1]
        done = np.all(~(np.abs(y_next - y) > _ROW_TOLERANCE_PX))  # NaN (behind the camera) counts as done
        y = y_next
        if done:
            break
    w = _rotate(-omega[:, None, :] * (mid0 + y * det.line_delay_s)[..., None], w_ref)
    x, y, _ = camera.project(w)
    v = np.einsum("...ij,...j->...i", camera.projection_jacobian(w), cross(w, omega[:, None, :]))
    return np.stack([x, y, v[..., 0], v[..., 1]], axis=-1)


def track_parameters(camera, attitude_ref, omega_rad_s, unit_icrs, t0_s: float, det: FrameDetector,
                     theta=None) -> np.ndarray:
    """Smear parameters ``(x, y, vx, vy)`` (n, 4; px, px/s) of stars ``unit_icrs`` (n, 3) in a frame
    whose row 0 starts exposing at ``t0_s`` (seconds after ``t_ref``), for the attitude
    ``attitude_ref`` (scipy Rotation, camera to ICRS, at ``t_ref``) and body rate ``omega_rad_s``
    perturbed by ``theta = (delta, eps)`` (module docstring)."""
    theta = np.zeros(6) if theta is None else np.asarray(theta, dtype=float)
    return _tracks(camera, attitude_ref, omega_rad_s, unit_icrs, t0_s, det, theta.reshape(1, 6))[0]


def track_jacobian(camera, attitude_ref, omega_rad_s, unit_icrs, t0_s: float,
                   det: FrameDetector) -> tuple[np.ndarray, np.ndarray]:
    """The stars' smear parameters (n, 4) and their derivatives ``d(x, y, vx, vy)/d(delta, eps)``
    (n, 4, 6), by central differences of :func:`track_parameters` (all 13 evaluations at once)."""
    steps = np.diag(np.r_[np.full(3, _DELTA_STEP_RAD), np.full(3, _EPS_STEP_RAD_S)])
    out = _tracks(camera, attitude_ref, omega_rad_s, unit_icrs, t0_s, det, np.vstack([np.zeros(6), steps, -steps]))
    jac = (out[1:7] - out[7:13]) / (2.0 * np.diag(steps))[:, None, None]  # (6, n, 4)
    return out[0], np.moveaxis(jac, 0, -1)


def frame_fisher(params: np.ndarray, jac: np.ndarray, electrons, det: FrameDetector,
                 velocity: bool = True) -> np.ndarray:
    """Fisher information (6 x 6) of ``(delta, eps)`` from the pixels of the stars with smear
    parameters ``params`` (n, 4), Jacobians ``jac`` (n, 4, 6) and signal ``electrons`` (n,);
    ``velocity`` False: the smears' velocities are taken as known, only their positions inform."""
    keep = [0, 1, 2, 3] if velocity else [0, 1]
    known = [] if velocity else [2, 3]  # parameters taken as known: left out of the star's information
    free = [k for k in range(6) if k not in known]
    fisher = np.zeros((6, 6))
    for p, a, flux in zip(params, jac, np.broadcast_to(electrons, (len(params),))):
        info = star_fisher(np.array([*p, flux, det.background_e]), det)[np.ix_(free, free)]
        s = schur_information(info, range(len(keep)))  # flux and background eliminated
        fisher += a[keep].T @ s @ a[keep]
    return fisher


def frame_crb(camera, attitude_ref, omega_rad_s, unit_icrs, electrons, t0_s: float, det: FrameDetector,
              velocity: bool = True) -> np.ndarray:
    """Joint Cramér–Rao bound (6 x 6) of ``(delta, eps)``: the attitude at ``t_ref`` (rad^2, top-left
    block) and the body rate ((rad/s)^2, bottom-right), both unknown, from one frame's pixels
    (module docstring); NaN when the frame does not determine both."""
    params, jac = track_jacobian(camera, attitude_ref, omega_rad_s, unit_icrs, t0_s, det)
    ok = np.all(np.isfinite(params), axis=1)
    fisher = frame_fisher(params[ok], jac[ok], np.broadcast_to(electrons, (len(params),))[ok], det, velocity)
    try:
        return np.linalg.inv(fisher)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.nan)
