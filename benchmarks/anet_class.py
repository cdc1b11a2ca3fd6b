"""astrometry.net's model class, fitted to training stars and scored on held-out stars.

astrometry.net describes each image by a TAN WCS with SIP distortion of order 2: a gnomonic
projection about a fitted sky centre (CRVAL), a linear map (CD matrix, CRPIX) and second-order
polynomial terms. Here the same class is written as a pointing and a polynomial:

- per image a rotation ``R`` (ICRS -> camera); a catalogue direction ``u`` becomes the tangent-plane
  coordinates ``(a, b) = (v_x / v_z, v_y / v_z)`` of ``v = R u`` (the gnomonic projection about the
  camera's z axis, which is the fitted sky centre);
- the pixel ``(x, y)`` is a full polynomial of degree 2 in ``(a, b)``: 6 coefficients per axis, which
  hold CRPIX (constant terms), the CD matrix (linear terms) and the SIP terms (quadratic terms).

On one image the rotation's roll is the polynomial's linear part (fixed here), so the image has
2 pointing angles + 12 coefficients = 14 parameters, as many as CRVAL (2) + CD (4) + CRPIX (2) +
SIP order 2 (6). SIP puts the polynomial on the pixel side (pixel -> sky), this module on the sky
side (sky -> pixel): inverting a quadratic distortion of ``D`` px at ``R`` px from the centre leaves
a cubic of about ``2 D^2 / R`` px (0.04 px for 3 px at 400 px), below the stars' noise here.
Fitted to every star of a creusot corr table, this class leaves at most astrometry.net's own
residual, and on the typical 16 mm scene the same: there astrometry.net's solution is the class's
least-squares optimum (tests/benchmarks/test_anet_class.py).

Several images of one lens (the joint recordings, which hold out whole images): a held-out image
has no fitted WCS of its own, so the polynomial (the lens) is shared by every image and each image
keeps its own rotation (3 angles; one roll fixed for the whole recording). The polynomial and the
training images' rotations are fitted to the training stars; each held-out image then gets its
rotation fitted to its own stars with the polynomial fixed, as the diagnosis fits a held-out
frame's attitude (3 degrees of freedom per image). A per-image affine map on top would give every
held-out image 6 more parameters than the diagnosis allows itself, so there is none.

Fit: variable projection. For given rotations the 12 polynomial coefficients are a linear least
squares problem (``numpy.linalg.lstsq``); the rotation angles around it are refined by
``scipy.optimize.least_squares``. Every star weighs the same (the stars of one creusot recording share
one centroid sigma).

Why by hand and not ``astropy.wcs.utils.fit_wcs_from_points(xy, SkyCoord, sip_degree=2)``, the
library way: it fits one image only (no distortion shared across images, which the joint
recordings need); it keeps the projection centre at the middle of the stars' bounding box instead
of fitting it; and with ``sip_degree`` set, astropy 8.0.2 returns a WCS whose pixels are 1 px off
on both axes (its SIP objective compares 0-based ``all_world2pix`` pixels with the 1-based CRPIX).
With that constant removed, the two agree on one image (tests/benchmarks/test_anet_class.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

POLY_TERMS = 6  # 1, a, b, a^2, ab, b^2 per pixel axis


@dataclass(frozen=True)
class ClassFit:
    """The fit of astrometry.net's model class to the training stars, scored on the held-out ones."""

    heldout_rms_px: float  # RMS per axis on the held-out stars
    train_rms_px: float  # RMS per axis on the training stars (in-sample)
    n_params: int  # parameters fitted to the training stars (polynomial + training rotations - the fixed roll)
    n_train: int  # training stars
    n_heldout: int


def design(ab: np.ndarray) -> np.ndarray:
    """The degree-2 polynomial terms of tangent-plane coordinates ``ab`` (n, 2) -> (n, 6)."""
    a, b = ab.T
    return np.column_stack([np.ones_like(a), a, b, a * a, a * b, b * b])


def tangent_plane(rot: Rotation, u: np.ndarray) -> np.ndarray:
    """Gnomonic coordinates (n, 2) of unit vectors ``u`` (n, 3) about the camera z axis of ``rot``."""
    v = rot.apply(u)
    return v[:, :2] / v[:, 2:3]


def pinhole_rotation(xy: np.ndarray, u: np.ndarray, focal_px: float, centre_px) -> Rotation:
    """A first rotation of one image: the stars' pinhole rays (focal length and principal point
    ``centre_px`` as guessed) aligned with their catalogue directions."""
    rays = np.column_stack([(xy - np.asarray(centre_px)) / focal_px, np.ones(len(xy))])
    rot, _ = Rotation.align_vectors(rays / np.linalg.norm(rays, axis=1, keepdims=True), u)
    return rot


def rotations(start: list[Rotation], angles: np.ndarray) -> list[Rotation]:
    """``start`` turned by small rotation vectors: 3 angles per image, the first image's roll fixed at 0
    (turning every image about its z axis by one angle is a linear map of the tangent-plane
    coordinates, which the polynomial holds already: one roll is no parameter)."""
    vecs = np.concatenate([angles[:2], [0.0], angles[2:]]).reshape(-1, 3)
    return [Rotation.from_rotvec(v) * r for v, r in zip(vecs, start)]


def shared_terms(rots: list[Rotation], slot: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Polynomial terms of every star, each through its own image's rotation (``slot``: its image's index)."""
    ab = np.empty((len(u), 2))
    for k, rot in enumerate(rots):
        ab[slot == k] = tangent_plane(rot, u[slot == k])
    return design(ab)


def fit_lens(slot: np.ndarray, xy: np.ndarray, u: np.ndarray, start: list[Rotation]):
    """The shared polynomial (6, 2) and the images' rotations fitted to the stars (``slot``: image index).

    Variable projection: the residual of given angles is that of the polynomial's linear least
    squares fit. Levenberg-Marquardt, as the pointing tilt is weakly determined (to first order it
    moves every pixel as the polynomial's constant term does)."""
    def coefficients(angles):
        terms = shared_terms(rotations(start, angles), slot, u)
        return terms, np.linalg.lstsq(terms, xy, rcond=None)[0]

    def residual(angles):
        terms, coef = coefficients(angles)
        return (xy - terms @ coef).ravel()

    sol = least_squares(residual, np.zeros(3 * len(start) - 1), method="lm")
    return coefficients(sol.x)[1], rotations(start, sol.x)


def fit_pointing(xy: np.ndarray, u: np.ndarray, coef: np.ndarray, start: Rotation) -> Rotation:
    """One image's rotation fitted to its stars with the polynomial ``coef`` fixed (3 angles)."""
    def residual(vec):
        return (xy - design(tangent_plane(Rotation.from_rotvec(vec) * start, u)) @ coef).ravel()

    return Rotation.from_rotvec(least_squares(residual, np.zeros(3), method="lm").x) * start


def rms(d: np.ndarray) -> float:
    """Residual RMS per axis of pixel residuals ``d`` (n, 2)."""
    return float(np.sqrt(np.mean(d**2)))


def fit_class(frame: np.ndarray, xy: np.ndarray, u: np.ndarray, heldout: np.ndarray, focal_px: float,
              centre_px) -> ClassFit | None:
    """astrometry.net's model class (module doc) fitted to the stars not ``heldout``, scored on those that are.

    ``frame``: each star's image; ``xy`` (n, 2) pixels; ``u`` (n, 3) catalogue unit vectors (ICRS);
    ``focal_px`` and ``centre_px``: a pinhole guess that only starts the rotations. None when the
    training stars are too few for the parameters (or nothing is held out).
    """
    train = ~heldout
    images = np.unique(frame[train])
    n_params = 2 * POLY_TERMS + 3 * images.size - 1
    if 2 * train.sum() <= n_params or not heldout.any():
        return None
    slot = np.searchsorted(images, frame[train])
    start = [pinhole_rotation(xy[train & (frame == k)], u[train & (frame == k)], focal_px, centre_px) for k in images]
    coef, rots = fit_lens(slot, xy[train], u[train], start)
    pred = np.full_like(xy, np.nan)
    for k in np.unique(frame):
        on = frame == k
        if k in images:
            rot = rots[int(np.searchsorted(images, k))]
        else:  # a held-out image: its pointing from its own stars, the lens as trained
            rot = fit_pointing(xy[on], u[on], coef, pinhole_rotation(xy[on], u[on], focal_px, centre_px))
        pred[on] = design(tangent_plane(rot, u[on])) @ coef
    return ClassFit(rms(xy[heldout] - pred[heldout]), rms(xy[train] - pred[train]), n_params, int(train.sum()),
                    int(heldout.sum()))
