"""Camera model: pinhole projection of camera-frame directions to pixels and back (he2021b eq 2),
with optional Brown-Conrady radial distortion."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    """Ideal pinhole camera.

    Pixel (x, y) = (column, row) with pixel centres at integer coordinates; the principal point
    ``(cx, cy)`` defaults to the detector centre ``((width - 1) / 2, (height - 1) / 2)``.
    The direction of a pixel is he2021b eq (2)::

        w = [-(x - cx) p, -(y - cy) p, f] / norm(...)

    so a star imaged to the right of the principal point has a negative camera x component.

    Radial distortion (``k1``, ``k2``, default 0: an ideal pinhole) maps the ideal pinhole pixel to
    the observed one about the principal point, in normalised coordinates ``r^2 = ((x - cx)^2 +
    (y - cy)^2) / f^2``: ``x' = cx + (x - cx)(1 + k1 r^2 + k2 r^4)`` (same for y), the convention of
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

    def __post_init__(self):
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
        """Full field of view (horizontal, vertical) in degrees."""
        half_w = self.width * self.pixel_size_m / 2
        half_h = self.height * self.pixel_size_m / 2
        return (
            float(np.degrees(2 * np.arctan(half_w / self.focal_length_m))),
            float(np.degrees(2 * np.arctan(half_h / self.focal_length_m))),
        )

    @property
    def distorted(self) -> bool:
        """True when the camera has radial distortion."""
        return self.k1 != 0.0 or self.k2 != 0.0

    def distort(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Ideal pinhole pixels -> observed pixels."""
        return radial_distort(x, y, self.cx, self.cy, self.focal_px, self.k1, self.k2)

    def undistort(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Observed pixels -> ideal pinhole pixels (NaN where the radial map folds over)."""
        return radial_undistort(x, y, self.cx, self.cy, self.focal_px, self.k1, self.k2)

    @property
    def half_diagonal_rad(self) -> float:
        """Angle from the boresight to the farthest detector corner (rad)."""
        if self.distorted:  # the corners' own directions (barrel distortion widens the field)
            corners = self.unproject([-0.5, self.width - 0.5, -0.5, self.width - 0.5],
                                     [-0.5, -0.5, self.height - 0.5, self.height - 0.5])
            if np.all(np.isfinite(corners)):
                return float(np.arccos(np.clip(corners[:, 2], -1.0, 1.0)).max())
        dx = max(self.cx + 0.5, self.width - 0.5 - self.cx)
        dy = max(self.cy + 0.5, self.height - 0.5 - self.cy)
        return float(np.arctan(np.hypot(dx, dy) / self.focal_px))

    def project(self, w_cam) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-frame directions (..., 3) to pixel coordinates.

        Returns ``(x, y, in_front)``; ``in_front`` is False (and x, y NaN) where ``w_z <= 0``.
        """
        w = np.asarray(w_cam, dtype=float)
        wz = w[..., 2]
        in_front = wz > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(in_front, 1.0 / wz, np.nan)
        x = self.cx - self.focal_px * w[..., 0] * inv
        y = self.cy - self.focal_px * w[..., 1] * inv
        if self.distorted:
            x, y = self.distort(x, y)
        return x, y, in_front

    def unproject(self, x, y) -> np.ndarray:
        """Pixel coordinates to unit camera-frame directions (..., 3), he2021b eq (2)."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        if self.distorted:
            x, y = self.undistort(x, y)
        w = np.stack([-(x - self.cx), -(y - self.cy), np.full(np.broadcast(x, y).shape, self.focal_px)], axis=-1)
        return w / np.linalg.norm(w, axis=-1, keepdims=True)

    def projection_jacobian(self, w_cam) -> np.ndarray:
        """d(x, y)/d(w) for unnormalised camera vectors, shape (..., 2, 3)."""
        w = np.asarray(w_cam, dtype=float)
        wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
        f = self.focal_px
        zero = np.zeros_like(wz)
        row_x = np.stack([-f / wz, zero, f * wx / wz**2], axis=-1)
        row_y = np.stack([zero, -f / wz, f * wy / wz**2], axis=-1)
        jac = np.stack([row_x, row_y], axis=-2)
        if self.distorted:  # chain rule through the radial map at the ideal pixel
            xn, yn = -wx / wz, -wy / wz
            r2 = xn * xn + yn * yn
            s = 1.0 + r2 * (self.k1 + self.k2 * r2)
            ds = 2.0 * (self.k1 + 2.0 * self.k2 * r2)  # d s / d(r^2) * 2
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


def radial_distort(x, y, cx: float, cy: float, focal_px: float, k1: float, k2: float) -> tuple[np.ndarray, np.ndarray]:
    """Ideal pinhole pixels -> distorted pixels, Brown-Conrady radial terms (:class:`PinholeCamera`)."""
    dx, dy = np.asarray(x, dtype=float) - cx, np.asarray(y, dtype=float) - cy
    r2 = (dx * dx + dy * dy) / focal_px**2
    s = 1.0 + r2 * (k1 + k2 * r2)
    return cx + dx * s, cy + dy * s


def radial_undistort(x, y, cx: float, cy: float, focal_px: float, k1: float, k2: float,
                     iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels -> ideal pinhole pixels: Newton on the radius ``rho (1 + k1 rho^2 + k2 rho^4) = r_d``.

    Hand-written because it is one scalar equation per star, vectorised (OpenCV's
    ``undistortPoints`` is not a dependency; tetra3rs' takes one point per call). Where the radial
    map stops being monotonic (``d r_d / d rho <= 0``, far outside any real field) the result is NaN.
    """
    dx, dy = np.asarray(x, dtype=float) - cx, np.asarray(y, dtype=float) - cy
    rd = np.hypot(dx, dy) / focal_px
    rho = rd.copy()
    for _ in range(iterations):
        g = rho * (1.0 + k1 * rho**2 + k2 * rho**4) - rd
        dg = 1.0 + 3.0 * k1 * rho**2 + 5.0 * k2 * rho**4
        step = g / np.where(dg > 0, dg, np.nan)
        rho = rho - step
        if np.all(~np.isfinite(step) | (np.abs(step) < 1e-13)):
            break
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(rd > 0, rho / rd, 1.0)
    return cx + dx * s, cy + dy * s
