"""The conformance checks themselves: a plugin written as docs/plugins.md shows passes them, and
deliberately broken plugins fail the check for what they break, with a message naming it."""
from __future__ import annotations

import numpy as np
import pytest
from pydantic import BaseModel

from rollingstar.estimators.attitude.quest import QuestSolver
from rollingstar.estimators.centroiders.cog import CogCentroider
from rollingstar.estimators.conformance import Check, check_plugin, plugin_checks
from rollingstar.estimators.conformance import checks as C
from rollingstar.estimators.corrections.time_domain import TimeDomainCorrection
from rollingstar.estimators.data import FrameData
from rollingstar.estimators.filters.base import StarMotionFilter
from rollingstar.estimators.filters.kf_cv import KfCvFilter
from rollingstar.estimators.identifiers.tracking import TrackingIdentifier
from rollingstar.estimators.plugin import Plugin
from rollingstar.estimators.rates.base import RateEstimator


class DifferenceFilter(StarMotionFilter):
    """Image velocity of each identified star from its last two positions (no smoothing).

    The example plugin of docs/plugins.md.
    """

    name = "difference"

    def setup(self, context) -> None:
        super().setup(context)
        self._last: dict[int, tuple[float, float, int]] = {}  # catalog_id -> (x, y, t_ns)

    def process(self, frame: FrameData) -> FrameData:
        stars = frame.stars
        if stars is None:
            return frame.evolve()
        vx, vy = stars.vx.copy(), stars.vy.copy()
        seen = {}
        for i in np.flatnonzero(stars.identified):
            key = int(stars.catalog_id[i])
            seen[key] = (float(stars.x[i]), float(stars.y[i]), int(stars.t_ns[i]))
            if key in self._last:
                x0, y0, t0 = self._last[key]
                dt_s = (seen[key][2] - t0) * 1e-9
                vx[i], vy[i] = (seen[key][0] - x0) / dt_s, (seen[key][1] - y0) / dt_s
        self._last = seen
        return frame.evolve(stars=stars.with_columns(vx=vx, vy=vy))


# ------------------------------------------------------------------------------ broken plugins
class MutatingFilter(KfCvFilter):
    """Writes into the star table it was given."""

    name = "mutating"

    def process(self, frame):
        out = super().process(frame)
        if frame.stars is not None and frame.stars.n:
            frame.stars.x[0] += 0.5
        return out


class NoVelocityFilter(DifferenceFilter):
    """Smooths nothing and leaves vx, vy unknown."""

    name = "no-velocity"

    def process(self, frame):
        return frame.evolve()


class PixelsPerFrameFilter(DifferenceFilter):
    """Velocity in px per frame instead of px/s."""

    name = "px-per-frame"

    def process(self, frame):
        out = super().process(frame)
        period_s = self.context.timing.frame_period_ns * 1e-9
        return out.evolve(stars=out.stars.with_columns(vx=out.stars.vx * period_s, vy=out.stars.vy * period_s))


class UnequalTimesCorrection(TimeDomainCorrection):
    """Moves the stars but leaves each its own time."""

    name = "unequal-times"

    def process(self, frame):
        out = super().process(frame)
        return out.evolve(stars=out.stars.with_columns(t_ns=frame.stars.t_ns))


class RelabelOnlyCorrection(TimeDomainCorrection):
    """Gives every star the common time without moving it."""

    name = "relabel-only"

    def process(self, frame):
        out = super().process(frame)
        return out.evolve(stars=out.stars.with_columns(x=frame.stars.x, y=frame.stars.y))


class SilentRate(RateEstimator):
    """Never sets frame.rate."""

    name = "silent"

    def process(self, frame):
        return frame.evolve()


class RoundingIdentifier(TrackingIdentifier):
    """Rounds the positions of the stars it identifies."""

    name = "rounding"

    def process(self, frame):
        out = super().process(frame)
        return out.evolve(stars=out.stars.with_columns(x=np.round(out.stars.x, 1)))


class FrameStartCentroider(CogCentroider):
    """Times every spot at the frame start."""

    name = "frame-start"

    def process(self, frame):
        out = super().process(frame)
        return out.evolve(stars=out.stars.with_columns(t_ns=np.full(out.stars.n, frame.t0_ns)))


class InverseAttitudeSolver(QuestSolver):
    """Reports the ICRS-to-camera rotation instead of camera-to-ICRS."""

    name = "inverse"

    def process(self, frame):
        out = super().process(frame)
        flipped = [e if not e.valid else type(e)(e.t_ns, e.rotation.inv().as_quat(), e.n_stars)
                   for e in out.attitudes[len(frame.attitudes):]]
        return out.evolve(attitudes=frame.attitudes + tuple(flipped))


class StatefulConstructor(DifferenceFilter):
    """Builds state in the constructor."""

    name = "stateful"

    def __init__(self, **params):
        super().__init__(**params)
        self.cache = {}


class LooseParams(BaseModel):
    smoothing: float = 1.0  # no extra="forbid": misspelt keys are ignored


class LooseParamsFilter(DifferenceFilter):
    """Accepts any parameter."""

    name = "loose"
    Params = LooseParams


class OracleByDefault(DifferenceFilter):
    """Asks for the truth with default parameters."""

    name = "oracle"
    needs_truth = True


class NoneFromUpdatePrior(DifferenceFilter):
    """update_prior answers None instead of a bool."""

    name = "none-prior"

    def update_prior(self, frame):
        return None


class RandomFilter(DifferenceFilter):
    """Different output on every run."""

    name = "random"

    def process(self, frame):
        out = super().process(frame)
        noise = np.random.default_rng().normal(0, 1e-3, out.stars.n)
        return out.evolve(stars=out.stars.with_columns(x=out.stars.x + noise))


class UnknownRole(Plugin):
    """A role the checks do not know."""

    role = "teleporter"
    name = "beam"


BROKEN = [
    (MutatingFilter, C.check_process_standard_frames, "values differ"),
    (MutatingFilter, C.check_process_moving_frames, "values differ"),
    (NoVelocityFilter, C.check_filter_fills_velocity, "without a velocity"),
    (PixelsPerFrameFilter, C.check_filter_fills_velocity, "from the true"),
    (UnequalTimesCorrection, C.check_correction_common_time, "different times"),
    (RelabelOnlyCorrection, C.check_correction_common_time, "kept their position"),
    (SilentRate, C.check_rate_sets_rate, "frame.rate not set"),
    (RoundingIdentifier, C.check_identifier_only_adds_identification, "not the input's"),
    (FrameStartCentroider, C.check_centroider_spots_follow_timing, "mid-exposure"),
    (InverseAttitudeSolver, C.check_process_moving_frames, "from the truth"),
    (StatefulConstructor, C.check_constructor_only_stores_params, "created state"),
    (LooseParamsFilter, C.check_unknown_param_rejected, "extra='forbid'"),
    (OracleByDefault, C.check_hooks_have_defaults, "needs_truth"),
    (NoneFromUpdatePrior, C.check_hooks_have_defaults, "update_prior"),
    (NoneFromUpdatePrior, C.check_process_moving_frames, "must return a bool"),
    (RandomFilter, C.check_deterministic_and_restartable, "values differ"),
    (UnknownRole, C.check_role_has_standard_input, "ROLE_INPUT"),
]


@pytest.mark.parametrize("cls, function, message", BROKEN, ids=[f"{c.name}-{f.__name__}" for c, f, _ in BROKEN])
def test_broken_plugin_fails_its_check(cls, function, message):
    with pytest.raises(AssertionError, match=message) as failure:
        Check(cls, function)()
    assert f"{function.__name__} failed for" in str(failure.value) and repr(cls.name) in str(failure.value)


def test_check_plugin_names_the_first_failed_check():
    with pytest.raises(AssertionError, match="check_correction_common_time failed for correction 'unequal-times'"):
        check_plugin(UnequalTimesCorrection)


def test_a_plugin_written_as_the_docs_show_passes():
    check_plugin(DifferenceFilter)


def test_checks_of_a_plugin_are_those_of_every_plugin_then_its_role():
    names = [c.name for c in plugin_checks(DifferenceFilter)]
    assert names == [f.__name__ for f in C.EVERY_PLUGIN + C.ROLE_CHECKS["filter"]]
    assert str(next(plugin_checks(DifferenceFilter))) == "filter-difference-check_role_has_standard_input"
    assert [c.name for c in plugin_checks(UnknownRole)] == [f.__name__ for f in C.EVERY_PLUGIN]


def test_every_role_with_a_standard_input_has_its_role_checks():
    assert set(C.ROLE_CHECKS) == set(C.ROLE_INPUT)


def test_plugin_base_declares_the_hook_defaults():
    assert Plugin.needs_truth is False and Plugin.defers_output is False
    plugin = Plugin()
    assert plugin.update_prior(FrameData(index=0, t0_ns=0)) is False
    assert plugin.finish() == [] and plugin.release() == []


def test_exceptions_from_the_plugin_become_named_assertion_errors():
    class Crashing(DifferenceFilter):
        """Raises on every frame."""

        name = "crashing"

        def process(self, frame):
            raise ValueError("boom")

    with pytest.raises(AssertionError, match="check_process_standard_frames failed for .*ValueError: boom"):
        Check(Crashing, C.check_process_standard_frames)()
