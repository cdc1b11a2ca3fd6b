"""Radial-distortion camera model and its least-squares fit to identified stars (one or many images).

Model (the convention of :class:`rollingstar.sensors.effects.radial_distortion.RadialDistortion`, Brown-Conrady
radial terms): a camera-frame direction ``w`` goes to the ideal pinhole position (he2021b eq 2)
``xn = -w_x / w_z``, ``yn = -w_y / w_z`` (normalised coordinates), then

    x = cx + f * xn * (1 + k1 r^2 + k2 r^4),   y = cy + f * yn * (1 + k1 r^2 + k2 r^4),   r^2 = xn^2 + yn^2.

``k1 < 0`` is barrel distortion. (tetra3rs' ``RadialDistortion`` is the same model in pixel
units, ``k1 / f^2``, ``k2 / f^4``.)

:func:`fit_camera` estimates, by Levenberg-Marquardt (``scipy.optimize.least_squares``, analytic Jacobian), one
attitude per image (``R_i = R0_i Exp(delta_i)``) together with *shared* intrinsics: the focal
length ``f`` and any of ``k1, k2, cx, cy`` chosen by the caller. Residuals are the pixel
differences ``(x, y)_obs - proj(R_i^T r)``; 1-sigma uncertainties come from
``cov = s^2 (J^T J)^-1`` with ``s^2 = sum r^2 / (2 n - p)`` (the observed scatter, not an assumed
centroid noise), so they are only as good as the model: check that independent images agree
within them (tests/realdata).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from rollingstar.sensors.camera import radial_distort, radial_undistort
from rollingstar.sensors.so3 import skew

INTRINSICS = ("focal_px", "k1", "k2", "cx", "cy")


@dataclass(frozen=True)
class RadialCamera:
    """Pinhole + radial distortion (module docstring). Pixel units; ``(cx, cy)`` is the principal point."""

    focal_px: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0

    @classmethod
    def from_pinhole(cls, camera, k1: float = 0.0, k2: float = 0.0) -> "RadialCamera":
        return cls(float(camera.focal_px), float(camera.cx), float(camera.cy), float(k1), float(k2))

    def pinhole(self, camera):
        """``camera`` (a :class:`rollingstar.sensors.camera.PinholeCamera`) with this focal length and principal point."""
        return replace(camera, focal_length_m=self.focal_px * camera.pixel_size_m, cx=self.cx, cy=self.cy)

    def camera(self, camera):
        """``camera`` with this model's focal length, principal point and distortion: the one camera
        model every later stage uses (``FrameData.camera``)."""
        return replace(self.pinhole(camera), k1=self.k1, k2=self.k2)

    def distort(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Ideal pinhole pixels -> observed (distorted) pixels."""
        return radial_distort(x, y, self.cx, self.cy, self.focal_px, self.k1, self.k2)

    def undistort(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Observed pixels -> ideal pinhole pixels (:func:`rollingstar.sensors.camera.radial_undistort`)."""
        return radial_undistort(x, y, self.cx, self.cy, self.focal_px, self.k1, self.k2)

    def project(self, w_cam) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-frame directions (n, 3) -> observed pixels ``(x, y, in_front)``."""
        w = np.asarray(w_cam, dtype=float).reshape(-1, 3)
        front = w[:, 2] > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = np.where(front, -w[:, 0] / w[:, 2], np.nan)
            yn = np.where(front, -w[:, 1] / w[:, 2], np.nan)
        x, y = self.distort(self.cx + self.focal_px * xn, self.cy + self.focal_px * yn)
        return x, y, front

    def unproject(self, x, y) -> np.ndarray:
        """Observed pixels -> unit camera-frame directions (he2021b eq 2 after undistortion)."""
        xu, yu = self.undistort(x, y)
        w = np.stack([-(xu - self.cx), -(yu - self.cy), np.full(np.shape(xu), self.focal_px)], axis=-1)
        return w / np.linalg.norm(w, axis=-1, keepdims=True)


@dataclass(frozen=True)
class CameraFit:
    """Result of :func:`fit_camera`.

    ``values``/``sigma``: fitted shared intrinsics by name (``INTRINSICS`` order, only those fitted
    in ``sigma``); ``camera``: the fitted :class:`RadialCamera`; ``attitudes``: per image;
    ``residuals``: per image ``(n_i, 2)`` observed - predicted px; ``rms_px`` over all stars.
    """

    camera: RadialCamera
    attitudes: tuple[Rotation, ...]
    fitted: tuple[str, ...]
    sigma: dict
    residuals: tuple[np.ndarray, ...]
    rms_px: float
    n_stars: int
    dof: int
    success: bool

    @property
    def values(self) -> dict:
        return {k: float(getattr(self.camera, k)) for k in INTRINSICS}

    def rms_per_image(self) -> np.ndarray:
        return np.array([np.sqrt(np.mean(np.sum(r**2, axis=1))) if r.size else np.nan for r in self.residuals])


def fit_camera(observations, attitudes, camera: RadialCamera, fit=("focal_px", "k1", "k2"),
               max_nfev: int | None = None) -> CameraFit:
    """Joint least squares of per-image attitudes and shared intrinsics (module docstring).

    ``observations``: sequence of ``(x, y, ref_icrs)`` per image (pixels, (n_i, 3) ICRS unit
    vectors of the identified stars); ``attitudes``: per-image starting camera-to-ICRS rotations;
    ``camera``: starting intrinsics (the ones not in ``fit`` stay fixed).
    """
    fit = tuple(fit)
    unknown = [k for k in fit if k not in INTRINSICS]
    if unknown:
        raise ValueError(f"fit_camera: unknown intrinsic(s) {unknown}; choose from {INTRINSICS}")
    m = len(observations)
    if m == 0 or len(attitudes) != m:
        raise ValueError(f"fit_camera: {m} observation sets and {len(attitudes)} attitudes")
    obs = [np.column_stack([np.asarray(x, float), np.asarray(y, float)]) for x, y, _ in observations]
    refs = [np.asarray(r, float).reshape(-1, 3) for _, _, r in observations]
    n = sum(o.shape[0] for o in obs)
    p = 3 * m + len(fit)
    if 2 * n <= p:
        raise ValueError(f"fit_camera: {n} stars give {2 * n} residuals for {p} parameters")
    base = {k: float(getattr(camera, k)) for k in INTRINSICS}

    def unpack(q):
        vals = dict(base)
        vals.update(zip(fit, q[3 * m:]))
        return RadialCamera(**vals), [a * Rotation.from_rotvec(q[3 * i:3 * i + 3]) for i, a in enumerate(attitudes)]

    def resid(q):
        cam, rots = unpack(q)
        out = []
        for o, r, R in zip(obs, refs, rots):
            x, y, _ = cam.project(R.inv().apply(r))
            out.append((o - np.column_stack([x, y])).ravel())
        return np.concatenate(out)

    def jac(q):
        """Analytic d(residual)/dq, image by image (:func:`_image_jacobian`)."""
        cam, rots = unpack(q)
        J = np.zeros((2 * n, p))
        row = 0
        for i, (r, R) in enumerate(zip(refs, rots)):
            k = r.shape[0]
            J[row:row + 2 * k, 3 * i:3 * i + 3], J[row:row + 2 * k, 3 * m:] = _image_jacobian(cam, R.inv().apply(r), fit)
            row += 2 * k
        return J

    q0 = np.concatenate([np.zeros(3 * m), [base[k] for k in fit]])
    scale = {"focal_px": base["focal_px"] * 1e-3, "k1": 1e-2, "k2": 1e-1, "cx": 1.0, "cy": 1.0}
    x_scale = np.concatenate([np.full(3 * m, 1e-4), [scale[k] for k in fit]])
    sol = least_squares(resid, q0, jac=jac, method="lm", x_scale=x_scale, max_nfev=max_nfev, xtol=1e-12, ftol=1e-12)
    cam, rots = unpack(sol.x)
    r = sol.fun
    dof = r.size - p
    s2 = float(r @ r) / dof
    J = jac(sol.x)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
        sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        sig = np.full(p, np.inf)
    sizes = np.cumsum([0] + [o.shape[0] for o in obs])
    res2 = r.reshape(-1, 2)
    residuals = tuple(res2[sizes[i]:sizes[i + 1]] for i in range(m))
    return CameraFit(camera=cam, attitudes=tuple(rots), fitted=fit, sigma=dict(zip(fit, sig[3 * m:].tolist())),
                     residuals=residuals, rms_px=float(np.sqrt(np.mean(np.sum(res2**2, axis=1)))), n_stars=n, dof=dof,
                     success=bool(sol.success))


def _image_jacobian(cam: RadialCamera, w: np.ndarray, fit: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """d(residual)/d(attitude increment) (2k, 3) and d(residual)/d(fitted intrinsics) (2k, len(fit))
    of one image's ``k`` stars with camera-frame directions ``w`` (k, 3), rows x0, y0, x1, y1, ...

    ``w = Exp(delta)^T R0^T r`` so ``dw/d delta = [w]_x`` (to first order in delta, which is what
    the iteration re-linearises about), then the chain rule through ``xn = -w_x / w_z``, the radial
    factor and the pixel map (module docstring)."""
    k = w.shape[0]
    iz = 1.0 / w[:, 2]
    xn, yn = -w[:, 0] * iz, -w[:, 1] * iz
    r2 = xn * xn + yn * yn
    s_ = 1.0 + cam.k1 * r2 + cam.k2 * r2 * r2
    ds = cam.k1 + 2.0 * cam.k2 * r2  # d s / d r2
    f = cam.focal_px
    # d(x, y)/d(xn, yn)
    a11 = f * (s_ + 2.0 * xn * xn * ds)
    a12 = f * 2.0 * xn * yn * ds
    a22 = f * (s_ + 2.0 * yn * yn * ds)
    # d(xn, yn)/dw
    dxn = np.column_stack([-iz, np.zeros(k), w[:, 0] * iz * iz])
    dyn = np.column_stack([np.zeros(k), -iz, w[:, 1] * iz * iz])
    dxdw = a11[:, None] * dxn + a12[:, None] * dyn
    dydw = a12[:, None] * dxn + a22[:, None] * dyn
    w_x = skew(w)  # dw/d delta = [w]_x (k, 3, 3)
    d_att = np.empty((2 * k, 3))
    d_att[0::2] = -np.einsum("kj,kjl->kl", dxdw, w_x)
    d_att[1::2] = -np.einsum("kj,kjl->kl", dydw, w_x)
    d_int = {"focal_px": (xn * s_, yn * s_), "k1": (f * xn * r2, f * yn * r2),
             "k2": (f * xn * r2 * r2, f * yn * r2 * r2), "cx": (np.ones(k), np.zeros(k)),
             "cy": (np.zeros(k), np.ones(k))}
    d_fit = np.empty((2 * k, len(fit)))
    for c, name in enumerate(fit):
        d_fit[0::2, c] = -d_int[name][0]
        d_fit[1::2, c] = -d_int[name][1]
    return d_att, d_fit
