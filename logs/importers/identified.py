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
  stars it fits best until that half stops changing (least trimmed squares), so that wrong
  identifications short of half neither pull it nor set the figure.

Frames of fewer than :data:`MIN_STARS` identified stars are not judged. The limits are set for no
refusal of legitimate data. The figures below were measured with scripts outside the repository
(a reviewer's sweep; no command here reproduces them); tests/logs/test_identified_checks.py checks
a subset (distorted 3.6-16 mm lenses with wrong identifications, 160 deg fisheyes, mirrors,
shuffled rows, angles in radians) and tests/logs/test_corr_checks.py the creusot tables: lenses that are
no pinhole (3.6-8 mm with k1 to -0.4, fisheyes to 160 deg, stars in one corner, a focal length
25 % off) leave at most 0.41 of the spread; wrong identifications up to 45 % leave at most 0.17;
a rolling shutter whose readout sweeps 60 % of a 1 deg field leaves 0.68; the creusot tables leave
0.013 at most. Directions that are not the stars' leave from about 1 (shuffled rows) to 50 (angles
in radians); right ascension in hours and right ascension and declination swapped leave 0.4-1.1
depending on the pointing, so they are caught only at some. A flipped axis or declination sign is
refused in 99 % of frames of 8 stars and every frame of 12 or more; x and y swapped (a mirror that
also changes the field's aspect) in 37 % of frames of 8 stars and 77 % of 40.
"""
from __future__ import annotations

import numpy as np

from rollingstar.logs.importers.common import ImportDataError
from rollingstar.sensors.camera import PinholeCamera

MAX_RESIDUAL_SPREAD = 0.8  # median distance left by the best rotation over the stars' median spread
MIRROR_GAIN = 0.25  # a reflection leaving less than this share of the rotation's residual: a mirror image
MIN_STARS = 8  # fewer identified stars in a frame are not judged (a few points fit a wrong map by chance)
TRIM_STEPS = 10  # C-steps of the trimmed fit, at most


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
    fit nor set the figure (least trimmed squares: C-steps until the half stops changing)."""
    d = np.linalg.norm(ref - w @ _rotation(w, ref, reflect).T, axis=1)
    best = None
    for _ in range(TRIM_STEPS):  # C-steps until the better half stops changing
        now = d <= np.median(d)
        if best is not None and np.array_equal(now, best):
            break
        best = now
        d = np.linalg.norm(ref - w @ _rotation(w[best], ref[best], reflect).T, axis=1)
    return float(np.median(d))


def check_identified(x, y, ref, focal_px: float, cx: float, cy: float, where: str) -> None:
    """Refuse identified stars whose catalogue directions ``ref`` (n, 3) cannot be the stars at
    ``x, y`` under the pinhole ``focal_px, cx, cy`` (module doc); ``where`` names the frame."""
    x, y, ref = np.asarray(x, dtype=float), np.asarray(y, dtype=float), np.asarray(ref, dtype=float).reshape(-1, 3)
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(ref).all(axis=1)
    x, y, ref = x[ok], y[ok], ref[ok]
    if x.size < MIN_STARS or not (np.isfinite(focal_px) and focal_px > 0):
        return
    # the pinhole's own unprojection (the detector size does not enter it)
    w = PinholeCamera(focal_px * 1e-6, 1e-6, int(2 * cx) + 1, int(2 * cy) + 1, cx=cx, cy=cy).unproject(x, y)
    mean = ref.mean(axis=0)
    spread = float(np.median(np.linalg.norm(ref - mean / max(np.linalg.norm(mean), 1e-300), axis=1)))
    if not spread > 1e-9:  # the stars at one direction: no geometry to judge
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
