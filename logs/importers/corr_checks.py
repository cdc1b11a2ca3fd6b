"""Checks that an astrometry.net corr table is what it says before it becomes a recording.

A corr table pairs each measured star (``field_x, field_y``) with the catalogue star it was
matched to (``index_ra, index_dec``) and that star's position under astrometry.net's own fit
(``index_x, index_y``). A table edited by hand, written by another tool or damaged in transit can
look valid column by column and still be none: rows repeated, a column replaced, a pixel origin
shifted, angles in radians. Each of these would otherwise reach the diagnosis as physics (a
repeated star is seen in training and again "held out"; a shifted column inflates the centroid
noise the table states). The checks below use only what any solved table must satisfy:

- every star once: a row repeated exactly is dropped; a catalogue star matched to two measured
  positions, or a measured position matched to two catalogue stars, is no identification and is
  dropped with its partners;
- the measured positions vary (a constant column is no measurement);
- astrometry.net's fit residual ``field - index`` is a centroid noise: no mean offset (the fit
  has the pointing free, so its residual averages to zero; on the 31 creusot tables the median
  offset is within 3.3 of its standard errors, taken from the MAD), and on most stars below
  :data:`MAX_RESIDUAL_FRACTION` of
  the image diagonal;
- the angles between catalogue stars match the pixel distances under ``log.json``'s field of view
  (median ratio within :data:`SCALE_LIMITS`; 0.978-1.006 on the creusot tables);
- ``log.json``'s pointing centre lies among the stars (a warning when it does not).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from rollingstar.logs.importers.common import ImportDataError, WarningLog

MAX_RESIDUAL_FRACTION = 0.02  # of the image diagonal: a corr residual beyond it is not a centroid noise
MEAN_OFFSET_Z = 8.0  # standard errors of a mean residual beyond which a column is shifted
MEAN_OFFSET_PX = 0.3  # and pixels: a shift below this is within what the fit's weighting leaves
SCALE_LIMITS = (0.5, 2.0)  # catalogue angle / pixel angle, median over star pairs
CENTRE_FIELDS = 0.5  # pointing centre further than this many diagonal fields from the stars: warned
MAX_PAIRS = 20_000  # star pairs compared for the scale (a random subset beyond)


def unique_rows(cols: dict[str, np.ndarray], path: Path, log: WarningLog) -> dict[str, np.ndarray]:
    """``cols`` with every star once: exact repeats dropped, ambiguous matches dropped with their
    partners (module doc); each said in one warning naming the table and the rows."""
    keys = ("field_x", "field_y", "index_ra", "index_dec")
    rows = np.column_stack([cols[k] for k in keys])
    _, first = np.unique(rows, axis=0, return_index=True)
    keep = np.zeros(rows.shape[0], dtype=bool)
    keep[first] = True
    if not keep.all():
        dropped = np.flatnonzero(~keep)
        log(f"{path}: {dropped.size} row(s) repeat an earlier row exactly and are dropped (rows "
            f"{', '.join(map(str, dropped[:10]))}): each star must be counted once")
    ambiguous = np.zeros_like(keep)
    for group in (rows[:, :2], rows[:, 2:]):
        _, inverse, counts = np.unique(group, axis=0, return_inverse=True, return_counts=True)
        ambiguous |= keep & (np.bincount(inverse.ravel(), weights=keep)[inverse.ravel()] > 1)
    if ambiguous.any():
        bad = np.flatnonzero(ambiguous)
        log(f"{path}: {bad.size} row(s) match one measured position to two catalogue stars or one catalogue star "
            f"to two positions and are dropped (rows {', '.join(map(str, bad[:10]))}): no identification")
    keep &= ~ambiguous
    return cols if keep.all() else {k: v[keep] for k, v in cols.items()}


def check_positions(cols: dict[str, np.ndarray], path: Path) -> None:
    """Refuse a table whose measured positions do not vary along an axis."""
    for c in ("field_x", "field_y"):
        if cols[c].size >= 2 and np.ptp(cols[c]) == 0:
            raise ImportDataError(f"{path}: {c} is {cols[c][0]:g} for every star; a corr table's {c} is each "
                                  "star's measured position (damaged or replaced column?)")


def residual_of(cols: dict[str, np.ndarray], path: Path, diagonal_px: float, log: WarningLog) -> np.ndarray:
    """Astrometry.net's residual ``field - index`` per star (n, 2), NaN when the table states none
    (no ``index_x/index_y``, or positions equal to them) and for a row whose residual is no
    centroid noise (beyond :data:`MAX_RESIDUAL_FRACTION` of the diagonal: a damaged index_x/y, said);
    refuses a table where most rows are so, or whose residual has a mean offset."""
    n = cols["field_x"].size
    if "index_x" not in cols or "index_y" not in cols:
        log(f"{path}: no index_x/index_y columns, so the table states no fit residual: the centroid noise is "
            "not known from it (the recording states none; `rollingstar diagnose` estimates it from the fit)")
        return np.full((n, 2), np.nan)
    with np.errstate(over="ignore", invalid="ignore"):
        resid = np.column_stack([cols["field_x"] - cols["index_x"], cols["field_y"] - cols["index_y"]])
    finite = np.isfinite(resid).all(axis=1)
    if n and not np.any(resid[finite]):
        why = "equal index_x, index_y for every star" if finite.any() else "have no finite index_x, index_y"
        log(f"{path}: field_x, field_y {why}, so the table states no fit residual: the centroid noise is not known "
            "from it (the recording states none; `rollingstar diagnose` estimates it from the fit)")
        return np.full((n, 2), np.nan)
    limit = MAX_RESIDUAL_FRACTION * diagonal_px
    wild = finite & (np.abs(np.where(finite[:, None], resid, 0.0)) > limit).any(axis=1)
    if n >= 3 and wild.sum() > 0.5 * finite.sum():
        raise ImportDataError(
            f"{path}: field_xy - index_xy exceed {limit:.3g} px ({MAX_RESIDUAL_FRACTION:.0%} of the image diagonal) on "
            f"{int(wild.sum())} of {int(finite.sum())} stars; astrometry.net's fit leaves a few pixels at most, so a "
            "position column is damaged or replaced")
    if wild.any():
        rows = np.flatnonzero(wild)
        log(f"{path}: {rows.size} row(s) with field_xy - index_xy beyond {limit:.3g} px (rows "
            f"{', '.join(map(str, rows[:10]))}): a damaged index_x/index_y, left out of the centroid noise")
        resid = np.where(wild[:, None], np.nan, resid)
    r = resid[np.isfinite(resid).all(axis=1)]
    if r.shape[0] >= 3:
        _refuse_offset(r, path)
    return resid


def _refuse_offset(r: np.ndarray, path: Path) -> None:
    """Refuse a residual with a mean offset (a shifted column: module doc). Median and MAD, so that
    a few poorly fitted stars do not make one."""
    mean = np.median(r, axis=0)
    std = 1.4826 * np.median(np.abs(r - mean), axis=0)
    z = np.abs(mean) / np.maximum(std / math.sqrt(r.shape[0]), 1e-12)
    for axis, c in enumerate("xy"):
        if z[axis] > MEAN_OFFSET_Z and abs(mean[axis]) > MEAN_OFFSET_PX:
            how = "the same for every star" if std[axis] < 1e-9 else f"{z[axis]:.0f} standard errors"
            raise ImportDataError(
                f"{path}: field_{c} - index_{c} is {mean[axis]:+.3g} px on average ({how}); "
                f"astrometry.net fits the pointing, so its residual averages to zero: field_{c} or index_{c} is "
                "shifted (a 0- against 1-based pixel origin, or an edited column)")


def check_scale(x: np.ndarray, y: np.ndarray, ref: np.ndarray, focal_px: float, path: Path, fov_deg: float) -> None:
    """Refuse a table whose catalogue angles do not match its pixel distances (module doc)."""
    n = x.size
    if n < 3:
        return
    i, j = np.triu_indices(n, 1)
    if i.size > MAX_PAIRS:
        pick = np.random.default_rng(0).choice(i.size, MAX_PAIRS, replace=False)
        i, j = i[pick], j[pick]
    pix = np.hypot(x[i] - x[j], y[i] - y[j]) / focal_px
    ang = 2.0 * np.arcsin(np.clip(0.5 * np.linalg.norm(ref[i] - ref[j], axis=1), 0.0, 1.0))
    use = pix > 0
    if not use.any():
        return
    ratio = float(np.median(ang[use] / pix[use]))
    if not SCALE_LIMITS[0] <= ratio <= SCALE_LIMITS[1]:
        raise ImportDataError(
            f"{path}: the angles between the catalogue stars (index_ra, index_dec) are {ratio:.3g} times those their "
            f"pixel distances span in log.json's field of view ({fov_deg:g} deg diagonal); expected about 1: check "
            "that index_ra, index_dec are in degrees and that fov_deg is the diagonal field in degrees")


def check_centre(ref: np.ndarray, centre_icrs: np.ndarray, fov_deg: float, where: str, log: WarningLog) -> None:
    """Warn when ``log.json``'s pointing centre lies far from the table's stars."""
    if ref.shape[0] == 0:
        return
    mean = ref.mean(axis=0)
    norm = np.linalg.norm(mean)
    if norm == 0:
        return
    off = math.degrees(math.acos(float(np.clip(np.dot(mean / norm, np.ravel(centre_icrs)), -1.0, 1.0))))
    if off > CENTRE_FIELDS * fov_deg:
        log(f"{where}: log.json's centre (ra_degrees, dec_degrees) is {off:.3g} deg from the mean direction of the "
            f"table's stars, more than half the {fov_deg:g} deg field: it is not this image's pointing (the stars "
            "identify the attitude; the centre is kept in import.details only as given)")
