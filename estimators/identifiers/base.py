"""Star identifiers: detected spots -> spots matched to catalogue stars."""
from __future__ import annotations

from rollingstar.estimators.plugin import Plugin


class Identifier(Plugin):
    """Sets ``catalog_id`` and ``ref_icrs`` of the stars it matches.

    ``frame.stars`` becomes the identified stars only; the detections it could not match go to
    ``frame.unmatched``.
    """

    role = "identifier"
    needs = frozenset({"spots"})
    provides = frozenset({"identified"})
