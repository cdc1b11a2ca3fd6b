"""The public Python API: what the ``rollingstar`` command line does, as functions.

Scenarios, rollingstar.pipelines and comparisons are given as a shipped config's name (``"he2021b"``), a YAML
path, or an already loaded config object. Every function writes what the matching command writes
and returns its summary; bad input raises :class:`rollingstar.errors.UserError` (the command line
turns it into exit code 2 and the message).

A runnable tour: ``examples/quickstart.py``.
"""
from __future__ import annotations

from pathlib import Path

from rollingstar.config import find_config
from rollingstar.errors import UserError
from rollingstar.estimators.centroiders.remeasure import remeasure_stars
from rollingstar.logs.importers import import_centroids, import_images
from rollingstar.logs.importers.corr import import_corr as _import_corr
from rollingstar.logs.reader import LogReader
from rollingstar.pipelines.compare import run_compare
from rollingstar.pipelines.compare.run import CompareOutcome
from rollingstar.pipelines.config import PipelineConfig, load_pipeline
from rollingstar.pipelines.diagnose import DiagnoseOptions, run_diagnose
from rollingstar.pipelines.evaluate import evaluate_log
from rollingstar.pipelines.runner import RunSummary, run_pipeline
from rollingstar.pipelines.simulate import SimulationSummary, simulate_to_log
from rollingstar.sensors.scenario import ScenarioConfig, load_scenario

__all__ = ["simulate", "run", "evaluate", "compare", "diagnose", "import_images", "import_corr",
           "import_centroids", "open_recording", "find_config"]


def _scenario(scenario: str | Path | ScenarioConfig) -> ScenarioConfig:
    return scenario if isinstance(scenario, ScenarioConfig) else load_scenario(find_config(scenario, "scenario"))


def _pipeline(pipeline: str | Path | PipelineConfig) -> tuple[PipelineConfig, str]:
    if isinstance(pipeline, PipelineConfig):
        return pipeline, f"<{pipeline.name}>"
    path = find_config(pipeline, "pipeline")
    return load_pipeline(path), str(path)


def import_corr(folder: str | Path, output: str | Path, centroids: str = "table") -> Path:
    """astrometry.net corr tables -> a recording (``rollingstar import corr``). ``centroids``:
    ``"table"`` keeps astrometry.net's positions, ``"image"`` measures each star again on the
    table's image (:func:`rollingstar.estimators.centroiders.remeasure.remeasure_stars`)."""
    if centroids not in ("table", "image"):
        raise UserError(f"--centroids {centroids!r}: expected 'table' (astrometry.net's positions) or 'image' "
                        "(measured again on the table's image)")
    return _import_corr(folder, output, remeasure_stars if centroids == "image" else None)


def simulate(scenario: str | Path | ScenarioConfig, output: str | Path, frames: int | None = None,
             seed: int | None = None, show_progress: bool = False) -> SimulationSummary:
    """Simulate a recording (``rollingstar simulate``); ``frames`` and ``seed`` override the scenario's."""
    inputs = [] if isinstance(scenario, ScenarioConfig) else [find_config(scenario, "scenario")]
    return simulate_to_log(_scenario(scenario), output, frames=frames, seed=seed, show_progress=show_progress,
                           inputs=inputs)


def run(pipeline: str | Path | PipelineConfig, recording: str | Path, output: str | Path, resume: bool = False,
        show_progress: bool = False) -> RunSummary:
    """Run a pipeline over a recording and write its estimates (``rollingstar run``)."""
    config, source = _pipeline(pipeline)
    inputs = [] if isinstance(pipeline, PipelineConfig) else [source]
    return run_pipeline(recording, config, output, pipeline_source=source, show_progress=show_progress,
                        resume=resume, inputs=inputs)


def evaluate(output: str | Path) -> dict:
    """Metrics of a run's output against the truth it carries (``rollingstar evaluate --json``)."""
    return evaluate_log(output)


def compare(config: str | Path, output: str | Path, workers: int = 1, baseline: str | Path | None = None,
            resume: bool = False, show_progress: bool = False) -> CompareOutcome:
    """Scenarios x rollingstar.pipelines x seeds into ``output/`` (``rollingstar compare``); with ``baseline``, the
    outcome lists every gated metric that got worse."""
    return run_compare(find_config(config, "compare"), output, workers=workers, baseline=baseline,
                       show_progress=show_progress, resume=resume)


def diagnose(recording: str | Path, sim: str | Path | None = None, pipeline: str | Path | None = None,
             output: str | Path | None = None, seed: int = 0) -> dict:
    """Name the physics a simulation leaves out of a recording (``rollingstar diagnose --json``);
    ``sim`` defaults to the sensor model the recording declares, ``output`` is the report folder."""
    return run_diagnose(Path(recording), None if sim is None else find_config(sim, "scenario"),
                        None if pipeline is None else find_config(pipeline, "pipeline"),
                        None if output is None else Path(output), DiagnoseOptions(seed=seed))


def open_recording(path: str | Path) -> LogReader:
    """A reader over a rollingstar MCAP recording or run output (topics, metadata, frames, truth)."""
    return LogReader(path)
