"""Angular-rate estimators: identified stars (and/or gyro) -> camera angular velocity."""
from __future__ import annotations

from rollingstar.estimators.plugin import Plugin


class RateEstimator(Plugin):
    """Sets ``frame.rate`` to a :class:`~rollingstar.estimators.data.RateEstimate` (camera frame, rad/s)."""

    role = "rate"
