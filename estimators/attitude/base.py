"""Attitude solvers and smoothers: identified stars -> attitude estimates."""
from __future__ import annotations

from rollingstar.estimators.plugin import Plugin


class AttitudeSolver(Plugin):
    """Appends one or more :class:`~rollingstar.estimators.data.AttitudeEstimate` to ``frame.attitudes``.

    An estimate that cannot be made (fewer than two identified stars, degenerate geometry) is
    appended with ``valid=False`` and a reason, never invented.
    """

    role = "attitude"
    needs = frozenset({"identified"})
    provides = frozenset({"attitude"})
