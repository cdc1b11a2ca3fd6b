"""Frame replay: side messages grouped with the frame they lead up to."""
import pytest

from rollingstar.logs import (
    LogFormatError,
    LogReader,
    LogWriter,
    arrays_to_stars,
    gyro_samples_from_arrays,
    iter_frames,
)

from .helpers import FRAME_PERIOD_NS, write_recording


def test_side_topics_grouped_per_frame(tmp_path):
    path = tmp_path / "sim.mcap"
    write_recording(path, n_frames=4)
    frames = list(iter_frames(LogReader(path), "/camera/image", ["/gyro", "/truth/attitude", "/truth/stars"]))
    assert [f.index for f in frames] == [0, 1, 2, 3]
    for f in frames:
        assert f.t0_ns == 1_000_000_000 + f.index * FRAME_PERIOD_NS
        assert [m.log_time_ns for m in f.side["/gyro"]] == [f.t0_ns]
        assert [m.log_time_ns for m in f.side["/truth/stars"]] == [f.t0_ns]
    # truth attitude is logged at its first sample (t0): same frame; nothing after the last frame
    assert [len(f.side["/truth/attitude"]) for f in frames] == [1, 1, 1, 1]


def test_window_boundaries_on_centroid_recordings(tmp_path):
    path = tmp_path / "centroids.mcap"
    with LogWriter(path, kind="import") as w:
        for t in (5, 10, 15, 20, 25, 30, 31):  # 5: before the first frame; 31: after the last
            w.write_json("/gyro", gyro_samples_from_arrays([t], [[0.0, 0.0, 1.0]]))
        for k, t0 in enumerate((10, 20, 30)):
            w.write_json("/camera/centroids", arrays_to_stars(k, t0, x=[1.0], y=[2.0], t_ns=t0))
    frames = list(iter_frames(LogReader(path), "/camera/centroids", ["/gyro"]))
    assert [[m.log_time_ns for m in f.side["/gyro"]] for f in frames] == [[5, 10], [15, 20], [25, 30]]
    assert frames[1].frame.record.frame == 1


def test_duplicate_frame_times_and_missing_topic_are_errors(tmp_path):
    path = tmp_path / "dup.mcap"
    with LogWriter(path) as w:
        for k in range(2):
            w.write_json("/camera/centroids", arrays_to_stars(k, 10, x=[1.0], y=[2.0], t_ns=10))
    reader = LogReader(path)
    with pytest.raises(LogFormatError, match="two messages on /camera/centroids at log time 10"):
        list(iter_frames(reader, "/camera/centroids"))
    with pytest.raises(LogFormatError, match=r"missing topic\(s\) /camera/image"):
        list(iter_frames(reader, "/camera/image", ["/gyro"]))
