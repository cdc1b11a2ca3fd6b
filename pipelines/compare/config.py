"""The comparison config (strict pydantic, loaded from YAML) and its expansion into tasks.

.. code-block:: yaml

    name: ci
    monte_carlo: 2            # seeds per (scenario variant, pipeline): seed, seed + 1, ...
    seed: 1                   # or `seeds: [1, 5, 9]`
    frames: 20                # default frame count (a scenario entry may override)
    pipelines:                # paths relative to this file, or a shipped config's bare name (baseline)
      - ../pipelines/baseline.yaml
      - {path: ../pipelines/ls_rate.yaml, name: ls}      # or rename
    scenarios:
      - path: ../scenarios/fu2022.yaml
        set: {noise.centroid_sigma_px: 0.02}              # dotted keys applied to every variant
        sweep:                                            # product over keys: one variant per combination
          motion.rate_deg_s: [[0.5, 0.5, 0], [1, 1, 0]]
        pipelines: [baseline, ls]                         # default: every pipeline
    tolerances:               # regression gate, per metric (fnmatch patterns on dotted metric names)
      "attitude_error_arcsec.*_rmse": {rel: 0.05}

Every problem names the config file and the key path (``scenarios[0].sweep.motion.rate_deg_s[1]``);
scenario and pipeline files are loaded and their stages built here, before any task runs.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    Field,
    NonNegativeFloat,
    PositiveInt,
    ValidationError,
    model_validator,
)

from rollingstar.config import (
    CONFIG_KINDS,
    CONFIGS,
    Strict,
    format_validation_error,
    read_yaml,
    register_kind,
    shipped_configs,
    to_yaml,
    validate,
)
from rollingstar.errors import ConfigError
from rollingstar.pipelines.config import PipelineConfig, load_pipeline
from rollingstar.pipelines.runner import build_stages
from rollingstar.sensors.scenario import ScenarioConfig, load_scenario


class PipelineEntry(Strict):
    path: str
    name: str | None = Field(None, description="label in the results; default the pipeline file's `name`")


class ScenarioEntry(Strict):
    path: str
    name: str | None = Field(None, description="label in the results; default the scenario file's `name`")
    frames: PositiveInt | None = None
    set: dict[str, Any] = {}
    sweep: dict[str, list[Any]] = {}
    pipelines: list[str] | None = Field(None, description="names of the pipelines run on this scenario; default all")

    @model_validator(mode="after")
    def _sweeps_not_empty(self):
        for key, values in self.sweep.items():
            if not values:
                raise ValueError(f"sweep {key!r} has no values")
        return self


class Tolerance(Strict):
    rel: NonNegativeFloat = 0.0
    abs: NonNegativeFloat = 0.0


class CompareConfig(Strict):
    name: str = "comparison"
    description: str = ""
    monte_carlo: PositiveInt = 1
    seed: int = 1
    seeds: list[int] | None = Field(None, min_length=1, description="explicit seeds (overrides monte_carlo and seed)")
    frames: PositiveInt | None = None
    pipelines: list[str | PipelineEntry] = Field(min_length=1)
    scenarios: list[ScenarioEntry] = Field(min_length=1)
    tolerances: dict[str, Tolerance] = {}
    plot_x: Literal["rate_norm", "rate_xy_norm"] = Field(
        "rate_norm", description="x axis of the error-vs-rate figures: |rate| or |(w_x, w_y)| (deg/s)")

    def seed_list(self) -> list[int]:
        return list(self.seeds) if self.seeds is not None else [self.seed + k for k in range(self.monte_carlo)]


register_kind("compare", CompareConfig)


@dataclass(frozen=True)
class Variant:
    """One scenario variant: the base scenario with one combination of the sweep applied."""

    scenario: str  # base label
    label: str  # unique label, e.g. "fu2022[motion.rate_deg_s=(1, 1, 0)]"
    params: dict  # the swept keys and their values
    config: ScenarioConfig
    pipelines: tuple[str, ...]

    @property
    def rate_deg_s(self) -> list[float]:
        return [float(v) for v in self.config.motion.rate_deg_s]


@dataclass(frozen=True)
class Task:
    """One unit of work: one scenario variant simulated once with one seed, then every pipeline chosen
    for the variant run on that recording (the recording depends on the variant and the seed only).
    Plain data, so it pickles to any worker."""

    index: int
    variant: str
    seed: int
    frames: int
    scenario_yaml: str
    pipelines: tuple[tuple[str, str], ...]  # (name, pipeline YAML) in the config's order


@dataclass(frozen=True)
class Comparison:
    config: CompareConfig
    source: str
    variants: list[Variant]
    pipelines: dict[str, PipelineConfig]
    pipeline_paths: dict[str, str]

    def tasks(self) -> list[Task]:
        """One task per (variant, seed), in config order; each runs the variant's pipelines."""
        out = []
        for v in self.variants:
            scenario_yaml = to_yaml(v.config)
            pipelines = tuple((p, to_yaml(self.pipelines[p])) for p in v.pipelines)
            for seed in self.config.seed_list():
                out.append(Task(len(out), v.label, seed, v.config.frames, scenario_yaml, pipelines))
        return out


def _fmt(value) -> str:
    if isinstance(value, (list, tuple)):
        return "(" + ", ".join(_fmt(v) for v in value) + ")"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _set_dotted(data: dict, key: str, value, where: str) -> None:
    parts = key.split(".")
    node = data
    for part in parts[:-1]:
        if not isinstance(node, dict) or part not in node or not isinstance(node[part], dict):
            raise ConfigError(f"{where}: {key!r}: no scenario section {part!r} (keys are dotted scenario keys, "
                              f"e.g. motion.rate_deg_s)")
        node = node[part]
    node[parts[-1]] = value


def _variant_config(base: ScenarioConfig, updates: dict, frames: int | None, source: str, where: str) -> ScenarioConfig:
    data = base.model_dump(mode="json")
    for key, value in updates.items():
        _set_dotted(data, key, value, f"{source}: {where}")
    if frames is not None:
        data["frames"] = frames
    try:
        return ScenarioConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(f"{source}: {where}", err)) from None


def load_compare(path: str | Path) -> Comparison:
    """Validate the config, load every scenario and pipeline it names, build the stages (fail early)."""

    path = Path(path)
    source = str(path)
    cfg = validate(CompareConfig, read_yaml(path), source)
    root = path.parent

    def resolve(p: str, where: str, kind: str) -> Path:
        """A file relative to the config, else a shipped config's bare name (``he2021b``, ``baseline``)."""
        full = (root / p) if not Path(p).is_absolute() else Path(p)
        if full.is_file():
            return full
        shipped = CONFIGS / CONFIG_KINDS[kind] / f"{Path(p).stem}.yaml"
        if len(Path(p).parts) == 1 and Path(p).suffix in ("", ".yaml", ".yml") and shipped.is_file():
            return shipped
        if full.is_dir():
            raise ConfigError(f"{source}: {where}: {full} is a folder, not a config file")
        raise ConfigError(f"{source}: {where}: file not found: {p} (paths are relative to the config file, here "
                          f"{full}; a bare name is a shipped {kind}: {', '.join(shipped_configs(kind))})")

    pipelines: dict[str, PipelineConfig] = {}
    paths: dict[str, str] = {}
    for k, entry in enumerate(cfg.pipelines):
        entry = PipelineEntry(path=entry) if isinstance(entry, str) else entry
        where = f"pipelines[{k}]"
        file = resolve(entry.path, f"{where}.path" if not isinstance(cfg.pipelines[k], str) else where, "pipeline")
        pipe = load_pipeline(file)
        build_stages(pipe, str(file))  # unknown kinds / bad params fail now, naming the file
        name = entry.name or pipe.name
        if name in pipelines:
            raise ConfigError(f"{source}: {where}: duplicate pipeline name {name!r} (set `name:` to tell them apart)")
        pipelines[name], paths[name] = pipe, str(entry.path)

    variants: list[Variant] = []
    labels: set[str] = set()
    for k, entry in enumerate(cfg.scenarios):
        where = f"scenarios[{k}]"
        base = load_scenario(resolve(entry.path, f"{where}.path", "scenario"))
        name = entry.name or base.name
        chosen = tuple(entry.pipelines) if entry.pipelines is not None else tuple(pipelines)
        for q, p in enumerate(chosen):
            if p not in pipelines:
                raise ConfigError(f"{source}: {where}.pipelines[{q}]: unknown pipeline {p!r}; "
                                  f"the config's pipelines are: {', '.join(pipelines)}")
        frames = entry.frames or cfg.frames
        base = _variant_config(base, entry.set, frames, source, f"{where}.set")
        keys = list(entry.sweep)
        for combo in itertools.product(*(entry.sweep[key] for key in keys)) if keys else [()]:
            params = dict(zip(keys, combo))
            sweep_where = f"{where}.sweep." + ", ".join(f"{key}={_fmt(v)}" for key, v in params.items()) if keys else where
            conf = _variant_config(base, params, None, source, sweep_where)
            label = name + ("[" + ", ".join(f"{key}={_fmt(v)}" for key, v in params.items()) + "]" if params else "")
            if label in labels:
                raise ConfigError(f"{source}: {where}: duplicate scenario variant {label!r} (set `name:` to tell them apart)")
            labels.add(label)
            variants.append(Variant(name, label, params, conf, chosen))
    return Comparison(cfg, source, variants, pipelines, paths)
