"""Rollingstar MCAP logs: records, writer, reader and frame replay (see docs/log-format.md)."""
from .errors import LogFormatError, TruncatedLogWarning
from .reader import LogInfo, LogReader, Message, TopicInfo
from .records import (
    FORMAT_VERSION,
    RECORD_TYPES,
    TOPIC_RECORDS,
    AttitudeEstimateRecord,
    AttitudeSamplesRecord,
    FrameStatusRecord,
    GyroSamplesRecord,
    Quaternion,
    RateEstimateRecord,
    StarsRecord,
    Vector3,
    arrays_to_stars,
    attitude_samples_from_arrays,
    attitude_samples_to_arrays,
    gyro_samples_from_arrays,
    gyro_samples_to_arrays,
    stars_to_arrays,
)
from .replay import FrameMessages, image_from_raw, iter_frames
from .writer import LogWriter

__all__ = [
    "FORMAT_VERSION", "RECORD_TYPES", "TOPIC_RECORDS", "AttitudeEstimateRecord", "AttitudeSamplesRecord",
    "FrameMessages", "FrameStatusRecord", "GyroSamplesRecord", "LogFormatError", "LogInfo",
    "LogReader", "LogWriter", "Message", "Quaternion", "RateEstimateRecord", "StarsRecord",
    "TopicInfo", "TruncatedLogWarning", "Vector3", "arrays_to_stars",
    "attitude_samples_from_arrays", "attitude_samples_to_arrays", "gyro_samples_from_arrays",
    "gyro_samples_to_arrays", "image_from_raw", "iter_frames", "stars_to_arrays",
]
