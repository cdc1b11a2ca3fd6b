"""The pipeline config: an ordered list of stages ``{kind: <plugin name>, params: {...}}``.

``kind`` is an open string checked against the plugin registry (built-ins and entry points alike),
never a closed union.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field

from rollingstar.config import Strict, read_yaml, register_kind, validate
from rollingstar.estimators.identifiers.integrity import DEFAULT_MAX_FALSE_MATCH_PROB


class StageConfig(Strict):
    kind: str
    params: dict[str, Any] = {}


class PipelineConfig(Strict):
    """An ordered list of stages; each is checked against the plugin registry when built."""

    name: str = "pipeline"
    description: str = ""
    stages: list[StageConfig] = Field(min_length=1)
    max_false_match_prob: float = Field(
        default=DEFAULT_MAX_FALSE_MATCH_PROB, gt=0.0, lt=1.0,
        description="Largest probability that a frame's identified stars are chance coincidences; a frame above "
        "it keeps no identification and no valid attitude (estimators/identifiers/integrity.py).")


register_kind("pipeline", PipelineConfig)


def load_pipeline(path: str | Path) -> PipelineConfig:
    return validate(PipelineConfig, read_yaml(path), str(path))


