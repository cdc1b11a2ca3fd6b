"""Configs as strict pydantic models read from YAML, with messages that name the key path.

Every layer reads its configs through this module: the scenario (``rollingstar.sensors.scenario``),
the pipeline (``rollingstar.pipelines.config``), the comparison and the importers' sidecars.
Unknown keys are rejected; errors name the file, the key path (``motion.rate_deg_s[0]``) and what
was expected.
"""
from __future__ import annotations

import difflib
import importlib.resources
import typing
from pathlib import Path

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from rollingstar.errors import ConfigError

#: The configs that ship with the package (the repository's ``configs/`` folder).
CONFIGS = Path(str(importlib.resources.files("rollingstar.configs")))
#: Config kinds and their folder under :data:`CONFIGS`.
CONFIG_KINDS = {"scenario": "scenarios", "pipeline": "pipelines", "camera": "cameras", "compare": "compare"}


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


def _key_path(loc: tuple) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "<top level>"


def _known_keys(model, loc: tuple) -> list[str]:
    """The keys valid where ``loc`` (minus its last part) points inside ``model`` (best effort)."""
    for part in loc[:-1]:
        if isinstance(part, int) or model is None:
            continue
        field = getattr(model, "model_fields", {}).get(part)
        if field is None:
            return []
        ann, model = field.annotation, None
        for cand in (ann, *typing.get_args(ann), *(a for t in typing.get_args(ann) for a in typing.get_args(t))):
            if isinstance(cand, type) and issubclass(cand, BaseModel):
                model = cand
                break
    return list(getattr(model, "model_fields", {}))


def format_validation_error(source: str, err: ValidationError, prefix: tuple = (), model=None) -> str:
    """One line per problem: ``file: key.path: message (got <input>)``; ``prefix`` is prepended to each key path.

    An unknown key gets the closest valid key as a hint (``exposure_s`` -> ``exposure_ms``: units are in
    the key names) when ``model`` is given."""
    lines = []
    for e in err.errors():
        path = _key_path(tuple(prefix) + tuple(e["loc"]))
        got = e.get("input")
        hint = "" if e["type"] == "missing" else f" (got {got!r})"
        msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"]
        if e["type"] == "extra_forbidden" and model is not None:
            close = difflib.get_close_matches(str(e["loc"][-1]), _known_keys(model, tuple(e["loc"])), n=1, cutoff=0.6)
            if close:
                key = str(e["loc"][-1])
                same_stem = "_" in key and close[0].rsplit("_", 1)[0] == key.rsplit("_", 1)[0]
                msg += f"; did you mean {close[0]!r}?" + (" (units are part of the key names)" if same_stem else "")
        lines.append(f"{source}: {path}: {msg}{hint}")
    return "\n".join(lines)


def read_yaml(path: str | Path) -> dict:
    """Parse a YAML mapping; syntax errors name the file and line."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config file: {exc.strerror}") from None
    return parse_yaml(text, str(path))


def parse_yaml(text: str, source: str) -> dict:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{source}:{where}: YAML syntax error: {problem}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a YAML mapping at the top level, got {type(data).__name__}")
    return data


def validate(model: type[Strict], data: dict, source: str):
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(source, err, model=model)) from None


def to_yaml(config: Strict) -> str:
    """The config as YAML (what goes into a log's metadata)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)


def shipped_configs(kind: str) -> list[str]:
    """Names of the shipped configs of one kind (``scenario``, ``pipeline``, ``camera``, ``compare``)."""
    return sorted(p.stem for p in (CONFIGS / CONFIG_KINDS[kind]).glob("*.yaml"))


def find_config(name: str | Path, kind: str) -> Path:
    """A config given on the command line or to the API: an existing file, or a shipped config's name.

    ``he2021b`` (or ``he2021b.yaml``) names ``configs/scenarios/he2021b.yaml`` when ``kind`` is
    ``scenario`` and no file of that name exists here. Anything else that is not a file is an error
    that lists the shipped names.
    """
    path = Path(name)
    if path.exists():
        return path
    bare = len(path.parts) == 1 and path.suffix in ("", ".yaml", ".yml")
    shipped = CONFIGS / CONFIG_KINDS[kind] / f"{path.stem}.yaml"
    if bare and shipped.is_file():
        return shipped
    raise ConfigError(f"{name}: config file not found, and it is not the name of a shipped {kind} config "
                      f"(shipped: {', '.join(shipped_configs(kind))})")
