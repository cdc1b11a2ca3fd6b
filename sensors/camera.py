"""Pinhole camera: projection of camera-frame directions to pixels and back (he2021b eq 2)."""
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
    """

    focal_length_m: float
    pixel_size_m: float
    width: int
    height: int
    cx: float | None = None
    cy: float | None = None

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
    def half_diagonal_rad(self) -> float:
        """Angle from the boresight to the farthest detector corner (rad)."""
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
        return x, y, in_front

    def unproject(self, x, y) -> np.ndarray:
        """Pixel coordinates to unit camera-frame directions (..., 3), he2021b eq (2)."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
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
        return np.stack([row_x, row_y], axis=-2)

    def contains(self, x, y, margin_px: float = 0.0) -> np.ndarray:
        """True where (x, y) lies on the detector, at least ``margin_px`` inside its edge."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        lo = -0.5 + margin_px
        return (x >= lo) & (y >= lo) & (x <= self.width - 0.5 - margin_px) & (y <= self.height - 0.5 - margin_px)
