"""The effect interface: one physical sensor effect acting on true image-plane positions.

An effect is a small forward model ``(x, y, t) -> (x', y')`` on *true* pixel positions (pixel
``(x, y) = (column, row)``, centres at integers; see :mod:`sensors.conventions`) at times ``t_ns``,
with named, bounded parameters and an analytic Jacobian with respect to those parameters. The
simulator applies a chain of effects after the ideal pinhole projection; estimators that diagnose
recordings fit the parameters (hence ``prior_scale``, ``bounds`` and the Jacobian).

Each effect lives in its own module and sets the class attributes ``name``, ``parameters``,
``explanation`` (one paragraph a user can read) and optionally ``aliases``. Constructors only
validate and store parameter values.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np


@dataclass(frozen=True)
class EffectParameter:
    """One scalar parameter of an effect.

    ``default`` is the value meaning "effect absent" where that exists; ``prior_scale`` is a
    typical magnitude (1-sigma of a zero-mean prior) in ``unit``; ``bounds`` are hard limits
    ``(lo, hi)`` inclusive.
    """

    name: str
    unit: str
    default: float
    prior_scale: float
    bounds: tuple[float, float]
    description: str

    def __post_init__(self):
        lo, hi = self.bounds
        if not lo < hi:
            raise ValueError(f"parameter {self.name!r}: bounds must satisfy lo < hi, got {self.bounds}")
        if not lo <= self.default <= hi:
            raise ValueError(f"parameter {self.name!r}: default {self.default} outside bounds {self.bounds}")
        if not self.prior_scale > 0:
            raise ValueError(f"parameter {self.name!r}: prior_scale must be > 0, got {self.prior_scale}")


class Effect:
    """Base class of sensor effects. Subclasses implement :meth:`apply` and :meth:`jacobian`."""

    name: ClassVar[str] = ""
    parameters: ClassVar[tuple[EffectParameter, ...]] = ()
    explanation: ClassVar[str] = ""
    aliases: ClassVar[tuple[str, ...]] = ()

    def __init__(self, **values):
        valid = self.parameter_names()
        unknown = sorted(set(values) - set(valid))
        if unknown:
            raise ValueError(
                f"effect {self.name!r}: unknown parameter(s) {', '.join(map(repr, unknown))}; "
                f"valid parameters: {', '.join(valid) or '(none)'}"
            )
        stored: dict[str, float] = {}
        for p in self.parameters:
            v = values.get(p.name, p.default)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"effect {self.name!r}: parameter {p.name!r} must be a number, got {v!r}") from None
            lo, hi = p.bounds
            if not (math.isfinite(v) and lo <= v <= hi):
                raise ValueError(
                    f"effect {self.name!r}: parameter {p.name!r} = {v} [{p.unit}] outside bounds [{lo}, {hi}]"
                )
            stored[p.name] = v
        self._values = stored

    @classmethod
    def parameter_names(cls) -> tuple[str, ...]:
        """Names of the parameters, in the column order of :meth:`jacobian`."""
        return tuple(p.name for p in cls.parameters)

    @property
    def values(self) -> dict[str, float]:
        """Current parameter values by name (a copy)."""
        return dict(self._values)

    def apply(self, x, y, t_ns, camera) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - interface
        """Forward model: true image-plane positions (px) at times ``t_ns`` to affected positions."""
        raise NotImplementedError

    def jacobian(self, x, y, t_ns, camera) -> np.ndarray:  # pragma: no cover - interface
        """Analytic ``d(x', y') / d(params)`` at the given positions, shape ``(n, 2, n_params)``."""
        raise NotImplementedError

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self._values.items())
        return f"{type(self).__name__}({args})"

    def __eq__(self, other) -> bool:
        return type(self) is type(other) and self._values == other._values

    def __hash__(self) -> int:
        return hash((type(self), tuple(self._values.items())))


def as_positions(x, y) -> tuple[np.ndarray, np.ndarray]:
    """Broadcast ``x, y`` to float arrays of a common shape (helper for effect implementations)."""
    x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
    return x, y
