"""The pipeline config: an ordered list of stages ``{kind: <plugin name>, params: {...}}``.

``kind`` is an open string checked against the plugin registry (built-ins and entry points alike),
never a closed union.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field

from rollingstar.config import Strict, read_yaml, validate


class StageConfig(Strict):
    kind: str
    params: dict[str, Any] = {}


class PipelineConfig(Strict):
    """An ordered list of stages; each is checked against the plugin registry when built."""

    name: str = "pipeline"
    description: str = ""
    stages: list[StageConfig] = Field(min_length=1)



def load_pipeline(path: str | Path) -> PipelineConfig:
    return validate(PipelineConfig, read_yaml(path), str(path))


