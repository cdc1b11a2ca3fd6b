"""Plugin registry: the built-in plugins plus those registered by other packages.

Third-party packages register a plugin class under the entry-point group ``rollingstar.plugins``::

    [project.entry-points."rollingstar.plugins"]
    my-centroider = "mypkg.centroid:MyCentroider"

The entry-point name is the plugin ``kind`` used in pipeline configs; the class must subclass a
role base class from ``estimators`` and is validated exactly like a built-in.
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
    "quest": "rollingstar.estimators.attitude.quest:QuestSolver",
    # he2021a plugins:
    "kf-cv": "rollingstar.estimators.filters.kf_cv:KfCvFilter",
    "time-domain": "rollingstar.estimators.corrections.time_domain:TimeDomainCorrection",
    # he2021b plugins:
    "request": "rollingstar.estimators.attitude.request:RequestSolver",
    # fu2022 plugins:
    "pso-rate": "rollingstar.estimators.rates.pso:PsoRateEstimator",
    "pso-correction": "rollingstar.estimators.rates.pso:PsoCorrection",
    # issue 5: least-squares 3-axis single-frame rate (and the correction with it):
    "ls-rate": "rollingstar.estimators.rates.ls_rate:LsRateEstimator",
    "ls-correction": "rollingstar.estimators.rates.ls_rate:LsRateCorrection",
    # liu2013 plugins:
    "windowed": "rollingstar.estimators.centroiders.windowed:WindowedCentroider",
    "gyro-kf": "rollingstar.estimators.filters.gyro_kf:GyroKalmanFilter",
    # issue 5 attitude estimators:
    "mekf": "rollingstar.estimators.attitude.mekf:MekfFilter",
    "gtsam": "rollingstar.estimators.attitude.gtsam_smoother:GtsamSmoother",
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
    return {ep.name: ep.value for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name not in BUILTIN}


def available_kinds() -> dict[str, str]:
    """Every registered kind -> its import target (built-ins first)."""
    return {**BUILTIN, **_third_party()}


def get_plugin_class(kind: str) -> type[Plugin]:
    """The plugin class registered as ``kind``; :class:`UnknownPluginError` lists valid kinds."""
    kinds = available_kinds()
    if kind not in kinds:
        raise UnknownPluginError(f"unknown plugin kind {kind!r}; valid kinds: {', '.join(sorted(kinds))}")
    return _load(kinds[kind])


def plugins_by_role() -> dict[str, list[type[Plugin]]]:
    """All plugin classes grouped by role (roles in pipeline order)."""
    out: dict[str, list[type[Plugin]]] = {role: [] for role in ROLES}
    for kind in available_kinds():
        cls = get_plugin_class(kind)
        out[cls.role].append(cls)
    return out
