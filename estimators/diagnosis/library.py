"""The candidate effects a diagnosis searches: adapters over :mod:`rollingstar.sensors.effects`.

A :class:`Candidate` wraps one registered effect class and gives the diagnosis what it needs: the
linearised image-plane signature ``d(x', y')/d(theta)`` at the "effect absent" values
(``EffectParameter.default``) evaluated inside the scenario's effect chain
(:func:`rollingstar.sensors.effects.chain.chain_jacobian`), instances at any ``theta`` for the nonlinear
forward model, the physics text, the declared aliases with their separating experiments, and the
scenario entry that switches it on.

Whether a candidate can be tested on a recording: it needs an image-plane channel (gyro-only
effects and effects visible only against an external attitude reference cannot be seen in
centroids) and every context field it ``needs`` (e.g. proper motions, the local zenith, a logged
covariate) must be available.
"""
from __future__ import annotations

import numpy as np

from rollingstar.estimators.diagnosis.observations import by_exposure
from rollingstar.sensors.effects import EFFECTS
from rollingstar.sensors.effects.chain import chain_jacobian


class Candidate:
    """One library effect as a diagnosis candidate."""

    def __init__(self, effect_cls):
        self.cls = effect_cls
        self.name: str = effect_cls.name
        self.parameters = tuple(effect_cls.parameters)
        self.explanation: str = getattr(effect_cls, "explanation", "")
        self.follows: str = getattr(effect_cls, "follows", "")
        self.shown_by: str = getattr(effect_cls, "shown_by", "")
        self.aliases = tuple(getattr(effect_cls, "aliases", ()))
        self.channels = frozenset(getattr(effect_cls, "channels", frozenset({"image"})))
        self.needs = tuple(getattr(effect_cls(), "needs", ()))  # may be a property of the instance
        self.defaults = np.array([p.default for p in self.parameters], dtype=float)
        self.scales = np.array([p.prior_scale for p in self.parameters], dtype=float)
        self.lower = np.array([p.bounds[0] for p in self.parameters], dtype=float)
        self.upper = np.array([p.bounds[1] for p in self.parameters], dtype=float)

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    @property
    def units(self) -> tuple[str, ...]:
        return tuple(p.unit for p in self.parameters)

    def instance(self, theta=None):
        theta = self.defaults if theta is None else np.clip(np.asarray(theta, dtype=float), self.lower, self.upper)
        return self.cls(**dict(zip(self.param_names, map(float, theta))))

    def testable(self, ctx, gyro: bool = False) -> str | None:
        """None when the recording can show this effect, else the reason it cannot (``gyro``: the
        recording has the gyro/attitude-increment channel, :mod:`rollingstar.estimators.diagnosis.gyro_channel`)."""
        if "image" not in self.channels and "time" not in self.channels and not (gyro and "gyro" in self.channels):
            return f"no image-plane signature (channels: {', '.join(sorted(self.channels))})"
        missing = [k for k in self.needs if (k.startswith("covariate:") and k.split(":", 1)[1] not in ctx.covariates)
                   or (not k.startswith("covariate:") and getattr(ctx, k, None) is None)]
        if missing:
            return f"the recording does not provide {', '.join(missing)}"
        return None

    def signature(self, ctx, base_effects=(), exposure_ns=None) -> np.ndarray:
        """``d(x', y')/d(theta)`` at the absent values inside the base chain, (n, 2, m), px per unit.

        ``exposure_ns`` (per observation) evaluates a recording that mixes exposure times group by
        group (:func:`rollingstar.estimators.diagnosis.observations.by_exposure`)."""
        eff = self.instance()
        chain = tuple(base_effects) + (eff,)

        def one(c):
            jac, labels = chain_jacobian(chain, c)
            cols = [i for i, (name, _) in enumerate(labels) if name == self.name]
            return jac[:, :, cols[-len(self.parameters):]]

        return by_exposure(ctx, exposure_ns, one)

    def alias_of(self, other: str):
        for a in self.aliases:
            if getattr(a, "other", None) == other:
                return a
        return None

    def scenario_entry(self, theta) -> dict:
        return {"kind": self.name, "params": {k: float(v) for k, v in zip(self.param_names, theta)}}


def library(exclude=()) -> dict[str, Candidate]:
    """Every registered physical effect as a candidate (by name), minus ``exclude`` (empirical
    shapes are never candidates: :mod:`rollingstar.sensors.effects.empirical`)."""
    return {name: Candidate(cls) for name, cls in sorted(EFFECTS.items())
            if name not in set(exclude) and not cls.empirical}


def separating_experiment(a: Candidate, b) -> str:
    """What would tell ``a`` from ``b`` (a Candidate or "attitude"/"rate"): the declared alias, else a rule."""
    bname = b if isinstance(b, str) else b.name
    alias = a.alias_of(bname)
    if alias is None and not isinstance(b, str):
        alias = b.alias_of(a.name)
    if alias is not None and getattr(alias, "separating_experiment", ""):
        return alias.separating_experiment
    if bname in ("attitude", "rate"):
        return "an external attitude and rate reference (gyro, second tracker or surveyed mount) logged with the frames"
    if a.follows and b.follows:  # from the two signatures: what each follows, and what would show it
        ways = a.shown_by if a.shown_by == b.shown_by else f"{a.shown_by}, or {b.shown_by}"
        return f"{a.name} follows {a.follows}, {bname} follows {b.follows}: {ways}"
    return (f"a measurement design in which {a.name} and {bname} move stars differently: vary the motion "
            "(rate reversal, another rotation axis, an inertial hold), the exposure time, and cover the whole "
            "field, centre to corners, with many stars")
