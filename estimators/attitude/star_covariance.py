"""The covariance of a star's camera-frame direction, from the 2 x 2 covariance of its pixel position.

A star at pixel ``(x, y)`` with position covariance ``C`` (2 x 2, px^2, image axes; a smeared spot's
is long along the smear and short across it) has the unit direction ``b = unproject(x, y)``
(he2021b eq 2, after undistortion when the camera has radial distortion). To first order a pixel
error ``d`` moves ``b`` by ``J d`` with ``J = d b / d(x, y)`` (3 x 2, both columns perpendicular to
``b``), so ``Cov(b) = J C J^T``: rank 2, in the plane perpendicular to ``b``. In an orthonormal
tangent basis ``E`` of that plane (:func:`tangent_basis`) it is the 2 x 2 ``Sigma = E^T J C J^T E``
(rad^2), with information ``Sigma^-1`` and the whitening ``W = L^-1`` (``L L^T = Sigma``, Cholesky),
so that ``W e`` has unit covariance for a tangent-plane error ``e`` and ``W^T W = Sigma^-1``.

``J`` from the camera's projection Jacobian ``P = d(x, y) / d w`` (2 x 3; it includes the radial
distortion of a distorted camera): ``P J = I`` and ``b^T J = 0`` give ``J = E (P E)^-1``. For a camera
model without ``projection_jacobian``, central differences of ``unproject``.

The solvers that weight stars by a scalar (QUEST, Davenport's K of REQUEST) use ``sigma_px / f``
rad for a star of isotropic position noise (the pixel's angular size at the principal point; the
off-axis foreshortening, about 1 % at the edge of a 10 deg field, is neglected). Every consumer
keeps exactly that scalar path for a frame whose stars all have isotropic covariances
(:func:`anisotropic_covariance` returns None), and weights every star of the frame by its exact
``Sigma`` as soon as one star carries a 2 x 2 covariance that is not isotropic.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from rollingstar.sensors.so3 import cross

__all__ = ["tangent_basis", "direction_jacobian", "DirectionCovariance", "direction_covariance",
           "anisotropic_covariance", "isotropic_sigma_px", "is_isotropic", "FD_STEP_PX"]

FD_STEP_PX = 1e-3  # central-difference step of the unprojection for cameras without projection_jacobian


def tangent_basis(u: np.ndarray) -> np.ndarray:
    """Two orthonormal vectors perpendicular to each unit vector: (n, 3, 2) columns ``e1, e2``."""
    u = np.asarray(u, dtype=float).reshape(-1, 3)
    # Helper axis: the coordinate axis least aligned with u (never parallel to it).
    helper = np.zeros_like(u)
    helper[np.arange(len(u)), np.argmin(np.abs(u), axis=1)] = 1.0
    e1 = cross(u, helper)
    e1 /= np.sqrt(np.einsum("ij,ij->i", e1, e1))[:, None]
    return np.stack([e1, cross(u, e1)], axis=-1)


def direction_jacobian(camera, x, y) -> tuple[np.ndarray, np.ndarray]:
    """Unit camera directions ``b`` (n, 3) of the pixels and ``J = d b / d(x, y)`` (n, 3, 2)."""
    body, _, J = _direction_basis_jacobian(camera, x, y)
    return body, J


def _direction_basis_jacobian(camera, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`direction_jacobian`'s ``b`` and ``J``, with the tangent basis ``E`` of ``b`` between them."""
    x = np.asarray(x, dtype=float).reshape(-1)
    y = np.asarray(y, dtype=float).reshape(-1)
    body = camera.unproject(x, y).reshape(-1, 3)
    body = body / np.linalg.norm(body, axis=1, keepdims=True)
    E = tangent_basis(body)
    if hasattr(camera, "projection_jacobian"):
        PE = np.asarray(camera.projection_jacobian(body), dtype=float) @ E  # (n, 2, 2)
        return body, E, E @ np.linalg.inv(PE)
    h = FD_STEP_PX
    cols = [(camera.unproject(x + dx, y + dy) - camera.unproject(x - dx, y - dy)).reshape(-1, 3) / (2 * h)
            for dx, dy in ((h, 0.0), (0.0, h))]
    return body, E, np.stack(cols, axis=-1)


@dataclass(frozen=True)
class DirectionCovariance:
    """Per star: unit direction ``body`` (n, 3), tangent basis ``basis`` (n, 3, 2), and in that basis
    the covariance ``cov`` (n, 2, 2) rad^2, its inverse ``info`` and the whitening ``whiten``
    (``whiten @ cov @ whiten^T = I``)."""

    body: np.ndarray
    basis: np.ndarray
    cov: np.ndarray
    info: np.ndarray
    whiten: np.ndarray

    @property
    def n(self) -> int:
        return int(self.body.shape[0])

    def take(self, index) -> "DirectionCovariance":
        return DirectionCovariance(*(np.asarray(a)[index] for a in (self.body, self.basis, self.cov, self.info, self.whiten)))


def direction_covariance(camera, x, y, cov_px) -> DirectionCovariance:
    """The tangent-plane covariance of each star's direction from its pixel covariance ``cov_px``
    (n, 2, 2) px^2 (module docstring: ``Sigma = E^T J C J^T E``)."""
    body, E, J = _direction_basis_jacobian(camera, x, y)
    C = np.ascontiguousarray(np.broadcast_to(np.asarray(cov_px, dtype=float), (len(body), 2, 2)))
    cov, info, whiten, ok = _tangent_covariance(np.ascontiguousarray(E), np.ascontiguousarray(J, dtype=float), C)
    if not ok.all():  # numpy's error for a covariance its Cholesky factorisation refuses
        raise np.linalg.LinAlgError(f"Matrix is not positive definite (star {int(np.flatnonzero(~ok)[0])})")
    return DirectionCovariance(body, E, cov, info, whiten)


@njit(cache=True, nogil=True, error_model="numpy")
def _tangent_covariance(E, J, C):  # pragma: no cover - compiled
    """Per star ``Sigma = M C M^T`` with ``M = E^T J`` (2 x 2), its inverse and the whitening
    ``L^-1`` (``L L^T = Sigma``), each 2 x 2 written out; and whether ``Sigma`` is positive
    definite (both Cholesky pivots positive and finite). Compiled: a dozen stacked 2 x 2 numpy
    operations per frame cost far more in calls than in arithmetic."""
    n = E.shape[0]
    cov, info, whiten = np.zeros((n, 2, 2)), np.zeros((n, 2, 2)), np.zeros((n, 2, 2))
    ok = np.zeros(n, dtype=np.bool_)
    M = np.zeros((2, 2))
    for i in range(n):
        for a in range(2):
            for b in range(2):
                M[a, b] = E[i, 0, a] * J[i, 0, b] + E[i, 1, a] * J[i, 1, b] + E[i, 2, a] * J[i, 2, b]
        c = C[i]
        s = np.zeros((2, 2))
        for a in range(2):
            for b in range(2):
                s[a, b] = (M[a, 0] * (c[0, 0] * M[b, 0] + c[0, 1] * M[b, 1])
                           + M[a, 1] * (c[1, 0] * M[b, 0] + c[1, 1] * M[b, 1]))
        off = 0.5 * (s[0, 1] + s[1, 0])
        cov[i, 0, 0], cov[i, 0, 1], cov[i, 1, 0], cov[i, 1, 1] = s[0, 0], off, off, s[1, 1]
        det = s[0, 0] * s[1, 1] - off * off
        info[i, 0, 0], info[i, 0, 1], info[i, 1, 0], info[i, 1, 1] = s[1, 1] / det, -off / det, -off / det, s[0, 0] / det
        l00 = np.sqrt(s[0, 0])
        l10 = off / l00
        pivot = s[1, 1] - l10 * l10
        ok[i] = s[0, 0] > 0 and pivot > 0 and np.isfinite(pivot) and np.isfinite(det)
        l11 = np.sqrt(pivot)
        whiten[i, 0, 0], whiten[i, 1, 0], whiten[i, 1, 1] = 1.0 / l00, -l10 / (l00 * l11), 1.0 / l11
    return cov, info, whiten, ok


def is_isotropic(cov_px) -> np.ndarray:
    """Stars whose pixel covariance is ``s^2 I`` exactly (n,) bool."""
    c = np.asarray(cov_px, dtype=float).reshape(-1, 2, 2)
    return (c[:, 0, 1] == 0.0) & (c[:, 1, 0] == 0.0) & (c[:, 0, 0] == c[:, 1, 1])


def isotropic_sigma_px(cov_px) -> np.ndarray:
    """The isotropic equivalent 1-sigma per axis (px) of each 2 x 2 covariance, ``sqrt(trace / 2)``
    (the ``sigma_px`` a centroider derives from its 2-D covariance)."""
    c = np.asarray(cov_px, dtype=float).reshape(-1, 2, 2)
    return np.sqrt(0.5 * (c[:, 0, 0] + c[:, 1, 1]))


def anisotropic_covariance(stars, default_sigma_px: float, use_star_sigma: bool = True,
                           star_covariance: bool = True) -> np.ndarray | None:
    """The stars' 2 x 2 position covariances (n, 2, 2) px^2 (:meth:`StarTable.position_covariance`) when
    the full-covariance weighting applies, None when the scalar ``sigma_px`` weighting is exact: with
    ``star_covariance`` off, or when every star's covariance is isotropic (see the module docstring)."""
    if not star_covariance or not use_star_sigma or stars is None or stars.n == 0:
        return None
    cov = stars.position_covariance(default_sigma_px, use_star_sigma)
    return None if is_isotropic(cov).all() else cov
