"""Angular-rate estimators: identified stars (and/or gyro) -> camera angular velocity."""
from __future__ import annotations

from typing import Literal

from rollingstar.estimators.data import FrameData, RateEstimate
from rollingstar.estimators.plugin import Plugin

#: The time a single-frame rate estimate refers to: ``frame_start`` = exposure start of row 0,
#: ``frame_mid`` = mid-exposure of the middle row (:func:`reference_time_ns`).
Reference = Literal["frame_start", "frame_mid"]


def reference_time_ns(reference: Reference, t0_ns: int, timing) -> int:
    """``t_ref`` (ns) of the frame starting at ``t0_ns`` for ``reference`` (see :data:`Reference`)."""
    return int(t0_ns) if reference == "frame_start" else int(timing.frame_reference_ns(t0_ns))


class RateEstimator(Plugin):
    """Sets ``frame.rate`` to a :class:`~rollingstar.estimators.data.RateEstimate` (camera frame, rad/s).

    A subclass implements :meth:`estimate`; :meth:`process` stores its result and flags the frame
    ``rate_invalid`` when it is not valid."""

    role = "rate"
    needs = frozenset({"identified"})
    provides = frozenset({"rate"})

    def estimate(self, frame: FrameData) -> RateEstimate:  # pragma: no cover - interface
        raise NotImplementedError

    def process(self, frame: FrameData) -> FrameData:
        rate = self.estimate(frame)
        out = frame.evolve(rate=rate)
        return out if rate.valid else out.flagged("rate_invalid")
