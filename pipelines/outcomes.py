"""What a run produced, frame by frame, in the one vocabulary ``run``, ``evaluate``, ``compare`` and
the reports share.

- **valid** frame: it has at least one valid attitude estimate;
- **invalid** frame: it has none; its reason is that of its last invalid estimate, or
  ``no attitude estimate`` when the pipeline wrote none for it (a smoother that has not caught up,
  a stage that gave up before the solver);
- **flagged** frame: it carries at least one flag, counted per flag name (the text before ``:``;
  ``saturated_stars:7`` counts as ``saturated_stars``). A flag is a note about the frame, not a
  verdict: a flagged frame can be valid.

Reasons are counted by their key: the text before the first ``:`` or `` (``, and after a ``:`` an
identifier that names a kind (the whole detail, or what precedes its ``(``), not a count, a value
or a sentence. So
``identification_rejected:3e-05``, ``saturated_stars:7`` and ``fewer than 2 identified stars (1)``
each group with their kind, while ``lost_in_space_rejected:mirrored_image`` and
``lost_in_space_rejected:residual(2.7px>2.0px)`` are counted apart: the reason is in that word.
"""
from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field

NO_ESTIMATE = "no attitude estimate"

#: What to do when a flag kind is on most frames of a run (:meth:`Outcomes.hints`).
HINTS = {
    "lost_in_space_rejected:mirrored_image": (
        "the star patterns are mirror images of the sky: image rows stored bottom-up (as FITS stores them) "
        "or a mirror in the light path. For images, set `mirrored: true` in the camera file and import them "
        "again (a principal point the file states is then read in the flipped image); for centroids, flip x "
        "(x -> W - 1 - x) where they are written (docs/log-format.md)"),
    "lost_in_space_rejected:solver_no_match": (
        "no star pattern matched the catalogue: check the field of view the camera file gives (focal length "
        "and pixel size, within the identifier's fov_tolerance) and that the catalogue reaches the stars' "
        "magnitudes (docs/log-format.md, the reference catalogue)"),
    "pixel_step_skipped:model_misfit": (
        "the pixel model explains fewer than half of the stars: a focal length or PSF unlike the declared "
        "ones; the frames keep their position solution (docs/high-dynamic.md)"),
}


def reason_key(text: str) -> str:
    """The group a reason or flag is counted under (module docstring)."""
    head, _, detail = text.partition(":")
    key = head.split(" (", 1)[0].strip()
    kind = re.match(r"[A-Za-z_][A-Za-z0-9_]*(?=\(|$)", detail.strip())
    if key and kind and kind.group(0).lower() not in ("inf", "nan"):
        key = f"{key}:{kind.group(0)}"
    return key or "unspecified"


def _counted(counter: Counter) -> str:
    return ", ".join(f"{name} {n}" for name, n in sorted(counter.items(), key=lambda kv: (-kv[1], kv[0])))


@dataclass
class Outcomes:
    """Frame outcomes and attitude-estimate counts of one run (module docstring)."""

    frames: int = 0
    valid: int = 0
    flagged: int = 0
    estimates: int = 0
    valid_estimates: int = 0
    invalid_reasons: Counter = field(default_factory=Counter)
    flag_reasons: Counter = field(default_factory=Counter)

    @property
    def invalid(self) -> int:
        return self.frames - self.valid

    def add(self, flags: Iterable[str], attitudes: Iterable[tuple[bool, str]]) -> None:
        """One frame: its flags and its attitude estimates as ``(valid, reason)`` pairs."""
        attitudes = list(attitudes)
        flags = list(flags)
        self.frames += 1
        self.estimates += len(attitudes)
        n_valid = sum(bool(v) for v, _ in attitudes)
        self.valid_estimates += n_valid
        if n_valid:
            self.valid += 1
        else:
            reasons = [r for v, r in attitudes if not v and r]
            self.invalid_reasons[reason_key(reasons[-1]) if reasons else NO_ESTIMATE] += 1
        if flags:
            self.flagged += 1
            self.flag_reasons.update({reason_key(f) for f in flags})

    @classmethod
    def from_records(cls, frames: Iterable[dict], attitudes: Iterable[dict]) -> Outcomes:
        """From an output log's ``/estimate/frame`` and ``/estimate/attitude`` records."""
        by_frame: dict[int, list[tuple[bool, str]]] = {}
        for a in attitudes:
            by_frame.setdefault(int(a.get("frame", -1)), []).append(
                (bool(a.get("valid")) and a.get("q") is not None, str(a.get("reason") or "")))
        out = cls()
        for f in frames:
            out.add(f.get("flags") or (), by_frame.get(int(f.get("frame", -1)), ()))
        return out

    def as_dict(self) -> dict:
        return {"frames": self.frames, "valid_frames": self.valid, "invalid_frames": self.invalid,
                "invalid_reasons": dict(self.invalid_reasons), "flagged_frames": self.flagged,
                "flag_reasons": dict(self.flag_reasons), "attitude_estimates": self.estimates,
                "valid_attitude_estimates": self.valid_estimates}

    @classmethod
    def from_dict(cls, d: dict) -> Outcomes:
        """The inverse of :meth:`as_dict` (a metrics JSON's ``outcomes``)."""
        return cls(int(d["frames"]), int(d["valid_frames"]), int(d["flagged_frames"]), int(d["attitude_estimates"]),
                   int(d["valid_attitude_estimates"]), Counter(d.get("invalid_reasons") or {}),
                   Counter(d.get("flag_reasons") or {}))

    def hints(self) -> list[str]:
        """The advice of :data:`HINTS` for every flag kind on more than half of the frames."""
        return [HINTS[k] for k, n in sorted(self.flag_reasons.items()) if k in HINTS and 2 * n > self.frames]

    def sentence(self) -> str:
        """``100 frames: 98 valid, 2 invalid (too_few_stars 2); 7 flagged (saturated_stars 7)``."""
        invalid = f"{self.invalid} invalid" + (f" ({_counted(self.invalid_reasons)})" if self.invalid else "")
        flagged = f"{self.flagged} flagged" + (f" ({_counted(self.flag_reasons)})" if self.flagged else "")
        extra = (f"; {self.valid_estimates}/{self.estimates} attitude estimates valid"
                 if self.estimates != self.frames else "")
        return f"{self.frames} frames: {self.valid} valid, {invalid}; {flagged}{extra}"
