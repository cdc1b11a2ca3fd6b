"""The identity rolling-shutter correction (the baseline: solve with the raw centroids)."""
from __future__ import annotations

from rollingstar.estimators.corrections.base import Correction
from rollingstar.estimators.data import FrameData


class NoCorrection(Correction):
    """No correction: positions unchanged, each star keeps ``t_ns`` = mid-exposure of its own row.

    Returns a new :class:`FrameData` with the same (unmodified) star table; a frame-level solver
    downstream therefore mixes positions from different times, which is the rolling-shutter error
    the other corrections remove.
    """

    name = "none"
    provides = frozenset()  # positions and times unchanged

    def process(self, frame: FrameData) -> FrameData:
        return frame.evolve()
