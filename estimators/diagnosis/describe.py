"""Describe what lies outside the library: the smallest generic shape that explains the residual left.

When the named model leaves an unexplained systematic, the training residual (whitened, every
frame's attitude projected out, as the selection sees it) is fitted by each shape below, and the one
with the lowest BIC (``-delta chi2 + k ln N``, ``k`` its coefficients plus one per scanned
location or period) is reported in words and numbers, checked on the held-out data, and written as
an empirical correction (:mod:`rollingstar.sensors.effects.empirical`) when the library has one of
its kind:

- ``step``: one axis moves by ``a`` for stars beyond a column (or row), the position scanned
  every ``STEP_GRID_PX`` and reported as the gap between the stars on either side;
- ``ripple``: one axis follows ``a sin + b cos`` of ``2 pi coordinate / P``, the frequency ``1 / P``
  scanned uniformly from half a cycle over the detector to ``1 / MIN_PERIOD_PX``, a quarter cycle
  over the detector apart, then refined around the best;
- the generic bases of :mod:`.catchall` (field cells, field polynomial, magnitude bins, pixel
  phase, row x image velocity) as whole models, each reduced to the directions the attitudes do
  not absorb (rank cut of its projected columns, as the catch-all test does); their size is
  reported as the displacement they fit after the attitudes, not as coefficients.

The named effects stay free while a shape is fitted (their signatures, at the fitted model, are
projected out of every shape's columns): an effect that absorbed part of an out-of-library
perturbation gives it back to the shape that describes it better.

A shape is reported only when its chi-square drop is significant after the look-elsewhere
correction of its scan (Bonferroni over the scanned values): z above :data:`.catchall.Z_LIMIT`.
Shapes are then compared in the units of what the best one leaves (quasi-likelihood BIC, Burnham
& Anderson 2002): with ``c_hat`` the chi-square per dof left by the plain-BIC best (dof net of the
shape, the attitudes and the named effects), chi-square differences are divided by ``c_hat``; the
shape so chosen must still be significant and lower the quasi-BIC. A large perturbation described by the right shape still
leaves a small misfit (its effect on the rates the attitudes imply, say); in raw chi-square a
20-parameter basis absorbs that misfit and wins, in its units the 2-parameter shape does.
A described shape is a measurement, not an explanation: it says where and how big.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import sparse, stats

from rollingstar.estimators.diagnosis import catchall, selection
from rollingstar.estimators.diagnosis.observations import (
    Observations,
    Prediction,
    frame_normal,
    solve_frames,
    whiten,
    whitened_residuals,
)
from rollingstar.estimators.diagnosis.residuals import z_from_sf

STEP_GRID_PX = 4.0
MIN_STEP_STARS = 2  # distinct stars a step needs on each side: one star beyond a line is an isolated misfit
MIN_PERIOD_PX = 8.0
CLOSE_BIC = 10.0  # a second shape this close is reported beside the best
AXES = ("x", "y")
COORDS = ("column", "row")


@dataclass(frozen=True)
class Shape:
    """One fitted shape: its columns' coefficients on the training rows and how much they explain."""

    kind: str
    label: dict  # what identifies it: axis, coordinate, position or period
    columns: np.ndarray  # (n, 2, k) px per unit coefficient, every star (not whitened)
    coef: np.ndarray  # (k,) px
    cov: np.ndarray  # (k, k) px^2
    delta_chi2: float
    scanned: int  # values scanned to find it (1: a fixed basis)
    rank: int | None = None  # independent directions fitted, when fewer than the columns

    @property
    def k(self) -> int:
        return int(self.coef.size) if self.rank is None else self.rank

    def bic(self, n_rows: int, c_hat: float = 1.0) -> float:
        """``-delta chi2 / c_hat + (k + 1 if scanned) ln N``; ``c_hat`` the overdispersion (module doc)."""
        return -self.delta_chi2 / c_hat + (self.k + (self.scanned > 1)) * np.log(n_rows)

    def z(self) -> float:
        p = min(1.0, float(stats.chi2.sf(self.delta_chi2, self.k)) * self.scanned)
        return float(z_from_sf(p))


@dataclass(frozen=True)
class Description:
    """The shape that describes the unexplained systematic, in words and numbers."""

    shape: Shape
    text: str
    heldout_chi2: tuple[float, float] | None  # held-out chi-square before and after subtracting the shape
    heldout_rows: int
    alternatives: list[dict]  # every shape tried: kind, BIC, z
    correction: dict | None  # scenario effect entry (empirical shape), None when the library has no such kind
    named_shift: np.ndarray | None = None  # the named effects' (prior-scaled) change when the shape is added (q,)
    chi2_left: float = 0.0  # training chi-square left after the shape
    n_rows: int = 0  # training residual rows

    def bic(self, n_named_params: int = 0) -> float:
        """BIC of the model this description completes: what is left, the shape's parameters (and
        its scanned position or period) and ``n_named_params`` named effect parameters."""
        return self.chi2_left + (self.shape.k + (self.shape.scanned > 1) + n_named_params) * np.log(self.n_rows)

    def as_json(self) -> dict:
        s = self.shape
        exact = s.kind in ("step", "ripple")  # a generic basis's coefficients are not identifiable (the attitudes absorb directions)
        return {"shape": s.kind, **s.label, "text": self.text, "coefficients_px": s.coef.tolist() if exact else None,
                "sigmas_px": np.sqrt(np.diag(s.cov)).tolist() if exact else None, "delta_chi2": s.delta_chi2, "dof": s.k,
                "z": s.z(), "heldout_chi2_before": None if self.heldout_chi2 is None else self.heldout_chi2[0],
                "heldout_chi2_after": None if self.heldout_chi2 is None else self.heldout_chi2[1],
                "heldout_rows": self.heldout_rows, "alternatives": self.alternatives, "correction": self.correction}


def describe(obs: Observations, pred: Prediction, train: np.ndarray, camera,
             named: tuple[np.ndarray, np.ndarray] | None = None) -> Description | None:
    """The smallest shape explaining the residual ``pred`` leaves on ``train`` (None: none significant).

    ``named``: the named effects' projected, whitened signature rows on the training and on the
    held-out stars, ((N, q), (N_h, q)); free while each shape is fitted, and moved with it on the
    held-out data."""
    aj = _Projector(obs, pred, None if named is None else named[0])
    r = aj.rows(whitened_residuals(obs, pred)[:, :, None], train)[:, 0]
    shapes = [*_steps(obs, aj, r, train, camera), *_ripples(obs, aj, r, train, camera), *_bases(obs, pred, aj, r, train, camera)]
    shapes = [s for s in shapes if s is not None]
    if not shapes:
        return None
    n_rows = r.size
    best = min(shapes, key=lambda s: s.bic(n_rows))
    if best.bic(n_rows) >= 0 or best.z() <= catchall.Z_LIMIT:
        return None
    # overdispersion: what the best shape leaves, per dof; chi-square differences between shapes
    # are compared in its units (quasi-likelihood BIC), so that a flexible basis does not win by
    # absorbing a small misfit of a large perturbation
    fixed = 3 * np.unique(obs.frame[train]).size + (0 if named is None else named[0].shape[1])  # attitudes, named
    c_hat = max(1.0, (float(r @ r) - best.delta_chi2) / max(n_rows - best.k - fixed, 1))
    quasi = min(shapes, key=lambda s: s.bic(n_rows, c_hat))
    if quasi.bic(n_rows, c_hat) < 0 and quasi.z() > catchall.Z_LIMIT:
        best = quasi
    held = ~train
    heldout, shift = None, None
    if named is not None and named[0].size:  # the named effects' share, moved with the shape on training
        shift = -np.linalg.pinv(named[0]) @ (aj.rows(whiten(obs, best.columns), train, free=False) @ best.coef)
    if held.any():
        rh = aj.rows(whitened_residuals(obs, pred)[:, :, None], held, free=False)[:, 0]
        fitted = aj.rows(whiten(obs, best.columns), held, free=False) @ best.coef
        if shift is not None:
            fitted = fitted + named[1] @ shift
        heldout = (float(rh @ rh), float(np.sum((rh - fitted) ** 2)))
    alts = sorted(({"shape": s.kind, **s.label, "bic": float(s.bic(n_rows, c_hat)), "z": s.z()}
                   for s in _best_per_kind(shapes, n_rows, c_hat)), key=lambda a: a["bic"])
    text = _text(best, obs, aj, train)
    runner = min((s for s in shapes if s.kind != best.kind), key=lambda s: s.bic(n_rows, c_hat), default=None)
    if runner is not None and runner.bic(n_rows, c_hat) - best.bic(n_rows, c_hat) < CLOSE_BIC:
        text += f" (about as likely, within {CLOSE_BIC:g} BIC: {_text(runner, obs, aj, train)})"
    correction = _correction(best)
    if heldout is not None and heldout[1] >= heldout[0]:  # a correction must hold up on data the fit never saw
        text += " (not confirmed on the held-out data: no correction written)"
        correction = None
    return Description(best, text, heldout, int(2 * held.sum()), alts, correction, shift,
                       float(r @ r) - best.delta_chi2, n_rows)


# ------------------------------------------------------------------------------------- shapes
def _rows(p: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(n, 2, m) -> the rows of ``mask``: all x rows, then all y rows (the selection's order), (N, m)."""
    return np.concatenate([p[mask, 0, :], p[mask, 1, :]])


class _Projector:
    """Whitened columns (n, 2, m) -> their rows with every frame's attitude and (on the training
    rows) the named effects projected out."""

    def __init__(self, obs: Observations, pred: Prediction, named: np.ndarray | None):
        self.obs, self.aj = obs, whiten(obs, pred.att_jac)
        self.q = None
        if named is not None and named.size:
            u, s, _ = np.linalg.svd(named, full_matrices=False)
            self.q = u[:, s > 1e-8 * s[0]]

    def rows(self, cols: np.ndarray, mask: np.ndarray, free: bool = True) -> np.ndarray:
        g = _rows(selection.project_frames(self.obs.frame, self.obs.n_frames, self.aj, cols), mask)
        if free and self.q is not None:
            g = g - self.q @ (self.q.T @ g)
        return g


class _SingleAxisRows:
    """:meth:`_Projector.rows` (``free``) of many columns that each move one image axis by a value
    per star: ``rows(values)`` is ``aj.rows(whiten(obs, _single_axis(values, axis)), mask)`` up
    to rounding.

    The period search projects hundreds of such columns at a time, where the general projection
    (per-star 2 x (3 + m) products summed per frame) was most of the diagnosis's time on
    thousands of stars. Here the products are sparse: a star's whitened column is its whitened unit
    vector along ``axis``, ``w_n``, times its value, so each frame's attitude normal right-hand
    side is ``sum_n (aj_n^T w_n) value_n``, one sparse (3F x n) product, and the fitted attitude
    motion on the ``mask`` rows another (2N x 3F)."""

    def __init__(self, proj: _Projector, axis: int, mask: np.ndarray):
        obs, aj = proj.obs, proj.aj
        unit = np.zeros((obs.n, 2, 1))
        unit[:, axis, 0] = 1.0
        w = whiten(obs, unit)[:, :, 0]  # (n, 2)
        h = np.einsum("nki,nk->ni", aj, w)  # (n, 3): each star's attitude normal per unit value
        self.n_frames, at = obs.n_frames, obs.frame[:, None] * 3 + np.arange(3)  # (n, 3) attitude columns
        self.h = sparse.csr_matrix((h.ravel(), (at.ravel(), np.repeat(np.arange(obs.n), 3))),
                                   shape=(3 * self.n_frames, obs.n))
        self.a = frame_normal(obs.frame, obs.n_frames, aj, np.ones(obs.n), np.zeros((obs.n, 2, 0)))[0]
        self.idx = np.flatnonzero(mask)
        k = self.idx.size
        rows = np.repeat(np.arange(2 * k), 3)
        vals = np.concatenate([aj[self.idx, 0, :].ravel(), aj[self.idx, 1, :].ravel()])
        self.j = sparse.csr_matrix((vals, (rows, np.concatenate([at[self.idx].ravel()] * 2))),
                                   shape=(2 * k, 3 * self.n_frames))
        self.w, self.q = w[self.idx], proj.q

    def rows(self, values: np.ndarray) -> np.ndarray:
        """The projected rows (2N, m) of the columns ``values`` (n, m) moving ``axis``."""
        coef = solve_frames(self.a, (self.h @ values).reshape(self.n_frames, 3, -1))
        v = values[self.idx]
        g = np.concatenate([self.w[:, :1] * v, self.w[:, 1:] * v]) - self.j @ coef.reshape(3 * self.n_frames, -1)
        if self.q is not None:
            g = g - self.q @ (self.q.T @ g)
        return g


def _coords(obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """The detector coordinates a shape can run along: column (x) and row (y) of every star."""
    return obs.x, obs.y


def _single_axis(values: np.ndarray, axis: int) -> np.ndarray:
    """(n, m) per-star values -> (n, 2, m) columns moving ``axis`` only."""
    out = np.zeros((values.shape[0], 2, values.shape[1]))
    out[:, axis, :] = values
    return out


def _steps(obs, aj, r, train, camera) -> list[Shape]:
    out = []
    for c, coord in enumerate(_coords(obs)):
        size = camera.width if c == 0 else camera.height
        grid = np.arange(STEP_GRID_PX, size - STEP_GRID_PX, STEP_GRID_PX) - 0.5
        sides = _stars_each_side(obs.catalog_id[train], coord[train], grid)
        beyond = (coord[:, None] > grid[None, :]).astype(float)
        for axis in (0, 1):
            cols = _single_axis(beyond, axis)
            g = aj.rows(whiten(obs, cols), train)
            gg = np.einsum("nm,nm->m", g, g)
            ok = (gg > 1e-9 * max(gg.max(initial=0.0), 1e-300)) & sides
            if not ok.any():
                continue
            gr = g.T @ r
            d = np.where(ok, gr**2 / np.where(ok, gg, 1.0), -np.inf)
            j = int(np.argmax(d))
            below, above = coord[train & (coord <= grid[j])], coord[train & (coord > grid[j])]
            gap = [float(below.max()) if below.size else 0.0, float(above.min()) if above.size else float(size)]
            label = {"axis": AXES[axis], "coordinate": COORDS[c], "position_px": 0.5 * (gap[0] + gap[1]), "between_px": gap}
            out.append(Shape("step", label, cols[:, :, j:j + 1], np.array([gr[j] / gg[j]]), np.array([[1.0 / gg[j]]]),
                             float(d[j]), 4 * int(ok.sum())))  # scanned: positions x 2 axes x 2 coordinates
    return out


def _stars_each_side(ids: np.ndarray, coord: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """For each step position of ``grid``: whether at least ``MIN_STEP_STARS`` distinct stars (by
    catalogue id) are seen below it and as many beyond it."""
    if ids.size == 0:
        return np.zeros(grid.size, dtype=bool)
    order = np.argsort(ids, kind="stable")
    ids, coord = ids[order], coord[order]
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    lo, hi = np.minimum.reduceat(coord, starts), np.maximum.reduceat(coord, starts)
    below = np.searchsorted(np.sort(lo), grid, side="right")  # stars seen at or below the position
    beyond = hi.size - np.searchsorted(np.sort(hi), grid, side="right")  # stars seen beyond it
    return (below >= MIN_STEP_STARS) & (beyond >= MIN_STEP_STARS)


def _ripples(obs, aj, r, train, camera) -> list[Shape]:
    out = []
    for c, coord in enumerate(_coords(obs)):
        size = camera.width if c == 0 else camera.height
        # uniform in frequency, 1 / (4 x the detector) apart: no period between two grid values
        # loses more than a quarter of a cycle over the detector
        freqs = np.arange(1.0 / (2.0 * size), 1.0 / MIN_PERIOD_PX, 1.0 / (4.0 * size))
        for axis in (0, 1):
            best = _best_period(obs, aj, r, train, coord, axis, 1.0 / freqs)
            df = 1.0 / (4.0 * size)
            fine = 1.0 / np.linspace(1.0 / best - df, 1.0 / best + df, 21)
            best = _best_period(obs, aj, r, train, coord, axis, fine)
            cols = _single_axis(_wave(coord, np.array([best])), axis)
            shape = _fit("ripple", {"axis": AXES[axis], "coordinate": COORDS[c], "period_px": float(best)}, cols,
                         obs, aj, r, train, 4 * freqs.size)  # scanned: frequencies x 2 axes x 2 coordinates
            if shape is not None:
                out.append(shape)
    return out


def _wave(coord: np.ndarray, periods: np.ndarray) -> np.ndarray:
    """(n, 2P): sin then cos of ``2 pi coord / P`` for every period, interleaved per period."""
    arg = 2.0 * np.pi * coord[:, None] / periods[None, :]
    return np.stack([np.sin(arg), np.cos(arg)], axis=-1).reshape(coord.size, -1)


PERIOD_CHUNK = 128  # periods projected at once (memory: stars x 2 x 2 x this)


def _best_period(obs, aj, r, train, coord, axis, periods) -> float:
    """The period of ``periods`` whose sine and cosine explain most of ``r`` (in chunks)."""
    d = np.empty(periods.size)
    rows = _SingleAxisRows(aj, axis, train)
    for i in range(0, periods.size, PERIOD_CHUNK):
        chunk = periods[i:i + PERIOD_CHUNK]
        g = rows.rows(_wave(coord, chunk)).reshape(-1, chunk.size, 2)
        # each period's 2 x 2 normal matrix from three sums (one 3-index einsum was 7x slower)
        s, c = g[..., 0], g[..., 1]
        sc = np.einsum("np,np->p", s, c)
        a = np.stack([np.einsum("np,np->p", s, s), sc, sc, np.einsum("np,np->p", c, c)], -1).reshape(-1, 2, 2)
        a = a + 1e-12 * np.eye(2)
        b = np.einsum("npi,n->pi", g, r)
        d[i:i + chunk.size] = np.einsum("pi,pi->p", b, np.linalg.solve(a, b[..., None])[..., 0])
    return float(periods[int(np.argmax(d))])


def _bases(obs, pred, aj, r, train, camera) -> list[Shape]:
    return [_fit(name, {}, cols, obs, aj, r, train, 1) for name, cols in catchall.generic_bases(obs, pred, camera).items()]


def _fit(kind: str, label: dict, cols: np.ndarray, obs, aj, r, train, scanned: int) -> Shape | None:
    """Least-squares coefficients of ``cols`` (n, 2, k, px per unit) on the projected residual ``r``,
    over the directions the projection leaves (singular values above 1e-8 of the largest)."""
    g = aj.rows(whiten(obs, cols), train)
    if not np.any(g):
        return None
    u, sv, vt = np.linalg.svd(g, full_matrices=False)
    keep = sv > 1e-8 * sv[0]
    if r.size < 5 * keep.sum():
        return None
    u, sv, vt = u[:, keep], sv[keep], vt[keep]
    cov = vt.T @ np.diag(sv**-2) @ vt  # the minimum-norm solution's covariance over the kept directions
    coef = vt.T @ ((u.T @ r) / sv)
    return Shape(kind, label, cols, coef, cov, float(np.sum((u.T @ r) ** 2)), scanned, int(keep.sum()))


def _best_per_kind(shapes: list[Shape], n_rows: int, c_hat: float) -> list[Shape]:
    best: dict[str, Shape] = {}
    for s in shapes:
        if s.kind not in best or s.bic(n_rows, c_hat) < best[s.kind].bic(n_rows, c_hat):
            best[s.kind] = s
    return list(best.values())


REFINE_Z = 3.0  # what the corrected model leaves of the shape is added when beyond this many sigma


def refine(first: Description, obs: Observations, pred: Prediction, train: np.ndarray,
           named: np.ndarray | None = None) -> Description | None:
    """``first`` with what ``pred`` (the model with ``first``'s correction in it) still leaves of
    the same shape (same position or period, coefficients refitted, the named effects' training
    rows ``named`` free) added to it; None when that is below ``REFINE_Z`` sigma. A ripple keeps
    its period: only its sine and cosine parts are refined."""
    s = first.shape
    aj = _Projector(obs, pred, named)
    r = aj.rows(whitened_residuals(obs, pred)[:, :, None], train)[:, 0]
    more = _fit(s.kind, s.label, _shape_columns(s, obs), obs, aj, r, train, 1)
    if more is None or more.coef.size != s.coef.size:
        return None
    z = float(np.sqrt(more.coef @ np.linalg.pinv(more.cov) @ more.coef))
    if z < REFINE_Z:
        return None
    shape = Shape(s.kind, s.label, _shape_columns(s, obs), s.coef + more.coef, more.cov, s.delta_chi2, s.scanned, s.rank)
    return replace(first, shape=shape, text=_shape_text(shape), correction=_correction(shape))


def _shape_columns(s: Shape, obs: Observations) -> np.ndarray:
    """The columns of a step or a ripple at ``obs``'s stars (n, 2, k)."""
    coord = obs.x if s.label["coordinate"] == "column" else obs.y
    axis = AXES.index(s.label["axis"])
    if s.kind == "step":
        return _single_axis((coord > s.label["position_px"]).astype(float)[:, None], axis)
    return _single_axis(_wave(coord, np.array([s.label["period_px"]])), axis)


# -------------------------------------------------------------------------------- words, scenario
def _text(s: Shape, obs: Observations, aj: "_Projector", train: np.ndarray) -> str:
    if s.kind in ("step", "ripple"):
        return _shape_text(s)
    # a generic basis: the displacement it fits once every frame's attitude is taken out, in px
    fitted = aj.rows(whiten(obs, s.columns), train, free=False) @ s.coef
    n = int(train.sum())
    sigma = obs.sigma[train]
    shift = np.hypot(fitted[:n] * sigma, fitted[n:] * sigma)
    worst = int(np.argmax(shift))
    size, at = float(shift[worst]), (obs.x[train][worst], obs.y[train][worst])
    rms = float(np.sqrt(np.mean(shift**2)))
    what = {"field polynomial": "a smooth field-wide displacement (cubic in the position)",
            "field cells": "a displacement that differs between regions of the detector (4 x 4 cells)",
            "magnitude bins": "a displacement that depends on the star's magnitude (quartiles)",
            "pixel phase": "an S-curve against the sub-pixel position",
            "row x image velocity": "a shift along the motion growing with the row (a timing error)"}.get(s.kind, s.kind)
    return f"{what}: {rms:.3g} px RMS after the attitudes, largest {size:.3g} px at ({at[0]:.0f}, {at[1]:.0f})"


def _shape_text(s: Shape) -> str:
    """A step or a ripple in words and numbers."""
    sig = np.sqrt(np.diag(s.cov))
    if s.kind == "step":
        lo, hi = s.label["between_px"]
        return (f"{s.label['axis']} residual steps by {s.coef[0]:+.3g} +- {sig[0]:.2g} px across {s.label['coordinate']} "
                f"{s.label['position_px']:.0f} (between the stars at {lo:.0f} and {hi:.0f}): stars beyond it are displaced")
    amp = float(np.hypot(*s.coef))
    amp_sigma = float(np.sqrt(s.coef @ s.cov @ s.coef)) / max(amp, 1e-300)
    along = "rows" if s.label["coordinate"] == "row" else "columns"
    return (f"ripple of period {s.label['period_px']:.0f} px along the {along}, amplitude {amp:.3g} +- {amp_sigma:.2g} px "
            f"in {s.label['axis']}")


def _correction(s: Shape) -> dict | None:
    """The scenario entry of an empirical shape that reproduces ``s`` (None: no empirical kind for it)."""
    axis = float(AXES.index(s.label["axis"])) if "axis" in s.label else None
    if s.kind == "step":
        return {"kind": "empirical_step", "params": {"axis": axis, "across": float(COORDS.index(s.label["coordinate"])),
                                                      "at_px": s.label["position_px"], "size_px": float(s.coef[0])}}
    if s.kind == "ripple":
        a_sin, a_cos = s.coef
        return {"kind": "empirical_ripple", "params": {"axis": axis, "along": float(COORDS.index(s.label["coordinate"])),
                                                        "period_px": s.label["period_px"],
                                                        "amplitude_px": float(np.hypot(a_sin, a_cos)),
                                                        "phase_rad": float(np.arctan2(a_cos, a_sin))}}
    return None
