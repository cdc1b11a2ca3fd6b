"""Writing and reading complete logs: every topic, metadata, versions, clear errors."""
import json
import warnings

import numpy as np
import pytest
from mcap.writer import Writer

from rollingstar.logs import (
    LogFormatError,
    LogReader,
    LogWriter,
    StarsRecord,
    TruncatedLogWarning,
    arrays_to_stars,
    gyro_samples_to_arrays,
    image_from_raw,
    stars_to_arrays,
)

from .helpers import write_recording

ALL_TOPICS = ["/gyro", "/truth/attitude", "/camera/image", "/truth/stars", "/estimate/stars",
              "/estimate/spots", "/estimate/attitude", "/estimate/pose", "/estimate/rate", "/estimate/frame"]


def test_round_trip_of_every_topic(tmp_path):
    path = tmp_path / "sim.mcap"
    write_recording(path, n_frames=3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        reader = LogReader(path)
    meta = reader.metadata()
    assert meta["rollingstar"]["format_version"] == "1.2"
    assert meta["rollingstar"]["kind"] == "simulation"
    assert meta["rollingstar"]["software_version"]
    assert meta["scenario"] == {"yaml": "name: test\n"}
    info = reader.summary_info()
    assert not info.truncated
    by_topic = info.topics
    assert sorted(by_topic) == sorted(ALL_TOPICS)
    assert all(t.message_count == 3 for t in info.topics.values())
    assert by_topic["/camera/image"].schema_name == "foxglove.RawImage"
    assert by_topic["/camera/image"].encoding == "protobuf"
    assert by_topic["/truth/stars"].schema_name == "rollingstar.Stars"
    assert by_topic["/truth/stars"].encoding == "json"
    assert by_topic["/gyro"].start_ns == 1_000_000_000 and by_topic["/gyro"].end_ns == 1_200_000_000
    assert by_topic["/truth/attitude"].start_ns == 1_000_000_000

    msgs = list(reader.messages())
    assert len(msgs) == 30
    times = [m.log_time_ns for m in msgs]
    assert times == sorted(times)
    first = {m.topic: m for m in reversed(msgs)}
    stars = stars_to_arrays(first["/truth/stars"].data)
    assert np.isnan(stars["magnitude"][2]) and stars["catalog_id"].tolist() == [1, 2, 3, 4]
    assert isinstance(first["/truth/stars"].record, StarsRecord)
    pose = first["/estimate/pose"].data
    assert pose.frame_id == "icrs" and pose.pose.orientation.w == 1.0
    assert pose.timestamp.seconds == 1 and pose.timestamp.nanos == 0
    spots = first["/estimate/spots"].data
    assert len(spots.circles) == 4 and [t.text for t in spots.texts] == ["1", "2", "4"]
    image = image_from_raw(first["/camera/image"])
    assert image.shape == (8, 10) and image.dtype == np.uint16
    assert first["/camera/image"].data.frame_id == "camera"
    assert first["/estimate/attitude"].data["q"] == {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}

    only = list(reader.messages(topics=["/gyro"]))
    assert [m.topic for m in only] == ["/gyro"] * 3
    assert gyro_samples_to_arrays(only[0].data)["t_ns"][-1] == only[0].log_time_ns


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_image_pixels_round_trip(tmp_path, dtype):
    path = tmp_path / "img.mcap"
    image = (np.arange(35).reshape(5, 7) * 997 % np.iinfo(dtype).max).astype(dtype)
    with LogWriter(path) as w:
        w.write_image("/camera/image", image, 42)
    (msg,) = LogReader(path).messages()
    assert msg.data.encoding == ("mono8" if dtype == np.uint8 else "mono16")
    back = image_from_raw(msg)
    assert back.dtype == dtype
    np.testing.assert_array_equal(back, image)


def test_image_size_mismatch_names_topic_and_time(tmp_path):
    path = tmp_path / "img.mcap"
    with LogWriter(path) as w:
        w.write_image("/camera/image", np.zeros((4, 4), np.uint16), 77)
    (msg,) = LogReader(path).messages()
    msg.data.height = 5
    with pytest.raises(LogFormatError, match=r"/camera/image at 77 ns: mono16 4x5 with step 8 needs 40 bytes, data has 32"):
        image_from_raw(msg)
    msg.data.height, msg.data.width = 4, 5
    with pytest.raises(LogFormatError, match="step 8 is less than width 5"):
        image_from_raw(msg)


def test_file_is_finished_when_the_body_raises(tmp_path):
    path = tmp_path / "crash.mcap"
    with pytest.raises(RuntimeError):
        with LogWriter(path) as w:
            w.write_json("/estimate/stars", arrays_to_stars(0, 5, x=[1.0], y=[2.0], t_ns=5))
            raise RuntimeError("pipeline failed")
    with warnings.catch_warnings():
        warnings.simplefilter("error", TruncatedLogWarning)
        reader = LogReader(path)
    assert [m.topic for m in reader.messages()] == ["/estimate/stars"]


def test_missing_directory_is_named(tmp_path):
    target = tmp_path / "nope" / "out.mcap"
    with pytest.raises(FileNotFoundError, match=str(target.parent)):
        LogWriter(target)


def test_writer_rejects_bad_input(tmp_path):
    with LogWriter(tmp_path / "x.mcap") as w:
        with pytest.raises(ValueError, match="kind"):
            LogWriter(tmp_path / "y.mcap", kind="movie")
        with pytest.raises(TypeError, match="metadata 'scenario'"):
            w.add_metadata("scenario", {"yaml": 3})
        with pytest.raises(ValueError, match="unit quaternion"):
            w.write_pose("/estimate/pose", 1, [0, 0, 0, 2])
        with pytest.raises(ValueError, match="uint8 or uint16"):
            w.write_image("/camera/image", np.zeros((2, 2), np.float32), 1)
        w.write_json("/estimate/stars", arrays_to_stars(0, 5, x=[1.0], y=[2.0], t_ns=5))
        with pytest.raises(ValueError, match="carries rollingstar.Stars"):
            w.write_pose("/estimate/stars", 1, [0, 0, 0, 1])


def test_not_an_mcap_file_is_named(tmp_path):
    path = tmp_path / "notes.mcap"
    path.write_text("hello, this is not a log at all")
    with pytest.raises(LogFormatError, match=r"notes.mcap is not an MCAP file"):
        LogReader(path)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(LogFormatError, match="empty.mcap"):
        LogReader(empty)


def _write_plain(path, metadata, payload=None):
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        if metadata is not None:
            w.add_metadata("rollingstar", metadata)
        if payload is not None:
            sid = w.register_schema("rollingstar.Stars", "jsonschema", b"{}")
            cid = w.register_channel("/camera/centroids", "json", sid)
            w.add_message(cid, log_time=10, publish_time=10, data=json.dumps(payload).encode())
        w.finish()


def test_version_checks(tmp_path):
    path = tmp_path / "v2.mcap"
    _write_plain(path, {"format_version": "2.0"})
    with pytest.raises(LogFormatError, match=r"v2.mcap has rollingstar format_version 2.0.*1.x"):
        LogReader(path)
    _write_plain(path, None)
    with pytest.raises(LogFormatError, match="not a rollingstar log"):
        LogReader(path)
    LogReader(path, check_version=False)
    stars = {"frame": 0, "t0_ns": 10, "x": [1.0], "y": [2.0], "t_ns": [10], "hue": [3]}
    _write_plain(path, {"format_version": "1.7"}, stars)
    with pytest.warns(UserWarning, match="newer"):
        reader = LogReader(path)
    (msg,) = reader.messages()
    assert msg.record.x == [1.0]


def test_invalid_record_names_file_topic_and_field(tmp_path):
    path = tmp_path / "bad.mcap"
    _write_plain(path, {"format_version": "1.0"}, {"frame": 0, "t0_ns": 10, "x": [1.0, 2.0], "y": [2.0], "t_ns": [10, 10]})
    with pytest.raises(LogFormatError, match=r"bad.mcap: topic /camera/centroids at log time 10 ns.*column 'y'"):
        list(LogReader(path).messages())


def test_require_topics_lists_present_ones(tmp_path):
    path = tmp_path / "sim.mcap"
    write_recording(path, n_frames=1)
    reader = LogReader(path)
    reader.require_topics(["/camera/image", "/gyro"])
    with pytest.raises(LogFormatError, match=r"sim.mcap: missing topic\(s\) /camera/centroids; topics present: .*/camera/image"):
        reader.require_topics(["/camera/image", "/camera/centroids"])


def test_third_party_one_gyro_sample_per_message(tmp_path):
    path = tmp_path / "gyro.mcap"
    with LogWriter(path, kind="import") as w:
        from rollingstar.logs import gyro_samples_from_arrays
        for t in [30, 10, 20]:  # out of write order: the reader sorts by log time
            w.write_json("/gyro", gyro_samples_from_arrays([t], [[0.1, 0.2, 0.3]]))
    assert [m.log_time_ns for m in LogReader(path).messages()] == [10, 20, 30]


def test_plain_dicts_are_validated_on_standard_topics(tmp_path):
    path = tmp_path / "copy.mcap"
    source = tmp_path / "sim.mcap"
    write_recording(source, n_frames=2)
    with LogWriter(path, kind="run") as w:
        for m in LogReader(source).messages(["/truth/stars", "/truth/attitude", "/gyro"]):
            w.write_json(m.topic, m.data, m.log_time_ns)
        with pytest.raises(TypeError, match="only accepted on the standard topics"):
            w.write_json("/my/topic", {"a": 1}, 0)
        with pytest.raises(ValueError, match="column 'y'"):
            w.write_json("/estimate/stars", {"frame": 0, "t0_ns": 0, "x": [1.0], "y": [], "t_ns": [0]})
    info = LogReader(path).summary_info()
    assert {t: i.message_count for t, i in info.topics.items()} == {"/truth/stars": 2, "/truth/attitude": 2, "/gyro": 2}
