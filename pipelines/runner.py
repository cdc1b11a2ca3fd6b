"""Run a pipeline over a recording: frame source -> stage pipeline -> sink.

Message time is the only clock: frames are replayed in log-time order and each frame carries the
gyro samples logged since the previous frame (:mod:`rollingstar.pipelines.source`); the stages run
over each frame in turn (:mod:`rollingstar.pipelines.stages`); the estimates are written to the
output log (:mod:`rollingstar.pipelines.sink`). The output log is self-contained for evaluation: it
holds the recording's scenario metadata and truth topics, the pipeline config, and the estimates.

``--resume`` wraps both ends: the source skips the frames a checkpoint already holds, and the sink
neither writes again what the partial output holds complete; a checkpoint is saved every
``checkpoint_every`` frames and once more after SIGINT (:mod:`rollingstar.pipelines.checkpoint`,
:mod:`rollingstar.pipelines.resume`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from pydantic import ValidationError

from rollingstar.config import format_validation_error, to_yaml
from rollingstar.errors import ConfigError
from rollingstar.estimators.plugin import Plugin
from rollingstar.logs.writer import LogWriter
from rollingstar.pipelines.checkpoint import (
    DEFAULT_EVERY,
    CheckpointWriter,
    RunState,
    load_checkpoint,
    run_key,
)
from rollingstar.pipelines.config import PipelineConfig
from rollingstar.pipelines.frame_checks import FrameChecker
from rollingstar.pipelines.interrupt import Interrupted, StopFlag, stop_on_sigint
from rollingstar.pipelines.registry import UnknownPluginError, get_plugin_class, stage_params
from rollingstar.pipelines.resume import Partial, load_partial, temp_path
from rollingstar.pipelines.sink import EstimateSink, new_counts
from rollingstar.pipelines.source import FrameSource, Recording, open_recording
from rollingstar.pipelines.stages import StagePipeline, setup_stages, zero_stage_seconds
from rollingstar.progress import progress_bar


@dataclass(frozen=True)
class RunSummary:
    output: str
    frames: int
    attitude_estimates: int
    valid_estimates: int
    flagged_frames: int
    stage_seconds: dict[str, float]
    resumed_after_frames: int = 0  # --resume: frames restored from a checkpoint instead of re-run


def build_stages(config: PipelineConfig, source: str = "<pipeline>") -> list[Plugin]:
    """Instantiate every stage; unknown kinds and bad params name the stage's key path."""
    stages = []
    for i, stage in enumerate(config.stages):
        try:
            cls = get_plugin_class(stage.kind)
        except UnknownPluginError as exc:
            raise ConfigError(f"{source}: stages[{i}].kind: {exc}") from None
        try:
            stages.append(cls(**stage_params(stage.kind, stage.params)))
        except ValidationError as err:
            raise ConfigError(format_validation_error(source, err, prefix=("stages", i, "params"))) from None
    return stages


def run_pipeline(recording: str | Path, pipeline: PipelineConfig, output: str | Path, pipeline_source: str = "<pipeline>",
                 show_progress: bool = True, max_frames: int | None = None, resume: bool = False,
                 checkpoint_every: int = DEFAULT_EVERY) -> RunSummary:
    """Run ``pipeline`` over ``recording`` and write estimates (plus truth and metadata) to ``output``.

    ``resume``: continue from a partial ``output`` (see :mod:`rollingstar.pipelines.resume`), from the newest
    usable checkpoint if there is one (:mod:`rollingstar.pipelines.checkpoint`, saved every
    ``checkpoint_every`` frames and on SIGINT; 0: none). On SIGINT the frame in hand is finished,
    the log finalised and :class:`rollingstar.pipelines.interrupt.Interrupted` raised.
    """
    stages = build_stages(pipeline, pipeline_source)
    rec = open_recording(recording)
    setup_stages(stages, rec.context, pipeline_source, recording)
    metadata = {"scenario": rec.scenario, "pipeline": {"yaml": to_yaml(pipeline), "source": str(pipeline_source)}}
    output = Path(output)
    start = _Start.find(rec, stages, metadata, output, resume, checkpoint_every)
    state = start.state
    run = StagePipeline(state.stages, rec.holds_centroids, state.stage_seconds)
    source = FrameSource(rec, state.checker, run.needs_truth, skip=state.frames_read, delivered=state.n_frames)
    target = temp_path(output) if resume else output
    with stop_on_sigint() as stop, LogWriter(target, kind="run", metadata=metadata) as writer, \
            progress_bar(f"run {pipeline.name}", rec.n_frame_messages, show_progress) as advance:
        sink = EstimateSink(writer, start.partial, state.counts, state.written)
        checkpoints = _Checkpoints(start.saver, state.key, source, run, sink)
        _stream(source, run, sink, checkpoints, max_frames, stop, advance)
    if resume:
        os.replace(target, output)
    if stop.requested:
        checkpoints.save()  # a resume continues right after the last frame written
        raise Interrupted(f"interrupted: {output} is finalised and holds the {source.delivered} frame(s) processed "
                          f"before SIGINT; continue with `rollingstar run ... -o {output} --resume`")
    start.saver.remove()
    counts = sink.counts
    return RunSummary(str(output), source.delivered, counts["att"], counts["valid"], counts["flagged"],
                      run.stage_seconds, source.skip)


def _stream(source: FrameSource, run: StagePipeline, sink: EstimateSink, checkpoints: _Checkpoints,
            max_frames: int | None, stop: StopFlag, advance) -> None:
    """Every frame from the source through the stages into the sink; then the frames the stages
    still hold, unless SIGINT cut the run (they would be estimates of a cut recording, not the ones
    a full run writes)."""
    sink.copy_kept()
    for item in source.frames(max_frames, stop):
        sink.write_truth(item.truth)
        if item.frame is not None:
            sink.write(run.process(item.frame))
            checkpoints.frame_done()
        if not item.duplicate:
            advance()
    if not stop.requested:
        sink.write(run.finish())


@dataclass(frozen=True)
class _Start:
    """Where a run starts: what the partial output holds (resume), the state to continue from, the
    checkpoint writer."""

    partial: Partial
    state: RunState
    saver: CheckpointWriter

    @classmethod
    def find(cls, rec: Recording, stages: list[Plugin], metadata: dict, output: Path, resume: bool,
             checkpoint_every: int) -> _Start:
        """A fresh run starts from the first frame with ``stages`` (and removes an earlier run's
        checkpoints); a resumed one keeps the partial output's complete frames and continues from
        the newest usable checkpoint, else from the first frame."""
        partial = load_partial(output, metadata) if resume else Partial()
        key = run_key(Path(rec.path), metadata)
        state = load_checkpoint(output, key, partial.done, rec.context) if resume else None
        saver = CheckpointWriter(output, rec.context, checkpoint_every, keep=state.frames_read if state else None)
        if not resume:
            saver.remove()  # an earlier run's checkpoints do not describe this output
        if state is None:
            state = RunState(key, 0, 0, stages, FrameChecker(rec.path, rec.frame_topic, rec.context), new_counts(),
                             zero_stage_seconds(stages))
        return cls(partial, state, saver)


class _Checkpoints:
    """Saves the run's state every ``saver.every`` frames read: where the source is, the stages,
    the frame checker and what the sink wrote."""

    def __init__(self, saver: CheckpointWriter, key: str, source: FrameSource, run: StagePipeline,
                 sink: EstimateSink) -> None:
        self.saver = saver
        self.key = key
        self.source = source
        self.run = run
        self.sink = sink

    def frame_done(self) -> None:
        """After a frame went through the stages and its output to the sink: save when due."""
        if self.saver.due(self.source.frames_read):
            self.save()

    def save(self) -> None:
        source, sink = self.source, self.sink
        self.saver.save(RunState(self.key, source.frames_read, source.delivered, self.run.stages, source.checker,
                                 sink.counts, self.run.stage_seconds, sink.written))
