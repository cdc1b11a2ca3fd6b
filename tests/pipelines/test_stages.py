"""The stage pipeline (pipelines/stages.py) and the plugin hooks it calls (estimators/plugin.py)."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.errors import PipelineError
from rollingstar.estimators.attitude.base import AttitudeSolver
from rollingstar.estimators.attitude.request import RequestSolver
from rollingstar.estimators.centroiders.base import Centroider
from rollingstar.estimators.data import FrameData, StarTable
from rollingstar.estimators.identifiers.base import Identifier
from rollingstar.estimators.plugin import Plugin
from rollingstar.pipelines.stages import StagePipeline, zero_stage_seconds


def _frame(index: int, identified: bool = False) -> FrameData:
    stars = StarTable.build(np.zeros(3), np.zeros(3), np.zeros(3, dtype=np.int64),
                            catalog_id=np.arange(3) if identified else np.full(3, -1),
                            ref_icrs=np.tile([0.0, 0.0, 1.0], (3, 1)) if identified else np.full((3, 3), np.nan))
    return FrameData(index=index, t0_ns=index * 100, stars=stars)


class Mark(AttitudeSolver):
    """Appends its name to the frame's flags; records the frames and priors it saw."""

    name = "mark"

    def __init__(self, label: str):
        super().__init__()
        self.label, self.seen, self.priors = label, [], []

    def process(self, frame):
        self.seen.append(frame.index)
        return frame.flagged(self.label)

    def update_prior(self, frame):
        self.priors.append((frame.index, frame.flags))
        return True


class Hold(Mark):
    """A smoother: holds ``lag`` frames back, releases the oldest one per frame after that."""

    name = "hold"
    defers_output = True

    def __init__(self, label: str, lag: int):
        super().__init__(label)
        self.lag, self.held, self.out = lag, [], []

    def process(self, frame):
        frame = super().process(frame)
        self.held.append(frame.flagged(f"{self.label}-final"))
        if len(self.held) > self.lag:
            self.out.append(self.held.pop(0))
        return frame.flagged(f"{self.label}-provisional")

    def release(self):
        out, self.out = self.out, []
        return out

    def finish(self):
        out, self.held = self.held, []
        return out


class Spots(Centroider):
    name = "spots"

    def process(self, frame):
        raise AssertionError("a centroid recording's frames never reach a centroider")


class Ident(Identifier):
    name = "ident"

    def __init__(self):
        super().__init__()
        self.seen = []

    def process(self, frame):
        self.seen.append(frame.index)
        return frame


def test_plugin_declares_every_hook_with_a_default():
    plugin = Mark("a")
    assert Plugin.needs_truth is False and Plugin.defers_output is False
    assert Plugin.update_prior(plugin, _frame(0)) is False
    assert Plugin().finish() == [] and Plugin().release() == []
    assert RequestSolver(rate_source="truth").needs_truth and not RequestSolver(rate_source="fixed").needs_truth


def test_needs_truth_is_any_stage_declaring_it():
    assert not StagePipeline([Mark("a")], holds_centroids=True).needs_truth
    assert StagePipeline([Mark("a"), RequestSolver(rate_source="truth")], holds_centroids=True).needs_truth


def test_every_stage_in_order_then_priors_then_frame_flags():
    a, b = Mark("a"), Mark("b")
    run = StagePipeline([a, b], holds_centroids=True)
    (out,) = run.process(_frame(0))
    assert out.flags[:2] == ("a", "b") and "too_few_stars" in out.flags  # the frame flags come after the priors
    assert a.priors == [(0, ("a", "b"))] and b.priors == a.priors
    assert set(run.stage_seconds) == {"0:mark", "1:mark"} == set(zero_stage_seconds([a, b]))


def test_centroiders_skipped_on_centroid_recordings_identifiers_on_identified_frames():
    ident = Ident()
    run = StagePipeline([Spots(), ident, Mark("a")], holds_centroids=True)
    run.process(_frame(0))
    run.process(_frame(1, identified=True))
    assert ident.seen == [0]
    with pytest.raises(PipelineError, match=r"stage 'spots' \(centroider\) failed on frame 0 \(t0 = 0 ns\): "
                                            r"AssertionError"):
        StagePipeline([Spots()], holds_centroids=False).process(_frame(0))


def test_a_smoother_releases_late_frames_through_the_later_stages_without_priors():
    first, smoother, last = Mark("first"), Hold("s", lag=2), Mark("last")
    run = StagePipeline([first, smoother, last], holds_centroids=True)
    written = [run.process(_frame(i)) for i in range(4)]
    assert [[f.index for f in w] for w in written] == [[], [], [0], [1]]
    assert written[2][0].flags[:3] == ("first", "s", "s-final") and "last" in written[2][0].flags
    # the priors see each frame once, provisional, up to the smoother
    assert first.priors == [(i, ("first", "s", "s-provisional")) for i in range(4)] and last.priors == first.priors
    assert last.seen == [0, 1]
    assert [f.index for f in run.finish()] == [2, 3] and last.seen == [0, 1, 2, 3]
    assert len(first.priors) == 4


def test_two_smoothers_pass_each_released_frame_all_the_way_before_the_next():
    inner, outer, last = Hold("inner", lag=1), Hold("outer", lag=0), Mark("last")
    run = StagePipeline([inner, outer, last], holds_centroids=True)
    out = [f.index for i in range(3) for f in run.process(_frame(i))]
    assert out == [0, 1] and last.seen == [0, 1]
    assert [f.index for f in run.finish()] == [2]


def test_finish_yields_each_stage_s_frames_before_the_next_stage_finishes():
    class Broken(Mark):
        name = "broken"

        def finish(self):
            raise RuntimeError("no")

    run = StagePipeline([Hold("s", lag=5), Broken("b")], holds_centroids=True)
    run.process(_frame(0))
    frames = run.finish()
    assert next(frames).index == 0  # written before the next stage's finish fails
    with pytest.raises(PipelineError, match=r"stage 'broken' \(attitude\) failed at the end of the recording"):
        next(frames)
