"""Rolling-shutter corrections: move star positions to a common time or undo centroid bias."""
from __future__ import annotations

from rollingstar.estimators.plugin import Plugin


class Correction(Plugin):
    """Returns corrected ``x, y`` and sets ``t_ns`` to the time the corrected positions refer to."""

    role = "correction"
    needs = frozenset({"spots"})
    provides = frozenset({"common_time"})
