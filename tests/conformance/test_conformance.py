"""The shared conformance suite: every registered plugin (built-in or third-party) of every role.

Parametrised over ``rollingstar.pipelines.registry.plugins_by_role()``, so a new plugin is checked as soon as it
is registered. Each role's standard input comes from ``scene.frames_for_role``.
"""
from __future__ import annotations

import copy
import dataclasses
import time

import numpy as np
import pydantic
import pytest

from rollingstar.estimators.data import (
    AttitudeEstimate,
    FrameData,
    RateEstimate,
    StarTable,
)
from rollingstar.pipelines.registry import plugins_by_role
from tests.conformance.scene import ROLE_INPUT, frames_for_role, make_scene

PLUGINS = [(role, cls) for role, classes in plugins_by_role().items() for cls in classes]
IDS = [f"{role}-{cls.name or cls.__name__}" for role, cls in PLUGINS]
pytestmark = pytest.mark.parametrize("role, cls", PLUGINS, ids=IDS)


@pytest.fixture(scope="module")
def scene():
    return make_scene(seed=101)


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
    plugin = cls()
    plugin.setup(scene.context)
    outs = [plugin.process(f) for f in frames]
    return outs + list(plugin.finish())


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


def check_frame(role, before: FrameData, out: FrameData, scene, empty: bool):
    where = f"frame {before.index}"
    assert isinstance(out, FrameData) and out is not before
    assert out.index == before.index and out.t0_ns == before.t0_ns
    for name in ("stars", "unmatched"):
        if getattr(out, name) is not None:
            check_table(getattr(out, name), scene, f"{where}.{name}")
    t_lo = before.t0_ns - scene.context.timing.frame_period_ns
    t_hi = scene.context.timing.frame_end_ns(before.t0_ns) + scene.context.timing.frame_period_ns
    if out.stars is not None and out.stars.n:
        assert np.all((out.stars.t_ns >= t_lo) & (out.stars.t_ns <= t_hi)), f"{where}: star times outside the frame"
    if role == "centroider":
        assert out.stars is not None
        assert not out.stars.identified.any()
        assert (out.stars.n == 0) if empty else (out.stars.n >= scene.x.size - 1)
    elif role == "identifier":
        assert out.stars is not None and out.unmatched is not None
        assert out.stars.identified.all()
        assert out.stars.n + out.unmatched.n == before.stars.n
        if not empty:
            assert out.stars.n >= before.stars.n - 1
    elif role in ("filter", "correction"):
        assert out.stars is not None
    if role == "attitude":
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
                err = (scene.truth.inv() * est.rotation).magnitude()
                assert np.degrees(err) * 3600 < 120, f"{where}: estimate {err} rad from the truth"
                if est.covariance_rad2 is not None:
                    P = np.asarray(est.covariance_rad2)
                    assert P.shape == (3, 3) and np.allclose(P, P.T) and np.all(np.linalg.eigvalsh(P) > 0)
            else:
                assert est.reason and np.all(np.isnan(est.q_xyzw))
        if not empty and len(before.stars) >= 3:
            assert any(e.valid for e in new)
    if role == "rate" and out.rate is not None:
        assert isinstance(out.rate, RateEstimate)
        assert np.shape(out.rate.omega_rad_s) == (3,)
        if out.rate.valid:
            assert np.all(np.isfinite(out.rate.omega_rad_s))
        else:
            assert out.rate.reason


# ------------------------------------------------------------------------------------------


def test_constructor_only_stores_params(role, cls):
    start = time.perf_counter()
    plugin = cls()
    assert time.perf_counter() - start < 0.05, "the constructor must not do heavy work"
    assert cls.role == role and cls.name
    assert set(vars(plugin)) == {"params"}, f"the constructor created state: {sorted(vars(plugin))}"
    assert isinstance(plugin.params, cls.Params)
    text = repr(plugin)
    assert text.startswith(cls.__name__ + "(")
    assert cls.__doc__ and cls.__doc__.strip()


def test_unknown_param_rejected(role, cls):
    with pytest.raises(pydantic.ValidationError):
        cls(definitely_not_a_param=1)
    assert cls.Params.model_config.get("extra") == "forbid"


def test_default_params_round_trip(role, cls):
    plugin = cls()
    again = cls(**plugin.params.model_dump())
    assert again.params == plugin.params


@pytest.mark.parametrize("empty", [False, True], ids=["stars", "empty"])
def test_process_standard_frames(role, cls, scene, empty):
    frames = frames_for_role(role, scene, empty=empty)
    snapshot = copy.deepcopy(frames)
    outs = run(cls, scene, frames)
    assert len(outs) >= 1
    # inputs not mutated (frames and every array inside them)
    for a, b in zip(frames, snapshot):
        assert_same(a, b)
    by_index = {o.index: o for o in outs}
    for f in frames:
        if f.index in by_index:
            check_frame(role, f, by_index[f.index], scene, empty)


def test_deterministic_and_restartable(role, cls, scene):
    frames = frames_for_role(role, scene)
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


def test_role_has_standard_input(role, cls):
    assert role in ROLE_INPUT, f"role {role!r} needs an entry in tests/conformance/scene.ROLE_INPUT"
