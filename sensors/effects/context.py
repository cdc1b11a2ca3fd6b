"""Build an :class:`~rollingstar.sensors.effects.base.EffectContext` from an attitude and catalogue directions.

This is how the simulator, the evaluation and the diagnosis all obtain *ideal* positions: the
pinhole projection (he2021b eq 2) of ``w = R^T u`` with ``R`` the camera->ICRS attitude at each
observation's time, plus the image velocity ``P(w) (w x omega)`` when the body rate is known
(:func:`rollingstar.sensors.effects.geometry.image_velocity`).
"""
from __future__ import annotations

import numpy as np

from rollingstar.sensors.effects.base import EffectContext
from rollingstar.sensors.effects.geometry import image_velocity, to_camera


def context_from_attitude(camera, attitude, unit_icrs, t_ns, omega_rad_s=None, **fields) -> EffectContext:
    """Context of stars ``unit_icrs`` (n, 3) seen at ``t_ns`` (n,) with ``attitude`` (n rotations).

    ``omega_rad_s`` (n, 3) (body rate) also fills ``vx, vy``; any other
    :class:`EffectContext` field can be passed in ``fields`` (``row``, ``t0_ns``, ``frame``,
    ``magnitude``, ``flux_e``, ``pm_rad_yr``, ``zenith_icrs``, ``covariates``, ``timing``...).
    """
    u = np.array(unit_icrs, dtype=float).reshape(-1, 3)
    w = to_camera(attitude, u)
    x, y, _ = camera.project(w)
    if omega_rad_s is not None:
        omega = np.broadcast_to(np.asarray(omega_rad_s, dtype=float).reshape(-1, 3), (u.shape[0], 3))
        fields.setdefault("vx", None)
        fields.setdefault("vy", None)
        if fields["vx"] is None or fields["vy"] is None:
            fields["vx"], fields["vy"] = image_velocity(camera, x, y, omega)
        fields["omega_rad_s"] = omega
    return EffectContext(camera=camera, x=x, y=y, t_ns=t_ns, attitude=attitude, unit_icrs=u, **fields)
