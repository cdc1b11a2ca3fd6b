"""Hostile recordings (docs/reliability.md): each is refused with exit 2 and a message naming the file,
topic, frame and what was expected, or is processed with the affected frames flagged."""
from __future__ import annotations

import json
import warnings

import pytest
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from rollingstar.logs.reader import LogReader
from rollingstar.logs.writer import LogWriter, timestamp_ns
from rollingstar.pipelines.config import PipelineConfig
from rollingstar.pipelines.runner import run_pipeline
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.scenario import load_scenario

from .helpers import PIPELINE, SCENARIO, assert_exit_2, cli, rewrite

QUEST = PipelineConfig(stages=[{"kind": "tracking"}, {"kind": "quest"}])


def _estimates(path):
    return [(m.topic, m.log_time_ns, json.dumps(m.data, sort_keys=True) if isinstance(m.data, dict)
             else m.data.SerializeToString()) for m in LogReader(path).messages() if m.topic.startswith("/estimate")]


def _frame_flags(path):
    return {m.data["frame"]: m.data["flags"] for m in LogReader(path).messages("/estimate/frame")}


def test_messages_out_of_time_order_in_the_file_are_replayed_in_time_order(tmp_path, small_recording):
    # the writer put every message in reverse order; the reader merges by log time
    rev = rewrite(small_recording, tmp_path / "rev.mcap", lambda ms: ms[::-1], chunk_size=4096)
    run_pipeline(small_recording, QUEST, tmp_path / "a.mcap", show_progress=False)
    run_pipeline(rev, QUEST, tmp_path / "b.mcap", show_progress=False)
    assert _estimates(tmp_path / "a.mcap") == _estimates(tmp_path / "b.mcap")


def test_frame_records_out_of_time_order_are_refused(tmp_path, small_recording):
    def swap_t0(ms):  # frame 6 claims a t0 before frame 5's (log times still increase)
        out = []
        for m in ms:
            if m.topic == "/camera/centroids" and m.data["frame"] == 6:
                d = dict(m.data, t0_ns=m.data["t0_ns"] - 150_000_000)
                m = type(m)(m.topic, m.log_time_ns, m.schema_name, d)
            out.append(m)
        return out

    bad = rewrite(small_recording, tmp_path / "order.mcap", swap_t0)
    msg = assert_exit_2(("run", PIPELINE, bad, "-o", tmp_path / "o.mcap"),
                        "order.mcap", "/camera/centroids frame 6", "frame time does not increase", "previous frame 5")
    print(msg)
    # nothing already written is lost: frames 0..5 are in the partial output (the output is not written)
    assert sorted(_frame_flags(tmp_path / "o.mcap.partial")) == [0, 1, 2, 3, 4, 5]


def test_duplicate_frames_are_skipped_with_a_warning(tmp_path, small_recording):
    def dup(ms):  # frame 4 written twice (same log time, same content) and frame 9 re-sent later
        out = []
        for m in ms:
            out.append(m)
            if m.topic == "/camera/centroids" and m.data["frame"] in (4,):
                out.append(m)
            if m.topic == "/camera/centroids" and m.data["frame"] == 9:
                out.append(type(m)(m.topic, m.log_time_ns + 1000, m.schema_name, m.data))
        return out

    rec = rewrite(small_recording, tmp_path / "dup.mcap", dup)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = run_pipeline(rec, QUEST, tmp_path / "o.mcap", show_progress=False)
    text = [str(w.message) for w in caught]
    assert any("duplicate frame on /camera/centroids" in t for t in text), text
    assert any("frame 9" in t and "duplicate of the previous frame" in t for t in text), text
    assert s.frames == 20 and s.valid_estimates == 20
    run_pipeline(small_recording, QUEST, tmp_path / "ref.mcap", show_progress=False)
    assert _estimates(tmp_path / "o.mcap") == _estimates(tmp_path / "ref.mcap")


def test_two_different_frames_at_one_time_are_refused(tmp_path, small_recording):
    def clash(ms):
        out = []
        for m in ms:
            out.append(m)
            if m.topic == "/camera/centroids" and m.data["frame"] == 3:
                out.append(type(m)(m.topic, m.log_time_ns, m.schema_name, dict(m.data, frame=99)))
        return out

    rec = rewrite(small_recording, tmp_path / "clash.mcap", clash)
    print(assert_exit_2(("run", PIPELINE, rec, "-o", tmp_path / "o.mcap"), "two messages on /camera/centroids",
                        "different content"))


def test_timestamp_jump_is_flagged_and_the_run_continues(tmp_path, small_recording):
    def drop(ms):  # frames 8..11 lost: frame 12 comes 5 periods after frame 7
        return [m for m in ms if not (isinstance(m.data, dict) and m.data.get("frame") in (8, 9, 10, 11)
                                      and m.topic == "/camera/centroids")]

    rec = rewrite(small_recording, tmp_path / "gap.mcap", drop)
    with pytest.warns(UserWarning, match=r"frame 12 .*500\.\d ms after the previous frame, expected 100\.2 ms"):
        s = run_pipeline(rec, QUEST, tmp_path / "o.mcap", show_progress=False)
    flags = _frame_flags(tmp_path / "o.mcap")
    assert s.frames == 16 and s.valid_estimates == 16
    assert [f for f, fl in flags.items() if any(x.startswith("time_gap") for x in fl)] == [12]
    assert flags[12] == ["time_gap:501ms"]


def test_unknown_format_version_and_unknown_schema_are_refused(tmp_path, small_recording):
    v2 = tmp_path / "v2.mcap"
    # an MCAP whose rollingstar record says 2.0 (LogWriter always writes 1.0): the raw mcap writer
    from mcap.writer import Writer

    with open(v2, "wb") as f:
        raw = Writer(f)
        raw.start(profile="rollingstar", library="future")
        raw.add_metadata("rollingstar", {"format_version": "2.0", "kind": "simulation"})
        raw.finish()
    print(assert_exit_2(("info", v2), "v2.mcap", "format_version 2.0", "understands 1.x"))

    odd = tmp_path / "schema.mcap"
    reader = LogReader(small_recording)
    with LogWriter(odd, kind="simulation", metadata={k: v for k, v in reader.metadata().items() if k != "rollingstar"}) as w:
        cid = w._mcap.register_channel(topic="/camera/centroids", message_encoding="json",
                                       schema_id=w._mcap.register_schema(name="rollingstar.Stars2", encoding="jsonschema", data=b"{}"))
        for m in reader.messages("/camera/centroids"):
            w._mcap.add_message(channel_id=cid, log_time=m.log_time_ns, publish_time=m.log_time_ns,
                                data=json.dumps(m.data).encode())
    print(assert_exit_2(("run", PIPELINE, odd, "-o", tmp_path / "o.mcap"), "schema.mcap", "topic /camera/centroids",
                        "'rollingstar.Stars2'", "'rollingstar.Stars'", "unknown schema version"))


@pytest.fixture(scope="module")
def image_recording(tmp_path_factory):
    """3 image-level frames of a 64 x 48 px, 12-bit sensor (the he2021b optics)."""
    cfg = load_scenario(SCENARIO)
    cfg = cfg.model_copy(update={"level": "image", "sensor": cfg.sensor.model_copy(update={"width_px": 64, "height_px": 48})})
    out = tmp_path_factory.mktemp("img") / "img.mcap"
    simulate_to_log(cfg, out, frames=3, show_progress=False)
    return out


def _replace_image(src, dst, make):
    """Frame 1's image replaced by ``make(RawImage of frame 1)`` (a RawImage)."""
    def edit(ms):
        out, k = [], 0
        for m in ms:
            if m.topic == "/camera/image":
                if k == 1:
                    m = type(m)(m.topic, m.log_time_ns, m.schema_name, make(m.data))
                k += 1
            out.append(m)
        return out

    return rewrite(src, dst, edit)


def _img(raw, **fields):
    return RawImage(timestamp=timestamp_ns(raw.timestamp.seconds * 10**9 + raw.timestamp.nanos), **fields)


CASES = {
    "zero_size": (lambda raw: _img(raw, frame_id="camera", width=0, height=0, encoding="mono16",
                                       step=0, data=b""), ["image is 0x0 px", "declares 64x48"]),
    "mismatched": (lambda raw: _img(raw, frame_id="camera", width=32, height=48, encoding="mono16",
                                        step=64, data=bytes(64 * 48)), ["image is 32x48 px", "declares 64x48"]),
    "8bit_as_16": (lambda raw: _img(raw, frame_id="camera", width=64, height=48, encoding="mono16",
                                        step=128, data=bytes(64 * 48)),
                   ["needs 6144 bytes, data has 3072", "8-bit pixels: an 8-bit image declared as mono16"]),
    "8bit_for_12bit_sensor": (lambda raw: _img(raw, frame_id="camera", width=64, height=48,
                                                   encoding="mono8", step=64, data=bytes(64 * 48)),
                              ["8-bit image (mono8)", "declares 12-bit pixels", "expected mono16"]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_images_name_topic_frame_and_expectation(tmp_path, image_recording, case):
    make, needles = CASES[case]
    rec = _replace_image(image_recording, tmp_path / f"{case}.mcap", make)
    p = tmp_path / "p.yaml"
    p.write_text("stages:\n  - {kind: cog}\n  - {kind: tracking}\n  - {kind: quest}\n")
    msg = assert_exit_2(("run", p, rec, "-o", tmp_path / "o.mcap"), f"{case}.mcap", "/camera/image", *needles)
    assert "frame 1" in msg or "ns" in msg
    print(msg)
    assert sorted(_frame_flags(tmp_path / "o.mcap.partial")) == [0]  # frame 0 was written before and is kept


def test_non_finite_values_in_a_side_record_skip_that_message_and_flag_its_frame(tmp_path, small_recording):
    # NaN in a gyro sample: JSON records forbid NaN/inf (null marks a missing centroid only). A bad
    # side message (gyro, truth) must not stop the run: it is skipped with a warning naming the
    # topic and log time, and the frame it belonged to is flagged; every frame is still estimated.
    reader = LogReader(small_recording)
    bad = tmp_path / "nan.mcap"
    meta = {k: v for k, v in reader.metadata().items() if k != "rollingstar"}
    with LogWriter(bad, kind="simulation", metadata=meta) as w:
        for m in reader.messages():
            w.write_message(m)
        from rollingstar.logs.records import GyroSamples

        t = m.log_time_ns - 1
        cid = w._channel("/gyro", GyroSamples.SCHEMA_NAME, lambda: w._mcap.register_schema(
            name=GyroSamples.SCHEMA_NAME, encoding="jsonschema", data=b"{}"))
        w._add(cid, t, b'{"t_ns": [%d], "x": [NaN], "y": [0.0], "z": [Infinity]}' % t)
    code, out, err = cli("run", PIPELINE, bad, "-o", tmp_path / "o.mcap")
    assert code == 0, (code, out, err)
    flags = _frame_flags(tmp_path / "o.mcap")
    clean = _frame_flags_of_run(small_recording, tmp_path / "clean.mcap")
    assert sorted(flags) == sorted(clean)  # every frame estimated
    flagged = [f for f, fl in flags.items() if "side_message_invalid:/gyro" in fl]
    assert flagged == [max(flags)]  # only the frame the bad message belonged to (the last one)
    with pytest.warns(UserWarning, match=r"topic /gyro at log time %d ns.*x\.0: Input should be a finite number" % t):
        run_pipeline(bad, PipelineConfig.model_validate(_yaml(PIPELINE)), tmp_path / "o2.mcap", show_progress=False)


def _frame_flags_of_run(recording, out):
    code, o, e = cli("run", PIPELINE, recording, "-o", out)
    assert code == 0, (o, e)
    return _frame_flags(out)


def _yaml(path):
    import yaml

    with open(path) as f:
        return yaml.safe_load(f)
