"""Small recordings written for the log tests."""
import numpy as np

from rollingstar.logs import (
    AttitudeEstimateRecord,
    FrameStatusRecord,
    LogWriter,
    RateEstimateRecord,
    arrays_to_stars,
    attitude_samples_from_arrays,
    gyro_samples_from_arrays,
)

FRAME_PERIOD_NS = 100_000_000
_UNIT_DIRECTIONS = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])


def write_recording(path, n_frames=5, chunk_size=256 * 1024, image_shape=(8, 10), **kwargs):
    """A simulation-like log with every topic of the format; log times never decrease."""
    rng = np.random.default_rng(0)
    with LogWriter(path, kind="simulation", chunk_size=chunk_size,
                   metadata={"scenario": {"yaml": "name: test\n"}, "pipeline": {"yaml": "stages: []\n"}},
                   **kwargs) as w:
        for k in range(n_frames):
            t0 = 1_000_000_000 + k * FRAME_PERIOD_NS
            gyro_t = t0 - np.array([60_000_000, 10_000_000, 0])
            w.write_json("/gyro", gyro_samples_from_arrays(gyro_t, rng.normal(0, 0.01, (3, 3))))
            w.write_json("/truth/attitude", attitude_samples_from_arrays([t0, t0 + 5], [[0, 0, 0, 1]] * 2, np.zeros((2, 3))))
            image = rng.integers(0, 4096, image_shape).astype(np.uint16)
            w.write_image("/camera/image", image, t0)
            x, y = rng.uniform(0, 10, 4), rng.uniform(0, 8, 4)
            w.write_json("/truth/stars", arrays_to_stars(k, t0, x=x, y=y, t_ns=t0, catalog_id=[1, 2, 3, 4],
                                                         ref_icrs=_UNIT_DIRECTIONS, magnitude=[5.0, 6.0, np.nan, 7.0]))
            w.write_json("/estimate/stars", arrays_to_stars(k, t0, x=x, y=y, t_ns=t0))
            w.write_annotations("/estimate/spots", t0, x, y, ["1", "2", None, "4"])
            w.write_json("/estimate/attitude", AttitudeEstimateRecord.from_values(k, t0, [0, 0, 0, 1], n_stars=4))
            w.write_pose("/estimate/pose", t0, [0, 0, 0, 1])
            w.write_json("/estimate/rate", RateEstimateRecord.from_values(k, t0, [0.0, 0.0, 0.01]))
            w.write_json("/estimate/frame", FrameStatusRecord(frame=k, t0_ns=t0, flags=[], n_detected=4, n_identified=4))
