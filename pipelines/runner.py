"""Run a pipeline over a recording: read in log-time order, feed the stages, write the outputs.

Message time is the only clock: frames are replayed in log-time order and each frame carries the
gyro samples logged since the previous frame. The output log is self-contained for evaluation: it
holds the recording's scenario metadata and truth topics, the pipeline config, and the estimates.
"""
from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rollingstar.config import format_validation_error, to_yaml
from rollingstar.errors import ConfigError, PipelineError, UserError
from rollingstar.estimators.data import (
    FrameData,
    GyroSamples,
    SensorContext,
    StarTable,
    TruthSamples,
)
from rollingstar.estimators.plugin import Plugin
from rollingstar.logs.errors import LogFormatError
from rollingstar.logs.reader import LogReader
from rollingstar.logs.records import AttitudeEstimate as AttitudeRecord
from rollingstar.logs.records import FrameStatus, arrays_to_stars, stars_to_arrays
from rollingstar.logs.records import RateEstimate as RateRecord
from rollingstar.logs.replay import image_from_raw, iter_frames
from rollingstar.logs.writer import LogWriter
from rollingstar.pipelines.checkpoint import (
    DEFAULT_EVERY,
    CheckpointWriter,
    RunState,
    add_index,
    load_checkpoint,
    run_key,
)
from rollingstar.pipelines.config import PipelineConfig
from rollingstar.pipelines.frame_checks import FrameChecker
from rollingstar.pipelines.interrupt import Interrupted, stop_on_sigint
from rollingstar.pipelines.registry import UnknownPluginError, get_plugin_class
from rollingstar.pipelines.resume import Partial, load_partial, temp_path
from rollingstar.pipelines.simulate import (
    TOPIC_CENTROIDS,
    TOPIC_GYRO,
    TOPIC_IMAGE,
    TOPIC_TRUTH_ATTITUDE,
    TOPIC_TRUTH_STARS,
)
from rollingstar.progress import progress_bar
from rollingstar.sensors.conventions import quat_to_fields
from rollingstar.sensors.scenario import scenario_from_yaml

TOPIC_EST_STARS = "/estimate/stars"
TOPIC_EST_SPOTS = "/estimate/spots"
TOPIC_EST_ATTITUDE = "/estimate/attitude"
TOPIC_EST_POSE = "/estimate/pose"
TOPIC_EST_RATE = "/estimate/rate"
TOPIC_EST_FRAME = "/estimate/frame"
TRUTH_TOPICS = (TOPIC_TRUTH_ATTITUDE, TOPIC_TRUTH_STARS)


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
    from pydantic import ValidationError

    stages = []
    for i, stage in enumerate(config.stages):
        try:
            cls = get_plugin_class(stage.kind)
        except UnknownPluginError as exc:
            raise ConfigError(f"{source}: stages[{i}].kind: {exc}") from None
        try:
            stages.append(cls(**stage.params))
        except ValidationError as err:
            raise ConfigError(format_validation_error(source, err, prefix=("stages", i, "params"))) from None
    return stages


def _stars_from_record(data: dict, topic: str, frame_index: int) -> tuple[StarTable, int]:
    cols = stars_to_arrays(data)
    n = len(cols["x"])
    keep = np.isfinite(cols["x"]) & np.isfinite(cols["y"])
    fields = {k: v for k, v in cols.items() if k in StarTable.__dataclass_fields__ and k not in ("x", "y", "t_ns", "row_time_ns")}
    table = StarTable.build(cols["x"], cols["y"], cols["t_ns"], cols.get("row_time_ns"), **fields)
    return table.take(keep), int(n - keep.sum())


def _gyro_from_messages(messages) -> GyroSamples:
    if not messages:
        return GyroSamples.empty()
    t = np.concatenate([np.asarray(m.data["t_ns"], dtype=np.int64) for m in messages])
    w = np.concatenate([np.column_stack([m.data["x"], m.data["y"], m.data["z"]]) for m in messages]).astype(float)
    return GyroSamples(t, w)


def _truth_from_messages(messages) -> TruthSamples | None:
    if not messages:
        return None
    t = np.concatenate([np.asarray(m.data["t_ns"], dtype=np.int64) for m in messages])
    q = np.concatenate([np.column_stack([m.data[k] for k in ("qx", "qy", "qz", "qw")]) for m in messages]).astype(float)
    w = np.concatenate([np.column_stack([m.data[k] for k in ("wx", "wy", "wz")]) for m in messages]).astype(float)
    return TruthSamples(t, q, w)


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
    reader = LogReader(recording)
    meta = reader.metadata()
    if "scenario" not in meta or "yaml" not in meta["scenario"]:
        raise UserError(f"{recording}: the recording declares no sensor model (metadata record 'scenario' with key 'yaml'); "
                        "import real data with `rollingstar import` so that it does")
    scenario = scenario_from_yaml(meta["scenario"]["yaml"], f"{recording} (metadata 'scenario')")
    context = SensorContext.from_scenario(scenario)
    info = reader.summary_info()
    topics = set(info.topics) if hasattr(info, "topics") else set(info)
    frame_topic = TOPIC_IMAGE if TOPIC_IMAGE in topics else TOPIC_CENTROIDS
    reader.require_topics([frame_topic])
    for i, stage in enumerate(stages):
        try:
            stage.setup(context)
        except ValueError as exc:  # a stage that cannot work with this recording says why; no traceback
            raise PipelineError(f"{pipeline_source}: stages[{i}] ({stage.name!r}) cannot run on {recording}: {exc}") from exc
    skip_centroiders = frame_topic == TOPIC_CENTROIDS
    # Oracle stages (e.g. request with rate_source truth) declare needs_truth; only they get truth.
    pass_truth = any(getattr(stage, "needs_truth", False) for stage in stages)
    total = None
    counts = getattr(info, "message_counts", None)
    if isinstance(counts, dict):
        total = counts.get(frame_topic)
    n_frames = n_att = n_valid = n_flagged = 0
    stage_seconds = {f"{i}:{s.name}": 0.0 for i, s in enumerate(stages)}
    metadata = {"scenario": meta["scenario"], "pipeline": {"yaml": to_yaml(pipeline), "source": str(pipeline_source)}}
    checker = FrameChecker(recording, frame_topic, context)  # sizes, bit depth, time order, gaps
    output = Path(output)
    # --resume: keep the partial output's complete frames; continue from a checkpoint or from the start (pipelines/resume.py)
    partial = load_partial(output, metadata) if resume else Partial()
    target = temp_path(output) if resume else output
    counts_ = {"att": 0, "valid": 0, "flagged": 0}
    key = run_key(Path(recording), metadata)
    state = load_checkpoint(output, key, partial.done, context) if resume else None
    saver = CheckpointWriter(output, context, checkpoint_every, keep=state.frames_read if state else None)
    if not resume:
        saver.remove()  # a fresh run: an earlier run's checkpoints do not describe this output
    skip, frames_read, written = 0, 0, []
    if state is not None:  # continue after the checkpoint's last frame (pipelines/checkpoint.py)
        stages, checker, n_frames, skip = state.stages, state.checker, state.n_frames, state.frames_read
        counts_, stage_seconds, written = dict(state.counts), dict(state.stage_seconds), list(state.written)

    def emit(out: FrameData) -> None:
        if out.index not in partial.done:
            _write_frame(writer, out)
        add_index(written, out.index)
        counts_["att"] += len(out.attitudes)
        counts_["valid"] += sum(a.valid for a in out.attitudes)
        counts_["flagged"] += bool(out.flags)

    def save_state() -> None:
        saver.save(RunState(key, frames_read, n_frames, stages, checker, counts_, stage_seconds, written))

    with stop_on_sigint() as stop, LogWriter(target, kind="run", metadata=metadata) as writer, \
            progress_bar(f"run {pipeline.name}", total, show_progress) as advance:
        for m in partial.copy:
            writer.write_message(m)
        for group in iter_frames(reader, frame_topic, [TOPIC_GYRO, *TRUTH_TOPICS], tolerate_bad_side=True):
            if (max_frames is not None and n_frames >= max_frames) or stop.requested:
                break
            frames_read += 1
            for topic in TRUTH_TOPICS:
                for m in group.side.get(topic, []):
                    if (topic, m.log_time_ns) not in partial.truth_keys:
                        writer.write_json(topic, m.data, m.log_time_ns)
            if frames_read <= skip:  # processed before the checkpoint
                advance()
                continue
            msg = group.frame
            try:
                frame = _frame_from_message(msg, frame_topic, n_frames)
            except LogFormatError as exc:  # a record that cannot be a frame: name the file and frame
                raise LogFormatError(f"{recording}: {frame_topic} frame {n_frames}: {exc}") from None
            frame = checker.check(frame, msg.data)
            if frame is None:  # an exact duplicate of the previous frame (warned)
                continue
            frame = frame.evolve(gyro=_gyro_from_messages(group.side.get(TOPIC_GYRO, [])))
            for topic in sorted({t for t, _ in group.dropped}):  # undecodable side messages were skipped (warned)
                frame = frame.flagged(f"side_message_invalid:{topic}")
            if pass_truth:
                frame = frame.evolve(truth=_truth_from_messages(group.side.get(TOPIC_TRUTH_ATTITUDE, [])))
            n_frames += 1
            for out in _run_stages(stages, frame, skip_centroiders, stage_seconds):
                emit(out)
            advance()
            if saver.due(frames_read):
                save_state()
        # Frames still held back (smoothers) flow on through the later stages, stage by stage.
        # Not after SIGINT: they would be estimates of a cut recording, not the ones a full run writes.
        for i, stage in enumerate(stages if not stop.requested else []):
            start = time.perf_counter()
            try:
                held_frames = stage.finish()
            except UserError:
                raise
            except Exception as exc:
                raise PipelineError(f"stage {stage.name!r} ({stage.role}) failed at the end of the recording (finish): "
                                    f"{type(exc).__name__}: {exc}") from exc
            stage_seconds[f"{i}:{stage.name}"] += time.perf_counter() - start
            for held in held_frames:
                for out in _run_stages(stages, held, skip_centroiders, stage_seconds, first=i + 1, priors=False):
                    emit(out)
    if resume:
        os.replace(target, output)
    if stop.requested:
        save_state()  # the state after the last frame written: a resume continues right there
    else:
        saver.remove()
    n_att, n_valid, n_flagged = counts_["att"], counts_["valid"], counts_["flagged"]
    if stop.requested:
        raise Interrupted(f"interrupted: {output} is finalised and holds the {n_frames} frame(s) processed before "
                          f"SIGINT; continue with `rollingstar run ... -o {output} --resume`")
    return RunSummary(str(output), n_frames, n_att, n_valid, n_flagged, stage_seconds, skip)


def _frame_from_message(msg, frame_topic: str, ordinal: int) -> FrameData:
    if frame_topic == TOPIC_IMAGE:
        image = image_from_raw(msg)
        return FrameData(index=ordinal, t0_ns=int(msg.log_time_ns), image=image)
    index = int(msg.data.get("frame", ordinal))
    stars, dropped = _stars_from_record(msg.data, frame_topic, index)
    frame = FrameData(index=index, t0_ns=int(msg.data.get("t0_ns", msg.log_time_ns)), stars=stars)
    if dropped:
        warnings.warn(f"{frame_topic} frame {index}: {dropped} centroid(s) with NaN/inf position dropped")
        frame = frame.flagged(f"non_finite_input:{dropped}")
    return frame


def _identified_in_recording(frame: FrameData) -> bool:
    """True when a centroid recording's stars all carry a catalogue id and direction (``import corr``)."""
    stars = frame.stars
    return (stars is not None and stars.n > 0 and bool(stars.identified.all())
            and bool(np.isfinite(stars.ref_icrs).all()))


def _run_stages(stages: list[Plugin], frame: FrameData, skip_centroiders: bool,
                stage_seconds: dict[str, float], first: int = 0, skip_identifiers: bool | None = None,
                priors: bool = True) -> list[FrameData]:
    """Frames to write after passing ``frame`` through ``stages[first:]``.

    Identifier stages are skipped on frames of a centroid recording whose stars are already all
    identified (``skip_identifiers`` None: decided from ``frame`` as it enters).

    Normally the one processed frame. A stage with ``defers_output`` (a smoother) holds frames
    back: its direct output is provisional (a causal estimate) and is not written, but it feeds
    the stages' ``update_prior`` hooks (e.g. the tracking identifier's prior for the next frame);
    the frames the stage releases (``release()``, and ``finish()`` at the end of the recording)
    continue through the later stages and are written without feeding the priors again
    (``priors`` False: they are late).
    """
    if skip_identifiers is None:
        skip_identifiers = skip_centroiders and _identified_in_recording(frame)
    for i in range(first, len(stages)):
        stage = stages[i]
        if (skip_centroiders and stage.role == "centroider") or (skip_identifiers and stage.role == "identifier"):
            continue
        try:
            start = time.perf_counter()
            frame = stage.process(frame)
            released = stage.release() if stage.defers_output else None
            stage_seconds[f"{i}:{stage.name}"] += time.perf_counter() - start
        except UserError:
            raise
        except Exception as exc:  # a plugin that raises: name it and the frame, keep what was written
            raise PipelineError(f"stage {stage.name!r} ({stage.role}) failed on frame {frame.index} "
                                f"(t0 = {frame.t0_ns} ns): {type(exc).__name__}: {exc}") from exc
        if released is not None:
            if priors:
                _update_priors(stages, frame)
            return [out for f in released for out in _run_stages(stages, f, skip_centroiders, stage_seconds, i + 1,
                                                                                      skip_identifiers, priors=False)]
    if priors:
        _update_priors(stages, frame)
    return [_finish_frame(frame)]


def _update_priors(stages: list[Plugin], frame: FrameData) -> None:
    for stage in stages:
        update = getattr(stage, "update_prior", None)
        if update is not None:
            update(frame)


def _finish_frame(frame: FrameData) -> FrameData:
    """Frame flags that need every stage's output.

    - ``too_few_stars``: fewer than 2 identified stars and no valid attitude;
    - ``saturated_stars:N``: N detections (identified or not) reached the saturation level;
    - ``attitude_degraded:all_stars_saturated``: a valid attitude made from saturated stars only
      (it is kept: the centroider's ``sigma_px`` of clipped spots, and so the covariance, is inflated
      for them, but the user should know the frame is not a normal one).
    """
    if frame.stars is not None and frame.stars.identified.sum() < 2 and not any(a.valid for a in frame.attitudes):
        frame = frame.flagged("too_few_stars")
    if frame.stars is not None:
        n_sat = int(frame.stars.saturated.sum()) + (int(frame.unmatched.saturated.sum()) if frame.unmatched is not None else 0)
        if n_sat:
            frame = frame.flagged(f"saturated_stars:{n_sat}")
        used = frame.stars.identified
        if used.any() and frame.stars.saturated[used].all() and any(a.valid for a in frame.attitudes):
            frame = frame.flagged("attitude_degraded:all_stars_saturated")
    return frame


def _write_frame(writer: LogWriter, frame: FrameData) -> None:
    t0 = int(frame.t0_ns)
    stars = frame.stars if frame.stars is not None else StarTable.empty()
    writer.write_json(TOPIC_EST_STARS, arrays_to_stars(
        frame.index, t0, x=stars.x, y=stars.y, t_ns=stars.t_ns, row_time_ns=stars.row_time_ns, flux=stars.flux,
        peak=stars.peak, npix=stars.npix, saturated=stars.saturated, snr=stars.snr, sigma_px=stars.sigma_px,
        vx=stars.vx, vy=stars.vy, catalog_id=stars.catalog_id, ref_icrs=stars.ref_icrs), t0)
    if stars.n:
        labels = [str(int(c)) if c >= 0 else "?" for c in stars.catalog_id]
        writer.write_annotations(TOPIC_EST_SPOTS, t0, stars.x, stars.y, labels)
    for est in frame.attitudes:
        cov = None if est.covariance_rad2 is None else np.asarray(est.covariance_rad2, dtype=float).reshape(-1).tolist()
        writer.write_json(TOPIC_EST_ATTITUDE, AttitudeRecord(
            frame=frame.index, t_ns=int(est.t_ns), q=quat_to_fields(est.q_xyzw) if est.valid else None, valid=bool(est.valid),
            reason=est.reason, n_stars=int(est.n_stars), covariance_rad2=cov,
            gyro_bias_rad_s=None if est.gyro_bias_rad_s is None else [float(v) for v in np.ravel(est.gyro_bias_rad_s)]),
            int(est.t_ns))
        if est.valid:
            writer.write_pose(TOPIC_EST_POSE, int(est.t_ns), est.q_xyzw)
    if frame.rate is not None:
        r = frame.rate
        writer.write_json(TOPIC_EST_RATE, RateRecord(
            frame=frame.index, t_ns=int(r.t_ns),
            omega=dict(zip("xyz", map(float, r.omega_rad_s))) if r.valid else None, valid=bool(r.valid), reason=r.reason,
            covariance=None if r.covariance is None else np.asarray(r.covariance, dtype=float).reshape(-1).tolist(),
            iterations=r.iterations), int(r.t_ns))
    n_det = (stars.n + (frame.unmatched.n if frame.unmatched is not None else 0))
    writer.write_json(TOPIC_EST_FRAME, FrameStatus(frame=frame.index, t0_ns=t0, flags=list(frame.flags),
                                                   n_detected=int(n_det), n_identified=int(stars.identified.sum())), t0)
