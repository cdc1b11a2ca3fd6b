"""The effect interface: one named physical effect, its forward model and its signatures.

An *effect* is a small, parameterised piece of physics that a nominal star-tracker model may leave
out. The simulator switches effects on to generate recordings; ``rollingstar diagnose`` screens the
library for the effect(s) that explain a mismatch between a simulation and a recording. Both use
the same objects, so everything below is the contract between them.

Observation context
-------------------
Effects act on *observations*: one star seen in one frame. :class:`EffectContext` carries, per
observation (arrays of length ``n``), everything an effect may need:

============== ========= ===========================================================================
field          shape     meaning
============== ========= ===========================================================================
camera         --        :class:`~rollingstar.sensors.camera.PinholeCamera` (nominal model)
x, y           (n,)      *ideal* pinhole position (px) of the star at ``t_ns`` (no effect applied)
t_ns           (n,) i8   time the observation refers to: mid-exposure of its row (nominal timing)
row            (n,)      detector row whose exposure times the observation (default ``y``)
t0_ns          (n,) i8   frame timestamp (start of exposure of row 0)
frame          (n,) i8   frame index
magnitude      (n,)      catalogue magnitude (Hp)
flux_e         (n,)      expected star signal (electrons)
vx, vy         (n,)      image velocity of the ideal position (px/s)
omega_rad_s    (n, 3)    body (camera-frame) angular rate at ``t_ns`` (rad/s)
attitude       Rotation  camera->ICRS attitude at ``t_ns`` (scipy, n rotations)
unit_icrs      (n, 3)    catalogue ICRS direction the ideal position was projected from
pm_rad_yr      (n, 3)    catalogue proper motion as an ICRS tangent vector (rad/yr)
zenith_icrs    (n, 3)    local zenith (ground-based observations only)
covariates     dict      logged covariates, name -> (n,) array (e.g. ``temperature_c``)
timing         --        :class:`~rollingstar.sensors.timing.DetectorTiming` (nominal) or None
t_start_ns     int       start of the recording (reference of time-linear drifts)
============== ========= ===========================================================================

Only ``camera, x, y, t_ns`` are mandatory; the others default to None (``covariates`` to ``{}``)
and an effect that needs a missing field raises :class:`MissingContextError` naming the field
(``Effect.needs`` lists them up front; :meth:`EffectContext.check` validates a context for a chain).

Effect interface (class attributes)
-----------------------------------
- ``name`` (registry key used in scenarios: ``effects: [{kind: <name>, params: {...}}]``),
  ``synonyms`` (other accepted spellings of the name);
- ``parameters``: :class:`EffectParameter` (name, unit, default = "effect absent", prior_scale,
  bounds, description). Column order of every Jacobian;
- ``stage``: where the effect sits in the forward chain (:data:`STAGE_TIME` < :data:`STAGE_SKY`
  < :data:`STAGE_OPTICS` < :data:`STAGE_DETECTOR` < :data:`STAGE_GYRO`); chains are applied in
  stage order, stably (:func:`rollingstar.sensors.effects.chain.ordered`);
- ``channels``: which measurement channels carry a signature: ``"image"`` (centroid positions),
  ``"time"`` (the effect shifts the instant a star is seen: :meth:`Effect.time_shift_s`),
  ``"gyro"`` (gyro samples: :meth:`Effect.apply_gyro`), ``"attitude"`` (visible only against an
  external attitude/rate reference after the per-frame attitude is refitted);
- ``needs``: context fields required beyond ``camera, x, y, t_ns``;
- ``image_level``: whether the image-level simulator can render it (False for biases that are
  properties of a centroid *estimator*, which an image simulation produces by itself);
- ``explanation``: one paragraph a user can read;
- ``empirical``: True for measured shapes written by a diagnosis (:mod:`.empirical`), which
  a diagnosis never offers as candidates;
- ``follows`` and ``shown_by``: what the displacement follows (``"r^3 from the principal point,
  radially"``) and the measurement that shows that dependence best (``"stars out to the detector
  corners"``); a diagnosis that cannot tell two effects apart without a declared alias builds its
  separating experiment from these;
- ``aliases``: :class:`Alias` entries: another effect (or ``"attitude"`` / ``"rate"``) whose
  signature is nearly collinear with this one, why, and the ``separating_experiment`` that tells
  them apart.

Effect interface (methods), all vectorised over the ``n`` observations
-----------------------------------------------------------------------
- ``apply(x, y, ctx) -> (x', y')``: the forward model on image positions. ``x, y`` are the chain's
  current positions (ideal positions for the first effect). Time-stage effects implement it as
  the rotation of the line of sight by ``Exp(-omega dt)`` with ``omega = ctx.omega_rad_s`` (exact for
  a constant rate); the simulator instead evaluates the true motion at the shifted time (exact
  for any motion) and skips their ``apply``. Effects after the time stage see the context of the
  instant the star is really seen (:func:`rollingstar.sensors.effects.chain.shifted_context`: ``t_ns`` and
  ``attitude`` shifted; covariates stay those sampled at the stamped time, as a log has them).
  Gyro-stage effects are the identity here. ``apply`` never writes ``x``, ``y`` or the context's
  arrays in place: callers keep the positions entering each effect
  (:func:`rollingstar.sensors.effects.chain.entering`) and contexts share arrays.
- ``jacobian(x, y, ctx) -> (n, 2, n_params)``: analytic ``d(x', y') / d(params)`` of ``apply`` at
  the same inputs (the image-plane signature, in px per parameter unit). Zero for gyro effects.
- ``time_shift_s(ctx) -> (n,)``: timing hook: seconds added to the instant the star is seen.
- ``apply_gyro(t_ns, omega_rad_s) -> omega'`` and ``gyro_jacobian(t_ns, omega_rad_s) -> (m, 3, p)``:
  gyro hook (body-frame rad/s samples).
- ``attitude_jacobian(ctx) -> (n, 3, n_params)``: the apparent body-frame attitude change (rad)
  per parameter unit that a per-frame attitude fit absorbs (the per-frame least-squares rotation
  fitted to the image signature; for effects whose image signature is collinear with attitude).
- ``signature_rms_px(ctx) -> (n_params,)``: RMS over observations of ``|d(x', y')/d p_j|`` (px per
  unit), the raw scale of each parameter's signature (see :mod:`rollingstar.sensors.effects.design` for
  detection limits with the per-frame attitude projected out).

Constructors only validate and store parameter values (unknown name / out of bounds / not a
number -> ``ValueError`` naming the effect and parameter). Effects are immutable values
(``==`` compares type and values); :meth:`Effect.with_values` returns a modified copy,
:meth:`Effect.from_vector` / :attr:`Effect.vector` convert to and from parameter vectors,
:attr:`Effect.is_identity` is True at the defaults.

Where the rest lives
--------------------
- :func:`rollingstar.sensors.effects.build_effect` / ``EFFECTS`` / ``resolve``: the registry (one module per effect);
- :func:`rollingstar.sensors.effects.context.context_from_attitude`: a context from an attitude (per
  observation), catalogue directions, times and the body rate (fills ideal ``x, y`` and ``vx, vy``);
- :func:`rollingstar.sensors.effects.chain.predict` (forward model of a chain on a context),
  :func:`~rollingstar.sensors.effects.chain.chain_jacobian` (stacked ``(n, 2, sum p)`` Jacobian and labels),
  :func:`~rollingstar.sensors.effects.chain.apply_gyro`, :func:`~rollingstar.sensors.effects.chain.ordered`;
- :mod:`rollingstar.sensors.effects.design`: nuisance (per-frame attitude, optionally rate) projection,
  Cramér–Rao parameter sigmas and :func:`~rollingstar.sensors.effects.design.detection_limit`;
- :mod:`rollingstar.sensors.effects.doc`: ``docs/effects.md``, generated;
- simulator side: :class:`rollingstar.sensors.centroid_sim.ObservationInfo` and
  :class:`rollingstar.sensors.simulate.StarTrackerSimulator` (time effects on the true motion, gyro hook via
  ``StarTrackerSimulator.apply_gyro``); scenarios: ``effects:`` and ``environment:``
  (``elevation_deg`` for refraction, ``covariates`` e.g. ``temperature_c``) in
  :class:`rollingstar.pipelines.config.ScenarioConfig`.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar

import numpy as np

from rollingstar.sensors.effects.design import absorbed_attitude

STAGE_TIME = 0  # shifts the instant a star is seen (rolling_shutter, time_offset, exposure_smear)
STAGE_SKY = 1  # changes the line of sight in the camera frame (aberration, refraction, roll, ...)
STAGE_OPTICS = 2  # lens/focal-plane mapping (focal length, distortion, principal point)
STAGE_DETECTOR = 3  # centroid-level biases (pixel phase, magnitude)
STAGE_GYRO = 4  # gyro channel only

CHANNELS = frozenset({"image", "time", "gyro", "attitude"})
NUISANCE = ("attitude", "rate")  # pseudo-effect names usable in Alias.other


class MissingContextError(ValueError):
    """An effect needs a context field that was not provided."""


@dataclass(frozen=True)
class EffectParameter:
    """One scalar parameter of an effect.

    ``default`` is the value meaning "effect absent" (every effect is the identity at its
    defaults); ``prior_scale`` is a typical magnitude (1-sigma of a zero-mean prior) in ``unit``;
    ``bounds`` are hard limits ``(lo, hi)`` inclusive.
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


@dataclass(frozen=True)
class Alias:
    """A known near-collinearity: ``other`` (an effect name, or ``"attitude"`` / ``"rate"``).

    ``reason`` says why the signatures look alike; ``separating_experiment`` is the measurement
    design (motion, exposure, field coverage, external reference) that separates them.
    """

    other: str
    reason: str
    separating_experiment: str


def _arr(v, dtype=float):
    return None if v is None else np.asarray(v, dtype=dtype)


@dataclass(frozen=True, eq=False)
class EffectContext:
    """Per-observation context of an effect chain (see the module docstring for every field)."""

    camera: Any
    x: np.ndarray
    y: np.ndarray
    t_ns: np.ndarray
    row: np.ndarray | None = None
    t0_ns: np.ndarray | None = None
    frame: np.ndarray | None = None
    magnitude: np.ndarray | None = None
    flux_e: np.ndarray | None = None
    vx: np.ndarray | None = None
    vy: np.ndarray | None = None
    omega_rad_s: np.ndarray | None = None
    attitude: Any = None  # scipy Rotation with n rotations
    unit_icrs: np.ndarray | None = None
    pm_rad_yr: np.ndarray | None = None
    zenith_icrs: np.ndarray | None = None
    covariates: Mapping[str, np.ndarray] = field(default_factory=dict)
    timing: Any = None
    t_start_ns: int = 0

    _VECTORS: ClassVar[tuple[str, ...]] = ("omega_rad_s", "unit_icrs", "pm_rad_yr", "zenith_icrs")
    _INTS: ClassVar[tuple[str, ...]] = ("t0_ns", "frame")
    _SCALARS: ClassVar[tuple[str, ...]] = ("row", "magnitude", "flux_e", "vx", "vy")

    def __post_init__(self):
        x, y = (np.array(a) for a in np.broadcast_arrays(np.asarray(self.x, dtype=float).reshape(-1),
                                                        np.asarray(self.y, dtype=float).reshape(-1)))
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "y", y)
        self._normalise(("t_ns", *self._INTS, *self._SCALARS, *self._VECTORS, "attitude", "covariates"))

    def _normalise(self, names) -> None:
        """Broadcast the fields ``names`` to this context's ``n`` observations (copies; a frozen
        dataclass, so set in place once) and check the attitude's length."""
        n = self.x.shape[0]
        for k in names:
            v = getattr(self, k)
            if v is None:
                continue
            if k in ("t_ns", *self._INTS):
                v = _broadcast_copy(v, np.int64, (n,))
            elif k in self._SCALARS:
                v = _broadcast_copy(v, float, (n,))
            elif k in self._VECTORS:
                v = _broadcast_copy(v, float, (n, 3))
            elif k == "covariates":
                v = {str(name): _broadcast_copy(c, float, (n,)) for name, c in dict(v).items()}
            elif k == "attitude":
                if not v.single and len(v) not in (n,):
                    raise ValueError(f"EffectContext.attitude: expected {n} rotations, got {len(v)}")
                continue
            else:
                continue
            object.__setattr__(self, k, v)

    @property
    def n(self) -> int:
        return int(self.x.shape[0])

    def __len__(self) -> int:
        return self.n

    @property
    def rows(self) -> np.ndarray:
        """The row timing each observation (``row`` if given, else ``y``)."""
        return self.y if self.row is None else self.row

    def require(self, names, who: str = "effect") -> None:
        """Raise :class:`MissingContextError` naming every field of ``names`` that is None.

        ``"timing"`` also requires ``t0_ns``; ``"covariate:<name>"`` requires that covariate.
        """
        missing = []
        for k in names:
            if k.startswith("covariate:"):
                if k.split(":", 1)[1] not in self.covariates:
                    missing.append(k)
            elif getattr(self, k) is None:
                missing.append(k)
        if missing:
            raise MissingContextError(f"{who} needs context field(s) {', '.join(missing)}, which were not provided")

    def check(self, effects) -> None:
        """Validate that this context carries every field the ``effects`` need."""
        for e in effects:
            self.require(e.needs, f"effect {e.name!r}")

    def take(self, index) -> "EffectContext":
        """The observations selected by an integer index array or boolean mask."""
        idx = np.asarray(index)
        kw = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("camera", "timing", "t_start_ns") or v is None:
                kw[f.name] = v
            elif f.name == "covariates":
                kw[f.name] = {k: c[idx] for k, c in v.items()}
            elif f.name == "attitude":
                kw[f.name] = v[idx] if not v.single else v
            else:
                kw[f.name] = np.asarray(v)[idx]
        if idx.ndim != 1:  # a scalar index: every field is broadcast to one observation again
            return EffectContext(**kw)
        # this context's fields are checked and broadcast already, and indexing by an array copies:
        # the selection needs neither again (the effect chain and the diagnosis take thousands a run)
        out = self._copy()
        for k, v in kw.items():
            object.__setattr__(out, k, v)
        return out

    def _copy(self) -> "EffectContext":
        """A shallow copy: what ``copy.copy`` makes of this dataclass (a new instance with the same
        field values), without the generic copy protocol's per-call cost."""
        out = object.__new__(type(self))
        out.__dict__.update(self.__dict__)
        return out

    def evolve(self, **changes) -> "EffectContext":
        """A copy with ``changes`` (e.g. new ideal positions ``x=..., y=...``). Only the changed
        fields are broadcast again while the number of observations stays (the effect chain and the
        diagnosis evolve contexts thousands of times per recording), so the copy shares its other
        arrays with this context: a context's arrays are never written in place, here or by its
        users. Positions of another length broadcast every field again."""
        unknown = set(changes) - set(self.__dataclass_fields__)
        if unknown:
            raise TypeError(f"EffectContext has no field(s) {', '.join(sorted(unknown))}")
        out = self._copy()
        if "x" in changes or "y" in changes:
            x, y = (np.array(changes.pop(k, getattr(self, k)), dtype=float).reshape(-1) for k in ("x", "y"))
            if not x.shape == y.shape == self.x.shape:
                return replace(self, x=x, y=y, **changes)
            object.__setattr__(out, "x", x)
            object.__setattr__(out, "y", y)
        for k, v in changes.items():
            object.__setattr__(out, k, v)
        out._normalise(tuple(changes))
        return out

    def unit_camera(self) -> np.ndarray:
        """Unit camera-frame line of sight of the ideal positions, (n, 3) (he2021b eq 2)."""
        return self.camera.unproject(self.x, self.y)


class Effect:
    """Base class of effects (see the module docstring for the full contract)."""

    name: ClassVar[str] = ""
    synonyms: ClassVar[tuple[str, ...]] = ()
    parameters: ClassVar[tuple[EffectParameter, ...]] = ()
    explanation: ClassVar[str] = ""
    follows: ClassVar[str] = ""  # what the displacement follows, e.g. "r^3 from the principal point"
    shown_by: ClassVar[str] = ""  # the measurement that shows that dependence best
    aliases: ClassVar[tuple[Alias, ...]] = ()
    stage: ClassVar[int] = STAGE_OPTICS
    channels: ClassVar[frozenset[str]] = frozenset({"image"})
    needs: ClassVar[tuple[str, ...]] = ()
    image_level: ClassVar[bool] = True
    empirical: ClassVar[bool] = False  # a measured shape (:mod:`.empirical`), never a diagnosis candidate

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

    # ------------------------------------------------------------ parameters
    @classmethod
    def parameter_names(cls) -> tuple[str, ...]:
        """Names of the parameters, in the column order of every Jacobian."""
        return tuple(p.name for p in cls.parameters)

    @classmethod
    def parameter(cls, name: str) -> EffectParameter:
        for p in cls.parameters:
            if p.name == name:
                return p
        raise KeyError(f"effect {cls.name!r} has no parameter {name!r}; valid: {', '.join(cls.parameter_names())}")

    @property
    def values(self) -> dict[str, float]:
        """Current parameter values by name (a copy)."""
        return dict(self._values)

    @property
    def vector(self) -> np.ndarray:
        """Parameter values in :meth:`parameter_names` order."""
        return np.array([self._values[p.name] for p in self.parameters], dtype=float)

    def with_values(self, **values) -> "Effect":
        """A copy with some parameters changed (validated like the constructor)."""
        return type(self)(**{**self._values, **values})

    @classmethod
    def from_vector(cls, vector) -> "Effect":
        """An instance from values in :meth:`parameter_names` order."""
        v = np.asarray(vector, dtype=float).reshape(-1)
        if v.size != len(cls.parameters):
            raise ValueError(f"effect {cls.name!r}: expected {len(cls.parameters)} values, got {v.size}")
        return cls(**dict(zip(cls.parameter_names(), v.tolist())))

    @property
    def is_identity(self) -> bool:
        """True when every parameter is at its default (effect absent)."""
        return all(self._values[p.name] == p.default for p in self.parameters)

    @classmethod
    def alias_names(cls) -> tuple[str, ...]:
        return tuple(a.other for a in cls.aliases)

    # --------------------------------------------------------- forward model
    def apply(self, x, y, ctx: EffectContext) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - interface
        """Forward model on image positions (px); see the module docstring."""
        raise NotImplementedError

    def jacobian(self, x, y, ctx: EffectContext) -> np.ndarray:  # pragma: no cover - interface
        """Analytic ``d(x', y') / d(params)`` of :meth:`apply`, shape ``(n, 2, n_params)``."""
        raise NotImplementedError

    # ----------------------------------------------------------------- hooks
    def time_shift_s(self, ctx: EffectContext) -> np.ndarray:
        """Seconds added to the instant each observation is seen (timing channel); default 0."""
        return np.zeros(ctx.n)

    def time_shift_jacobian(self, ctx: EffectContext) -> np.ndarray:
        """``d time_shift_s / d(params)``, shape ``(n, n_params)``; default zeros."""
        return np.zeros((ctx.n, len(self.parameters)))

    def apply_gyro(self, t_ns, omega_rad_s) -> np.ndarray:
        """Gyro hook: measured body rates (m, 3) rad/s -> affected rates; default identity."""
        return np.asarray(omega_rad_s, dtype=float)

    def gyro_jacobian(self, t_ns, omega_rad_s) -> np.ndarray:
        """``d(apply_gyro) / d(params)``, shape ``(m, 3, n_params)``; default zeros."""
        m = np.asarray(omega_rad_s, dtype=float).reshape(-1, 3).shape[0]
        return np.zeros((m, 3, len(self.parameters)))

    def attitude_jacobian(self, ctx: EffectContext) -> np.ndarray:
        """Apparent body-frame attitude change (rad) per parameter unit, ``(n, 3, n_params)``.

        What a per-frame attitude fit absorbs of the image signature: the per-frame
        least-squares rotation fitted to :meth:`jacobian` (:func:`rollingstar.sensors.effects.design.absorbed_attitude`),
        repeated for every observation of the frame. Diagnosis compares it with a gyro or truth
        reference for effects whose image signature is (nearly) a rigid rotation.
        """
        return absorbed_attitude(self.jacobian(ctx.x, ctx.y, ctx), ctx)

    def signature_rms_px(self, ctx: EffectContext) -> np.ndarray:
        """RMS over the observations of ``|d(x', y') / d p_j|`` (px per parameter unit), (n_params,).

        Evaluated at the ideal positions of ``ctx`` (the raw signature, before any nuisance is
        projected out; see :func:`rollingstar.sensors.effects.design.detection_limit` for the projected one).
        """
        jac = self.jacobian(ctx.x, ctx.y, ctx)
        return np.sqrt(np.mean(np.sum(jac * jac, axis=1), axis=0)) if ctx.n else np.zeros(len(self.parameters))

    # ------------------------------------------------------------- plumbing
    def _require(self, ctx: EffectContext) -> None:
        ctx.require(self.needs, f"effect {self.name!r}")

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self._values.items())
        return f"{type(self).__name__}({args})"

    def __eq__(self, other) -> bool:
        return type(self) is type(other) and self._values == other._values

    def __hash__(self) -> int:
        return hash((type(self), tuple(self._values.items())))


def _broadcast_copy(value, dtype, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as a new array of ``dtype`` and ``shape`` (flattened to ``shape``'s last axis first,
    then broadcast): a copy, so that a context never shares an array its caller may change."""
    a = np.asarray(value, dtype=dtype)
    if a.shape == shape:
        return a.copy()
    return np.array(np.broadcast_to(a.reshape((-1,) + shape[1:]), shape))


def as_positions(x, y) -> tuple[np.ndarray, np.ndarray]:
    """Broadcast ``x, y`` to 1-D float arrays of a common length (helper for effect implementations)."""
    x, y = np.asarray(x, dtype=float).reshape(-1), np.asarray(y, dtype=float).reshape(-1)
    if x.shape == y.shape:  # the usual case, without broadcast_arrays' per-call cost
        return x, y
    x, y = np.broadcast_arrays(x, y)
    return x, y


def stack_jacobian(*columns) -> np.ndarray:
    """Stack per-parameter ``(n, 2)`` columns into an ``(n, 2, p)`` Jacobian."""
    return np.stack(columns, axis=-1)
