"""Plugin registry: the built-in plugins plus those registered by other packages.

Third-party packages register a plugin class under the entry-point group ``rollingstar.plugins``::

    [project.entry-points."rollingstar.plugins"]
    my-centroider = "mypkg.centroid:MyCentroider"

The entry-point name is the plugin ``kind`` used in pipeline configs; the class must subclass a
role base class from ``estimators`` and is validated exactly like a built-in.

:data:`ALIASES` are further kind names, each standing for a built-in kind with some of its
parameters set (:func:`stage_params`); a config may use either name.

:func:`check_stage_order` checks a pipeline's stages against each other when they are built, and
:func:`check_stages_on_recording` against a recording before the first frame, with what each
stage declares it needs and provides (:attr:`~rollingstar.estimators.plugin.Plugin.needs`).
"""
from __future__ import annotations

import importlib
from collections.abc import Sequence
from functools import lru_cache
from importlib.metadata import entry_points

from rollingstar.errors import ConfigError, PipelineError
from rollingstar.estimators.attitude.base import AttitudeSolver
from rollingstar.estimators.centroiders.base import Centroider
from rollingstar.estimators.corrections.base import Correction
from rollingstar.estimators.filters.base import StarMotionFilter
from rollingstar.estimators.identifiers.base import Identifier
from rollingstar.estimators.plugin import FRAME_CONTENTS, Plugin
from rollingstar.estimators.rates.base import RateEstimator

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
    "rs-bundle": "rollingstar.estimators.attitude.rs_bundle:RsBundleSolver",
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
    # streak-aware centroiding (matched filter along the motion, maximum-likelihood streak fit):
    "streak": "rollingstar.estimators.centroiders.streak:StreakCentroider",
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


# ------------------------------------------------------------------ the order of a pipeline's stages
#: What a recording can hold in place of a stage's output: images, centroids (``spots``), or
#: centroids already identified (imported astrometry.net tables).
RECORDING_CAN_PROVIDE = frozenset({"image", "spots", "identified"})
VALID_ORDER = ("centroider -> identifier -> [star-motion filter] -> [rolling-shutter correction] -> attitude solver; "
               "rate estimators after identification")
ROLE_LABELS = {"centroider": "centroider", "identifier": "identifier", "filter": "star-motion filter",
               "correction": "rolling-shutter correction", "attitude": "attitude solver", "rate": "rate estimator"}
#: word -> the role whose base class provides it (what to add when nothing does).
PROVIDER_ROLE = {word: ROLE_LABELS[base.role] for base in
                 (Centroider, Identifier, StarMotionFilter, Correction, RateEstimator, AttitudeSolver)
                 for word in base.provides}


def _declared(stage: Plugin, attribute: str) -> frozenset[str]:
    return frozenset(getattr(stage, attribute, ()) or ())


def _describe(i: int, stage: Plugin, kinds: Sequence[str] | None) -> str:
    kind = kinds[i] if kinds is not None else stage.name
    return f"stages[{i}] ({kind!r}, {ROLE_LABELS.get(stage.role, stage.role)})"


def _need(word: str) -> str:
    return f"{word!r} ({FRAME_CONTENTS[word]})" if word in FRAME_CONTENTS else repr(word)


def _remedy(word: str) -> str:
    if word == "image":
        return "run it on an image recording"
    role = PROVIDER_ROLE.get(word)
    return f"add a {role} before it" if role else "add a stage that provides it before it"


def _first_problem(stages: Sequence[Plugin], kinds: Sequence[str] | None, from_recording: frozenset[str],
                   recording: str | None, skip_centroiders: bool) -> str | None:
    """The first stage whose needs neither an earlier stage nor the recording meet, said in one
    sentence; None when every stage has what it needs. ``from_recording``: what the recording holds
    (``recording`` None: what any recording could hold)."""
    active = [(i, s) for i, s in enumerate(stages) if not (skip_centroiders and isinstance(s, Centroider))]
    available: set[str] = set()
    for n, (i, stage) in enumerate(active):
        for word in sorted(_declared(stage, "needs") - available):
            where = f"{_describe(i, stage, kinds)} needs {_need(word)}"
            later = next((j for j, s in active[n + 1:] if word in _declared(s, "provides")), None)
            if later is not None:
                return (f"{where}, which only the later {_describe(later, stages[later], kinds)} provides: "
                        f"reorder the stages (valid order: {VALID_ORDER})")
            if word in from_recording:
                continue
            source = ("no recording holds" if recording is None else
                      f"the recording {recording} does not hold (it holds {', '.join(map(repr, sorted(from_recording)))})")
            return (f"{where}, which no stage before it provides and {source}: {_remedy(word)} "
                    f"(valid order: {VALID_ORDER})")
        available |= _declared(stage, "needs") | _declared(stage, "provides")
    return None


def check_stage_order(stages: Sequence[Plugin], source: str = "<pipeline>", kinds: Sequence[str] | None = None) -> None:
    """Check that every stage gets what it needs (:attr:`Plugin.needs`) from a stage before it or from
    a recording (:data:`RECORDING_CAN_PROVIDE`); :class:`ConfigError` naming the pipeline ``source``,
    the stage (index and ``kinds[i]``, the config's names) and what it misses, with a valid order.

    A need that only a later stage provides is an order error, even where a recording could hold it.
    """
    problem = _first_problem(stages, kinds, RECORDING_CAN_PROVIDE, None, skip_centroiders=False)
    if problem:
        raise ConfigError(f"{source}: {problem}")


def check_stages_on_recording(stages: Sequence[Plugin], provided: frozenset[str], recording: str,
                              source: str = "<pipeline>", kinds: Sequence[str] | None = None) -> None:
    """:func:`check_stage_order` with what this recording holds (``provided``, a subset of
    :data:`RECORDING_CAN_PROVIDE`); :class:`PipelineError`. A recording without images skips the
    centroiders (the run does), so they neither need nor provide anything on it."""
    problem = _first_problem(stages, kinds, frozenset(provided), recording, skip_centroiders="image" not in provided)
    if problem:
        raise PipelineError(f"{source}: {problem}")
