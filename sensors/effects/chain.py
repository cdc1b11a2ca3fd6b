"""Chains of effects: canonical order, prediction, stacked Jacobians, total time shift, gyro hook.

A chain is applied in stage order (:data:`~rollingstar.sensors.effects.base.STAGE_TIME` first, then sky,
optics, detector; stable within a stage), whatever order a scenario lists its effects in:
time effects need the ideal line of sight, sky effects need an undistorted line of sight, and
centroid biases come last.

:func:`predict` is the forward model for callers that have a context but not the motion (the
diagnosis): time effects rotate the line of sight by the context's body rate. The simulator
(:mod:`rollingstar.sensors.centroid_sim`) evaluates the time channel on the true motion instead, via
:func:`time_shift_s`, and applies only :func:`image_effects`. For a constant rate both agree
exactly; otherwise they differ by ``alpha dt^2 / 2`` (``alpha`` the angular acceleration).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rollingstar.sensors.conventions import NS_PER_S
from rollingstar.sensors.effects.base import (
    STAGE_GYRO,
    STAGE_TIME,
    Effect,
    EffectContext,
)
from rollingstar.sensors.so3 import quat_multiply


def ordered(effects: Sequence[Effect]) -> tuple[Effect, ...]:
    """Effects in canonical stage order (stable within a stage)."""
    return tuple(sorted(effects, key=lambda e: e.stage))


def time_effects(effects: Sequence[Effect]) -> tuple[Effect, ...]:
    return tuple(e for e in ordered(effects) if e.stage == STAGE_TIME)


def image_effects(effects: Sequence[Effect]) -> tuple[Effect, ...]:
    """The effects the simulator applies as image-plane maps (not time, not gyro)."""
    return tuple(e for e in ordered(effects) if STAGE_TIME < e.stage < STAGE_GYRO)


def gyro_effects(effects: Sequence[Effect]) -> tuple[Effect, ...]:
    return tuple(e for e in ordered(effects) if "gyro" in e.channels)


def time_shift_s(effects: Sequence[Effect], ctx: EffectContext) -> np.ndarray:
    """Total time shift (s) of every observation from the chain's time effects."""
    total = np.zeros(ctx.n)
    for e in time_effects(effects):
        total = total + e.time_shift_s(ctx)
    return total


def shifted_context(effects: Sequence[Effect], ctx: EffectContext) -> EffectContext:
    """The context the effects after the time stage see: the instant each star is really seen.

    ``t_ns`` moves by the chain's total time shift ``dt`` (rounded to ns) and the attitude by the
    body rotation ``Exp(omega dt)``, so that e.g. a covariate, an angular acceleration or the zenith
    direction are evaluated when the star is seen -- as the simulator does on the true motion.
    """
    if not time_effects(effects):
        return ctx
    dt = time_shift_s(effects, ctx)
    if not dt.any():
        return ctx
    from scipy.spatial.transform import Rotation  # local: only needed with time effects

    changes = {"t_ns": ctx.t_ns + np.rint(dt * NS_PER_S).astype(np.int64)}
    if ctx.attitude is not None and ctx.omega_rad_s is not None:
        step = Rotation.from_rotvec(ctx.omega_rad_s * dt[:, None]).as_quat()
        changes["attitude"] = Rotation.from_quat(quat_multiply(ctx.attitude.as_quat(), step))
    return ctx.evolve(**changes)


def predict(effects: Sequence[Effect], ctx: EffectContext) -> tuple[np.ndarray, np.ndarray]:
    """Affected positions of the observations in ``ctx`` (starting from its ideal ``x, y``).

    Time effects act first (on the ideal line of sight); the later ones see :func:`shifted_context`.
    """
    ctx.check(effects)
    return _run(ordered(effects), ctx, 0, ctx.x, ctx.y)


def entering(effects: Sequence[Effect], ctx: EffectContext) -> list[tuple[np.ndarray, np.ndarray]]:
    """The positions entering each effect of ``ordered(effects)`` in :func:`predict`, then its result."""
    ctx.check(effects)
    trace: list = []
    trace.append(_run(ordered(effects), ctx, 0, ctx.x, ctx.y, trace))
    return trace


def resume(effects: Sequence[Effect], ctx: EffectContext, start: int, x, y) -> tuple[np.ndarray, np.ndarray]:
    """:func:`predict` of ``effects`` continued from ``ordered(effects)[start]``, which ``x, y`` enter.

    For a chain that differs from one traced by :func:`entering` only from position ``start`` on
    (the same effects before it, in the same order): the result is then its :func:`predict`, to
    the bit, without running the effects before ``start`` again. The shifted context is made from
    ``effects``, so the effect at ``start`` may be a time effect.
    """
    ctx.check(effects)
    return _run(ordered(effects), ctx, start, x, y)


def _run(chain: tuple[Effect, ...], ctx: EffectContext, start: int, x, y, trace: list | None = None):
    """The ordered ``chain`` from position ``start`` on positions ``x, y``; ``trace`` collects the
    positions entering each effect."""
    later = None  # the shifted context, made once when the first later effect needs it
    for e in chain[start:]:
        if trace is not None:
            trace.append((x, y))
        if e.stage == STAGE_TIME:
            x, y = e.apply(x, y, ctx)
        elif e.stage < STAGE_GYRO:
            if later is None:
                later = shifted_context(chain, ctx)
            x, y = e.apply(x, y, later)
    return np.asarray(x, dtype=float), np.asarray(y, dtype=float)


def chain_jacobian(effects: Sequence[Effect], ctx: EffectContext) -> tuple[np.ndarray, list[tuple[str, str]]]:
    """Stacked image-plane Jacobian of a chain, ``(n, 2, sum p)``, and its column labels.

    Each effect's block is evaluated at the positions entering it in the chain. The block is
    exact for that effect alone; cross terms (how later effects warp an earlier one's
    displacement) are neglected -- they are products of two small effects.
    """
    ctx.check(effects)
    x, y = ctx.x, ctx.y
    blocks, labels = [], []
    later = shifted_context(effects, ctx)
    for e in ordered(effects):
        if e.stage >= STAGE_GYRO:
            blocks.append(np.zeros((ctx.n, 2, len(e.parameters))))
        else:
            c = ctx if e.stage == STAGE_TIME else later
            blocks.append(e.jacobian(x, y, c))
            x, y = e.apply(x, y, c)
        labels += [(e.name, p.name) for p in e.parameters]
    jac = np.concatenate(blocks, axis=-1) if blocks else np.zeros((ctx.n, 2, 0))
    return jac, labels


def apply_gyro(effects: Sequence[Effect], t_ns, omega_rad_s) -> np.ndarray:
    """Gyro samples (m, 3) rad/s after every gyro-channel effect of the chain."""
    w = np.asarray(omega_rad_s, dtype=float)
    for e in gyro_effects(effects):
        w = e.apply_gyro(t_ns, w)
    return w
