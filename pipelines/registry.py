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

from estimators.plugin import Plugin

ENTRY_POINT_GROUP = "rollingstar.plugins"
ROLES = ("centroider", "identifier", "filter", "correction", "attitude", "rate")

# kind -> "module:Class". Imported lazily so that listing plugins stays cheap.
BUILTIN: dict[str, str] = {
    "cog": "estimators.centroiders.cog:CogCentroider",
    "tracking": "estimators.identifiers.tracking:TrackingIdentifier",
    "lost-in-space": "estimators.identifiers.lost_in_space:LostInSpaceIdentifier",
    "none": "estimators.corrections.none:NoCorrection",
    "quest": "estimators.attitude.quest:QuestSolver",
    # he2021a plugins:
    "kf-cv": "estimators.filters.kf_cv:KfCvFilter",
    "time-domain": "estimators.corrections.time_domain:TimeDomainCorrection",
    # he2021b plugins:
    "request": "estimators.attitude.request:RequestSolver",
    # fu2022 plugins:
    "pso-rate": "estimators.rates.pso:PsoRateEstimator",
    "pso-correction": "estimators.rates.pso:PsoCorrection",
    # issue 5: least-squares 3-axis single-frame rate (and the correction with it):
    "ls-rate": "estimators.rates.ls_rate:LsRateEstimator",
    "ls-correction": "estimators.rates.ls_rate:LsRateCorrection",
    # liu2013 plugins:
    "windowed": "estimators.centroiders.windowed:WindowedCentroider",
    "gyro-kf": "estimators.filters.gyro_kf:GyroKalmanFilter",
    # issue 5 attitude estimators:
    "mekf": "estimators.attitude.mekf:MekfFilter",
    "gtsam": "estimators.attitude.gtsam_smoother:GtsamSmoother",
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
