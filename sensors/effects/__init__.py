"""Sensor effects: small forward models on true image-plane positions, with analytic Jacobians.

``EFFECTS`` maps each effect's ``name`` to its class; :func:`build_effect` also accepts the
aliases an effect declares. See :mod:`sensors.effects.base` for the interface.
"""
from __future__ import annotations

from sensors.effects.base import Effect, EffectParameter
from sensors.effects.principal_point import PrincipalPointOffset
from sensors.effects.radial_distortion import RadialDistortion

EFFECTS: dict[str, type[Effect]] = {cls.name: cls for cls in (RadialDistortion, PrincipalPointOffset)}


class UnknownEffectError(ValueError):
    """Raised for an effect name nobody registered; the message lists the valid names."""


def _resolve(name: str) -> type[Effect]:
    if name in EFFECTS:
        return EFFECTS[name]
    for cls in EFFECTS.values():
        if name in cls.aliases:
            return cls
    listing = ", ".join(
        f"{n} (aliases: {', '.join(c.aliases)})" if c.aliases else n for n, c in sorted(EFFECTS.items())
    )
    raise UnknownEffectError(f"unknown effect {name!r}; valid effects: {listing}")


def build_effect(name: str, params: dict | None = None) -> Effect:
    """Instantiate the effect registered as ``name`` (or one of its aliases) with ``params``."""
    return _resolve(name)(**(params or {}))


__all__ = ["EFFECTS", "Effect", "EffectParameter", "PrincipalPointOffset", "RadialDistortion", "UnknownEffectError", "build_effect"]
