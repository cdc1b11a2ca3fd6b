"""Star-motion filters: smooth identified star positions over frames and estimate image velocity."""
from __future__ import annotations

from rollingstar.estimators.plugin import Plugin


class StarMotionFilter(Plugin):
    """Replaces ``x, y`` (and ``sigma_px``) with filtered values and fills ``vx, vy`` (px/s)."""

    role = "filter"
    needs = frozenset({"identified"})  # tracks are keyed by catalogue id
    provides = frozenset({"velocities"})
