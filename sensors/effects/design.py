"""Detectability of an effect in a measurement design: signature size after the nuisance is refitted.

For a design (the observations of a recording, as an :class:`~rollingstar.sensors.effects.base.EffectContext`
with ``frame`` indices) with isotropic centroid noise ``sigma_px`` per axis, the Fisher
information of an effect's parameters ``p`` with the per-frame attitude (and optionally rate)
refitted is ``F = J_perp^T J_perp / sigma^2`` where ``J_perp`` is the image-plane signature
``J = d(x', y') / dp`` with its least-squares projection on the nuisance columns removed frame by
frame: attitude columns ``A = d(x, y) / d rotvec = P(w) [w]x``
(:func:`rollingstar.sensors.effects.geometry.rotation_jacobian`) and, for ``nuisance="attitude_rate"``,
``A * tau`` with ``tau`` the time from the frame's mean observation time (a rate refitted per
frame). The Cramér–Rao sigma of ``p_j`` alone (others fixed) is ``sigma / |J_perp,j|`` and
:func:`detection_limit` is ``n_sigma`` times that: the parameter value whose projected signature
reaches ``n_sigma`` standard deviations -- "1x the detection limit" in ``rollingstar bench
discrepancy`` when ``n_sigma`` is the benchmark's threshold.

Effects whose signature lives only in the gyro channel (``gyro_bias``, ``gyro_scale``) have no
image signature: their image detection limit is ``inf``; :func:`gyro_detection_limit` gives the
limit from gyro samples against a reference rate.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from rollingstar.sensors.conventions import NS_PER_S
from rollingstar.sensors.effects.geometry import rotation_jacobian

if TYPE_CHECKING:  # names in annotations only: base imports this module
    from rollingstar.sensors.effects.base import Effect, EffectContext

NUISANCES = (None, "attitude", "attitude_rate")


def nuisance_columns(ctx: EffectContext, nuisance: str | None) -> np.ndarray:
    """Per-observation nuisance Jacobian ``(n, 2, q)`` (q = 0, 3 or 6)."""
    if nuisance not in NUISANCES:
        raise ValueError(f"nuisance must be one of {NUISANCES}, got {nuisance!r}")
    if nuisance is None:
        return np.zeros((ctx.n, 2, 0))
    a = rotation_jacobian(ctx.camera, ctx.x, ctx.y)
    if nuisance == "attitude":
        return a
    frame = _frames(ctx)
    t = ctx.t_ns.astype(np.float64) / NS_PER_S
    _, inv = np.unique(frame, return_inverse=True)
    mean_t = np.bincount(inv, weights=t) / np.bincount(inv)
    tau = t - mean_t[inv]
    return np.concatenate([a, a * tau[:, None, None]], axis=-1)


def _frames(ctx: EffectContext) -> np.ndarray:
    return np.zeros(ctx.n, dtype=np.int64) if ctx.frame is None else np.asarray(ctx.frame)


def project_out(jac: np.ndarray, ctx: EffectContext, nuisance: str | None = "attitude") -> np.ndarray:
    """``J`` (n, 2, p) minus its per-frame least-squares fit by the nuisance columns.

    Vectorised over frames: per-frame normal matrices are accumulated with ``np.add.at`` and
    solved in one batched ``lstsq``-equivalent (pseudo-inverse, so frames with too few stars to
    determine the nuisance are handled: their signature is then fully absorbed where unresolved).
    """
    a = nuisance_columns(ctx, nuisance)
    if a.shape[-1] == 0 or ctx.n == 0:
        return jac
    _, inv = np.unique(_frames(ctx), return_inverse=True)
    coef = _frame_fit(a, jac, inv)  # (nf, q, p)
    return jac - np.einsum("nkq,nqp->nkp", a, coef[inv])


def absorbed_attitude(jac: np.ndarray, ctx: EffectContext) -> np.ndarray:
    """Per-frame least-squares body rotation (rad) fitted to ``jac`` (n, 2, p), per observation (n, 3, p)."""
    a = nuisance_columns(ctx, "attitude")
    if ctx.n == 0:
        return np.zeros((0, 3, jac.shape[-1]))
    _, inv = np.unique(_frames(ctx), return_inverse=True)
    coef = _frame_fit(a, jac, inv)
    return coef[inv]


def _frame_fit(a: np.ndarray, jac: np.ndarray, inv: np.ndarray) -> np.ndarray:
    """Per-frame least-squares coefficients (nf, q, p) of ``jac`` on the columns ``a``."""
    nf, q, p = inv.max() + 1, a.shape[-1], jac.shape[-1]
    ata = np.zeros((nf, q, q))
    atj = np.zeros((nf, q, p))
    np.add.at(ata, inv, np.einsum("nki,nkj->nij", a, a))
    np.add.at(atj, inv, np.einsum("nki,nkj->nij", a, jac))
    return np.linalg.pinv(ata, hermitian=True) @ atj


def projected_signature(effect: Effect, ctx: EffectContext, nuisance: str | None = "attitude") -> np.ndarray:
    """The effect's image Jacobian at the ideal positions with the nuisance projected out."""
    ctx.check([effect])
    return project_out(effect.jacobian(ctx.x, ctx.y, ctx), ctx, nuisance)


def signature_norm_px(effect: Effect, ctx: EffectContext, nuisance: str | None = "attitude") -> np.ndarray:
    """``|J_perp,j|`` over all observations (px per parameter unit), (n_params,)."""
    jp = projected_signature(effect, ctx, nuisance)
    return np.sqrt(np.sum(jp * jp, axis=(0, 1)))


def parameter_sigma(effect: Effect, ctx: EffectContext, sigma_px: float, nuisance: str | None = "attitude") -> np.ndarray:
    """Cramér–Rao sigma of each parameter alone (others fixed), in parameter units (inf if invisible)."""
    norm = signature_norm_px(effect, ctx, nuisance)
    with np.errstate(divide="ignore"):
        return np.where(norm > 0, sigma_px / np.where(norm > 0, norm, 1.0), np.inf)


def detection_limit(effect: Effect, ctx: EffectContext, sigma_px: float, n_sigma: float = 5.0,
                    nuisance: str | None = "attitude") -> dict[str, float]:
    """Parameter value (per parameter, in its unit) whose projected signature is ``n_sigma`` sigmas."""
    s = parameter_sigma(effect, ctx, sigma_px, nuisance)
    return {p.name: float(n_sigma * sj) for p, sj in zip(effect.parameters, s)}


def gyro_detection_limit(effect: Effect, t_ns, omega_rad_s, gyro_sigma_rad_s: float, n_sigma: float = 5.0) -> dict[str, float]:
    """Like :func:`detection_limit` for the gyro channel: samples (m, 3) with white noise per axis."""
    jac = effect.gyro_jacobian(t_ns, omega_rad_s)
    norm = np.sqrt(np.sum(jac * jac, axis=(0, 1)))
    with np.errstate(divide="ignore"):
        lim = np.where(norm > 0, n_sigma * gyro_sigma_rad_s / np.where(norm > 0, norm, 1.0), np.inf)
    return {p.name: float(v) for p, v in zip(effect.parameters, lim)}
