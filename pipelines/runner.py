"""Run a pipeline over a recording: frame source -> stage pipeline -> sink.

Message time is the only clock: frames are replayed in log-time order and each frame carries the
gyro samples logged since the previous frame (:mod:`rollingstar.pipelines.source`); the stages run
over each frame in turn (:mod:`rollingstar.pipelines.stages`); the estimates are written to the
output log (:mod:`rollingstar.pipelines.sink`). The output log is self-contained for evaluation: it
holds the recording's scenario metadata and truth topics, the pipeline config, the estimates, and
what it was made from (metadata record ``run``: SHA-256 of the recording's content, the scenario
and the pipeline, :class:`~rollingstar.pipelines.checkpoint.RunIdentity`).

The output is written through :func:`rollingstar.outputs.safe_output`: never over an input, one
writer at a time, an earlier output replaced only when the run completes; a failed or interrupted
run leaves ``<output>.partial``, a killed one ``.<output name>.tmp-<pid>``. ``--resume`` continues
from there (:mod:`rollingstar.pipelines.resume`) with a checkpoint of the stages' state, saved
every ``checkpoint_every`` frames and once more after SIGINT (:mod:`rollingstar.pipelines.checkpoint`).
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from pydantic import ValidationError

from rollingstar.config import format_validation_error, to_yaml
from rollingstar.errors import ConfigError
from rollingstar.estimators.plugin import Plugin
from rollingstar.logs.errors import LogWriteError
from rollingstar.logs.writer import RECORDING, LogWriter
from rollingstar.outputs import PARTIAL_SUFFIX, check_not_an_input, safe_output
from rollingstar.pipelines.checkpoint import (
    DEFAULT_EVERY,
    CheckpointWriter,
    RunIdentity,
    RunState,
    check_checkpoint_dir,
)
from rollingstar.pipelines.config import PipelineConfig
from rollingstar.pipelines.frame_checks import FrameChecker
from rollingstar.pipelines.interrupt import Interrupted, StopFlag, stop_on_sigint
from rollingstar.pipelines.outcomes import Outcomes
from rollingstar.pipelines.registry import (
    UnknownPluginError,
    check_stage_order,
    check_stages_on_recording,
    get_plugin_class,
    stage_params,
)
from rollingstar.pipelines.resume import IDENTITY_RECORD, ResumePoint, find_resume_point, leftovers
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
    outcomes: Outcomes | None = None  # valid / invalid / flagged frames with their reasons


def build_stages(config: PipelineConfig, source: str = "<pipeline>") -> list[Plugin]:
    """Instantiate every stage; unknown kinds and bad params name the stage's key path, a stage that
    lacks what it needs the stage and the missing input (:func:`check_stage_order`)."""
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
    check_stage_order(stages, source, [stage.kind for stage in config.stages])
    return stages


def run_pipeline(recording: str | Path, pipeline: PipelineConfig, output: str | Path, pipeline_source: str = "<pipeline>",
                 show_progress: bool = True, max_frames: int | None = None, resume: bool = False,
                 checkpoint_every: int = DEFAULT_EVERY, inputs: Iterable[str | Path] = (),
                 with_images: bool = False) -> RunSummary:
    """Run ``pipeline`` over ``recording`` and write estimates (plus truth and metadata) to ``output``.

    ``output`` is refused when it is, or links to, the recording or one of ``inputs`` (the pipeline
    file). ``resume``: continue from the partial output an earlier run of the same recording,
    scenario and pipeline left (:mod:`rollingstar.pipelines.resume`), from the newest usable
    checkpoint (saved every ``checkpoint_every`` frames and on SIGINT; 0: none). On SIGINT the frame
    in hand is finished, the log finalised as ``<output>.partial`` and
    :class:`rollingstar.pipelines.interrupt.Interrupted` raised. ``with_images``: copy the recording's
    frames to the output's ``/camera/image`` too (an image-level recording), so that the output
    opens complete in Foxglove; a resume continues only an output written with the same choice.
    """
    output = Path(output)
    inputs = [recording, *inputs]
    check_not_an_input(output, inputs)
    check_checkpoint_dir(output)
    stages = build_stages(pipeline, pipeline_source)
    rec = open_recording(recording)
    check_stages_on_recording(stages, rec.provides, str(recording), pipeline_source, [s.kind for s in pipeline.stages])
    setup_stages(stages, rec.context, pipeline_source, recording)
    pipeline_yaml = to_yaml(pipeline)
    identity = RunIdentity.of(recording, rec.scenario.get("yaml", ""), pipeline_yaml, with_images)
    metadata = {"scenario": rec.scenario, "pipeline": {"yaml": pipeline_yaml, "source": str(pipeline_source)},
                IDENTITY_RECORD: identity.as_metadata()}
    tmp = None
    try:
        with safe_output(output, inputs, replaces=RECORDING) as tmp:
            start = _Start.find(rec, stages, identity, output, resume, checkpoint_every if tmp != output else 0)
            summary = _run(rec, pipeline.name, start, tmp, metadata, output, max_frames, show_progress,
                           pipeline.max_false_match_prob, with_images)
            _remove_leftovers(output, tmp, start)
    except LogWriteError as exc:  # it names the temporary file, kept as <output>.partial
        if tmp is None or tmp == output:
            raise
        raise LogWriteError(str(exc).replace(str(tmp), str(_partial(output)))) from None
    return summary


def _partial(output: Path) -> Path:
    return output.with_name(output.name + PARTIAL_SUFFIX)


def _run(rec: Recording, name: str, start: _Start, target: Path, metadata: dict, output: Path,
         max_frames: int | None, show_progress: bool, max_false_match_prob: float, with_images: bool) -> RunSummary:
    """The run itself, into ``target``: copy what the resume point holds, then stream the frames."""
    state = start.state
    run = StagePipeline(state.stages, rec.holds_centroids, state.stage_seconds, rec.context, max_false_match_prob)
    source = FrameSource(rec, state.checker, run.needs_truth, skip=state.frames_read, delivered=state.n_frames)
    with stop_on_sigint() as stop, LogWriter(target, kind="run", metadata=metadata, digest=True) as writer, \
            progress_bar(f"run {name}", rec.n_frame_messages, show_progress) as advance:
        start.point.copy_into(writer)
        sink = EstimateSink(writer, state.counts, with_images)
        checkpoints = _Checkpoints(start.saver, state.identity, source, run, sink)
        _stream(source, run, sink, checkpoints, max_frames, stop, advance)
    if stop.requested:
        checkpoints.save()  # a resume continues right after the last frame written
        raise Interrupted(f"interrupted: {output} was not written (an earlier one is kept as it was); "
                          f"{_partial(output)} holds the {source.delivered} frame(s) processed before SIGINT; "
                          f"continue with `rollingstar run ... -o {output} --resume`")
    counts = sink.counts
    return RunSummary(str(output), source.delivered, counts.estimates, counts.valid_estimates, counts.flagged,
                      run.stage_seconds, source.skip, counts)


def _remove_leftovers(output: Path, tmp: Path, start: _Start) -> None:
    """The run completed: what earlier attempts left (the checkpoints, killed runs' temporary files,
    the partial outputs of this recording, scenario and pipeline a resume found) describes nothing
    the user still needs."""
    start.saver.remove()
    partial = _partial(output)
    for path in leftovers(output):
        if path != tmp and (path != partial or path in start.point.partials):
            path.unlink(missing_ok=True)


def _stream(source: FrameSource, run: StagePipeline, sink: EstimateSink, checkpoints: _Checkpoints,
            max_frames: int | None, stop: StopFlag, advance) -> None:
    """Every frame from the source through the stages into the sink; then the frames the stages
    still hold, unless SIGINT cut the run (they would be estimates of a cut recording, not the ones
    a full run writes)."""
    for item in source.frames(max_frames, stop):
        sink.write_truth(item.truth)
        if item.frame is not None:
            sink.write_source(item.frame)
            sink.write(run.process(item.frame))
            checkpoints.frame_done()
        if not item.duplicate:
            advance()
    if not stop.requested:
        sink.write(run.finish())


@dataclass(frozen=True)
class _Start:
    """Where a run starts: the state to continue from, what it copies from a partial output (a
    resume) and the checkpoint writer."""

    state: RunState
    point: ResumePoint
    saver: CheckpointWriter

    @classmethod
    def find(cls, rec: Recording, stages: list[Plugin], identity: RunIdentity, output: Path, resume: bool,
             checkpoint_every: int) -> _Start:
        """A fresh run starts from the first frame with ``stages`` (and removes an earlier run's
        checkpoints); a resumed one from the newest checkpoint whose messages the newest partial
        output holds, else from the first frame."""
        point = find_resume_point(output, identity, rec.context) if resume else ResumePoint()
        state = point.state
        saver = CheckpointWriter(output, rec.context, checkpoint_every, keep=state.frames_read if state else None)
        if point.partial is None:
            saver.remove()  # checkpoints without their partial output describe nothing this run can use
        if state is None:
            state = RunState(identity, 0, 0, stages, FrameChecker(rec.path, rec.frame_topic, rec.context),
                             new_counts(), zero_stage_seconds(stages))
        return cls(state, point, saver)


class _Checkpoints:
    """Saves the run's state every ``saver.every`` frames read: where the source is, the stages,
    the frame checker, the counters and the messages written so far (count and digest)."""

    def __init__(self, saver: CheckpointWriter, identity: RunIdentity, source: FrameSource, run: StagePipeline,
                 sink: EstimateSink) -> None:
        self.saver = saver
        self.identity = identity
        self.source = source
        self.run = run
        self.sink = sink

    def frame_done(self) -> None:
        """After a frame went through the stages and its output to the sink: save when due."""
        if self.saver.due(self.source.frames_read):
            self.save()

    def save(self) -> None:
        source, digest = self.source, self.sink.writer.digest
        self.saver.save(RunState(self.identity, source.frames_read, source.delivered, self.run.stages, source.checker,
                                 self.sink.counts, self.run.stage_seconds, digest.count, digest.hexdigest()))
