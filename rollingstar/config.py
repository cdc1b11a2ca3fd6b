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
from pydantic import BaseModel, ConfigDict, ValidationError, ValidationInfo, field_validator

from rollingstar.errors import ConfigError

#: The configs that ship with the package (the repository's ``configs/`` folder).
CONFIGS = Path(str(importlib.resources.files("rollingstar.configs")))
#: Config kinds and their folder under :data:`CONFIGS`.
CONFIG_KINDS = {"scenario": "scenarios", "pipeline": "pipelines", "camera": "cameras", "compare": "compare"}


def _types_in(annotation) -> list:
    """``annotation`` and every type inside it (union members, list and tuple items, dict values)."""
    return [annotation, *(t for arg in typing.get_args(annotation) for t in _types_in(arg))]


def _number_only(annotation) -> bool:
    """True for a field of numbers (``int``, ``float`` or containers of them) that no boolean fits: no
    ``bool``, ``Any`` or nested model (which checks its own fields) anywhere in its type."""
    types = _types_in(annotation)
    takes_number = any(t is int or t is float for t in types)
    takes_other = any(t is bool or t is typing.Any or (isinstance(t, type) and issubclass(t, BaseModel))
                      for t in types)
    return takes_number and not takes_other


def _holds_bool(value) -> bool:
    if isinstance(value, bool):
        return True
    if isinstance(value, (list, tuple)):
        return any(_holds_bool(v) for v in value)
    return isinstance(value, dict) and any(_holds_bool(v) for v in value.values())


class NoBooleanNumbers(BaseModel):
    """A model whose number fields refuse booleans, which pydantic would otherwise take as 1 and 0.

    YAML reads ``true``, ``yes`` and ``on`` as booleans: ``focal_length_mm: yes`` is a typo, not a
    1 mm lens.
    """

    @field_validator("*", mode="before")
    @classmethod
    def _no_boolean_for_a_number(cls, value, info: ValidationInfo):
        if _holds_bool(value) and _number_only(cls.model_fields[info.field_name].annotation):
            raise ValueError("expected a number, got a boolean (true/false; in YAML also yes/no and on/off)")
        return value


class Strict(NoBooleanNumbers):
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
        whole = isinstance(got, dict) and e["type"] == "value_error"  # a check across keys: the message names them
        hint = "" if e["type"] == "missing" or whole else f" (got {excerpt(got)})"
        msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden" and model is not None:
            close = difflib.get_close_matches(str(e["loc"][-1]), _known_keys(model, tuple(e["loc"])), n=1, cutoff=0.6)
            if close:
                key = str(e["loc"][-1])
                same_stem = "_" in key and close[0].rsplit("_", 1)[0] == key.rsplit("_", 1)[0]
                msg += f"; did you mean {close[0]!r}?" + (" (units are part of the key names)" if same_stem else "")
        lines.append(f"{source}: {path}: {msg}{hint}")
    return "\n".join(lines)


#: Limits on a YAML document: its size on disk, the number of nodes once every alias is expanded
#: (a few hundred bytes of nested aliases can stand for billions of nodes) and its nesting depth.
#: The largest shipped config has about 400 nodes and depth 6.
MAX_YAML_BYTES = 4 << 20
MAX_YAML_NODES = 200_000
MAX_YAML_DEPTH = 64


def excerpt(value, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters, for error messages about values of any size."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit - 5]} ...{text[-1]}"


def read_yaml(path: str | Path) -> dict:
    """Parse a YAML mapping from a regular file; errors name the file and line."""
    path = Path(path)
    try:
        if not path.exists():
            raise ConfigError(f"{path}: config file not found")
        if not path.is_file():
            raise ConfigError(f"{path}: not a regular file (a config must be a YAML file)")
        if path.stat().st_size > MAX_YAML_BYTES:
            raise ConfigError(f"{path}: {path.stat().st_size} bytes; a config may be at most {MAX_YAML_BYTES} bytes")
        text = path.read_text()
    except UnicodeDecodeError as exc:
        if path.read_bytes()[:5] == b"\x89MCAP":
            raise ConfigError(f"{path}: an MCAP recording where a YAML config was expected; are the arguments in "
                              "order (e.g. `rollingstar run PIPELINE RECORDING -o OUTPUT`)?") from None
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}): a config must be a YAML file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config file: {exc.strerror}") from None
    return parse_yaml(text, str(path))


class _BoundedLoader(yaml.SafeLoader):
    """PyYAML's safe loader that refuses duplicate keys (PyYAML keeps the last one silently)."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            if isinstance(key, (str, int, float, bool)) and key in seen:
                raise ConfigError(f"{self.name}: line {key_node.start_mark.line + 1}: duplicate key {excerpt(key)} "
                                  f"(first at line {seen[key]}); each key may appear once")
            seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep)

    def construct_yaml_timestamp(self, node):
        """A date the YAML grammar accepts but the calendar does not (2019-02-30) is an error naming its line."""
        try:
            return super().construct_yaml_timestamp(node)
        except ValueError as exc:
            raise ConfigError(f"{self.name}: line {node.start_mark.line + 1}: {excerpt(node.value)} is not a valid "
                              f"date or time ({exc})") from None


_BoundedLoader.add_constructor("tag:yaml.org,2002:timestamp", _BoundedLoader.construct_yaml_timestamp)


def _node_children(node) -> list:
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    return node.value if isinstance(node, yaml.SequenceNode) else []


def _check_expanded_size(root, source: str) -> None:
    """Refuse a document whose alias-expanded tree is too large, too deep or recursive.

    Sizes and depths are computed once per node (aliases share nodes), so the check costs the size
    of the document as written, not as expanded."""
    size, depth, visiting = {}, {}, set()
    stack = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        key = id(node)
        if key in size:
            continue
        children = _node_children(node)
        if not children_done:
            if key in visiting:
                raise ConfigError(f"{source}: a YAML alias refers to a node that contains it (recursive structure)")
            visiting.add(key)
            stack.append((node, True))
            stack.extend((child, False) for child in children if id(child) not in size)
            continue
        visiting.discard(key)
        size[key] = 1 + sum(size[id(c)] for c in children)
        depth[key] = 1 + max((depth[id(c)] for c in children), default=0)
        if size[key] > MAX_YAML_NODES or depth[key] > MAX_YAML_DEPTH:
            raise ConfigError(f"{source}: the YAML document expands to more than {MAX_YAML_NODES} nodes or nests "
                              f"deeper than {MAX_YAML_DEPTH} levels (aliases included); a config is far smaller")


def _load_bounded(text: str, source: str):
    loader = _BoundedLoader(text)
    loader.name = source
    try:
        root = loader.get_single_node()
        if root is None:
            return None
        _check_expanded_size(root, source)
        return loader.construct_document(root)
    finally:
        loader.dispose()


def parse_yaml(text: str, source: str) -> dict:
    """A YAML mapping from text, within :data:`MAX_YAML_BYTES`, :data:`MAX_YAML_NODES` and
    :data:`MAX_YAML_DEPTH`, without duplicate keys."""
    if len(text) > MAX_YAML_BYTES:
        raise ConfigError(f"{source}: {len(text)} characters; a config may be at most {MAX_YAML_BYTES}")
    try:
        data = _load_bounded(text, source)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{source}:{where}: YAML syntax error: {problem}") from None
    except RecursionError:
        raise ConfigError(f"{source}: the YAML document nests deeper than {MAX_YAML_DEPTH} levels") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a YAML mapping at the top level, got {type(data).__name__}")
    return data


#: The top-level model of each kind of config file, registered by the module that defines it
#: (:func:`register_kind`), so that a file of one kind given where another is expected is named.
#: Only the kinds whose modules the command has loaded are known (this layer imports none of them):
#: a file of another kind is then reported by its unknown keys alone.
KIND_MODELS: dict[str, type] = {}


def register_kind(kind: str, model: type[Strict]) -> type[Strict]:
    """Record ``model`` as the top-level model of config files of ``kind`` (``CONFIG_KINDS``)."""
    KIND_MODELS[kind] = model
    return model


def _other_kind(model: type[Strict], data) -> str | None:
    """The kind of config ``data`` is when it is not ``model``'s: some of its top-level keys are
    unknown to ``model`` and every one is a key of that kind's model."""
    if not isinstance(data, dict) or not data or not set(data) - set(model.model_fields):
        return None
    return next((kind for kind, other in KIND_MODELS.items()
                 if other is not model and set(data) <= set(other.model_fields)), None)


def validate(model: type[Strict], data: dict, source: str):
    try:
        return model.model_validate(data)
    except ValidationError as err:
        text = format_validation_error(source, err, model=model)
        kind = _other_kind(model, data)
        expected = next((k for k, m in KIND_MODELS.items() if m is model), None)
        if kind is not None:
            text += (f"\n{source}: its keys are those of a {kind} config, not of a "
                     f"{expected or model.__name__} config: was it given in the wrong place?")
        raise ConfigError(text) from None


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
