"""The standard topic names of a rollingstar log (docs/log-format.md, section Topics).

Every module that writes or reads one of these topics uses the name from here.
"""
from __future__ import annotations

# What a recording holds: one frame topic (an image or measured centroids) and the side topics.
TOPIC_IMAGE = "/camera/image"
TOPIC_CENTROIDS = "/camera/centroids"
TOPIC_GYRO = "/gyro"
TOPIC_TRUTH_ATTITUDE = "/truth/attitude"
TOPIC_TRUTH_STARS = "/truth/stars"
TRUTH_TOPICS = (TOPIC_TRUTH_ATTITUDE, TOPIC_TRUTH_STARS)

# What ``rollingstar run`` adds: the pipeline's estimates.
TOPIC_EST_STARS = "/estimate/stars"
TOPIC_EST_SPOTS = "/estimate/spots"
TOPIC_EST_ATTITUDE = "/estimate/attitude"
TOPIC_EST_POSE = "/estimate/pose"
TOPIC_EST_RATE = "/estimate/rate"
TOPIC_EST_FRAME = "/estimate/frame"
# Written beside the estimates when the recording carries /truth/attitude (for plotting while replaying).
TOPIC_EST_ATTITUDE_ERROR = "/estimate/attitude_error"
