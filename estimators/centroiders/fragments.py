"""Smears broken into several spots by the threshold: found, and their covariance widened.

A fast, faint smear whose brightness per pixel is near the threshold breaks where the noise pulls
a stretch of it below: the centroider then reports two or three spots on one line, each centred
on its own piece, off the star's position by up to half the smear (measured on the he2021a
sensor at 10 deg/s: 7 % of the spots; `rollingstar figures centroid-covariance`). Nothing in a
piece's own pixels shows this, but its neighbours do: pieces of one smear are elongated along
the same direction, lie on one line and nearly touch.

:func:`fragment_groups` finds them: two spots, at least one elongated (smear length over
:data:`~rollingstar.estimators.centroiders.covariance.STREAK_LENGTH_WIDTHS` widths), belong to
one smear when the line joining them runs within :data:`MAX_OFFSET_WIDTHS` widths (plus 1 px) of
the longer one's axis and the gap between their ends along it is at most
:data:`MAX_GAP_LENGTHS` times the longer piece (plus :data:`MIN_GAP_PX`). (A short piece's own
axis is too noisy to compare, and at the rates that break smears every smear in the frame runs
the same way, so the axes' agreement would tell little.)

:func:`with_fragments` widens each piece's covariance along the smear by the square of its
offset from the flux-weighted centre of its group (the group's centre stands for the star's
position; the piece's offset from it is an error the piece's own pixels cannot see) plus the
square of half the group's gaps (the part of the smear no piece holds). The positions are left
as measured, and the frame is flagged ``fragmented_stars:N``.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from rollingstar.estimators.centroiders.covariance import STREAK_LENGTH_WIDTHS, SpotShape

MAX_OFFSET_WIDTHS = 2.0
MAX_GAP_LENGTHS = 0.5
MIN_GAP_PX = 3.0


def fragment_groups(x: np.ndarray, y: np.ndarray, shape: SpotShape) -> np.ndarray:
    """Group label per spot (-1: not part of a broken smear; see the module docstring)."""
    n = x.size
    labels = np.full(n, -1)
    long = np.flatnonzero(np.isfinite(x) & np.isfinite(y) & (shape.length > STREAK_LENGTH_WIDTHS * shape.width))
    if long.size == 0 or n < 2:
        return labels
    reach = np.nanmax(shape.length[long]) * (1.0 + MAX_GAP_LENGTHS) + MIN_GAP_PX
    ok = np.isfinite(x) & np.isfinite(y)
    idx = np.flatnonzero(ok)
    pairs = cKDTree(np.column_stack([x[idx], y[idx]])).query_pairs(reach, output_type="ndarray")
    if pairs.size == 0:
        return labels
    i, j = idx[pairs[:, 0]], idx[pairs[:, 1]]
    long_mask = np.zeros(n, dtype=bool)
    long_mask[long] = True
    keep = long_mask[i] | long_mask[j]
    i, j = i[keep], j[keep]
    link = _same_smear(i, j, x, y, shape)
    i, j = i[link], j[link]
    if i.size == 0:
        return labels
    graph = coo_matrix((np.ones(i.size), (i, j)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    members = np.bincount(comp, minlength=n)
    grouped = members[comp] > 1
    labels[grouped] = comp[grouped]
    return labels


def _same_smear(i, j, x, y, shape: SpotShape) -> np.ndarray:
    """Whether each pair ``(i, j)`` of spots lies on one smear (module docstring), judged along the
    longer spot's axis (a short piece's own axis is too noisy to compare)."""
    a = np.where(shape.length[i] >= shape.length[j], i, j)
    ux, uy = shape.ux[a], shape.uy[a]
    dx, dy = x[j] - x[i], y[j] - y[i]
    along = np.abs(dx * ux + dy * uy)
    offset = np.abs(dx * uy - dy * ux)
    width = np.maximum(shape.width[i], shape.width[j])
    gap = along - 0.5 * (shape.length[i] + shape.length[j])
    longest = np.maximum(shape.length[i], shape.length[j])
    return (offset <= MAX_OFFSET_WIDTHS * width + 1.0) & (gap <= MAX_GAP_LENGTHS * longest + MIN_GAP_PX)


def with_fragments(cov: np.ndarray, x: np.ndarray, y: np.ndarray, flux: np.ndarray,
                   shape: SpotShape) -> tuple[np.ndarray, np.ndarray]:
    """(``cov`` (rows ``xx, xy, yy``) widened along the smear for the pieces of broken smears, mask
    of those pieces); ``cov`` itself when there are none (module docstring)."""
    groups = fragment_groups(x, y, shape)
    pieces = groups >= 0
    if not pieces.any():
        return cov, pieces
    extra = np.zeros(x.size)
    ux, uy = np.zeros(x.size), np.zeros(x.size)
    for g in np.unique(groups[pieces]):
        m = np.flatnonzero(groups == g)
        lead = m[np.argmax(shape.length[m])]
        gx, gy = shape.ux[lead], shape.uy[lead]
        w = np.maximum(flux[m], 0.0)
        total = max(float(np.sum(w)), 1e-300)
        cx, cy = np.sum(w * x[m]) / total, np.sum(w * y[m]) / total
        s = (x[m] - cx) * gx + (y[m] - cy) * gy  # offsets along the smear
        ends = np.concatenate([s - 0.5 * shape.length[m], s + 0.5 * shape.length[m]])
        missing = max(ends.max() - ends.min() - np.sum(shape.length[m]), 0.0)
        extra[m] = s**2 + (0.5 * missing) ** 2
        ux[m], uy[m] = gx, gy
    add = np.where(pieces, extra, 0.0)
    return np.stack([cov[0] + add * ux * ux, cov[1] + add * ux * uy, cov[2] + add * uy * uy]), pieces
