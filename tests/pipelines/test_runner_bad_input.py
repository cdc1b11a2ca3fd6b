"""The runner on degraded input: truncated logs, frames with too few stars, NaN centroids."""
import warnings

import numpy as np
import pytest

from rollingstar.logs.errors import TruncatedLogWarning
from rollingstar.logs.reader import LogReader
from rollingstar.logs.writer import LogWriter
from rollingstar.pipelines.config import PipelineConfig
from rollingstar.pipelines.evaluate import evaluate_log
from rollingstar.pipelines.runner import run_pipeline

PIPELINE = PipelineConfig(stages=[{"kind": "tracking"}, {"kind": "none"}, {"kind": "quest"}])


def _copy_with_edits(src, dst, edit_centroids=lambda d: d, chunk_size=262144):
    """Rewrite a recording, passing every /camera/centroids record through ``edit_centroids``."""
    reader = LogReader(src)
    meta = reader.metadata()
    with LogWriter(dst, kind="simulation", metadata={k: v for k, v in meta.items() if k != "rollingstar"},
                   chunk_size=chunk_size) as w:
        for m in reader.messages():
            data = edit_centroids(m.data) if m.topic == "/camera/centroids" else m.data
            w.write_json(m.topic, data, m.log_time_ns)


def test_truncated_recording_runs_on_every_complete_message(tmp_path, small_recording):
    chunked = tmp_path / "chunked.mcap"
    _copy_with_edits(small_recording, chunked, chunk_size=16384)  # several chunks, as a long recording has
    cut = tmp_path / "cut.mcap"
    data = chunked.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    with pytest.warns(TruncatedLogWarning):
        summary = run_pipeline(cut, PIPELINE, tmp_path / "out.mcap", show_progress=False)
    assert 0 < summary.frames < 20
    assert summary.valid_estimates == summary.frames


def test_frames_with_fewer_than_two_stars_are_flagged_and_the_run_continues(tmp_path, small_recording):
    def keep_one_star_in_frame_5(d):
        if d["frame"] != 5:
            return d
        return {k: (v[:1] if isinstance(v, list) else v) for k, v in d.items()}

    rec = tmp_path / "sparse.mcap"
    _copy_with_edits(small_recording, rec, keep_one_star_in_frame_5)
    out = tmp_path / "out.mcap"
    summary = run_pipeline(rec, PIPELINE, out, show_progress=False)
    assert summary.frames == 20 and summary.attitude_estimates == 20 and summary.valid_estimates == 19
    est = [m.data for m in LogReader(out).messages("/estimate/attitude")]
    bad = [e for e in est if not e["valid"]]
    assert len(bad) == 1 and bad[0]["frame"] == 5 and bad[0]["q"] is None and bad[0]["reason"]
    flags = {m.data["frame"]: m.data["flags"] for m in LogReader(out).messages("/estimate/frame")}
    assert flags[5] and not flags[6]
    metrics = evaluate_log(out)
    assert metrics["attitude_updates"] == 19 and metrics["invalid_attitude_estimates"] == 1


def test_nan_centroids_are_dropped_and_flagged_not_propagated(tmp_path, small_recording):
    def nan_in_frame_3(d):
        if d["frame"] != 3:
            return d
        d = dict(d)
        d["x"] = [None] + list(d["x"][1:])  # NaN is carried as null in the JSON records
        return d

    rec = tmp_path / "nan.mcap"
    _copy_with_edits(small_recording, rec, nan_in_frame_3)
    out = tmp_path / "out.mcap"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = run_pipeline(rec, PIPELINE, out, show_progress=False)
    assert any("frame 3" in str(w.message) and "NaN" in str(w.message) for w in caught)
    assert summary.valid_estimates == 20
    flags = {m.data["frame"]: m.data["flags"] for m in LogReader(out).messages("/estimate/frame")}
    assert any(f.startswith("non_finite_input") for f in flags[3])
    est = [m.data for m in LogReader(out).messages("/estimate/attitude")]
    assert all(np.isfinite([e["q"][k] for k in "xyzw"]).all() for e in est)
