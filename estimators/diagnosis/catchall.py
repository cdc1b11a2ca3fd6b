"""Detect residual structure no library effect explains: generic bases and a likelihood-ratio test.

After the best library model, the whitened residuals ``r`` (attitude projected out) are tested
against generic bases ``G`` that can represent almost any smooth or piecewise systematic:

- ``field cells``: a free offset per axis in each cell of a 4 x 4 partition of the detector;
- ``field polynomial``: monomials ``u^i v^j`` (``i + j <= 3``) of the normalised position per axis;
- ``magnitude bins``: a free offset per axis in each magnitude quartile;
- ``pixel phase``: ``sin, cos (2 pi phase)`` per axis (sub-pixel S-curves);
- ``row x image velocity``: ``v (row - row_c)`` and ``v (row - row_c)^2`` (timing errors).

With ``M G`` the projected basis and ``Q`` an orthonormal basis of it, ``||Q^T r||^2`` is
chi-square with ``rank(Q)`` dof when the residual is pure noise (likelihood-ratio test with known
noise). The one-sided z of its p-value above ``Z_LIMIT`` (4.5, i.e. p < 3.4e-6 per basis) marks an
*unexplained systematic*. These bases are never offered to the selection: they say that something
is there, not what it is.
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from rollingstar.estimators.diagnosis.residuals import z_from_sf

Z_LIMIT = 4.5
CELLS = 4


def _axis_cols(values: np.ndarray) -> np.ndarray:
    """(n, k) per-star basis values -> (n, 2, 2k): the same basis on the x axis, then on the y axis."""
    n, k = values.shape
    out = np.zeros((n, 2, 2 * k))
    out[:, 0, :k] = values
    out[:, 1, k:] = values
    return out


def generic_bases(obs, pred, camera) -> dict[str, np.ndarray]:
    """The generic bases of the module doc, each (n, 2, m) in px per unit coefficient."""
    u = (pred.x - camera.cx) / (camera.width / 2.0)
    v = (pred.y - camera.cy) / (camera.height / 2.0)
    out = {}
    gx = np.clip(((u + 1) / 2 * CELLS).astype(int), 0, CELLS - 1)
    gy = np.clip(((v + 1) / 2 * CELLS).astype(int), 0, CELLS - 1)
    cell = gy * CELLS + gx
    out["field cells"] = _axis_cols(np.eye(CELLS * CELLS)[cell])
    mono = [u**i * v**j for i in range(4) for j in range(4 - i)]
    out["field polynomial"] = _axis_cols(np.stack(mono, axis=-1))
    if np.all(np.isfinite(obs.magnitude)) and np.ptp(obs.magnitude) > 0:
        q = np.quantile(obs.magnitude, [0.25, 0.5, 0.75])
        out["magnitude bins"] = _axis_cols(np.eye(4)[np.searchsorted(q, obs.magnitude)])
    px, py = 2 * np.pi * (obs.x - np.round(obs.x)), 2 * np.pi * (obs.y - np.round(obs.y))
    ph = np.zeros((obs.n, 2, 4))
    ph[:, 0, 0], ph[:, 0, 1], ph[:, 1, 2], ph[:, 1, 3] = np.sin(px), np.cos(px), np.sin(py), np.cos(py)
    out["pixel phase"] = ph
    rc = (obs.y - camera.cy) / camera.height
    speed = np.hypot(pred.vx, pred.vy)
    if np.max(speed, initial=0.0) > 0:
        tv = np.zeros((obs.n, 2, 4))
        tv[:, 0, 0], tv[:, 1, 1] = pred.vx * rc, pred.vy * rc
        tv[:, 0, 2], tv[:, 1, 3] = pred.vx * rc**2, pred.vy * rc**2
        out["row x image velocity"] = tv
    return out


def residual_structure(r: np.ndarray, bases: dict[str, np.ndarray], min_rows_per_col: int = 5) -> list[dict]:
    """Likelihood-ratio z of each projected, whitened basis (N, m) against residual ``r`` (N,)."""
    rows = []
    for name, g in bases.items():
        norms = np.linalg.norm(g, axis=0)
        g = g[:, norms > 1e-9 * max(norms.max(initial=0.0), 1e-300)]
        if g.shape[1] == 0 or r.shape[0] < min_rows_per_col * g.shape[1]:
            continue
        q, s, _ = np.linalg.svd(g, full_matrices=False)
        q = q[:, s > 1e-8 * s[0]]
        d_chi2 = float(np.sum((q.T @ r) ** 2))
        k = q.shape[1]
        z = float(z_from_sf(stats.chi2.sf(d_chi2, k)))
        rows.append({"basis": name, "delta_chi2": d_chi2, "dof": k, "z": z, "significant": bool(z > Z_LIMIT)})
    return sorted(rows, key=lambda row: -row["z"])
