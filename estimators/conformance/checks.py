"""The conformance checks: each takes a plugin class and raises AssertionError when it breaks a rule.

Every check is a plain function of the plugin class. :func:`plugin_checks` lists those that apply to
a class (the checks every plugin passes, then those of its role) as :class:`Check` objects, and
:func:`check_plugin` runs them all. The input frames come from :mod:`.scenes`: a static scene
(the standard input of each role, with and without stars) and a moving scene (the camera turning,
with gyro samples), each simulated once per process.
"""
from __future__ import annotations

import copy
import dataclasses
import json
from collections.abc import Callable, Iterator

import numpy as np
import pydantic

from rollingstar.estimators.conformance.scenes import (
    ROLE_INPUT,
    MovingScene,
    moving_frames,
    moving_scene,
    standard_frames,
    standard_scene,
)
from rollingstar.estimators.data import AttitudeEstimate, FrameData, RateEstimate, StarTable
from rollingstar.estimators.plugin import Plugin
from rollingstar.sensors.effects.geometry import image_velocity

ARCSEC_PER_RAD = 206264.806
STATIC_MAX_ERROR_ARCSEC = 120.0
# On the moving scene a solver that ignores the rolling shutter is off by a few hundred arcsec in
# roll (the small field turns a readout-time shear into a roll error); the bound only catches a
# wrong convention or a wrong time stamp, not an inaccurate method.
MOVING_MAX_ERROR_ARCSEC = 1800.0
CENTROID_MATCH_PX = 0.5  # a detected spot in the moving scene lies this close to a true star
# A filter's velocity may be off by this fraction of the true image velocity plus this floor
# (the scene's velocities are ~90 px/s; a px-per-frame or sign mistake is off by ~100 %).
VELOCITY_RELATIVE_TOLERANCE = 0.3
VELOCITY_FLOOR_PX_S = 5.0
# The columns an identifier sets; every other column of a star passes through unchanged.
IDENTIFICATION_COLUMNS = ("catalog_id", "ref_icrs")


# ------------------------------------------------------------------------------ comparing and running
def assert_same(a, b, path="frame"):
    """Deep equality of frames and their parts (arrays compared exactly, NaN == NaN)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and a.dtype == b.dtype, f"{path}: {a.dtype}{a.shape} != {b.dtype}{b.shape}"
        assert np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"), f"{path}: values differ"
    elif dataclasses.is_dataclass(a) and not isinstance(a, type):
        assert type(a) is type(b), f"{path}: {type(a)} != {type(b)}"
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, (tuple, list)):
        assert isinstance(b, (tuple, list)) and len(a) == len(b), f"{path}: length differs"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{path}[{i}]")
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


def run(cls, scene, frames):
    """A fresh plugin set up on ``scene`` and run over ``frames``: its outputs, then those of finish()."""
    plugin = cls()
    plugin.setup(scene.context)
    outs = [plugin.process(f) for f in frames]
    return outs + list(plugin.finish())


def run_as_runner(cls, scene, frames) -> list[FrameData]:
    """Run ``frames`` through a fresh plugin as the pipeline runner does.

    After each frame: the frames a ``defers_output`` stage releases, then :meth:`Plugin.update_prior`
    with the frame carrying the true attitude at the frame's reference time (what the attitude
    solver downstream of the stage would give); it must return a bool. Returns every frame the
    plugin gave (provisional ones first, so the last frame of each index is its final one).
    """
    plugin = cls()
    plugin.setup(scene.context)
    timing = scene.context.timing
    outs = []
    for frame in frames:
        out = plugin.process(frame)
        outs.append(out)
        if cls.defers_output:
            outs += list(plugin.release())
        t_ref = int(timing.frame_reference_ns(frame.t0_ns))
        n = 0 if out.stars is None else out.stars.n
        truth = AttitudeEstimate(t_ref, scene.attitude(t_ref).as_quat(), n)
        took = plugin.update_prior(out.evolve(attitudes=out.attitudes + (truth,)))
        assert isinstance(took, bool), f"update_prior must return a bool, got {took!r}"
    return outs + list(plugin.finish())


def final_outputs(outs: list[FrameData]) -> dict[int, FrameData]:
    """The last frame given for each frame index."""
    return {o.index: o for o in outs}


def _input_kind(cls) -> str:
    assert cls.role in ROLE_INPUT, (f"role {cls.role!r} has no standard input: add it to "
                                    "rollingstar.estimators.conformance.scenes.ROLE_INPUT")
    return ROLE_INPUT[cls.role]


# ------------------------------------------------------------------------------ what every output frame satisfies
def check_table(table: StarTable, scene, where: str):
    assert isinstance(table, StarTable), f"{where}: not a StarTable"
    n = table.n
    for f in dataclasses.fields(StarTable):
        col = getattr(table, f.name)
        assert isinstance(col, np.ndarray), f"{where}.{f.name}: not an array"
        assert col.shape == ((n, 3) if f.name == "ref_icrs" else (n,)), f"{where}.{f.name}: shape {col.shape}"
    for name in ("t_ns", "row_time_ns", "catalog_id", "npix"):
        assert getattr(table, name).dtype == np.int64, f"{where}.{name} must be int64"
    assert table.saturated.dtype == bool
    cam = scene.context.camera
    finite = np.isfinite(table.x) & np.isfinite(table.y)
    assert finite.all(), f"{where}: non-finite positions"
    assert np.all(cam.contains(table.x, table.y, margin_px=-1.0)), f"{where}: positions outside the detector"
    ident = table.identified
    if ident.any():
        np.testing.assert_allclose(np.linalg.norm(table.ref_icrs[ident], axis=1), 1.0, atol=1e-9)
        cat = scene.context.catalog
        assert np.all(cat.index_of(table.catalog_id[ident]) >= 0), f"{where}: catalog_id not in the catalogue"
    assert np.all(np.isnan(table.ref_icrs[~ident]))


def frame_window_ns(scene, t0_ns: int) -> tuple[int, int]:
    """Times a frame's results may refer to: from a frame period before its start to one after its end."""
    timing = scene.context.timing
    return t0_ns - timing.frame_period_ns, timing.frame_end_ns(t0_ns) + timing.frame_period_ns


def check_frame(role, before: FrameData, out: FrameData, scene, empty: bool, expected_stars: int,
                max_error_arcsec: float = STATIC_MAX_ERROR_ARCSEC):
    """The rules every output frame of ``role`` follows; ``expected_stars``: the stars on the detector."""
    where = f"frame {before.index}"
    assert isinstance(out, FrameData) and out is not before
    assert out.index == before.index and out.t0_ns == before.t0_ns
    for name in ("stars", "unmatched"):
        if getattr(out, name) is not None:
            check_table(getattr(out, name), scene, f"{where}.{name}")
    t_lo, t_hi = frame_window_ns(scene, before.t0_ns)
    if out.stars is not None and out.stars.n:
        assert np.all((out.stars.t_ns >= t_lo) & (out.stars.t_ns <= t_hi)), f"{where}: star times outside the frame"
    if role == "centroider":
        assert out.stars is not None
        assert not out.stars.identified.any()
        assert (out.stars.n == 0) if empty else (out.stars.n >= expected_stars - 1)
    elif role == "identifier":
        assert out.stars is not None and out.unmatched is not None
        assert out.stars.identified.all()
        assert out.stars.n + out.unmatched.n == before.stars.n
        if not empty:
            assert out.stars.n >= before.stars.n - 1
    elif role in ("filter", "correction"):
        assert out.stars is not None
    if role == "attitude":
        check_attitudes(before, out, scene, empty, max_error_arcsec)
    if role == "rate" and out.rate is not None:
        assert isinstance(out.rate, RateEstimate)
        assert np.shape(out.rate.omega_rad_s) == (3,)
        if out.rate.valid:
            assert np.all(np.isfinite(out.rate.omega_rad_s))
        else:
            assert out.rate.reason


def check_attitudes(before: FrameData, out: FrameData, scene, empty: bool, max_error_arcsec: float):
    """An attitude solver keeps the estimates it was given and appends its own, near the truth."""
    where = f"frame {before.index}"
    t_lo, t_hi = frame_window_ns(scene, before.t0_ns)
    new = out.attitudes[len(before.attitudes):]
    assert_same(out.attitudes[: len(before.attitudes)], before.attitudes, f"{where}.attitudes")
    assert len(new) >= 1, f"{where}: an attitude solver must append an estimate"
    for est in new:
        assert isinstance(est, AttitudeEstimate)
        assert isinstance(est.t_ns, (int, np.integer)) and t_lo <= est.t_ns <= t_hi
        if empty:
            assert not est.valid and est.reason, "no stars must give an invalid estimate with a reason"
        if est.valid:
            assert est.q_xyzw.shape == (4,)
            assert np.isclose(np.linalg.norm(est.q_xyzw), 1.0, atol=1e-9)
            err = (scene.attitude(int(est.t_ns)).inv() * est.rotation).magnitude()
            assert err * ARCSEC_PER_RAD < max_error_arcsec, f"{where}: estimate {err} rad from the truth"
            if est.covariance_rad2 is not None:
                P = np.asarray(est.covariance_rad2)
                assert P.shape == (3, 3) and np.allclose(P, P.T) and np.all(np.linalg.eigvalsh(P) > 0)
        else:
            assert est.reason and np.all(np.isnan(est.q_xyzw))
    if not empty and len(before.stars) >= 3:
        assert any(e.valid for e in new)


# ------------------------------------------------------------------------------ checks of every plugin
def check_constructor_only_stores_params(cls):
    """The constructor validates the parameters into ``cls.Params`` and stores nothing else (heavy
    work belongs in ``setup``; checked by what the instance holds, never by a clock)."""
    plugin = cls()
    assert issubclass(cls, Plugin), "a plugin subclasses a role base class of rollingstar.estimators"
    assert cls.role and cls.name, "a plugin class sets role and name"
    assert set(vars(plugin)) == {"params"}, f"the constructor created state: {sorted(vars(plugin))}"
    assert isinstance(plugin.params, cls.Params)
    text = repr(plugin)
    assert text.startswith(cls.__name__ + "(")
    assert cls.__doc__ and cls.__doc__.strip()


def check_unknown_param_rejected(cls):
    """A misspelt parameter is an error, not silently ignored."""
    assert cls.Params.model_config.get("extra") == "forbid", "Params needs model_config = ConfigDict(extra='forbid')"
    try:
        cls(definitely_not_a_param=1)
    except pydantic.ValidationError:
        return
    raise AssertionError("an unknown parameter was accepted")


def check_params_round_trip(cls):
    """Parameters round-trip through the constructor, as given and through JSON (a config file)."""
    plugin = cls()
    again = cls(**plugin.params.model_dump())
    assert again.params == plugin.params
    assert plugin.params == cls.Params(), "the constructor changed the default parameters"
    given = plugin.params.model_dump()
    assert cls(**given).params.model_dump() == given, "the constructor did not store the parameters as given"
    from_json = cls(**json.loads(plugin.params.model_dump_json()))
    assert from_json.params == plugin.params, "the parameters do not survive a round trip through JSON"


def check_hooks_have_defaults(cls):
    """The optional hooks of :class:`Plugin` keep their declared types and defaults.

    With default parameters a plugin is no oracle (``needs_truth`` False: it runs on real data); a
    freshly set-up plugin holds no frames back (``finish`` and ``release`` give ``[]``) and takes no
    prior from a frame without an attitude (``update_prior`` False).
    """
    plugin = cls()
    assert isinstance(cls.defers_output, bool), f"defers_output must be a bool, got {cls.defers_output!r}"
    assert plugin.needs_truth is False, f"needs_truth must be False with default parameters, got {plugin.needs_truth!r}"
    plugin.setup(standard_scene().context)
    took = plugin.update_prior(standard_frames("attitude")[0])  # identified stars, no attitude
    assert took is False, f"update_prior of a frame without an attitude must be False, got {took!r}"
    assert plugin.release() == [], "a freshly set-up plugin has released nothing"
    assert plugin.finish() == [], "a freshly set-up plugin holds no frames back"


def check_role_has_standard_input(cls):
    """The plugin's role is one the checks know the input of."""
    _input_kind(cls)


def _process_standard(cls, empty: bool):
    _input_kind(cls)
    scene = standard_scene()
    frames = standard_frames(cls.role, empty=empty)
    snapshot = copy.deepcopy(frames)
    outs = run(cls, scene, frames)
    assert len(outs) >= 1
    # inputs not mutated (frames and every array inside them)
    for a, b in zip(frames, snapshot):
        assert_same(a, b)
    by_index = final_outputs(outs)
    for f in frames:
        if f.index in by_index:
            check_frame(cls.role, f, by_index[f.index], scene, empty, scene.x.size)


def check_process_standard_frames(cls):
    """The static scene's standard input: valid output frames, the input left untouched."""
    _process_standard(cls, empty=False)


def check_process_empty_frames(cls):
    """The same frames without any star: valid output frames (invalid estimates say why)."""
    _process_standard(cls, empty=True)


def check_deterministic_and_restartable(cls):
    """Two runs give the same frames, and setup() again restarts the plugin."""
    _input_kind(cls)
    scene = standard_scene()
    frames = standard_frames(cls.role)
    a = run(cls, scene, frames)
    b = run(cls, scene, frames)
    assert_same(a, b)
    # setup() again restarts the plugin: the same outputs again
    plugin = cls()
    plugin.setup(scene.context)
    first = [plugin.process(f) for f in frames]
    plugin.setup(scene.context)
    second = [plugin.process(f) for f in frames]
    assert_same(first, second)


def check_process_moving_frames(cls):
    """The moving scene (camera turning, gyro samples) run as the runner does: valid output frames,
    the input left untouched, ``update_prior`` answering a bool."""
    _input_kind(cls)
    scene = moving_scene()
    frames = moving_frames(cls.role)
    snapshot = copy.deepcopy(frames)
    by_index = final_outputs(run_as_runner(cls, scene, frames))
    for a, b in zip(frames, snapshot):
        assert_same(a, b)
    for f in frames:
        assert f.index in by_index, f"frame {f.index}: no output"
        check_frame(cls.role, f, by_index[f.index], scene, False, len(scene.stars[f.index]), MOVING_MAX_ERROR_ARCSEC)


# ------------------------------------------------------------------------------ the role contracts, on the moving scene
def _moving_run(cls) -> tuple[MovingScene, list[FrameData], dict[int, FrameData]]:
    """The moving scene, ``cls``'s input frames in it, and its final output frame of each index."""
    scene = moving_scene()
    frames = moving_frames(cls.role)
    return scene, frames, final_outputs(run_as_runner(cls, scene, copy.deepcopy(frames)))


def check_centroider_spots_follow_timing(cls):
    """Spots lie on the true stars, timed by the sensor timing: ``row_time_ns`` the exposure start of
    the centroid row, ``t_ns`` its mid-exposure."""
    scene, frames, outs = _moving_run(cls)
    timing = scene.context.timing
    for f in frames:
        stars, truth, where = outs[f.index].stars, scene.stars[f.index], f"frame {f.index}"
        row_start = timing.row_start_ns(f.t0_ns, stars.y)
        assert np.all(np.abs(stars.row_time_ns - row_start) <= 1), f"{where}: row_time_ns is not the centroid row's start"
        mid = timing.row_mid_exposure_ns(f.t0_ns, stars.y)
        assert np.all(np.abs(stars.t_ns - mid) <= 1), f"{where}: t_ns is not the centroid row's mid-exposure"
        dist = np.hypot(stars.x[:, None] - truth.x[None, :], stars.y[:, None] - truth.y[None, :])
        off = dist.min(axis=1, initial=np.inf)
        assert np.all(off <= CENTROID_MATCH_PX), f"{where}: spots {np.round(off, 2)} px from the nearest true star"


def check_identifier_only_adds_identification(cls):
    """Identified stars and unmatched detections are the input detections with only ``catalog_id``
    and ``ref_icrs`` set, and every identification is right."""
    scene, frames, outs = _moving_run(cls)
    catalog = scene.context.catalog
    for f in frames:
        out, truth, where = outs[f.index], scene.stars[f.index], f"frame {f.index}"
        given = {(x, y): i for i, (x, y) in enumerate(zip(f.stars.x, f.stars.y))}
        for name, table in (("stars", out.stars), ("unmatched", out.unmatched)):
            rows = [given.get((x, y), -1) for x, y in zip(table.x, table.y)]
            assert min(rows, default=0) >= 0, f"{where}.{name}: positions that are not the input's"
            source = f.stars.take(np.asarray(rows, dtype=np.intp))
            for col in dataclasses.fields(StarTable):
                if col.name not in IDENTIFICATION_COLUMNS:
                    assert_same(getattr(table, col.name), getattr(source, col.name), f"{where}.{name}.{col.name}")
            if name == "stars":
                wrong = table.catalog_id != truth.catalog_id[rows]
                assert not wrong.any(), f"{where}: {int(wrong.sum())} stars identified as the wrong catalogue star"
                expected = catalog.unit_icrs[catalog.index_of(table.catalog_id)]
                np.testing.assert_allclose(table.ref_icrs, expected, atol=1e-12, err_msg=f"{where}: ref_icrs")
            else:
                assert not table.identified.any(), f"{where}: unmatched stars carry a catalog_id"


def check_filter_fills_velocity(cls):
    """Every star tracked since the previous frame gets its image velocity ``vx, vy`` in px/s."""
    scene, frames, outs = _moving_run(cls)
    camera = scene.context.camera
    previous: set[int] = set()
    for f in frames:
        stars, where = outs[f.index].stars, f"frame {f.index}"
        tracked = stars.identified & np.isin(stars.catalog_id, list(previous))
        previous = set(f.stars.catalog_id[f.stars.identified].tolist())
        if f.index == frames[0].index:
            continue
        assert tracked.any(), f"{where}: no star of the previous frame in the output"
        vx, vy = stars.vx[tracked], stars.vy[tracked]
        assert np.all(np.isfinite(vx) & np.isfinite(vy)), f"{where}: tracked stars without a velocity"
        tx, ty = image_velocity(camera, stars.x[tracked], stars.y[tracked], scene.omega_rad_s)
        err, speed = np.hypot(vx - tx, vy - ty), np.hypot(tx, ty)
        bad = err > VELOCITY_RELATIVE_TOLERANCE * speed + VELOCITY_FLOOR_PX_S
        assert not bad.any(), f"{where}: velocities {np.round(err[bad], 1)} px/s from the true {np.round(speed[bad], 1)}"


def check_correction_common_time(cls):
    """A correction moves every star to one common time and says so in ``t_ns`` (a correction that
    leaves the stars exactly as they were, the identity baseline, passes too)."""
    scene, frames, outs = _moving_run(cls)
    for f in frames:
        stars, where = outs[f.index].stars, f"frame {f.index}"
        assert stars.n == f.stars.n, f"{where}: a correction keeps every star ({stars.n} of {f.stars.n})"
        unchanged = all(np.array_equal(getattr(stars, c), getattr(f.stars, c)) for c in ("x", "y", "t_ns"))
        if unchanged:
            continue
        times = np.unique(stars.t_ns)
        assert times.size == 1, f"{where}: corrected stars refer to {times.size} different times"
        t_lo, t_hi = frame_window_ns(scene, f.t0_ns)
        assert t_lo <= times[0] <= t_hi, f"{where}: the common time {times[0]} ns is outside the frame"
        moved_in_time = stars.t_ns != f.stars.t_ns
        still = moved_in_time & (stars.x == f.stars.x) & (stars.y == f.stars.y)
        assert not still.any(), f"{where}: {int(still.sum())} stars got a new time but kept their position"


def check_rate_sets_rate(cls):
    """A rate estimator sets ``frame.rate`` on every frame: valid and finite with enough stars."""
    scene, frames, outs = _moving_run(cls)
    for f in frames:
        rate, where = outs[f.index].rate, f"frame {f.index}"
        assert isinstance(rate, RateEstimate), f"{where}: frame.rate not set (got {rate!r})"
        assert rate.valid, f"{where}: invalid rate with {f.stars.n} stars: {rate.reason}"
        assert np.shape(rate.omega_rad_s) == (3,) and np.all(np.isfinite(rate.omega_rad_s))
        t_lo, t_hi = frame_window_ns(scene, f.t0_ns)
        assert t_lo <= rate.t_ns <= t_hi, f"{where}: the rate's time {rate.t_ns} ns is outside the frame"
        if rate.covariance is not None:
            assert np.shape(rate.covariance) == (3, 3), f"{where}: rate covariance of shape {np.shape(rate.covariance)}"


# ------------------------------------------------------------------------------ which checks apply
EVERY_PLUGIN: tuple[Callable, ...] = (
    check_role_has_standard_input,
    check_constructor_only_stores_params,
    check_unknown_param_rejected,
    check_params_round_trip,
    check_hooks_have_defaults,
    check_process_standard_frames,
    check_process_empty_frames,
    check_deterministic_and_restartable,
    check_process_moving_frames,
)
ROLE_CHECKS: dict[str, tuple[Callable, ...]] = {
    "centroider": (check_centroider_spots_follow_timing,),
    "identifier": (check_identifier_only_adds_identification,),
    "filter": (check_filter_fills_velocity,),
    "correction": (check_correction_common_time,),
    "rate": (check_rate_sets_rate,),
    "attitude": (),  # its contract (estimates near the truth at their time) is in check_process_moving_frames
}


@dataclasses.dataclass(frozen=True)
class Check:
    """One check of one plugin class; calling it runs the check.

    Failures (and any exception the plugin raises) come out as AssertionError naming the check and
    the plugin. ``str(check)`` is a test id such as ``filter-kf-cv-check_filter_fills_velocity``.
    """

    plugin_class: type
    function: Callable[[type], None]

    @property
    def name(self) -> str:
        return self.function.__name__

    def __call__(self) -> None:
        cls = self.plugin_class
        try:
            self.function(cls)
        except AssertionError as exc:
            raise AssertionError(f"{self.name} failed for {_label(cls)}: {exc}") from exc
        except Exception as exc:
            raise AssertionError(f"{self.name} failed for {_label(cls)}: {type(exc).__name__}: {exc}") from exc

    def __str__(self) -> str:
        return f"{getattr(self.plugin_class, 'role', '') or '?'}-{_kind(self.plugin_class)}-{self.name}"


def _kind(cls) -> str:
    return getattr(cls, "name", "") or cls.__name__


def _label(cls) -> str:
    return f"{getattr(cls, 'role', '') or 'plugin'} {_kind(cls)!r} ({cls.__module__}.{cls.__qualname__})"


def plugin_checks(plugin_class: type) -> Iterator[Check]:
    """The checks of ``plugin_class``: those of every plugin, then those of its role."""
    for function in EVERY_PLUGIN + ROLE_CHECKS.get(getattr(plugin_class, "role", ""), ()):
        yield Check(plugin_class, function)


def check_plugin(plugin_class: type) -> None:
    """Run every check of ``plugin_class``; the first failure raises AssertionError naming it."""
    for check in plugin_checks(plugin_class):
        check()
