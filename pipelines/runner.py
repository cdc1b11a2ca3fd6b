"""Run a pipeline over a recording: read in log-time order, feed the stages, write the outputs.

Message time is the only clock: frames are replayed in log-time order and each frame carries the
gyro samples logged since the previous frame. The output log is self-contained for evaluation: it
holds the recording's scenario metadata and truth topics, the pipeline config, and the estimates.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimators.data import FrameData, GyroSamples, StarTable, TruthSamples
from estimators.plugin import Plugin
from logs.reader import LogReader
from logs.records import AttitudeEstimate as AttitudeRecord
from logs.records import FrameStatus, RateEstimate as RateRecord, arrays_to_stars, stars_to_arrays
from logs.replay import iter_frames, image_from_raw
from logs.writer import LogWriter
from pipelines import build
from pipelines.config import PipelineConfig, format_validation_error, scenario_from_yaml, to_yaml
from pipelines.errors import ConfigError, PipelineError, UserError
from pipelines.progress import progress_bar
from pipelines.registry import UnknownPluginError, get_plugin_class
from pipelines.simulate import TOPIC_CENTROIDS, TOPIC_GYRO, TOPIC_IMAGE, TOPIC_TRUTH_ATTITUDE, TOPIC_TRUTH_STARS
from sensors.conventions import quat_to_fields

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
                 show_progress: bool = True, max_frames: int | None = None) -> RunSummary:
    """Run ``pipeline`` over ``recording`` and write estimates (plus truth and metadata) to ``output``."""
    stages = build_stages(pipeline, pipeline_source)
    reader = LogReader(recording)
    meta = reader.metadata()
    if "scenario" not in meta or "yaml" not in meta["scenario"]:
        raise UserError(f"{recording}: the recording declares no sensor model (metadata record 'scenario' with key 'yaml'); "
                        "import real data with `rollingstar import` so that it does")
    scenario = scenario_from_yaml(meta["scenario"]["yaml"], f"{recording} (metadata 'scenario')")
    context = build.build_context(scenario)
    info = reader.summary_info()
    topics = set(info.topics) if hasattr(info, "topics") else set(info)
    frame_topic = TOPIC_IMAGE if TOPIC_IMAGE in topics else TOPIC_CENTROIDS
    reader.require_topics([frame_topic])
    for stage in stages:
        stage.setup(context)
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
    with LogWriter(output, kind="run", metadata=metadata) as writer, \
            progress_bar(f"run {pipeline.name}", total, show_progress) as advance:
        for group in iter_frames(reader, frame_topic, [TOPIC_GYRO, *TRUTH_TOPICS]):
            if max_frames is not None and n_frames >= max_frames:
                break
            for topic in TRUTH_TOPICS:
                for m in group.side.get(topic, []):
                    writer.write_json(topic, m.data, m.log_time_ns)
            msg = group.frame
            frame = _frame_from_message(msg, frame_topic, n_frames)
            frame = frame.evolve(gyro=_gyro_from_messages(group.side.get(TOPIC_GYRO, [])))
            if pass_truth:
                frame = frame.evolve(truth=_truth_from_messages(group.side.get(TOPIC_TRUTH_ATTITUDE, [])))
            frame = _run_stages(stages, frame, skip_centroiders, stage_seconds)
            _write_frame(writer, frame)
            n_frames += 1
            n_att += len(frame.attitudes)
            n_valid += sum(a.valid for a in frame.attitudes)
            n_flagged += bool(frame.flags)
            advance()
        for stage in stages:
            for frame in stage.finish():
                _write_frame(writer, frame)
    return RunSummary(str(output), n_frames, n_att, n_valid, n_flagged, stage_seconds)


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


def _run_stages(stages: list[Plugin], frame: FrameData, skip_centroiders: bool,
                stage_seconds: dict[str, float]) -> FrameData:
    for i, stage in enumerate(stages):
        if skip_centroiders and stage.role == "centroider":
            continue
        try:
            start = time.perf_counter()
            frame = stage.process(frame)
            stage_seconds[f"{i}:{stage.name}"] += time.perf_counter() - start
        except UserError:
            raise
        except Exception as exc:  # a plugin that raises: name it and the frame, keep what was written
            raise PipelineError(f"stage {stage.name!r} ({stage.role}) failed on frame {frame.index} "
                                f"(t0 = {frame.t0_ns} ns): {type(exc).__name__}: {exc}") from exc
    for stage in stages:
        update = getattr(stage, "update_prior", None)
        if update is not None:
            update(frame)
    if frame.stars is not None and frame.stars.identified.sum() < 2 and not any(a.valid for a in frame.attitudes):
        frame = frame.flagged("too_few_stars")
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
            reason=est.reason, n_stars=int(est.n_stars), covariance_rad2=cov), int(est.t_ns))
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
