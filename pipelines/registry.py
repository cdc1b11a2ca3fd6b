"""Plugin registry: the built-in plugins plus those registered by other packages.

Third-party packages register a plugin class under the entry-point group ``rollingstar.plugins``::

    [project.entry-points."rollingstar.plugins"]
    my-centroider = "mypkg.centroid:MyCentroider"

The entry-point name is the plugin ``kind`` used in pipeline configs; the class must subclass a
role base class from ``estimators`` and is validated exactly like a built-in.

:data:`ALIASES` are further kind names, each standing for a built-in kind with some of its
parameters set (:func:`stage_params`); a config may use either name.
"""
from __future__ import annotations

import importlib
from functools import lru_cache
from importlib.metadata import entry_points

from rollingstar.estimators.plugin import Plugin

ENTRY_POINT_GROUP = "rollingstar.plugins"
ROLES = ("centroider", "identifier", "filter", "correction", "attitude", "rate")

# kind -> "module:Class". Imported lazily so that listing plugins stays cheap.
BUILTIN: dict[str, str] = {
    "cog": "rollingstar.estimators.centroiders.cog:CogCentroider",
    "tracking": "rollingstar.estimators.identifiers.tracking:TrackingIdentifier",
    "lost-in-space": "rollingstar.estimators.identifiers.lost_in_space:LostInSpaceIdentifier",
    "none": "rollingstar.estimators.corrections.none:NoCorrection",
    "rate-correction": "rollingstar.estimators.corrections.rate:RateCorrection",
    "quest": "rollingstar.estimators.attitude.quest:QuestSolver",
    # he2021a plugins:
    "kf-cv": "rollingstar.estimators.filters.kf_cv:KfCvFilter",
    "time-domain": "rollingstar.estimators.corrections.time_domain:TimeDomainCorrection",
    # he2021b plugins:
    "request": "rollingstar.estimators.attitude.request:RequestSolver",
    # fu2022 plugins:
    "pso-rate": "rollingstar.estimators.rates.pso:PsoRateEstimator",
    # least-squares 3-axis single-frame rate:
    "ls-rate": "rollingstar.estimators.rates.ls_rate:LsRateEstimator",
    # liu2013 plugins:
    "windowed": "rollingstar.estimators.centroiders.windowed:WindowedCentroider",
    "gyro-kf": "rollingstar.estimators.filters.gyro_kf:GyroKalmanFilter",
    # sequential attitude estimators:
    "mekf": "rollingstar.estimators.attitude.mekf:MekfFilter",
    "gtsam": "rollingstar.estimators.attitude.gtsam_smoother:GtsamSmoother",
}

# alias -> (the built-in kind it stands for, parameters that make that plugin behave as the alias).
# Both aliases are rate-correction with a rate estimator of its own. A config of an alias gives that
# estimator's parameters beside the correction's; stage_params moves them into estimator_params.
ALIASES: dict[str, tuple[str, dict]] = {
    # rate-correction that runs the PSO itself on frames without a valid rate (fu2022's one-stage form)
    "pso-correction": ("rate-correction", {"estimator": "pso-rate", "rotation_form": "rotation-vector"}),
    # rate-correction that estimates the rate with ls-rate on every frame
    "ls-correction": ("rate-correction", {"estimator": "ls-rate", "reuse_rate": False}),
}


class UnknownPluginError(LookupError):
    """Raised for a plugin kind nobody registered; the message lists the valid kinds."""


def _load(target: str) -> type[Plugin]:
    module_name, _, attr = target.partition(":")
    cls = getattr(importlib.import_module(module_name), attr)
    if not (isinstance(cls, type) and issubclass(cls, Plugin)) or cls.role not in ROLES:
        raise TypeError(f"plugin {target} must subclass a role base class from estimators (roles: {', '.join(ROLES)})")
    return cls


@lru_cache(maxsize=1)
def _third_party() -> dict[str, str]:
    return {ep.name: ep.value for ep in entry_points(group=ENTRY_POINT_GROUP)
            if ep.name not in BUILTIN and ep.name not in ALIASES}


def available_kinds() -> dict[str, str]:
    """Every registered kind -> its import target (built-ins first; aliases not included)."""
    return {**BUILTIN, **_third_party()}


def get_plugin_class(kind: str) -> type[Plugin]:
    """The plugin class registered as ``kind`` (or that an alias stands for); :class:`UnknownPluginError`
    lists valid kinds."""
    kinds = available_kinds()
    kind = ALIASES[kind][0] if kind in ALIASES else kind
    if kind not in kinds:
        raise UnknownPluginError(f"unknown plugin kind {kind!r}; valid kinds: {', '.join(sorted([*kinds, *ALIASES]))}")
    return _load(kinds[kind])


def stage_params(kind: str, params: dict) -> dict:
    """The parameters to construct a stage of ``kind`` with (a pipeline config's ``params``).

    For an alias: its parameters, then the stage's own; those the plugin does not take go to its
    ``estimator_params`` (see :data:`ALIASES`).
    """
    if kind not in ALIASES:
        return dict(params)
    target, preset = ALIASES[kind]
    fields = get_plugin_class(target).Params.model_fields
    own = {k: v for k, v in params.items() if k in fields}
    nested = {k: v for k, v in params.items() if k not in fields}
    out = {**preset, **own}
    if nested:
        out["estimator_params"] = {**out.get("estimator_params", {}), **nested}
    return out


def plugins_by_role() -> dict[str, list[type[Plugin]]]:
    """All plugin classes grouped by role (roles in pipeline order)."""
    out: dict[str, list[type[Plugin]]] = {role: [] for role in ROLES}
    for kind in available_kinds():
        cls = get_plugin_class(kind)
        out[cls.role].append(cls)
    return out
