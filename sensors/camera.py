"""Camera model: central projection of camera-frame directions to pixels and back, perspective
(pinhole, he2021b eq 2) or one of the wide-angle projections, with optional radial distortion."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

#: The central projections: the image radius ``r`` (px) of a direction ``theta`` from the
#: boresight, ``r = f rho(theta)``. Perspective (pinhole): ``tan theta``; equidistant (most
#: fisheye lenses): ``theta``; equisolid-angle: ``2 sin(theta / 2)``; stereographic:
#: ``2 tan(theta / 2)``; orthographic: ``sin theta``.
Projection = Literal["perspective", "equidistant", "equisolid", "stereographic", "orthographic"]
PROJECTIONS: tuple[str, ...] = ("perspective", "equidistant", "equisolid", "stereographic", "orthographic")
#: The largest ``theta`` each projection images (rad; open bound): a hemisphere for perspective
#: and orthographic, all but the backward direction for the others.
MAX_THETA = {"perspective": np.pi / 2, "equidistant": np.pi, "equisolid": np.pi, "stereographic": np.pi,
             "orthographic": np.pi / 2}


def projection_rho(theta, projection: str) -> tuple[np.ndarray, np.ndarray]:
    """``rho(theta)`` of ``projection`` (normalised image radius, ``r / f``) and ``d rho / d theta``."""
    t = np.asarray(theta, dtype=float)
    if projection == "perspective":
        return np.tan(t), 1.0 / np.cos(t) ** 2
    if projection == "equidistant":
        return t, np.ones_like(t)
    if projection == "equisolid":
        return 2.0 * np.sin(0.5 * t), np.cos(0.5 * t)
    if projection == "stereographic":
        return 2.0 * np.tan(0.5 * t), 1.0 / np.cos(0.5 * t) ** 2
    if projection == "orthographic":
        return np.sin(t), np.cos(t)
    raise ValueError(f"unknown projection {projection!r}; expected one of {', '.join(PROJECTIONS)}")


def projection_theta(rho, projection: str) -> np.ndarray:
    """The inverse of :func:`projection_rho`: ``theta`` of a normalised radius (NaN outside the image
    of the projection: ``rho > 2`` for equisolid-angle, ``rho > 1`` for orthographic)."""
    r = np.asarray(rho, dtype=float)
    with np.errstate(invalid="ignore"):
        if projection == "perspective":
            return np.arctan(r)
        if projection == "equidistant":
            return np.where(r < np.pi, r, np.nan)
        if projection == "equisolid":
            return np.where(r <= 2.0, 2.0 * np.arcsin(np.minimum(0.5 * r, 1.0)), np.nan)
        if projection == "stereographic":
            return 2.0 * np.arctan(0.5 * r)
        if projection == "orthographic":
            return np.where(r <= 1.0, np.arcsin(np.minimum(r, 1.0)), np.nan)
    raise ValueError(f"unknown projection {projection!r}; expected one of {', '.join(PROJECTIONS)}")


@dataclass(frozen=True)
class PinholeCamera:
    """Central camera: an ideal pinhole by default, or a wide-angle projection.

    Pixel (x, y) = (column, row) with pixel centres at integer coordinates; the principal point
    ``(cx, cy)`` defaults to the detector centre ``((width - 1) / 2, (height - 1) / 2)``.
    The direction of a pixel is he2021b eq (2)::

        w = [-(x - cx) p, -(y - cy) p, f] / norm(...)

    so a star imaged to the right of the principal point has a negative camera x component.

    ``projection`` (default ``perspective``, the pinhole above) sets how far from the principal
    point a direction at ``theta`` from the boresight is imaged: ``r = f rho(theta)``
    (:data:`Projection`), along the same azimuth as the pinhole's, so the axes are the pinhole's
    whatever the projection. Every projection agrees with the pinhole to first order at the
    boresight (``rho ~ theta``).

    Radial distortion (``k1``, ``k2``, ``k3``, default 0: none) maps the ideal pixel to the observed
    one about the principal point, in normalised coordinates ``r^2 = ((x - cx)^2 + (y - cy)^2) /
    f^2``: ``x' = cx + (x - cx)(1 + k1 r^2 + k2 r^4 + k3 r^6)`` (same for y), the convention of
    :class:`rollingstar.sensors.effects.radial_distortion.RadialDistortion`. ``project`` returns
    observed pixels and ``unproject`` takes them; ``k1 < 0`` is barrel distortion.
    """

    focal_length_m: float
    pixel_size_m: float
    width: int
    height: int
    cx: float | None = None
    cy: float | None = None
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    projection: Projection = "perspective"

    def __post_init__(self):
        if self.projection not in PROJECTIONS:
            raise ValueError(f"unknown projection {self.projection!r}; expected one of {', '.join(PROJECTIONS)}")
        if self.cx is None:
            object.__setattr__(self, "cx", (self.width - 1) / 2.0)
        if self.cy is None:
            object.__setattr__(self, "cy", (self.height - 1) / 2.0)

    @property
    def focal_px(self) -> float:
        """Focal length in pixels, ``f / p``."""
        return self.focal_length_m / self.pixel_size_m

    @property
    def ifov_rad(self) -> float:
        """Instantaneous field of view of one pixel at the principal point (rad)."""
        return self.pixel_size_m / self.focal_length_m

    @property
    def fov_deg(self) -> tuple[float, float]:
        """Full field of view (horizontal, vertical) in degrees (without distortion); a side wider
        than the projection's image circle sees the circle's full angle, ``2 MAX_THETA``."""
        half = np.array([self.width, self.height]) * self.pixel_size_m / 2 / self.focal_length_m
        theta = np.nan_to_num(projection_theta(half, self.projection), nan=MAX_THETA[self.projection])
        return tuple(float(np.degrees(2 * t)) for t in theta)

    @property
    def distorted(self) -> bool:
        """True when the camera has radial distortion."""
        return self.k1 != 0.0 or self.k2 != 0.0 or self.k3 != 0.0

    def distort(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Ideal pixels -> observed pixels."""
        return radial_distort(x, y, self.cx, self.cy, self.focal_px, self.k1, self.k2, self.k3)

    def undistort(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Observed pixels -> ideal pixels (NaN where the radial map folds over)."""
        return radial_undistort(x, y, self.cx, self.cy, self.focal_px, self.k1, self.k2, self.k3)

    @property
    def half_diagonal_rad(self) -> float:
        """Angle from the boresight to the farthest detector corner (rad)."""
        if self.distorted or self.projection != "perspective":  # the corners' own directions
            corners = self.unproject([-0.5, self.width - 0.5, -0.5, self.width - 0.5],
                                     [-0.5, -0.5, self.height - 0.5, self.height - 0.5])
            if np.all(np.isfinite(corners)):
                return float(np.arccos(np.clip(corners[:, 2], -1.0, 1.0)).max())
            if self.projection != "perspective":  # a corner beyond the image circle: the circle's rim
                return float(MAX_THETA[self.projection])
        dx = max(self.cx + 0.5, self.width - 0.5 - self.cx)
        dy = max(self.cy + 0.5, self.height - 0.5 - self.cy)
        return float(np.arctan(np.hypot(dx, dy) / self.focal_px))

    def project(self, w_cam) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-frame directions (..., 3) to pixel coordinates.

        Returns ``(x, y, in_front)``; ``in_front`` is False (and x, y NaN) where the projection does
        not image the direction (:data:`MAX_THETA`: ``w_z <= 0`` for the pinhole).
        """
        w = np.asarray(w_cam, dtype=float)
        if self.projection != "perspective":
            return self._project_wide(w)
        wz = w[..., 2]
        in_front = wz > 0
        inv = np.divide(1.0, wz, out=np.full(wz.shape, np.nan), where=in_front)
        x = self.cx - self.focal_px * w[..., 0] * inv
        y = self.cy - self.focal_px * w[..., 1] * inv
        if self.distorted:
            x, y = self.distort(x, y)
        return x, y, in_front

    def _project_wide(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`project` for the wide-angle projections: ``x = cx - g w_x``, ``y = cy - g w_y`` with
        ``g = f rho_d(theta) / s``, ``s = |(w_x, w_y)|`` (``g = f / w_z`` on the boresight)."""
        g, _, in_front = self._radial_gain(w)
        x = np.where(in_front, self.cx - g * w[..., 0], np.nan)
        y = np.where(in_front, self.cy - g * w[..., 1], np.nan)
        return x, y, in_front

    def _radial_gain(self, w: np.ndarray):
        """``g = f rho_d(theta) / s`` and ``d g / d w`` (..., 3) of unnormalised directions, and which
        ones the projection images; ``rho_d`` the distorted normalised radius."""
        wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
        s = np.hypot(wx, wy)
        n2 = s * s + wz * wz
        theta = np.arctan2(s, wz)
        in_front = (theta < MAX_THETA[self.projection]) & (n2 > 0)
        rho, drho = projection_rho(np.where(in_front, theta, 0.0), self.projection)
        poly = 1.0 + rho**2 * (self.k1 + rho**2 * (self.k2 + rho**2 * self.k3))
        dpoly = 1.0 + rho**2 * (3.0 * self.k1 + rho**2 * (5.0 * self.k2 + 7.0 * self.k3 * rho**2))
        f = self.focal_px
        r, dr = f * rho * poly, f * dpoly * drho  # image radius and d r / d theta
        axis = s <= 1e-12 * np.sqrt(n2)  # on the boresight: r / s -> f / w_z
        with np.errstate(divide="ignore", invalid="ignore"):
            safe = np.where(axis, 1.0, s)
            g = np.where(axis, f / np.where(wz > 0, wz, 1.0), r / safe)
            dtheta = np.stack([wz * wx / safe, wz * wy / safe, -s], axis=-1) / n2[..., None]
            ds = np.stack([wx / safe, wy / safe, np.zeros_like(s)], axis=-1)
            dg = (dr[..., None] * dtheta * s[..., None] - r[..., None] * ds) / (safe * safe)[..., None]
        # on the boresight g = f / w_z to first order in s: dg = (0, 0, -f / w_z^2)
        on_axis = np.stack([np.zeros_like(s), np.zeros_like(s), -f / np.where(wz > 0, wz, 1.0) ** 2], axis=-1)
        dg = np.where(axis[..., None], on_axis, dg)
        return g, dg, in_front

    def unproject(self, x, y) -> np.ndarray:
        """Pixel coordinates to unit camera-frame directions (..., 3), he2021b eq (2) for the pinhole
        (NaN where no direction images there: beyond an equisolid-angle or orthographic image's rim)."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        if self.distorted:
            x, y = self.undistort(x, y)
        if self.projection != "perspective":
            dx, dy = x - self.cx, y - self.cy
            r = np.hypot(dx, dy)
            theta = projection_theta(r / self.focal_px, self.projection)
            safe = np.where(r > 0, r, 1.0)
            sin = np.sin(theta)
            return np.stack([-sin * dx / safe, -sin * dy / safe, np.cos(theta)], axis=-1)
        w = np.empty(np.broadcast_shapes(x.shape, y.shape) + (3,))
        w[..., 0], w[..., 1], w[..., 2] = -(x - self.cx), -(y - self.cy), self.focal_px
        return w / np.sqrt(np.add.reduce(w * w, axis=-1, keepdims=True))  # the sum np.linalg.norm makes, without its checks

    def projection_jacobian(self, w_cam) -> np.ndarray:
        """d(x, y)/d(w) for unnormalised camera vectors, shape (..., 2, 3)."""
        w = np.asarray(w_cam, dtype=float)
        if self.projection != "perspective":
            g, dg, _ = self._radial_gain(w)
            eye = np.zeros(w.shape[:-1] + (2, 3))
            eye[..., 0, 0] = eye[..., 1, 1] = 1.0
            return -(g[..., None, None] * eye + w[..., :2, None] * dg[..., None, :])
        wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
        f = self.focal_px
        jac = np.zeros(w.shape[:-1] + (2, 3))
        jac[..., 0, 0] = jac[..., 1, 1] = -f / wz
        jac[..., 0, 2] = f * wx / wz**2
        jac[..., 1, 2] = f * wy / wz**2
        if self.distorted:  # chain rule through the radial map at the ideal pixel
            xn, yn = -wx / wz, -wy / wz
            r2 = xn * xn + yn * yn
            s = 1.0 + r2 * (self.k1 + r2 * (self.k2 + self.k3 * r2))
            ds = 2.0 * (self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2))  # d s / d(r^2) * 2
            d = np.stack([np.stack([s + ds * xn * xn, ds * xn * yn], -1),
                          np.stack([ds * xn * yn, s + ds * yn * yn], -1)], -2)
            jac = d @ jac
        return jac

    def contains(self, x, y, margin_px: float = 0.0) -> np.ndarray:
        """True where (x, y) lies on the detector, at least ``margin_px`` inside its edge."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        lo = -0.5 + margin_px
        return (x >= lo) & (y >= lo) & (x <= self.width - 0.5 - margin_px) & (y <= self.height - 0.5 - margin_px)


def radial_distort(x, y, cx: float, cy: float, focal_px: float, k1: float, k2: float,
                   k3: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Ideal pixels -> distorted pixels, Brown-Conrady radial terms (:class:`PinholeCamera`)."""
    dx, dy = np.asarray(x, dtype=float) - cx, np.asarray(y, dtype=float) - cy
    r2 = (dx * dx + dy * dy) / focal_px**2
    s = 1.0 + r2 * (k1 + r2 * (k2 + k3 * r2))
    return cx + dx * s, cy + dy * s


def radial_undistort(x, y, cx: float, cy: float, focal_px: float, k1: float, k2: float, k3: float = 0.0,
                     iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels -> ideal pixels: Newton on the radius ``rho (1 + k1 rho^2 + k2 rho^4 + k3 rho^6) = r_d``.

    Hand-written because it is one scalar equation per star, vectorised (OpenCV's
    ``undistortPoints`` is not a dependency; tetra3rs' takes one point per call). Where the radial
    map stops being monotonic (``d r_d / d rho <= 0``, far outside any real field) the result is NaN.
    """
    dx, dy = np.asarray(x, dtype=float) - cx, np.asarray(y, dtype=float) - cy
    rd = np.hypot(dx, dy) / focal_px
    rho = rd.copy()
    for _ in range(iterations):
        g = rho * (1.0 + rho**2 * (k1 + rho**2 * (k2 + k3 * rho**2))) - rd
        dg = 1.0 + rho**2 * (3.0 * k1 + rho**2 * (5.0 * k2 + 7.0 * k3 * rho**2))
        step = g / np.where(dg > 0, dg, np.nan)
        rho = rho - step
        if np.all(~np.isfinite(step) | (np.abs(step) < 1e-13)):
            break
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(rd > 0, rho / rd, 1.0)
    return cx + dx * s, cy + dy * s
