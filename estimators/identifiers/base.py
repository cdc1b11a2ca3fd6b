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
    #: True for an identifier that checks its own output: it puts the integrity check of the frame it
    #: returns (:func:`rollingstar.estimators.identifiers.integrity.check_frame` on that frame's
    #: camera and the context's catalogue), or None, in ``frame.identification``. The stage
    #: mechanics then use that check, when its bound is the pipeline's, instead of computing it again.
    verifies_identification: bool = False
