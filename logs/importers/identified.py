"""Checks on stars that arrive identified (a centroid table's ``catalog_id, ra_deg, dec_deg``, an
astrometry.net corr table): their catalogue directions must be the stars at their positions.

``rollingstar run`` trusts an identification it is given (no identifier runs on such frames), so
directions in another unit (right ascension in hours or radians), swapped or shuffled columns, or
a mirrored image would otherwise become attitudes reported valid, tens of degrees off. One frame's
stars under the declared camera (a pinhole, as the importers declare it) give unit vectors ``w``;
the rotation that best takes them to the catalogue directions (Kabsch's SVD) then leaves:

- a reflection fitting much better than any rotation: a mirror image (an axis flipped, or x and
  y swapped);
- a median distance left beyond :data:`MAX_RESIDUAL_SPREAD` of the stars' median distance from
  their centre: the directions are not these stars'. The fit is made again on the half of the
  stars it fits best (least trimmed squares), so a few wrong identifications neither pull it nor
  set the figure. A lens that is no pinhole leaves a share of the spread too: 0.007-0.18 on
  astrometry.net-style tables of 3.6-8 mm lenses (k1 to -0.38, a nominal field 11 % off, 2-4
  wrong identifications of 40), 0.14-0.15 for fisheye projections of a 160 deg field read as a
  pinhole, 0.013 at most on the 31 creusot tables; directions that are not the stars' leave
  0.4-1.2 (shuffled 1.2, right ascension in hours 0.57, right ascension and declination swapped
  0.38; tests/logs/test_identified_checks.py).
"""
from __future__ import annotations

import numpy as np

from rollingstar.logs.importers.common import ImportDataError

MAX_RESIDUAL_SPREAD = 0.3  # median distance left by the best rotation over the stars' median spread
MIRROR_GAIN = 0.5  # a reflection leaving less than this share of the rotation's residual: a mirror image


def _pinhole_directions(x: np.ndarray, y: np.ndarray, focal_px: float, cx: float, cy: float) -> np.ndarray:
    """Unit camera vectors of pixel positions under a pinhole (docs/conventions.md, he2021b eq 2)."""
    w = np.column_stack([-(x - cx), -(y - cy), np.full(x.shape, focal_px)])
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def _rotation(w: np.ndarray, ref: np.ndarray, reflect: bool) -> np.ndarray:
    """The rotation (or, ``reflect``, the reflection) taking ``w`` closest to ``ref`` (Kabsch), camera -> ICRS."""
    u, _, vt = np.linalg.svd(w.T @ ref)
    d = np.ones(3)
    det = np.linalg.det(vt.T @ u.T)
    d[2] = -np.sign(det) if reflect else np.sign(det)
    return (vt.T * d) @ u.T


def _miss(w: np.ndarray, ref: np.ndarray, reflect: bool) -> float:
    """Median distance (rad) between ``ref`` and ``w`` under the best rotation (reflection), fitted
    again to the half of the stars it fits best: a few wrong identifications neither pull the
    fit nor set the figure (least trimmed squares, one C-step)."""
    d = np.linalg.norm(ref - w @ _rotation(w, ref, reflect).T, axis=1)
    best = d <= np.median(d)
    if best.sum() >= 3:
        d = np.linalg.norm(ref - w @ _rotation(w[best], ref[best], reflect).T, axis=1)
    return float(np.median(d))


def check_identified(x, y, ref, focal_px: float, cx: float, cy: float, where: str) -> None:
    """Refuse identified stars whose catalogue directions ``ref`` (n, 3) cannot be the stars at
    ``x, y`` under the pinhole ``focal_px, cx, cy`` (module doc); ``where`` names the frame."""
    x, y, ref = np.asarray(x, dtype=float), np.asarray(y, dtype=float), np.asarray(ref, dtype=float).reshape(-1, 3)
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(ref).all(axis=1)
    x, y, ref = x[ok], y[ok], ref[ok]
    if x.size < 3:
        return
    w = _pinhole_directions(x, y, focal_px, cx, cy)
    mean = ref.mean(axis=0)
    spread = float(np.median(np.linalg.norm(ref - mean / np.linalg.norm(mean), axis=1)))
    if spread <= 0:
        return
    proper, mirrored = _miss(w, ref, False), _miss(w, ref, True)
    if mirrored < MIRROR_GAIN * proper and proper > 0.1 * spread:
        raise ImportDataError(f"{where}: the stars' positions are a mirror image of their catalogue directions (a "
                              f"reflection fits them {proper / max(mirrored, 1e-15):.3g} times better than any rotation): x "
                              "or y flipped, x and y swapped, or the declination's sign; x is the column and y the row, "
                              "counted from the first pixel's centre (docs/conventions.md)")
    if proper > MAX_RESIDUAL_SPREAD * spread:
        raise ImportDataError(f"{where}: the catalogue directions are not these stars': the best rotation leaves "
                              f"{np.degrees(proper):.3g} deg (median) for stars {np.degrees(spread):.3g} deg from their "
                              "centre (median): "
                              "right ascension and declination in degrees expected (not hours or radians, not "
                              "swapped), each on its own star's row, and the camera's focal length right")
