"""``rollingstar run --resume``: continue a run whose output was cut short (killed or interrupted).

The partial output is read with the damaged-file reader (every complete chunk). A frame is
*complete* when its ``/estimate/frame`` record is there (the runner writes it last for each frame).
The resumed run writes a new log beside the output (``<output>.resume-tmp``) and moves it over the
output at the end (so a resume killed in turn leaves the old partial output to resume from):

1. the partial output's truth messages and every message of its complete frames are copied;
2. the stages carry state (tracking priors, filters, smoothers) that only the frames before can
   rebuild: the run restores it from the newest usable checkpoint (:mod:`rollingstar.pipelines.checkpoint`)
   and reads on from the frame after it, or, without one, runs again from the first frame of the
   recording; a frame already complete is processed but not written again, a truth message
   already copied is not written again.

*Equivalent* (what the tests check): the resumed log and an uninterrupted run's log hold the same
messages — topic, log time and decoded content, in log-time order — and the same metadata apart
from the wall-clock ``rollingstar.created_utc``. This holds because the runner is deterministic.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

from rollingstar.errors import UserError
from rollingstar.logs.errors import LogFormatError, TruncatedLogWarning
from rollingstar.logs.reader import LogReader, Message
from rollingstar.logs.topics import TOPIC_EST_ATTITUDE, TOPIC_EST_FRAME, TOPIC_EST_POSE, TOPIC_EST_SPOTS, TRUTH_TOPICS


@dataclass
class Partial:
    """What a resumed run keeps from the partial output."""

    done: set[int] = field(default_factory=set)
    copy: list[Message] = field(default_factory=list)
    truth_keys: set[tuple[str, int]] = field(default_factory=set)


def temp_path(output: Path) -> Path:
    return output.with_name(output.name + ".resume-tmp")


def load_partial(output: Path, metadata: dict[str, dict[str, str]]) -> Partial:
    """The complete frames of ``output``; a :class:`UserError` when it was not written by this pipeline and recording."""
    output = Path(output)
    if not output.exists():
        warnings.warn(f"--resume: {output} does not exist; running from the start")
        return Partial()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TruncatedLogWarning)  # a cut file is what resume is for
        try:
            reader = LogReader(output)
        except LogFormatError as exc:
            raise UserError(f"--resume: cannot read the partial output: {exc}") from None
        meta = reader.metadata()
        for name in ("scenario", "pipeline"):
            if meta.get(name, {}).get("yaml") != metadata[name].get("yaml"):
                raise UserError(f"--resume: {output} was written by a different {name} "
                                f"(its metadata '{name}' differs from this run's); remove it or choose another -o")
        messages = list(reader.messages())
    done = {int(m.data["frame"]) for m in messages if m.topic == TOPIC_EST_FRAME}
    t0_done = {int(m.data["t0_ns"]) for m in messages if m.topic == TOPIC_EST_FRAME}
    att_times = {int(m.data["t_ns"]) for m in messages
                 if m.topic == TOPIC_EST_ATTITUDE and int(m.data["frame"]) in done and m.data["valid"]}
    part = Partial(done=done)
    for m in messages:
        if m.topic in TRUTH_TOPICS:
            keep = True
            part.truth_keys.add((m.topic, m.log_time_ns))
        elif isinstance(m.data, dict) and "frame" in m.data:
            keep = int(m.data["frame"]) in done
        elif m.topic == TOPIC_EST_SPOTS:
            keep = m.log_time_ns in t0_done
        elif m.topic == TOPIC_EST_POSE:
            keep = m.log_time_ns in att_times
        else:
            keep = False
        if keep:
            part.copy.append(m)
    return part
