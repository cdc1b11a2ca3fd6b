"""Where a star lands on a rolling-shutter detector: projection at a star's own exposure time.

A star with ICRS direction ``u`` is seen in the camera frame as ``w(t) = R(t)^T u`` (``R`` the
camera-to-ICRS attitude), projected by the pinhole model (he2021b eq 2) and then displaced by the
chain of sensor effects: ``(X(t), Y(t)) = effects(project(w(t + dt)), t)`` where ``dt`` is the
total time shift of the chain's time-stage effects (rolling-shutter line-delay error, clock
offset, smear bias; :func:`rollingstar.sensors.effects.chain.time_shift_s`), evaluated on the *true* motion,
and the image-stage effects get an :class:`~rollingstar.sensors.effects.base.EffectContext` built from the
attitude, body rate and the per-star :class:`ObservationInfo` (magnitude, proper motion, frame,
covariates...).

With a rolling shutter, row ``r`` exposes over ``[t0 + r ld, t0 + r ld + T]`` (``ld`` line delay,
``T`` exposure), so the centroid row ``y`` of a star is the row whose mid-exposure sees the star
on that very row -- the implicit equation::

    y = Y(t0 + y ld + T / 2)                                              (1)

(with time effects, ``Y`` is evaluated at ``t0 + y ld + T/2 + dt(y)``, e.g. ``dt = y d_ld``).

Solved by fixed-point iteration ``y_{k+1} = Y(t0 + y_k ld + T / 2)``. The map is a contraction
with factor ``|dY/dt| ld = |v_y| ld`` (image velocity in px/s times line delay in s); for a star
tracker this is tiny (1 deg/s on the he2021a sensor: 76 px/s * 43.9 us = 3.3e-3), so each
iteration gains ~2.5 decimal digits and 4-5 iterations reach 1e-9 px from the frame-reference
guess (stopping when a step is below 1e-9 px leaves an error ~|v_y| ld * 1e-9). Newton's
method would need ``dY/dt`` for no practical gain. The iteration converges whenever
``|v_y| ld < 1`` (image slower than one row per line delay, ~300 deg/s here). A global shutter
has ``ld = 0`` and (1) is explicit. For stars far off the detector the row used for the time is
clipped to ``[-1, H]`` (such rows have no exposure time; the clip keeps the map a contraction, so
those stars converge too and are then discarded).

Times are integer ns; ``t0 + y ld + T/2`` is not, so the attitude at a fractional ns ``t + d``
(``0 <= d < 1`` ns) is ``R(t) Exp(omega(t) d)`` (body-frame rate, the kinematics convention of
:mod:`rollingstar.sensors.motion`); the neglected term ``alpha d^2 / 2`` is below 1e-18 rad.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.sensors.conventions import NS_PER_S
from rollingstar.sensors.effects.base import EffectContext
from rollingstar.sensors.effects.chain import (
    image_effects,
    ordered,
    time_effects,
    time_shift_s,
)
from rollingstar.sensors.effects.geometry import image_velocity

DEFAULT_TOL_PX = 1e-9  # stop when a step is below this; the remaining error is ~|v_y| ld times it
DEFAULT_MAX_ITER = 60


@dataclass(frozen=True, eq=False)
class ObservationInfo:
    """What the simulator knows about the stars of one frame beyond their directions.

    Per star (m,): ``magnitude``, ``flux_e`` (expected electrons), ``pm_rad_yr`` (m, 3); per frame:
    ``t0_ns``, ``frame``, ``timing``; per recording: ``zenith_icrs`` (3,) for ground-based
    scenarios, ``covariates`` (name -> function of int64 ns times giving values) and
    ``t_start_ns``. Turned into an :class:`EffectContext` by :meth:`context`.
    """

    magnitude: np.ndarray | None = None
    flux_e: np.ndarray | None = None
    pm_rad_yr: np.ndarray | None = None
    t0_ns: int | None = None
    frame: int | None = None
    timing: object = None
    zenith_icrs: np.ndarray | None = None
    covariates: Mapping[str, Callable[[np.ndarray], np.ndarray]] = field(default_factory=dict)
    t_start_ns: int = 0

    def context(self, camera, x, y, t_ns, index=None, rows=None, attitude=None, unit_icrs=None,
                omega_rad_s=None, covariates: bool = True, stamp_ns=None) -> EffectContext:
        """Context of observations ``index`` (into the per-star arrays) at ideal positions ``x, y``.

        Covariates are sampled at ``stamp_ns`` (default ``t_ns``): the stamped time of the
        observation, as a log provides them (``covariates`` False skips them when no effect needs them).
        """
        def take(a):
            return None if a is None else (a if index is None else a[index])

        n = np.asarray(x).reshape(-1).shape[0]
        vx = vy = None
        if omega_rad_s is not None:
            vx, vy = image_velocity(camera, x, y, omega_rad_s)
        return EffectContext(
            camera=camera, x=x, y=y, t_ns=t_ns, row=rows, t0_ns=self.t0_ns, frame=self.frame,
            magnitude=take(self.magnitude), flux_e=take(self.flux_e), vx=vx, vy=vy, omega_rad_s=omega_rad_s,
            attitude=attitude, unit_icrs=unit_icrs, pm_rad_yr=take(self.pm_rad_yr),
            zenith_icrs=None if self.zenith_icrs is None else np.broadcast_to(self.zenith_icrs, (n, 3)),
            covariates={k: f(np.asarray(t_ns if stamp_ns is None else stamp_ns, dtype=np.int64))
                        for k, f in self.covariates.items()} if covariates else {},
            timing=self.timing, t_start_ns=self.t_start_ns,
        )


def image_positions(camera, motion, effects: Sequence, unit_icrs, t_ns, frac_ns=None,
                    omega_rad_s=None, rows=None, info: ObservationInfo | None = None,
                    index=None) -> tuple[np.ndarray, np.ndarray]:
    """Affected image positions ``(x, y)`` of stars ``unit_icrs`` (m, 3) at times ``t_ns`` (m,).

    ``t_ns`` are integer ns; optional ``frac_ns`` (m,) in ``[0, 1)`` adds a sub-ns offset using
    the body rate ``omega_rad_s`` (m, 3) (default: ``motion.angular_velocity(t_ns)``; a rate from
    a nearby time is as good: its change times 1 ns is negligible). Stars behind the camera give NaN.

    With effects: ``rows`` (m,) are the detector rows whose exposure times each observation
    (row-dependent time effects such as ``rolling_shutter`` use them; 0 when not given);
    ``info`` / ``index`` give the per-star context (:class:`ObservationInfo`; ``index`` into its
    per-star arrays, default all of them in order).
    """
    t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
    u = np.asarray(unit_icrs, dtype=float).reshape(-1, 3)
    if not u.flags.writeable:  # scipy's Rotation.apply rejects read-only buffers (catalogue arrays)
        u = u.copy()
    if t.size == 0:
        return np.zeros(0), np.zeros(0)
    effects = ordered(effects)
    frac = None if frac_ns is None else np.asarray(frac_ns, dtype=float).reshape(-1)
    info = info if info is not None else ObservationInfo()
    stamp = t  # the nominal instant: covariates are sampled here, as a log would have them
    timers = time_effects(effects)
    if timers:
        r = np.zeros(t.size) if rows is None else np.broadcast_to(np.asarray(rows, dtype=float).reshape(-1), t.shape)
        pre = info.context(camera, np.zeros(t.size), r, t, index, rows=r, covariates=False)
        shift = time_shift_s(timers, pre) * NS_PER_S + (0.0 if frac is None else frac)
        whole = np.floor(shift)
        t = t + whole.astype(np.int64)
        frac = shift - whole
        omega_rad_s = None  # the rate at the shifted time is evaluated below
    rot = motion.attitude(t)
    if frac is not None and np.any(frac != 0.0):
        omega = motion.angular_velocity(t) if omega_rad_s is None else np.asarray(omega_rad_s, dtype=float)
        rot = rot * Rotation.from_rotvec(omega * (frac / NS_PER_S)[:, None])
    w = rot.inv().apply(u)
    x, y, _ = camera.project(w)
    mapped = image_effects(effects)
    if mapped:
        needs = {n for e in mapped for n in e.needs}
        rate = motion.angular_velocity(t) if needs & {"omega_rad_s", "vx", "vy"} else None  # only when used
        ctx = info.context(camera, x, y, t, index, rows=rows, attitude=rot, unit_icrs=u, omega_rad_s=rate,
                           covariates=any(n.startswith("covariate:") for n in needs), stamp_ns=stamp)
        ctx.check(mapped)
        for effect in mapped:
            x, y = effect.apply(x, y, ctx)
    return np.asarray(x, dtype=float), np.asarray(y, dtype=float)


def solve_star_rows(camera, timing, motion, effects: Sequence, unit_icrs, t0_ns: int,
                    tol_px: float = DEFAULT_TOL_PX, max_iter: int = DEFAULT_MAX_ITER,
                    info: ObservationInfo | None = None):
    """Solve equation (1) for every star, vectorised; returns ``(x, y, iterations)``.

    ``x`` is evaluated at the same (continuous) time as ``y``. Stars behind the camera are NaN.
    Raises RuntimeError when the iteration does not converge (``|v_y| * line_delay >= 1``).
    """
    u = np.asarray(unit_icrs, dtype=float).reshape(-1, 3)
    n = u.shape[0]
    if n == 0:
        return np.zeros(0), np.zeros(0), 0
    ld = float(timing.effective_line_delay_ns)
    exposure = int(timing.exposure_ns)
    base = np.int64(t0_ns) + np.int64(exposure // 2)
    row_lo, row_hi = -1.0, float(camera.height)
    half_rem = exposure / 2.0 - exposure // 2  # 0 or 0.5 ns
    kw = dict(info=info)
    # initial guess: positions at the frame's reference time (mid-exposure of the middle row)
    t_ref = np.full(n, timing.frame_reference_ns(t0_ns), dtype=np.int64)
    if ld == 0.0 and not time_effects(effects):
        t_int = np.full(n, base, dtype=np.int64)
        x, y = image_positions(camera, motion, effects, u, t_int, np.full(n, half_rem), **kw)
        return x, y, 1
    x, y = image_positions(camera, motion, effects, u, t_ref, rows=np.full(n, (camera.height - 1) / 2.0), **kw)
    omega = np.broadcast_to(motion.angular_velocity(t_ref[:1]), (n, 3))  # for the sub-ns step only
    for it in range(1, max_iter + 1):
        # rows beyond the detector have no exposure time: clip (1-Lipschitz, so still a contraction)
        row = np.clip(np.where(np.isfinite(y), y, 0.0), row_lo, row_hi)
        offset = row * ld + half_rem
        whole = np.floor(offset)
        t_int = base + whole.astype(np.int64)
        x_new, y_new = image_positions(camera, motion, effects, u, t_int, offset - whole, omega, rows=row, **kw)
        delta = np.abs(y_new - y)
        x, y = x_new, y_new
        finite = np.isfinite(delta)
        if not np.any(finite) or np.max(delta[finite]) <= tol_px:
            return x, y, it
    raise RuntimeError(
        f"rolling-shutter row equation did not converge in {max_iter} iterations "
        f"(max step {np.nanmax(delta):.3g} px): image velocity * line delay must be << 1 row"
    )
