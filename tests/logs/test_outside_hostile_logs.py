"""Hostile logs written from docs/log-format.md alone, with the plain ``mcap`` package.

Each log is the small valid recording below with one thing wrong, the way a third-party writer
gets it wrong. ``rollingstar run`` (the command line, in-process) must refuse it with exit code 2
and a message naming the file, the topic or frame and what was expected, and never write an
output from it as if it were fine.
"""
from __future__ import annotations

import copy
import json
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
import yaml
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf import descriptor_pb2
from mcap.writer import CompressionType, Writer
from typer.testing import CliRunner

FRAMES = 4
FRAME_NS = 100_000_000
T_FIRST = 2_000_000_000
EXPOSURE_NS = 50_000_000
LINE_NS = 49_000
SCENARIO = {
    "name": "outside hostile", "level": "centroid",
    "sensor": {"focal_length_mm": 24.09, "pixel_size_um": 5.5, "width_px": 1024, "height_px": 1024},
    "shutter": {"mode": "rolling", "exposure_ms": EXPOSURE_NS / 1e6, "line_delay_us": LINE_NS / 1e3,
                "frame_period_ms": FRAME_NS / 1e6},
    "catalog": {"source": "hipparcos", "magnitude_limit": 6.0, "epoch_year": 2025.0},
    "motion": {"initial_attitude": {"ra_deg": 83.8, "dec_deg": -5.4, "roll_deg": 0.0}},
    "frames": FRAMES,
}


def stars_record(k: int) -> dict:
    """Frame k's ``rollingstar.Stars``: four identified stars, each at the mid-exposure of its row."""
    t0 = T_FIRST + k * FRAME_NS
    y = np.array([100.0, 300.0, 600.0, 900.0])
    row = t0 + np.rint(y * LINE_NS).astype(np.int64)
    ref = np.array([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.6, 0.0, 0.8], [0.48, 0.6, 0.64]])
    return {"frame": k, "t0_ns": t0, "x": [100.0, 400.0, 700.0, 900.0], "y": y.tolist(),
            "t_ns": (row + EXPOSURE_NS // 2).tolist(), "row_time_ns": row.tolist(),
            "catalog_id": [11, 12, 13, 14], "ref_icrs": ref.tolist()}


def _descriptor_set(descriptor) -> bytes:
    """The ``FileDescriptorSet`` of a protobuf message and its imports (the protobuf schema data)."""
    files, seen = descriptor_pb2.FileDescriptorSet(), set()

    def add(fd):
        if fd.name not in seen:
            for dep in fd.dependencies:
                add(dep)
            seen.add(fd.name)
            fd.CopyToProto(files.file.add())
    add(descriptor.file)
    return files.SerializeToString()


def write_log(path: Path, frames: list[dict], *, centroid_encoding: str = "json",
              images: list[tuple[int, bytes, str]] = (), scenario: dict = SCENARIO) -> Path:
    """A log of ``frames`` (Stars records, the k-th logged at the k-th frame time) and ``images``
    ((log time, payload, message encoding) on ``/camera/image``), with the metadata the format requires."""
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="rollingstar", library="outside writer")
        w.add_metadata("rollingstar", {"format_version": "1.2", "software_version": "outside writer",
                                       "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                                       "kind": "import"})
        w.add_metadata("scenario", {"yaml": yaml.safe_dump(scenario, sort_keys=False)})
        stars = w.register_channel("/camera/centroids", centroid_encoding,
                                   w.register_schema("rollingstar.Stars", "jsonschema", b"{}"))
        for k, record in enumerate(frames):
            t = T_FIRST + k * FRAME_NS
            w.add_message(stars, log_time=t, publish_time=t, data=json.dumps(record).encode())
        if images:
            schema = w.register_schema("foxglove.RawImage", "protobuf", _descriptor_set(RawImage.DESCRIPTOR))
            channels = {}
            for t, data, encoding in images:
                if encoding not in channels:
                    channels[encoding] = w.register_channel("/camera/image", encoding, schema)
                w.add_message(channels[encoding], log_time=t, publish_time=t, data=data)
        w.finish()
    return path


def good_frames() -> list[dict]:
    return [stars_record(k) for k in range(FRAMES)]


def edited(k: int, **fields) -> list[dict]:
    """The good frames with frame k's fields replaced."""
    frames = copy.deepcopy(good_frames())
    frames[k].update(fields)
    return frames


def run(tmp_path: Path, recording: Path, pipeline: str = "baseline") -> tuple[int, str, Path]:
    """``rollingstar run PIPELINE RECORDING -o OUT`` in-process: (exit code, stderr on one line, output)."""
    from rollingstar.cli import app

    output = tmp_path / "out.mcap"
    res = CliRunner().invoke(app, ["run", pipeline, str(recording), "-o", str(output), "-q"])
    return res.exit_code, " ".join(res.stderr.split()), output


def assert_refused(tmp_path: Path, recording: Path, *needles: str) -> str:
    code, err, output = run(tmp_path, recording)
    assert code == 2, (code, err)
    assert "Traceback" not in err and "unexpected" not in err, err
    for needle in (recording.name, *needles):
        assert needle in err, (needle, err)
    assert not output.exists()
    return err


def test_the_valid_log_runs(tmp_path):
    code, err, output = run(tmp_path, write_log(tmp_path / "good.mcap", good_frames()))
    assert code == 0, err
    assert output.is_file()


def test_a_json_topic_in_another_message_encoding_is_refused(tmp_path):
    rec = write_log(tmp_path / "cbor.mcap", good_frames(), centroid_encoding="cbor")
    assert_refused(tmp_path, rec, "topic /camera/centroids", "message encoding 'cbor'", "'json'")


def test_an_image_topic_in_json_is_refused(tmp_path):
    scenario = {**SCENARIO, "level": "image", "sensor": {**SCENARIO["sensor"], "width_px": 8, "height_px": 6}}
    image = json.dumps({"width": 8, "height": 6, "encoding": "mono16"}).encode()
    rec = write_log(tmp_path / "json_image.mcap", [], images=[(T_FIRST, image, "json")], scenario=scenario)
    assert_refused(tmp_path, rec, "topic /camera/image", "message encoding 'json'", "'protobuf'")


@pytest.mark.parametrize("k, field, value, needle", [
    (1, "t0_ns", 10**30, "t0_ns: Input should be less than or equal to 9223372036854775807"),
    (0, "t0_ns", -5, "t0_ns: Input should be greater than or equal to 0"),
    (1, "t_ns", [10**30, 0, 0, 0], "t_ns.0: Input should be less than or equal to 9223372036854775807"),
])
def test_times_outside_int64_or_before_zero_are_refused(tmp_path, k, field, value, needle):
    rec = write_log(tmp_path / "times.mcap", edited(k, **{field: value}))
    assert_refused(tmp_path, rec, "topic /camera/centroids", needle)


def test_a_reference_direction_that_is_not_a_unit_vector_is_refused(tmp_path):
    # [0, 0, 0] where an unknown direction is null: every star arrives identified, so before this
    # was refused the attitude solver took it as a direction and reported a valid attitude
    ref = stars_record(1)["ref_icrs"]
    ref[2] = [0.0, 0.0, 0.0]
    rec = write_log(tmp_path / "ref.mcap", edited(1, ref_icrs=ref))
    assert_refused(tmp_path, rec, "topic /camera/centroids", "ref_icrs", "star 2", "not a unit vector (|v| = 0)")


def test_a_log_without_frames_is_refused(tmp_path):
    rec = write_log(tmp_path / "empty.mcap", [])
    assert_refused(tmp_path, rec, "/camera/centroids", "holds no frame")


@pytest.mark.parametrize("edit", ["microseconds", "five_frames_late"])
def test_star_times_outside_their_frame_are_refused(tmp_path, edit):
    # star times in microseconds, or copied from another frame: before this was refused, the run
    # reported valid attitudes from them, wrong by the rotation over the time error
    record = stars_record(1)
    shift = {"microseconds": lambda t: t // 1000, "five_frames_late": lambda t: t + 5 * FRAME_NS}[edit]
    rec = write_log(tmp_path / "star_times.mcap", edited(1, t_ns=[shift(t) for t in record["t_ns"]]))
    assert_refused(tmp_path, rec, "/camera/centroids frame 1", "a star has t_ns", "expected a time from")


def test_diagnose_refuses_a_hostile_log_without_pointing_at_its_own_temporary_files(tmp_path):
    from rollingstar.cli import app

    rec = write_log(tmp_path / "bad.mcap", edited(2, x="not a list"))
    res = CliRunner().invoke(app, ["diagnose", "--recording", str(rec), "-q"])
    err = " ".join(res.stderr.split())
    assert res.exit_code == 2, err
    squeezed = "".join(err.split())  # the console may wrap inside the long temporary path
    assert "bad.mcap:topic/camera/centroidsatlogtime2200000000ns" in squeezed and "x: Input should be" in err, err
    assert "diagnose_run" not in err and ".partial" not in err, err  # the run's output is diagnose's own scratch file


def test_a_frame_logged_at_another_time_than_its_t0_is_refused(tmp_path):
    """Frames logged by another clock than their sensor times, 5 s apart (``t0_ns`` and the stars'
    times consistent with each other): gyro and truth messages join frames by log time, so the run
    would pair them wrongly; it is refused naming the frame and both times."""
    shift = 5_000_000_000
    frames = []
    for k in range(FRAMES):
        r = stars_record(k)
        frames.append({**r, "t0_ns": r["t0_ns"] + shift, "t_ns": [t + shift for t in r["t_ns"]],
                       "row_time_ns": [t + shift for t in r["row_time_ns"]]})
    rec = write_log(tmp_path / "clock.mcap", frames)
    assert_refused(tmp_path, rec, "/camera/centroids frame 0", f"log time {T_FIRST} ns differs from its t0_ns "
                   f"{T_FIRST + shift} ns")
