"""Single-frame angular rate by particle swarm optimisation (Fu et al. 2022, eqs 8-18, Algorithm 1).

Model (derived from OUR camera model, ``docs/conventions.md``)
----------------------------------------------------------------
A star's camera-frame direction is ``w(t) = R(t)^T u`` with ``R(t + dt) = R(t) Exp(omega dt)``, so
``dw/dt = w x omega``. With the pinhole projection ``x = cx - F w_x / w_z``,
``y = cy - F w_y / w_z`` (he2021b eq 2, ``F`` focal length in px) the image velocity is, to first
order in the off-axis angle::

    v_x =  F omega_y + (y - cy) omega_z
    v_y = -F omega_x - (x - cx) omega_z                                        (fu2022 eq 7)

(:func:`image_velocity_px_s` gives the exact field). fu2022 eqs 6-8 agree with this in sign: their
``C = A(t+dt) A(t)^T = I - [omega]x dt`` is our ``Exp(-omega dt)``. With ``omega_z = 0`` (the
paper's collinear reverse installation, section 2.2) the velocity is uniform (eq 8)::

    v = (F omega_y, -F omega_x).

fu2022 eq 9 prints the two axes swapped (``Delta x = int f omega_x``); eq 8 and the discussion of
Fig 11 ("Delta y ... directly related to omega_x") confirm the form above.

Centroid error (eqs 11-14). A raw centroid refers to the mid-exposure of its own row,
``t_i = t0 + y_i' ld + T/2`` (the StarTable ``t_ns`` column). Relative to a reference time
``t_ref`` its displacement is ``Delta_i = v (t_i - t_ref)``; eq 11 is the case ``t_ref = t0``
(``Delta_i = (y_i t_line + T/2) v``). Eq 13 (every star's error from star 1's) follows because
``v`` is common, so parametrising by ``(Delta x_1, Delta y_1)`` (the paper) or by
``(omega_x, omega_y)`` (here, Algorithm 1's "velocity solutions") is the same search up to the
linear map of eqs 8 and 12. The corrected positions are ``x_i = x_i' - Delta_i`` (eq 14).

``model="rotation"`` (the default) replaces the pixel shift by the exact rotation of each star's
direction to ``t_ref``: ``w_i(t_ref) = Exp(omega (t_i - t_ref)) w_i(t_i)`` (no small-field
approximation). The uniform pixel shift of ``model="linear"`` is not a rotation: off axis the
plate scale grows as ``1 + tan^2``, so shifting all stars by ``v (T/2 + y ld)`` changes their
angular distances and biases the rate (0.08 deg/s median at wx = wy = 1 deg/s, no noise, with ``t_ref = t0`` on the
Table 1 sensor, see docs/reproductions/fu2022.md); ``reference="frame_mid"`` (default) shrinks the
shifts but does not remove the bias.

Loss (eqs 15-16): ``J = sum_{i<j} |theta_ij - theta'_ij|`` over the pairs of the selected stars,
``theta_ij`` from the catalogue (``ref_icrs``) and ``theta'_ij`` between the corrected directions
(eq 2); angles computed as ``atan2(|a x b|, a . b)`` (eq 15's arccos, better conditioned).

Search: standard PSO (eq 17), ``c1 = c2 = 2``, inertia weight falling linearly from 0.9 to 0.4
(eq 18), personal and global best updates of Algorithm 1; vectorised over particles (one loss
evaluation per generation for the whole swarm).
"""
from __future__ import annotations

from itertools import combinations
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from rollingstar.estimators.data import FrameData, RateEstimate, StarTable, frame_camera
from rollingstar.estimators.rates.base import RateEstimator, Reference, reference_time_ns
from rollingstar.sensors.conventions import DEG_TO_RAD, S_PER_NS
from rollingstar.sensors.so3 import rotate_by_rotvec

W_MAX, W_MIN = 0.9, 0.4  # eq 18
C1 = C2 = 2.0  # eq 17


# ----------------------------------------------------------------------------- model helpers
def image_velocity_px_s(camera, omega_rad_s, x, y) -> tuple[np.ndarray, np.ndarray]:
    """Exact image velocity (px/s) of stars at pixels ``(x, y)`` for body rate ``omega`` (3,).

    ``dw/dt = w x omega`` and ``d/dt (cx - F w_x / w_z) = -F (w_x' w_z - w_x w_z') / w_z^2`` (same
    for y), with ``w = [-(x - cx), -(y - cy), F]`` (he2021b eq 2, unnormalised). To first order this
    is fu2022 eq 7: ``v_x = F w_y + (y - cy) w_z``, ``v_y = -F w_x - (x - cx) w_z``.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    F = camera.focal_px
    w = np.stack([-(x - camera.cx), -(y - camera.cy), np.full(np.broadcast(x, y).shape, F)], axis=-1)
    wd = np.cross(w, np.asarray(omega_rad_s, dtype=float))
    vx = -F * (wd[..., 0] * w[..., 2] - w[..., 0] * wd[..., 2]) / w[..., 2] ** 2
    vy = -F * (wd[..., 1] * w[..., 2] - w[..., 1] * wd[..., 2]) / w[..., 2] ** 2
    return vx, vy


def uniform_velocity_px_s(focal_px: float, omega_xy) -> np.ndarray:
    """fu2022 eq 8 (``omega_z = 0``): ``v = (F omega_y, -F omega_x)`` px/s for rates (..., 2) rad/s."""
    om = np.asarray(omega_xy, dtype=float)
    return np.stack([focal_px * om[..., 1], -focal_px * om[..., 0]], axis=-1)


def _unit_from_pixels(camera, x, y) -> np.ndarray:
    """he2021b / fu2022 eq 2 for arrays of any shape (..., 3)."""
    return camera.unproject(x, y)


def _pair_angles(u: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Angles between ``u[..., i, :]`` and ``u[..., j, :]`` (eq 15, via atan2 for accuracy)."""
    a, b = u[..., i, :], u[..., j, :]
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def corrected_positions(camera, omega_xy, x, y, dt_s) -> tuple[np.ndarray, np.ndarray]:
    """Eqs 11-14 with eq 8: ``x_i = x_i' - v_x dt_i``, ``y_i = y_i' - v_y dt_i``, ``dt_i = t_i - t_ref``.

    ``omega_xy`` (..., 2) rad/s broadcasts against the stars (n,): the result is (..., n).
    """
    v = uniform_velocity_px_s(camera.focal_px, omega_xy)
    dt = np.asarray(dt_s, dtype=float)
    return x - v[..., 0:1] * dt, y - v[..., 1:2] * dt


def corrected_directions(camera, omega_xy, x, y, dt_s, model: str = "linear", w: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame unit directions (..., n, 3) of the stars moved to the reference time.

    ``model="linear"``: eqs 11-14 then eq 2 (``omega_x, omega_y`` only: eq 8 assumes ``omega_z = 0``);
    ``model="rotation"``: ``Exp(omega dt_i) w_i`` exactly, with ``omega = (omega_x, omega_y, 0)`` for a
    (..., 2) ``omega_xy`` or the full body rate for a (..., 3) one (e.g. a gyro rate applied by
    ``rate-correction``). ``w``: the stars' unit directions ``unproject(x, y)`` when already
    computed (``model="rotation"``; the swarm's loss reuses them in every generation).
    """
    om = np.asarray(omega_xy, dtype=float)
    if model == "linear":
        xc, yc = corrected_positions(camera, om[..., :2], x, y, dt_s)
        return _unit_from_pixels(camera, xc, yc)
    w = _unit_from_pixels(camera, x, y) if w is None else w  # (n, 3)
    om3 = om if om.shape[-1] == 3 else np.concatenate([om, np.zeros(om.shape[:-1] + (1,))], axis=-1)  # (..., 3)
    rotvec = om3[..., None, :] * np.asarray(dt_s, dtype=float)[:, None]  # (..., n, 3)
    return rotate_by_rotvec(rotvec, w)


def angular_distance_loss(camera, omega_xy, x, y, dt_s, cat_angles, pairs, model: str = "linear",
                          w: np.ndarray | None = None) -> np.ndarray:
    """Eq 16: ``J(omega) = sum_pairs |theta_ij - theta'_ij|`` (rad), vectorised over ``omega_xy`` (..., 2).
    ``w``: see :func:`corrected_directions`."""
    u = corrected_directions(camera, omega_xy, x, y, dt_s, model, w)
    i, j = pairs
    return np.sum(np.abs(_pair_angles(u, i, j) - cat_angles), axis=-1)


def triple_conditioning(x, y, dt_s, focal_px: float, triples: np.ndarray) -> np.ndarray:
    """Smallest singular value (rad per rad/s) of each triple's 3 x 2 sensitivity of the pair
    distances to ``(omega_x, omega_y)``: row ``ij`` is ``-(dt_i - dt_j) F [-e_y, e_x] / F`` with
    ``e`` the pair's unit vector in the image (eqs 8, 11-14 linearised). Vectorised over triples (m, 3).
    """
    i = triples[:, [0, 0, 1]]
    j = triples[:, [1, 2, 2]]
    ex, ey = x[i] - x[j], y[i] - y[j]
    d = np.hypot(ex, ey)
    d = np.where(d > 0, d, 1.0)
    ddt = dt_s[i] - dt_s[j]
    J = np.stack([ddt * ey / d, -ddt * ex / d], axis=-1)  # (m, 3, 2), in units of F * rad/(rad/s) / F
    return np.linalg.svd(J, compute_uv=False)[:, -1]


def select_stars(stars: StarTable, n_stars: int | str, camera, selection: str = "adjacent",
                 dt_s: np.ndarray | None = None) -> np.ndarray:
    """Indices of the stars used (eq 16's sum runs over their pairs).

    ``selection="spread"`` (``n_stars = 3`` only): the triple of identified stars whose pair
    distances are most sensitive to the rate in their least sensitive direction (largest smallest
    singular value, :func:`triple_conditioning`); needs ``dt_s`` (the stars' ``t_i - t_ref``).

    ``"all"``: every identified star. An integer ``n``: the "adjacent" stars of fu2022 section 2.3 --
    star 1 (eq 12's reference star) is the brightest identified star (largest ``flux``; without
    fluxes the one closest to the principal point), plus its ``n - 1`` nearest identified
    neighbours in the image. Ties are broken by the table order, so the choice is deterministic.
    """
    ident = np.flatnonzero(stars.identified & np.isfinite(stars.x) & np.isfinite(stars.y))
    if n_stars == "all" or ident.size <= int(n_stars):
        return ident
    if selection == "spread":
        triples = np.array(list(combinations(range(ident.size), 3)), dtype=np.intp)
        score = triple_conditioning(stars.x[ident], stars.y[ident], np.asarray(dt_s)[ident], camera.focal_px, triples)
        return ident[triples[int(np.argmax(score))]]
    flux = stars.flux[ident]
    if np.any(np.isfinite(flux)):
        key = np.where(np.isfinite(flux), -flux, np.inf)
    else:
        key = np.hypot(stars.x[ident] - camera.cx, stars.y[ident] - camera.cy)
    first = ident[int(np.argmin(key))]
    d = np.hypot(stars.x[ident] - stars.x[first], stars.y[ident] - stars.y[first])
    order = np.argsort(d, kind="stable")
    return ident[order[: int(n_stars)]]


# ------------------------------------------------------------------------------------- PSO
class PsoResult:
    """Outcome of :func:`pso_minimise`: best position, its loss, convergence generation, generations run."""

    __slots__ = ("best", "loss", "iterations", "generations")

    def __init__(self, best, loss, iterations, generations):
        self.best, self.loss, self.iterations, self.generations = best, loss, iterations, generations


def pso_minimise(loss, lo, hi, particles: int, max_iterations: int, tolerance: float, rng: np.random.Generator,
                 max_step_fraction: float = 0.2, patience: int | None = None) -> PsoResult:
    """Standard PSO (fu2022 eq 17, Algorithm 1) with eq 18's inertia weight.

    ``loss`` maps positions (P, d) to (P,). Positions start uniform in ``[lo, hi]``, velocities
    uniform in ``+-max_step`` (``max_step = max_step_fraction (hi - lo)``, also the velocity clamp:
    the paper gives none, and eq 17 with ``c1 = c2 = 2`` and ``w = 0.9`` diverges without one);
    positions are clipped to the box. Generation ``g = 0 .. N-1`` uses
    ``w_g = w_min + (N - g) / N (w_max - w_min)``, ``r1, r2 ~ U[0, 1]`` per particle and dimension;
    a personal best is replaced when the new loss is not larger (Algorithm 1 line 11), the global
    best when a personal best is strictly better (lines 12-16).

    ``iterations`` (convergence generation): the last generation in which the global best moved
    by more than ``tolerance`` from where it stood at the previous such generation (0 if the
    initial best was never bettered by more than that). With ``patience`` the search stops once
    the global best has stayed within ``tolerance`` for that many generations.
    """
    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)
    d = lo.shape[0]
    vmax = max_step_fraction * (hi - lo)
    X = lo + (hi - lo) * rng.random((particles, d))
    V = vmax * (2.0 * rng.random((particles, d)) - 1.0)
    f = loss(X)
    P, fP = X.copy(), f.copy()
    k = int(np.argmin(fP))
    G, fG = P[k].copy(), float(fP[k])
    anchor, converged_at, g_run = G.copy(), 0, 0
    N = max_iterations
    for g in range(N):
        w = W_MIN + (N - g) / N * (W_MAX - W_MIN)  # eq 18
        r = rng.random((2, particles, d))
        V = np.clip(w * V + C1 * r[0] * (P - X) + C2 * r[1] * (G - X), -vmax, vmax)  # eq 17
        X = np.clip(X + V, lo, hi)
        f = loss(X)
        better = f <= fP  # Algorithm 1 line 11
        P[better], fP[better] = X[better], f[better]
        k = int(np.argmin(fP))
        if fP[k] < fG:  # lines 12-16
            G, fG = P[k].copy(), float(fP[k])
        g_run = g + 1
        if np.max(np.abs(G - anchor)) > tolerance:
            anchor, converged_at = G.copy(), g + 1
        elif patience is not None and g + 1 - converged_at >= patience:
            break
    return PsoResult(G, fG, converged_at, g_run)


# ---------------------------------------------------------------------------------- plugins
class PsoParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    particles: int = Field(default=30, ge=2, description="Swarm size N0 (Algorithm 1; not given by the paper).")
    max_iterations: int = Field(default=50, ge=1, description="Generations N (eq 18, Algorithm 1).")
    tolerance_deg_s: float = Field(
        default=1e-3, gt=0,
        description="A generation counts towards convergence when the global best moves more than this (deg/s, per axis).")
    patience: int | None = Field(
        default=None, ge=1, description="Stop after this many generations without such a move; None: run all N (Algorithm 1).")
    search_deg_s: float = Field(default=10.0, gt=0, description="Search box +-this for omega_x and omega_y (deg/s).")
    max_step_fraction: float = Field(default=0.1, gt=0, le=1.0, description="Velocity clamp as a fraction of the box width.")
    n_stars: int | Literal["all"] = Field(default=3, description="Adjacent stars used (>= 3) or 'all' identified stars.")
    selection: Literal["adjacent", "spread"] = Field(
        default="adjacent",
        description="'adjacent': brightest star and its nearest neighbours (fu2022 section 2.3); "
        "'spread': the best-conditioned triple (n_stars = 3 only).")
    model: Literal["linear", "rotation"] = Field(
        default="rotation", description="'linear': fu2022 eqs 11-14 pixel shift; 'rotation': exact rotation to t_ref.")
    reference: Reference = Field(
        default="frame_mid",
        description="t_ref: 'frame_start' = row 0 exposure start (eq 11 as printed); 'frame_mid' = mid-exposure of the middle row.")
    seed: int = Field(default=0, ge=0, description="PSO random stream: default_rng([seed, frame.index]).")

    @field_validator("n_stars")
    @classmethod
    def _at_least_three(cls, v):
        if v != "all" and int(v) < 3:
            raise ValueError("n_stars must be >= 3 (two unknowns need three angular distances) or 'all'")
        return v

    @model_validator(mode="after")
    def _spread_needs_three(self):
        if self.selection == "spread" and self.n_stars != 3:
            raise ValueError("selection='spread' chooses a triple: it needs n_stars = 3")
        return self


class PsoRateEstimator(RateEstimator):
    """Single-frame rate from angular-distance invariance, solved by PSO (fu2022 eqs 8-18, Algorithm 1).

    Uses ``n_stars`` adjacent identified stars (default 3: the brightest and its two nearest
    neighbours; ``"all"``: every identified star) of ``frame.stars`` with their raw ``t_ns``
    (mid-exposure of their own row). Finds ``(omega_x, omega_y)`` minimising eq 16 over
    ``+-search_deg_s`` with the standard PSO of eqs 17-18 (``c1 = c2 = 2``, ``w`` 0.9 -> 0.4),
    deterministic: random stream ``default_rng([seed, frame.index])``.

    Sets ``frame.rate`` to a :class:`RateEstimate` in the camera frame (rad/s) at ``t_ref``
    (``reference``), with ``omega_z = 0`` **by assumption** (the paper's collinear reverse
    installation; the method cannot observe ``omega_z``) and ``iterations`` = the PSO convergence
    generation (see :func:`pso_minimise`). Fewer than three identified stars: an invalid estimate
    with reason ``too_few_stars`` (and frame flag ``rate_invalid``). Stars are not modified
    (``rate-correction`` after this stage applies eqs 11-14 with the rate).
    """

    name = "pso-rate"
    Params = PsoParams

    def estimate(self, frame: FrameData) -> RateEstimate:
        """The rate estimate of ``frame`` at ``t_ref`` (invalid, with the reason, below three stars)."""
        p = self.params
        t_ref = reference_time_ns(p.reference, frame.t0_ns, self.context.timing)
        stars = frame.stars if frame.stars is not None else StarTable.empty()
        cam = frame_camera(frame, self.context)
        dt_all = (stars.t_ns - np.int64(t_ref)).astype(float) * S_PER_NS
        sel = select_stars(stars, p.n_stars, cam, p.selection, dt_all)
        if sel.size < 3:
            return RateEstimate(t_ns=t_ref, omega_rad_s=np.full(3, np.nan), valid=False,
                                reason=f"too_few_stars: {sel.size} identified, the PSO rate needs >= 3")
        x, y, dt = stars.x[sel], stars.y[sel], dt_all[sel]
        i, j = np.triu_indices(sel.size, k=1)
        ref = stars.ref_icrs[sel]
        cat = _pair_angles(ref, i, j)
        w = _unit_from_pixels(cam, x, y) if p.model == "rotation" else None  # once, not in every generation

        def loss(om):
            return angular_distance_loss(cam, om, x, y, dt, cat, (i, j), p.model, w)

        rng = np.random.default_rng([p.seed, int(frame.index)])
        S = p.search_deg_s * DEG_TO_RAD
        res = pso_minimise(loss, [-S, -S], [S, S], p.particles, p.max_iterations, p.tolerance_deg_s * DEG_TO_RAD, rng,
                           p.max_step_fraction, p.patience)
        omega = np.array([res.best[0], res.best[1], 0.0])  # omega_z = 0: the paper's installation assumption
        return RateEstimate(t_ns=t_ref, omega_rad_s=omega, valid=True, iterations=int(res.iterations))
