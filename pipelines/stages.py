"""The stage pipeline of a run: a pipeline's stages applied to one frame at a time, in order.

A stage may hold frames back (``defers_output``, a smoother): the frame it returns is provisional
(a causal estimate) and is not written, but it feeds every stage's ``update_prior`` hook (e.g. the
tracking identifier's prior for the next frame); the frames the stage releases (``release()``
after each frame, ``finish()`` at the end of the recording) continue through the later stages
and are written, without feeding the priors again (they are late).

On a centroid recording the centroiders are skipped (the recording holds their output), and so
are the identifiers on a frame whose stars all arrive identified (``rollingstar import`` of
astrometry.net tables).

Every identifier's output is checked for chance coincidences
(:func:`rollingstar.estimators.identifiers.integrity.check_identification`, whatever the
identifier): a frame whose matches are more likely than ``max_false_match_prob`` to be chance
keeps no identified star (they move to ``unmatched``), is flagged
``identification_rejected:<reason>``, and any attitude a later stage still reports for it is
made invalid with that reason; a frame whose matches are not likely chance but too few to verify
(``unverifiable``, ``inconsistent_residuals``) keeps its identified stars for per-star stages and
is flagged the same way, and no attitude made from them is valid. A frame of five or more stars
whose scatter contradicts their stated position covariances (the check's chi-square,
``integrity.inconsistent``) keeps its attitudes: when the majority scatters wider than stated,
their covariances are scaled by the majority's factor (flag ``covariance_scaled:<factor>``);
when only a few stars do, they are counted (``outlier_stars:N``). ``frame.identification``
carries the check either way.
"""
from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import replace

import numpy as np

from rollingstar.errors import PipelineError, UserError
from rollingstar.estimators.centroiders.base import Centroider
from rollingstar.estimators.data import AttitudeEstimate, FrameData, SensorContext, StarTable, frame_camera
from rollingstar.estimators.identifiers.base import Identifier
from rollingstar.estimators.identifiers.integrity import (
    DEFAULT_MAX_FALSE_MATCH_PROB,
    SCALE_THRESHOLD,
    check_frame,
    inconsistent,
)
from rollingstar.estimators.plugin import Plugin


def setup_stages(stages: list[Plugin], context: SensorContext, pipeline_source: str, recording) -> None:
    """Call every stage's ``setup``; a stage that cannot work with the recording says why (no traceback)."""
    for i, stage in enumerate(stages):
        try:
            stage.setup(context)
        except ValueError as exc:
            raise PipelineError(f"{pipeline_source}: stages[{i}] ({stage.name!r}) cannot run on {recording}: {exc}") from exc


def zero_stage_seconds(stages: list[Plugin]) -> dict[str, float]:
    """Each stage's time before the first frame, keyed ``"<index>:<name>"`` (the run summary's keys)."""
    return {f"{i}:{stage.name}": 0.0 for i, stage in enumerate(stages)}


class StagePipeline:
    """Runs ``stages`` over frames and times them.

    ``holds_centroids``: the recording holds centroids, not images (centroiders are skipped).
    ``stage_seconds``: seconds spent in each stage so far (:func:`zero_stage_seconds` when not given).
    ``context``: the sensor context the identification check uses (None: no check, for tests of
    the stage mechanics); ``max_false_match_prob`` its bound.
    """

    def __init__(self, stages: list[Plugin], holds_centroids: bool, stage_seconds: dict[str, float] | None = None,
                 context: SensorContext | None = None, max_false_match_prob: float = DEFAULT_MAX_FALSE_MATCH_PROB):
        self.stages = stages
        self.holds_centroids = holds_centroids
        self.stage_seconds = stage_seconds if stage_seconds is not None else zero_stage_seconds(stages)
        self.context = context
        self.max_false_match_prob = max_false_match_prob

    @property
    def needs_truth(self) -> bool:
        """True when a stage reads ``frame.truth`` (an oracle stage)."""
        return any(stage.needs_truth for stage in self.stages)

    def process(self, frame: FrameData) -> list[FrameData]:
        """The frames to write after ``frame``: normally ``frame`` processed; with a smoother, the
        frames it released (maybe none)."""
        skip_identifiers = self._skips_identifiers(frame)
        frame, deferred_at, released = self._run_from(0, frame, skip_identifiers)
        for stage in self.stages:
            stage.update_prior(frame)
        if deferred_at is None:
            return [finish_frame(frame)]
        return self._run_late(deferred_at + 1, released, skip_identifiers)

    def finish(self) -> Iterator[FrameData]:
        """The frames the stages still hold at the end of the recording, stage by stage, each
        through the stages after the one that held it."""
        for i, stage in enumerate(self.stages):
            start = time.perf_counter()
            try:
                held = stage.finish()
            except UserError:
                raise
            except Exception as exc:
                raise PipelineError(f"stage {stage.name!r} ({stage.role}) failed at the end of the recording (finish): "
                                    f"{type(exc).__name__}: {exc}") from exc
            self.stage_seconds[f"{i}:{stage.name}"] += time.perf_counter() - start
            for frame in held:
                yield from self._run_late(i + 1, [frame], self._skips_identifiers(frame))

    def _skips_identifiers(self, frame: FrameData) -> bool:
        """True for a frame of a centroid recording whose stars all carry a catalogue id and direction."""
        stars = frame.stars
        return (self.holds_centroids and stars is not None and stars.n > 0 and bool(stars.identified.all())
                and bool(np.isfinite(stars.ref_icrs).all()))

    def _skips(self, stage: Plugin, skip_identifiers: bool) -> bool:
        return ((self.holds_centroids and isinstance(stage, Centroider))
                or (skip_identifiers and isinstance(stage, Identifier)))

    def _run_from(self, first: int, frame: FrameData,
                  skip_identifiers: bool) -> tuple[FrameData, int | None, list[FrameData]]:
        """``frame`` through ``stages[first:]``, up to the first stage that defers its output.

        Returns the frame, the index of that stage (None when every stage ran) and the frames it released.
        """
        for i in range(first, len(self.stages)):
            stage = self.stages[i]
            if self._skips(stage, skip_identifiers):
                continue
            frame, released = self._call(i, frame)
            if stage.defers_output:
                return frame, i, released
        return frame, None, []

    def _run_late(self, first: int, frames: list[FrameData], skip_identifiers: bool) -> list[FrameData]:
        """Frames released by a deferring stage, through ``stages[first:]`` one after the other (a
        later deferring stage's releases go on before the next frame), ready to write."""
        done = []
        pending = [(first, frame) for frame in reversed(frames)]  # a stack: the next frame is last
        while pending:
            first, frame = pending.pop()
            frame, deferred_at, released = self._run_from(first, frame, skip_identifiers)
            if deferred_at is None:
                done.append(finish_frame(frame))
            else:
                pending.extend((deferred_at + 1, f) for f in reversed(released))
        return done

    def _call(self, i: int, frame: FrameData) -> tuple[FrameData, list[FrameData]]:
        """Stage ``i`` on ``frame``, timed: the processed frame and what the stage released."""
        stage = self.stages[i]
        try:
            start = time.perf_counter()
            frame = stage.process(frame)
            if isinstance(stage, Identifier) and self.context is not None:
                frame = verify_identification(frame, self.context, self.max_false_match_prob,
                                              own=stage.verifies_identification)
            released = stage.release() if stage.defers_output else []
            self.stage_seconds[f"{i}:{stage.name}"] += time.perf_counter() - start
        except UserError:
            raise
        except Exception as exc:  # a plugin that raises: name it and the frame, keep what was written
            raise PipelineError(f"stage {stage.name!r} ({stage.role}) failed on frame {frame.index} "
                                f"(t0 = {frame.t0_ns} ns): {type(exc).__name__}: {exc}") from exc
        return frame, released


def verify_identification(frame: FrameData, context: SensorContext, bound: float, own: bool = False) -> FrameData:
    """``frame`` with its identification check; its identified stars withdrawn when the check fails
    (see the module docstring). ``own``: the identifier put its check of this frame in
    ``frame.identification`` (:attr:`Identifier.verifies_identification`), used when its bound is ``bound``."""
    check = frame.identification if own else None
    if check is None or check.bound != float(bound):
        check = check_frame(frame, frame_camera(frame, context), context.catalog, bound)
    frame = frame.evolve(identification=check)
    if check.passed or check.n_matched < 2:
        return frame
    if not check.reason.startswith("false_match_probability"):  # unverifiable or inconsistent: ids kept
        return frame.flagged(f"identification_rejected:{check.reason}")
    stars = frame.stars
    keep = ~stars.identified
    unmatched = stars.take(stars.identified).with_columns(
        catalog_id=np.full(check.n_matched, -1), ref_icrs=np.full((check.n_matched, 3), np.nan))
    if frame.unmatched is not None:
        unmatched = StarTable.concat(frame.unmatched, unmatched)
    return frame.evolve(stars=stars.take(keep), unmatched=unmatched,
                        flags=frame.flags + (f"identification_rejected:{check.reason}",))


def _checked_attitudes(frame: FrameData) -> FrameData:
    """The frame's attitudes as its identification check allows: invalid with its reason when it
    failed, covariances scaled when the stars' scatter contradicts their covariances (module docstring)."""
    check = frame.identification
    if check is None or check.n_matched < 2 or not any(a.valid for a in frame.attitudes):
        return frame
    if not check.passed:
        reason = f"identification_rejected:{check.reason}"
        return frame.evolve(attitudes=tuple(
            AttitudeEstimate.invalid(a.t_ns, a.n_stars, reason) if a.valid else a for a in frame.attitudes))
    if not inconsistent(check):
        return frame
    if not check.scatter_scale >= SCALE_THRESHOLD:  # an honest majority with a few outliers
        return frame.flagged(f"outlier_stars:{check.n_outliers}") if check.n_outliers else frame
    factor = check.scatter_scale
    scaled = tuple(replace(a, covariance_rad2=np.asarray(a.covariance_rad2) * factor)
                   if a.valid and a.covariance_rad2 is not None else a for a in frame.attitudes)
    return frame.evolve(attitudes=scaled).flagged(f"covariance_scaled:{factor:.3g}")


def finish_frame(frame: FrameData) -> FrameData:
    """Frame flags that need every stage's output.

    - ``too_few_stars``: fewer than 2 identified stars and no valid attitude;
    - ``saturated_stars:N``: N detections (identified or not) reached the saturation level;
    - ``attitude_degraded:all_stars_saturated``: a valid attitude made from saturated stars only
      (it is kept: the centroider's ``sigma_px`` of clipped spots, and so the covariance, is inflated
      for them, but the user should know the frame is not a normal one);
    - a valid attitude on a frame whose identification check failed is made invalid with its reason;
      ``covariance_scaled:<factor>`` when the check found the majority of the stars scattering wider
      than their covariances (the attitudes' covariances are scaled by that factor), or
      ``outlier_stars:N`` when only a few stars do.
    """
    frame = _checked_attitudes(frame)
    if frame.stars is not None and frame.stars.identified.sum() < 2 and not any(a.valid for a in frame.attitudes):
        frame = frame.flagged("too_few_stars")
    if frame.stars is not None:
        n_sat = int(frame.stars.saturated.sum()) + (int(frame.unmatched.saturated.sum()) if frame.unmatched is not None else 0)
        if n_sat:
            frame = frame.flagged(f"saturated_stars:{n_sat}")
        used = frame.stars.identified
        if used.any() and frame.stars.saturated[used].all() and any(a.valid for a in frame.attitudes):
            frame = frame.flagged("attitude_degraded:all_stars_saturated")
    return frame
