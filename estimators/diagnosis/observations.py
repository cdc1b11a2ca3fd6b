"""Identified star observations of a recording and the simulation model that predicts them.

Every identified star ``i`` of frame ``k`` is one observation: measured pixel position
``(x_i, y_i)`` with 1-sigma ``sigma_i`` per axis, catalogue direction ``u_i`` (ICRS), the time its
position refers to ``t_i`` (mid-exposure of its own row, see :mod:`rollingstar.sensors.centroid_sim`).
When the recording's stars carry 2 x 2 position covariances ``C_i`` that are not all isotropic
(a smeared spot's is long along the smear), every residual and Jacobian is whitened by ``C_i``
instead of ``sigma_i`` (:func:`whiten`: ``L_i^-1 (dx, dy)`` with ``L_i L_i^T = C_i``), and the
weights of the attitude fits are the information matrices ``C_i^-1`` (:func:`star_weights`).

The *simulation model* predicts it from a per-frame attitude ``R_k`` at the frame reference time
``t_ref,k`` (mid-exposure of the middle row) and a per-frame body rate ``omega_k``::

    R(t_i) = R_k Exp(omega_k (t_i - t_ref,k))
    w_i    = R(t_i)^T u_i                               (camera frame)
    (x, y) = chain(project(w_i))                         (he2021b eq 2, then the effect chain)

where the chain is :func:`rollingstar.sensors.effects.chain.predict` over the scenario's effects (and the
candidate effects being fitted) with the per-star :class:`~rollingstar.sensors.effects.base.EffectContext`.

The attitude is the always-refitted nuisance. Its image-plane Jacobian is a small body rotation
``delta`` (``R -> R Exp(delta)`` gives ``w -> w + w x delta``)::

    d(x, y)/d(delta) = P(w) [w]_x                        (P = camera.projection_jacobian)

and the image velocity of a star is the same Jacobian applied to the rate, ``v = P(w) [w]_x omega``.

The per-frame rate is not a free per-frame nuisance: within one frame a rate change is exactly
collinear with a line-delay change (both move a star by ``omega * (row - row_c) * line_delay``),
so the rate comes from the attitude sequence across frames (:func:`rates_from_attitudes`).
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.sensors.conventions import NS_PER_S
from rollingstar.sensors.effects.base import EffectContext
from rollingstar.sensors.effects.chain import entering as chain_entering
from rollingstar.sensors.effects.chain import predict as chain_predict
from rollingstar.sensors.effects.chain import resume as chain_resume
from rollingstar.sensors.so3 import quat_multiply, skew

POS_STEP_PX = 1e-3
TILED_MAX_STARS = 1000  # up to this many stars the chain runs once over 5 copies of them (in predict)
# the position and its four central-difference neighbours, (dx, dy) px
POS_OFFSETS = np.array([[0.0, 0.0], [POS_STEP_PX, 0.0], [-POS_STEP_PX, 0.0], [0.0, POS_STEP_PX], [0.0, -POS_STEP_PX]])
# A frame takes a one-sided (backward/forward) rate instead of the central difference only when it
# fits its stars better by this much chi-square: picking the best of three on noise alone overfits
# the rate and biases every time-like effect (measured: rolling-shutter pulls shifted by -0.5
# sigma); a rate reversal at a frame boundary gains orders of magnitude more.
RATE_SWITCH_CHI2 = 25.0


@dataclass(frozen=True, eq=False)
class Observations:
    """All identified stars of a recording, flattened over frames (arrays of length ``n``).

    ``frame`` indexes the per-frame arrays (length ``F``): ``frame_index`` (the recording's frame
    numbers), ``t0_ns`` and ``t_ref_ns``. ``heldout`` marks observations split off before any fit.
    The arrays are never written in place (a changed set of observations is a new object,
    ``dataclasses.replace`` or :meth:`take`): the predictions keep context fields made from them
    (:func:`observation_context`).
    """

    frame: np.ndarray
    x: np.ndarray
    y: np.ndarray
    sigma: np.ndarray
    t_ns: np.ndarray
    u_icrs: np.ndarray
    magnitude: np.ndarray
    catalog_id: np.ndarray
    flux: np.ndarray
    frame_index: np.ndarray
    t0_ns: np.ndarray
    t_ref_ns: np.ndarray
    heldout: np.ndarray = field(default=None)
    sigma_source: str = "recording"
    pm_rad_yr: np.ndarray | None = None  # (n, 3) catalogue proper motions (ICRS tangent, rad/yr) when known
    exposure_ns: np.ndarray | None = None  # (F,) per-frame exposure when the recording mixes exposure times
    channel: object = None  # gyro_channel.GyroChannel: attitude increments vs the gyro, when the recording has one
    cov: np.ndarray | None = None  # (n, 2, 2) px^2 position covariances, when not all isotropic (module doc)
    noise_sigma_ln: float = 0.0  # standard error of ln(sigma) when the noise scale was measured (:mod:`.noise`)

    def __post_init__(self):
        if self.heldout is None:
            object.__setattr__(self, "heldout", np.zeros(self.n, dtype=bool))

    @property
    def n(self) -> int:
        return int(self.x.shape[0])

    @property
    def n_frames(self) -> int:
        return int(self.t0_ns.shape[0])

    def take(self, mask) -> "Observations":
        """The observations selected by ``mask`` (boolean over stars); frames are kept."""
        m = np.asarray(mask)
        per_star = ("frame", "x", "y", "sigma", "t_ns", "u_icrs", "magnitude", "catalog_id", "flux", "heldout", "pm_rad_yr",
                    "cov")
        return replace(self, **{k: getattr(self, k)[m] for k in per_star if getattr(self, k) is not None})

    def dt_s(self) -> np.ndarray:
        """Time of each star relative to its frame's reference time (s)."""
        return (self.t_ns - self.t_ref_ns[self.frame]).astype(float) / NS_PER_S


def whiten(obs: Observations, v: np.ndarray, idx=None) -> np.ndarray:
    """Pixel-space rows ``v`` (m, 2, ...) (x then y per star, of the stars ``idx``, default all) in
    units of each star's noise: ``v / sigma``, or ``L^-1 v`` with ``L L^T`` the star's 2 x 2 covariance."""
    v = np.asarray(v, dtype=float)
    if obs.cov is None:
        sig = obs.sigma if idx is None else obs.sigma[idx]
        return v / sig.reshape((-1,) + (1,) * (v.ndim - 1))
    cov = obs.cov if idx is None else obs.cov[idx]
    return np.einsum("nij,nj...->ni...", np.linalg.inv(np.linalg.cholesky(cov)), v)


def whitened_residuals(obs: Observations, pred, idx=None) -> np.ndarray:
    """``(obs - pred)`` of the stars ``idx`` (default all) whitened by their noise (:func:`whiten`), (m, 2)."""
    if idx is None:
        return whiten(obs, np.stack([obs.x - pred.x, obs.y - pred.y], axis=-1))
    return whiten(obs, np.stack([obs.x[idx] - pred.x[idx], obs.y[idx] - pred.y[idx]], axis=-1), idx)


def star_chi2(obs: Observations, pred) -> np.ndarray:
    """Each star's chi-square against ``pred`` (2 dof), ``|whitened residual|^2``, (n,)."""
    if obs.cov is None:
        return ((obs.x - pred.x) ** 2 + (obs.y - pred.y) ** 2) / obs.sigma**2
    return np.sum(whitened_residuals(obs, pred) ** 2, axis=1)


def star_weights(obs: Observations, use=None) -> np.ndarray:
    """Weights of the stars in a weighted least-squares fit: ``1 / sigma^2`` (n,), or the information
    matrices ``C^-1`` (n, 2, 2) when the stars carry 2 x 2 covariances; 0 outside ``use``."""
    use = np.ones(obs.n, dtype=bool) if use is None else np.asarray(use, dtype=bool)
    if obs.cov is None:
        return np.where(use, 1.0 / obs.sigma**2, 0.0)
    return np.where(use[:, None, None], np.linalg.inv(obs.cov), 0.0)


@dataclass(frozen=True, eq=False)
class Nuisance:
    """Per-frame attitude at ``t_ref`` (camera->ICRS) and body rate (rad/s), the refitted nuisance."""

    attitude: Rotation
    omega: np.ndarray

    def with_attitude(self, attitude: Rotation) -> "Nuisance":
        return Nuisance(attitude, self.omega)


@dataclass(frozen=True, eq=False)
class Prediction:
    """Model positions of every observation, the ideal (pinhole) positions and the effect context."""

    x: np.ndarray
    y: np.ndarray
    x_ideal: np.ndarray
    y_ideal: np.ndarray
    w_cam: np.ndarray
    att_jac: np.ndarray  # (n, 2, 3): d(x, y)/d(body rotation)
    vx: np.ndarray
    vy: np.ndarray
    omega: np.ndarray  # (n, 3) body rate of each star's frame
    ctx: EffectContext
    exposure_ns: np.ndarray | None = None  # (n,) per-star exposure when the recording mixes exposure times
    nuisance: Nuisance | None = None  # the nuisance and effect chain this prediction was made with
    effects: tuple = ()


def camera_rotations(obs: Observations, nuis: Nuisance) -> Rotation:
    """Camera->ICRS attitude at every observation's time, ``R_k Exp(omega_k dt_i)`` (composed as
    quaternions: :func:`rollingstar.sensors.so3.quat_multiply`; at rate zero the step is the
    identity and is not composed)."""
    q = nuis.attitude.as_quat()[obs.frame]
    if nuis.omega.any():
        q = quat_multiply(q, Rotation.from_rotvec(nuis.omega[obs.frame] * obs.dt_s()[:, None]).as_quat())
    return Rotation.from_quat(q)


def effect_context(obs: Observations, camera, timing, rot: Rotation, x, y, vx, vy, omega) -> EffectContext:
    """The per-observation :class:`rollingstar.sensors.effects.base.EffectContext` of the ideal positions."""
    return observation_context(obs).evolve(x=x, y=y, vx=vx, vy=vy, omega_rad_s=omega, attitude=rot, camera=camera,
                                           timing=timing)


# The context fields of each set of observations, made once (docstring of observation_context);
# weakly keyed, so that they go with the observations and are never copied or pickled with them.
_OBSERVATION_FIELDS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def observation_context(obs: Observations, k: int = 1) -> EffectContext:
    """The context fields that depend on the observations alone (times, rows, frames, magnitudes,
    catalogue directions), with no camera or timing, for the stars (``k=1``) or for ``k`` copies
    of them one after the other (:func:`predict`'s tiled chain). A prediction evolves them with its
    camera, timing, positions, rates and attitudes; they are made once per set of observations
    (the diagnosis predicts the same observations tens of thousands of times), whose arrays are
    never written in place."""
    kept = _OBSERVATION_FIELDS.setdefault(obs, {})
    if 1 not in kept:
        kept[1] = EffectContext(camera=None, x=obs.x, y=obs.y, t_ns=obs.t_ns, row=obs.y, t0_ns=obs.t0_ns[obs.frame],
                                frame=obs.frame, magnitude=obs.magnitude, unit_icrs=obs.u_icrs, pm_rad_yr=obs.pm_rad_yr,
                                t_start_ns=int(obs.t0_ns.min()) if obs.n_frames else 0)
    if k not in kept:
        kept[k] = kept[1].take(np.tile(np.arange(obs.n), k))
    return kept[k]


def tiled_context(ctx: EffectContext, tiled: EffectContext, k: int, x, y) -> EffectContext:
    """``ctx.take(np.tile(np.arange(n), k)).evolve(x=x, y=y)`` from ``tiled``, ``ctx``'s observation
    fields already in ``k`` copies (:func:`observation_context`): only the fields of the prediction
    are copied again."""
    changes = {"vx": copies(ctx.vx, k), "vy": copies(ctx.vy, k), "omega_rad_s": copies(ctx.omega_rad_s, k),
               "attitude": ctx.attitude if ctx.attitude.single else ctx.attitude[np.tile(np.arange(ctx.n), k)]}
    return tiled.evolve(x=x, y=y, camera=ctx.camera, timing=ctx.timing, **changes)


def offset_positions(ctx: EffectContext) -> tuple[np.ndarray, np.ndarray]:
    """The context's ideal positions moved by each of ``POS_OFFSETS`` in turn, (k n,) each."""
    n, k = ctx.n, len(POS_OFFSETS)
    return copies(ctx.x, k) + np.repeat(POS_OFFSETS[:, 0], n), copies(ctx.y, k) + np.repeat(POS_OFFSETS[:, 1], n)


def copies(a: np.ndarray, k: int) -> np.ndarray:
    """``k`` copies of ``a`` one after the other along its first axis (``np.tile`` along that axis,
    without its per-call cost)."""
    return np.concatenate((a,) * k) if k else a[:0]


def mixes_exposures(ctx: EffectContext, exposure_ns) -> bool:
    """Whether the observations of ``ctx`` mix exposure times (then each group runs its own chain)."""
    return exposure_ns is not None and ctx.timing is not None and np.unique(exposure_ns).size > 1


def by_exposure(ctx: EffectContext, exposure_ns, fn):
    """``fn(ctx)`` evaluated per exposure time of a recording that mixes them.

    :class:`~rollingstar.sensors.effects.base.EffectContext` carries one :class:`~rollingstar.sensors.timing.DetectorTiming`;
    a recording whose frames alternate exposure times (``Observations.exposure_ns``) is evaluated
    group by group with that group's exposure (one call per distinct exposure, not per star) and
    the results (arrays over observations, first axis) put back in order. ``fn`` returns an array
    or a tuple of arrays.
    """
    if not mixes_exposures(ctx, exposure_ns):
        return fn(ctx)
    out = None
    for e in np.unique(exposure_ns):
        idx = np.flatnonzero(exposure_ns == e)
        sub = ctx.take(idx).evolve(timing=replace(ctx.timing, exposure_ns=int(e)))
        res = fn(sub)
        res_t = res if isinstance(res, tuple) else (res,)
        if out is None:
            out = [np.zeros((ctx.n,) + np.shape(r)[1:], dtype=np.asarray(r).dtype) for r in res_t]
        for o, r in zip(out, res_t):
            o[idx] = r
    return tuple(out) if isinstance(res, tuple) else out[0]


def frame_reference_times(t0_ns: np.ndarray, timing, exposure_ns: np.ndarray | None = None) -> np.ndarray:
    """Per-frame reference time (mid-exposure of the middle row), with per-frame exposures if given."""
    t_ref = np.array([timing.frame_reference_ns(int(t)) for t in t0_ns], dtype=np.int64)
    if exposure_ns is not None:
        t_ref = t_ref + (np.asarray(exposure_ns, dtype=np.int64) - np.int64(timing.exposure_ns)) // 2
    return t_ref


@dataclass(frozen=True, eq=False)
class Pinhole:
    """What :func:`predict` computes of a nuisance before the effect chain (:func:`pinhole`): the
    lines of sight ``w``, ideal positions, their attitude Jacobian (n, 2, 3), image velocities and
    body rates, and the effect context of the ideal positions; with the observations, nuisance,
    camera and timing it was made for."""

    obs: Observations
    nuisance: Nuisance
    camera: object
    timing: object
    w: np.ndarray
    att_jac: np.ndarray
    v: np.ndarray
    omega: np.ndarray
    ctx: EffectContext
    exposure_ns: np.ndarray | None

    @cached_property
    def tiled(self) -> EffectContext:
        """The context of every star at each of ``POS_OFFSETS`` from its ideal position, in turn."""
        k = len(POS_OFFSETS)
        return tiled_context(self.ctx, observation_context(self.obs, k), k, *offset_positions(self.ctx))

    def made_for(self, obs: Observations, nuis: Nuisance, camera, timing) -> bool:
        return self.obs is obs and self.nuisance is nuis and self.camera is camera and self.timing is timing


def pinhole(obs: Observations, nuis: Nuisance, camera, timing=None) -> Pinhole:
    """The pinhole part of :func:`predict` (everything before the chain), for callers that
    predict one nuisance under many chains."""
    rot = camera_rotations(obs, nuis)
    w = rot.inv().apply(obs.u_icrs)
    x0, y0, _ = camera.project(w)
    jac = camera.projection_jacobian(w) @ skew(w)  # (n, 2, 3)
    omega = nuis.omega[obs.frame]
    v = np.einsum("nij,nj->ni", jac, omega)
    ctx = effect_context(obs, camera, timing, rot, x0, y0, v[:, 0], v[:, 1], omega)
    expo = None if obs.exposure_ns is None else obs.exposure_ns[obs.frame]
    return Pinhole(obs, nuis, camera, timing, w, jac, v, omega, ctx, expo)


def predict(obs: Observations, nuis: Nuisance, camera, timing=None, effects=(), attitude_jacobian: bool = True,
            start: Pinhole | None = None) -> Prediction:
    """Predict every observation: ideal pinhole position, then the effect chain in stage order.

    ``attitude_jacobian=False``: positions only; ``att_jac`` is then the pinhole's, without the
    chain's position Jacobian (the chain at four more positions of each star), for callers that
    difference positions. ``start``: :func:`pinhole` of these arguments, when the caller has it."""
    p = pinhole(obs, nuis, camera, timing) if start is None else start
    if not p.made_for(obs, nuis, camera, timing):
        raise ValueError("predict: the pinhole part given was made for another nuisance, camera, timing or set of "
                         "observations")
    ctx, expo, effects = p.ctx, p.exposure_ns, tuple(effects)
    x, y, jac = ctx.x, ctx.y, p.att_jac
    if effects and not attitude_jacobian:
        x, y = _run_chain(ctx, expo, effects)
    elif effects:
        x, y, pos_jac = by_exposure(ctx, expo, lambda c: _chain_with_position_jacobian(effects, c, p))
        jac = pos_jac @ jac  # (n, 2, 2) @ (n, 2, 3)
    return Prediction(np.asarray(x, float), np.asarray(y, float), ctx.x, ctx.y, p.w, jac, p.v[:, 0], p.v[:, 1], p.omega,
                      ctx, expo, nuis, effects)


def _chain_with_position_jacobian(effects: tuple, c: EffectContext, p: Pinhole):
    """The chain's positions of the context ``c`` and its position Jacobian d(x', y')/d(x, y) (n, 2, 2).

    The attitude moves the ideal position; the chain maps that motion through its position
    Jacobian, taken by central differences (the effects publish only parameter Jacobians). Needed
    where an effect is strongly nonlinear in position. Up to TILED_MAX_STARS stars, each position
    and its four neighbours go through the chain in one call over 5n copies (every effect acts on
    each star alone: tests/diagnosis/test_observations_tiling.py): the chain's cost is then per
    call; beyond TILED_MAX_STARS copying the context costs more. ``c`` is ``p``'s context, or one
    exposure group of it when the recording mixes exposure times.
    """
    n, k = c.n, len(POS_OFFSETS)
    if n <= TILED_MAX_STARS:
        if c is p.ctx:  # the whole recording: its tiled context is made once per pinhole part
            big = p.tiled
        else:
            bx, by = offset_positions(c)
            big = c.take(np.tile(np.arange(n), k)).evolve(x=bx, y=by)
        xs, ys = (np.reshape(a, (k, n)) for a in chain_predict(effects, big))
    else:
        xs, ys = (np.stack(a) for a in zip(*(chain_predict(effects, c.evolve(x=c.x + dx, y=c.y + dy))
                                             for dx, dy in POS_OFFSETS)))
    cols = [np.stack([xs[k] - xs[k + 1], ys[k] - ys[k + 1]], axis=-1) / (2 * POS_STEP_PX) for k in (1, 3)]
    return xs[0], ys[0], np.stack(cols, axis=-1)


def chain_positions(pred: Prediction, effects, trace: list | None = None, start: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The positions ``predict(..., effects, attitude_jacobian=False)`` gives with the nuisance
    ``pred`` was made with: only the chain runs again, on ``pred``'s ideal positions and context
    (for callers that difference one chain against others at the same attitudes).

    ``trace``: :func:`chain_trace` of a chain that ``effects`` equals before position ``start`` of
    its stage order; the chain then runs from ``start`` on (:func:`rollingstar.sensors.effects.chain.resume`)."""
    if trace is None or start == 0:
        x, y = _run_chain(pred.ctx, pred.exposure_ns, effects)
    else:
        x, y = chain_resume(tuple(effects), pred.ctx, start, *trace[start])
    return np.asarray(x, float), np.asarray(y, float)


def chain_trace(pred: Prediction, effects) -> list | None:
    """The positions entering each effect of the stage-ordered chain on ``pred``'s context
    (:func:`rollingstar.sensors.effects.chain.entering`); None when the recording mixes exposure
    times (each exposure group runs a chain of its own, :func:`by_exposure`)."""
    if mixes_exposures(pred.ctx, pred.exposure_ns):
        return None
    return chain_entering(tuple(effects), pred.ctx)


def _run_chain(ctx: EffectContext, exposure_ns, effects) -> tuple[np.ndarray, np.ndarray]:
    """The effect chain's positions of the context's ideal positions, per exposure group."""
    return by_exposure(ctx, exposure_ns, lambda c: chain_predict(tuple(effects), c))


def frame_normal(obs_frame: np.ndarray, n_frames: int, jac: np.ndarray, wts: np.ndarray, rhs: np.ndarray):
    """Per-frame normal matrices ``sum J^T W J`` (F, 3, 3) and ``sum J^T W r`` (F, 3, m).

    ``jac`` (n, 2, 3), ``wts`` (n,) inverse variances or (n, 2, 2) information matrices
    (:func:`star_weights`), ``rhs`` (n, 2, m). Vectorised over stars (:func:`frame_sums`; no
    per-frame Python loop).
    """
    jw = jac * wts[:, None, None] if wts.ndim == 1 else wts @ jac
    # the sums over the two image axes written out: what einsum("nki,nkj->nij") computes, to the
    # bit, in half its time on thousands of stars
    both = np.concatenate([jac, rhs], axis=-1)  # one sum per frame for J^T W J and J^T W r
    ab = frame_sums(obs_frame, n_frames, jw[:, 0, :, None] * both[:, 0, None, :] + jw[:, 1, :, None] * both[:, 1, None, :])
    return ab[..., :3], ab[..., 3:]


def frame_sums(obs_frame: np.ndarray, n_frames: int, values: np.ndarray) -> np.ndarray:
    """``values`` (n, ...) summed per frame, (n_frames, ...): ``np.add.at(out, obs_frame, values)``.

    One ``np.bincount`` over every element (frame-major bins): it adds each bin's values in the
    stars' order as ``np.add.at`` does, so the sums are the same to the bit, and is several times
    faster on thousands of stars."""
    k = math.prod(values.shape[1:])
    flat = values.reshape(values.shape[0], k)
    bins = (np.asarray(obs_frame, dtype=np.int64)[:, None] * k + np.arange(k)).ravel()
    sums = np.bincount(bins, weights=flat.ravel(), minlength=n_frames * k).astype(float, copy=False)
    return sums.reshape((n_frames,) + values.shape[1:])


def solve_frames(big_a: np.ndarray, big_b: np.ndarray) -> np.ndarray:
    """Solve every frame's 3x3 system; frames with fewer than 2 stars (singular) get zeros."""
    tr = np.trace(big_a, axis1=1, axis2=2)
    ok = np.linalg.det(big_a) > 1e-12 * np.maximum(tr, 1e-300) ** 3  # well conditioned (det vs trace^3)
    if ok.all():  # the usual case, without the copies of the selection (each system is solved alone)
        return np.linalg.solve(big_a, big_b)
    out = np.zeros_like(big_b)
    if ok.any():
        out[ok] = np.linalg.solve(big_a[ok], big_b[ok])
    return out


def fit_attitudes(obs: Observations, nuis: Nuisance, camera, timing=None, effects=(), mask=None,
                  iterations: int = 4, start: Pinhole | None = None) -> tuple[Nuisance, Prediction]:
    """Gauss-Newton refit of every frame's attitude (weighted least squares over its stars).

    Only observations in ``mask`` (default: all) contribute; the prediction returned covers all.
    ``start``: :func:`pinhole` of ``nuis``, for callers that refit from one nuisance many times.
    """
    use = np.ones(obs.n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    wts = star_weights(obs, use)
    pred = predict(obs, nuis, camera, timing, effects, start=start)
    for _ in range(iterations):
        r = np.stack([obs.x - pred.x, obs.y - pred.y], axis=-1)[:, :, None]
        if not np.isfinite(r).all():  # stars the model cannot place (weight 0 outside ``mask``)
            r = np.nan_to_num(r)
        a, b = frame_normal(obs.frame, obs.n_frames, pred.att_jac, wts, r)
        delta = solve_frames(a, b)[:, :, 0]
        nuis = nuis.with_attitude(nuis.attitude * Rotation.from_rotvec(delta))
        pred = predict(obs, nuis, camera, timing, effects)
        if np.max(np.abs(delta)) < 1e-12:
            break
    return nuis, pred


def rates_from_attitudes(attitude: Rotation, t_ref_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Backward, forward and central finite-difference body rates of a per-frame attitude sequence.

    ``omega_fwd,k = log(R_k^T R_{k+1}) / (t_{k+1} - t_k)`` (body frame); the backward rate of frame
    ``k`` is the forward rate of ``k-1``. End frames reuse their only neighbour. With one frame
    all rates are zero (a single image carries no rate information).
    """
    f = len(t_ref_ns)
    if f < 2:
        z = np.zeros((f, 3))
        return z, z, z
    dt = np.diff(t_ref_ns).astype(float) / NS_PER_S
    step = (attitude[:-1].inv() * attitude[1:]).as_rotvec() / dt[:, None]
    fwd = np.vstack([step, step[-1:]])
    bwd = np.vstack([step[:1], step])
    central = 0.5 * (fwd + bwd)
    return bwd, fwd, central


def frame_chi2(obs: Observations, pred: Prediction, mask=None) -> np.ndarray:
    """Chi-square of every frame's observations (in ``mask``) against the prediction, (F,)."""
    use = np.ones(obs.n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    c = star_chi2(obs, pred)
    return np.bincount(obs.frame[use], weights=c[use], minlength=obs.n_frames)


def fit_nuisance(obs: Observations, start, camera, timing=None, effects=(), mask=None,
                 moving: bool = True) -> tuple[Nuisance, Prediction]:
    """Attitudes and rates for the model, from ``start`` (per-frame attitudes, or a :class:`Nuisance`).

    From bare attitudes: attitudes at rate 0, rates from the attitude sequence, attitudes again;
    from a Nuisance its rates are kept for the first attitude fit (an effect that is strongly
    nonlinear in position needs a start near the solution). Then twice: rates from the attitude
    sequence and attitudes again. Per frame the central difference is kept unless a one-sided
    (backward or forward) difference fits its stars better by ``RATE_SWITCH_CHI2``, so that a rate
    reversal between frames costs nothing while a constant rate is not overfitted.
    """
    if isinstance(start, Nuisance):
        nuis = start
    else:
        nuis = Nuisance(start, np.zeros((obs.n_frames, 3)))
    nuis, pred = fit_attitudes(obs, nuis, camera, timing, effects, mask)
    if not moving or obs.n_frames < 2:
        return nuis, pred
    for _ in range(2):
        options = rates_from_attitudes(nuis.attitude, obs.t_ref_ns)
        fits = [fit_attitudes(obs, Nuisance(nuis.attitude, omega), camera, timing, effects, mask) for omega in options]
        chis = np.stack([frame_chi2(obs, p_j, mask) for _, p_j in fits])  # (3, F): backward, forward, central
        one_sided = np.argmin(chis[:2], axis=0)
        gain = chis[2] - chis[:2].min(axis=0)
        best = np.where(gain > RATE_SWITCH_CHI2, one_sided, 2)
        if np.all(best == best[0]):  # one choice for every frame: that fit is the refit (the same inputs)
            nuis, pred = fits[int(best[0])]
            continue
        omega = np.stack(options)[best, np.arange(obs.n_frames)]
        nuis, pred = fit_attitudes(obs, Nuisance(nuis.attitude, omega), camera, timing, effects, mask)
    return nuis, pred
