"""Effect library: registry, parameter validation, identity at defaults, analytic Jacobians vs finite
differences of every forward model (hypothesis over positions and parameters), known answers,
detection-limit invariants and the generated doc."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.conventions import ARCSEC_TO_RAD, attitude_from_radec_roll
from rollingstar.sensors.effects import (
    EFFECTS,
    NUISANCE,
    Effect,
    EffectContext,
    EffectParameter,
    MissingContextError,
    UnknownEffectError,
    build_effect,
)
from rollingstar.sensors.effects.chain import chain_jacobian, entering, ordered, predict, resume
from rollingstar.sensors.effects.context import context_from_attitude
from rollingstar.sensors.effects.design import (
    detection_limit,
    parameter_sigma,
    project_out,
)
from rollingstar.sensors.effects.doc import render_markdown
from rollingstar.sensors.effects.principal_point import PrincipalPointOffset
from rollingstar.sensors.effects.radial_distortion import RadialDistortion
from rollingstar.sensors.timing import DetectorTiming

CAMERA = PinholeCamera(focal_length_m=24.09e-3, pixel_size_m=5.5e-6, width=1024, height=1024)
TIMING = DetectorTiming("rolling", exposure_ns=50_000_000, line_delay_ns=49_000, rows=1024)
ROOT = Path(__file__).resolve().parents[2]


def full_context(seed=1, n=200, frames=4) -> EffectContext:
    """Every context field populated: stars over the detector seen by a turning camera on the ground."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.5, 1023.5, n)
    y = rng.uniform(-0.5, 1023.5, n)
    frame = rng.integers(0, frames, n)
    t0 = TIMING.frame_start_ns(frame)
    t = TIMING.row_mid_exposure_ns(t0, y) + 3_600_000_000_000 * 2  # two hours into the recording (drift)
    t0 = t0 + 3_600_000_000_000 * 2
    att0 = attitude_from_radec_roll(*rng.uniform([0, -60, -180], [360, 60, 180]))
    omega = np.deg2rad(rng.uniform(-3, 3, 3))
    att = att0 * Rotation.from_rotvec(np.outer((t - t[0]) / 1e9, omega))
    unit = att.apply(CAMERA.unproject(x, y))
    pm = rng.normal(0, 200e-3 * ARCSEC_TO_RAD, (n, 3))
    pm -= np.sum(pm * unit, axis=1, keepdims=True) * unit  # tangent to the sphere
    zen = att0.apply([0.0, -np.cos(0.6), np.sin(0.6)])  # boresight elevation ~34 deg
    return context_from_attitude(
        CAMERA, att, unit, t, np.broadcast_to(omega, (n, 3)), t0_ns=t0, frame=frame, row=y,
        magnitude=rng.uniform(1, 7, n), flux_e=rng.uniform(1e3, 1e5, n), pm_rad_yr=pm,
        zenith_icrs=np.broadcast_to(zen, (n, 3)), covariates={"temperature_c": rng.uniform(-10, 40, n)},
        timing=TIMING, t_start_ns=0,
    )


def random_values(cls, rng, scale=3.0):
    """Values a few prior scales from the defaults, inside the bounds."""
    out = {}
    for p in cls.parameters:
        lo, hi = p.bounds
        margin = 1e-2 * (hi - lo)  # room for finite differences
        out[p.name] = float(np.clip(p.default + scale * p.prior_scale * rng.uniform(-1, 1), lo + margin, hi - margin))
    return out


NAMES = sorted(EFFECTS)
# physical effects: every parameter has a first-order signature at the defaults; empirical shapes
# (sensors/effects/empirical.py) have discrete choices and location parameters that do not
PHYSICAL = [n for n in NAMES if not EFFECTS[n].empirical]
REQUIRED = ("rolling_shutter", "exposure_smear", "radial_distortion", "tangential_distortion", "principal_point",
            "focal_length", "boresight_rotation", "stellar_aberration", "time_offset", "gyro_bias", "gyro_scale",
            "thermal_focal_drift", "pixel_phase_bias", "magnitude_bias", "angular_acceleration", "catalog_epoch",
            "refraction")


def test_library_has_every_effect_of_the_issue():
    assert set(REQUIRED) <= set(EFFECTS)


@pytest.mark.parametrize("name", NAMES)
def test_registry_entry_is_well_formed(name):
    cls = EFFECTS[name]
    assert issubclass(cls, Effect) and cls.name == name
    assert cls.parameters and all(isinstance(p, EffectParameter) for p in cls.parameters)
    assert len(set(cls.parameter_names())) == len(cls.parameters)
    assert len(cls.explanation) > 200  # a paragraph a user can read
    assert cls.channels and cls.channels <= {"image", "time", "gyro", "attitude"}
    for synonym in cls.synonyms:
        assert type(build_effect(synonym, {})) is cls
    assert cls.aliases, "every effect names what it can be confused with"
    for a in cls.aliases:
        assert a.other in EFFECTS or a.other in NUISANCE
        assert a.other != name and len(a.separating_experiment) > 30 and a.reason


def test_synonyms_are_unique_and_do_not_shadow_names():
    synonyms = [a for cls in EFFECTS.values() for a in cls.synonyms]
    assert len(synonyms) == len(set(synonyms))
    assert not set(synonyms) & set(EFFECTS)


@pytest.mark.parametrize("name", NAMES)
def test_defaults_are_identity(name):
    ctx = full_context()
    effect = build_effect(name, {})
    assert effect.is_identity
    x2, y2 = effect.apply(ctx.x, ctx.y, ctx)
    np.testing.assert_array_equal(x2, ctx.x)
    np.testing.assert_array_equal(y2, ctx.y)
    np.testing.assert_array_equal(effect.time_shift_s(ctx), 0.0)
    w = np.random.default_rng(0).normal(size=(20, 3))
    np.testing.assert_array_equal(effect.apply_gyro(np.arange(20), w), w)


def _fd_check(cls, ctx, values):
    """Analytic Jacobian at ``values`` against central differences of ``apply`` (and of the gyro hook)."""
    effect = cls(**values)
    jac = effect.jacobian(ctx.x, ctx.y, ctx)
    assert jac.shape == (ctx.n, 2, len(cls.parameters))
    omega = np.random.default_rng(3).normal(0, 0.05, (30, 3))
    gjac = effect.gyro_jacobian(np.arange(30), omega)
    assert gjac.shape == (30, 3, len(cls.parameters))
    for j, p in enumerate(cls.parameters):
        h = 1e-3 * p.prior_scale
        plus, minus = dict(values), dict(values)
        plus[p.name] += h
        minus[p.name] -= h
        xp, yp = cls(**plus).apply(ctx.x, ctx.y, ctx)
        xm, ym = cls(**minus).apply(ctx.x, ctx.y, ctx)
        fd = np.stack([(xp - xm) / (2 * h), (yp - ym) / (2 * h)], axis=-1)
        # central differences: truncation ~h^2 f''' (tiny here: every forward model is smooth on
        # the scale of 1e-3 prior scales), round-off ~1e-13 px / h
        scale = max(np.abs(fd).max(), 1e-300)
        np.testing.assert_allclose(jac[:, :, j], fd, rtol=1e-5, atol=1e-6 * scale + 1e-11 / h,
                                   err_msg=f"{cls.name}.{p.name}")
        gp = cls(**plus).apply_gyro(np.arange(30), omega)
        gm = cls(**minus).apply_gyro(np.arange(30), omega)
        np.testing.assert_allclose(gjac[:, :, j], (gp - gm) / (2 * h), rtol=1e-6, atol=1e-15 / h)


@pytest.mark.parametrize("name", PHYSICAL)
@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_jacobian_matches_finite_differences(name, seed):
    rng = np.random.default_rng(seed)
    cls = EFFECTS[name]
    _fd_check(cls, full_context(seed=seed % 1000, n=60), random_values(cls, rng))


@pytest.mark.parametrize("name", PHYSICAL)
def test_jacobian_at_defaults_is_the_signature(name):
    """At the defaults the Jacobian is the whole first-order signature: apply(p) - x ~ J p."""
    cls = EFFECTS[name]
    ctx = full_context(seed=5)
    small = {p.name: p.default + 1e-3 * p.prior_scale for p in cls.parameters}
    x2, y2 = cls(**small).apply(ctx.x, ctx.y, ctx)
    pred = cls().jacobian(ctx.x, ctx.y, ctx) @ np.array([1e-3 * p.prior_scale for p in cls.parameters])
    d = np.stack([x2 - ctx.x, y2 - ctx.y], axis=-1)
    np.testing.assert_allclose(d, pred, atol=1e-4 * max(np.abs(pred).max(), 1e-12) + 1e-12)


# ------------------------------------------------------------------------------- known answers
def test_radial_distortion_known_answer():
    f = CAMERA.focal_px
    xn, yn = 0.1, -0.05
    x, y = CAMERA.cx + f * xn, CAMERA.cy + f * yn
    r2 = xn**2 + yn**2
    k1, k2 = 0.02, -0.3
    ctx = EffectContext(camera=CAMERA, x=[x, CAMERA.cx], y=[y, CAMERA.cy], t_ns=0)
    (xd, xc), (yd, yc) = RadialDistortion(k1=k1, k2=k2).apply(ctx.x, ctx.y, ctx)
    scale = 1 + k1 * r2 + k2 * r2**2
    assert xd == pytest.approx(CAMERA.cx + f * xn * scale, abs=1e-9)
    assert yd == pytest.approx(CAMERA.cy + f * yn * scale, abs=1e-9)
    assert (xc, yc) == (CAMERA.cx, CAMERA.cy)  # the principal point is a fixed point
    assert (xd - x) * (y - CAMERA.cy) - (yd - y) * (x - CAMERA.cx) == pytest.approx(0.0, abs=1e-6)  # radial


def test_principal_point_shifts_every_position():
    ctx = full_context()
    xs, ys = PrincipalPointOffset(dx=2.5, dy=-1.25).apply(ctx.x, ctx.y, ctx)
    np.testing.assert_allclose(xs - ctx.x, 2.5, atol=1e-12)
    np.testing.assert_allclose(ys - ctx.y, -1.25, atol=1e-12)


def test_boresight_rotation_rotates_the_image_about_the_principal_point():
    ctx = full_context()
    gamma = 300.0  # arcsec
    x2, y2 = build_effect("boresight_rotation", {"roll_arcsec": gamma}).apply(ctx.x, ctx.y, ctx)
    a = np.arctan2(ctx.y - CAMERA.cy, ctx.x - CAMERA.cx)
    a2 = np.arctan2(y2 - CAMERA.cy, x2 - CAMERA.cx)
    r, r2 = np.hypot(ctx.x - CAMERA.cx, ctx.y - CAMERA.cy), np.hypot(x2 - CAMERA.cx, y2 - CAMERA.cy)
    np.testing.assert_allclose(r2, r, atol=1e-9)
    # w' = Rz(g)^T w turns camera vectors by -g; image x ~ -w_x, y ~ -w_y keeps the sense: -g in the image
    np.testing.assert_allclose(np.angle(np.exp(1j * (a2 - a))), -gamma * ARCSEC_TO_RAD, atol=1e-12)


def test_time_offset_equals_the_true_motion_at_the_shifted_time():
    """For a constant rate, apply() of a time shift is exactly the pinhole position at t + dt."""
    ctx = full_context()
    dt = 0.0123
    x2, y2 = build_effect("time_offset", {"offset_ms": dt * 1e3}).apply(ctx.x, ctx.y, ctx)
    later = ctx.attitude * Rotation.from_rotvec(ctx.omega_rad_s * dt)
    xe, ye, _ = CAMERA.project(later.inv().apply(ctx.unit_icrs))
    np.testing.assert_allclose(x2, xe, atol=1e-9)
    np.testing.assert_allclose(y2, ye, atol=1e-9)


def test_rolling_shutter_shift_is_row_times_line_delay_error():
    ctx = full_context()
    e = build_effect("rolling_shutter", {"line_delay_error_us": 30.0})
    np.testing.assert_allclose(e.time_shift_s(ctx), ctx.rows * 30e-6, rtol=1e-12)


def test_refraction_lifts_stars_towards_the_zenith_by_r0_cot_e():
    ctx = full_context()
    r0 = 58.0
    x2, y2 = build_effect("refraction", {"r0_arcsec": r0}).apply(ctx.x, ctx.y, ctx)
    w, w2 = CAMERA.unproject(ctx.x, ctx.y), CAMERA.unproject(x2, y2)
    z = ctx.attitude.inv().apply(np.array(ctx.zenith_icrs))
    e, e2 = np.arcsin(np.sum(w * z, 1)), np.arcsin(np.sum(w2 * z, 1))
    np.testing.assert_allclose((e2 - e) / ARCSEC_TO_RAD, r0 / np.tan(e), rtol=1e-6)


def test_stellar_aberration_is_v_over_c_towards_the_apex():
    ctx = full_context()
    v = np.array([20.0, -10.0, 5.0])
    x2, y2 = build_effect("stellar_aberration", dict(zip(("vx_km_s", "vy_km_s", "vz_km_s"), v))).apply(ctx.x, ctx.y, ctx)
    u2 = ctx.attitude.apply(CAMERA.unproject(x2, y2))
    u = ctx.unit_icrs
    beta = v / 299_792.458
    sin_theta = np.linalg.norm(np.cross(u, beta / np.linalg.norm(beta)), axis=1)
    shift = np.arccos(np.clip(np.sum(u * u2, 1), -1, 1))
    np.testing.assert_allclose(shift, np.linalg.norm(beta) * sin_theta, rtol=2e-4)  # first order in beta


def test_gyro_hooks_known_answers():
    w = np.array([[0.1, -0.2, 0.3]])
    b = build_effect("gyro_bias", {"bx_deg_h": 36.0}).apply_gyro([0], w)
    np.testing.assert_allclose(b - w, [[np.radians(36.0) / 3600, 0, 0]], atol=1e-15)
    s = build_effect("gyro_scale", {"sz_ppm": 1000.0}).apply_gyro([0], w)
    np.testing.assert_allclose(s - w, [[0, 0, 0.3e-3]], atol=1e-15)


# ------------------------------------------------------------------- chains, context and design
def test_chain_order_is_canonical_and_predict_composes():
    effs = [build_effect("pixel_phase_bias", {"ax_px": 0.01}), build_effect("time_offset", {"offset_ms": 3.0}),
            build_effect("focal_length", {"df_ppm": 100.0})]
    assert [e.name for e in ordered(effs)] == ["time_offset", "focal_length", "pixel_phase_bias"]
    ctx = full_context()
    x, y = ctx.x, ctx.y
    for e in ordered(effs):
        x, y = e.apply(x, y, ctx)
    np.testing.assert_array_equal(predict(effs, ctx), (x, y))
    jac, labels = chain_jacobian(effs, ctx)
    assert jac.shape == (ctx.n, 2, 4) and labels[0] == ("time_offset", "offset_ms")


def test_missing_context_field_is_named():
    ctx = EffectContext(camera=CAMERA, x=[1.0], y=[2.0], t_ns=[0])
    with pytest.raises(MissingContextError, match="magnitude"):
        predict([build_effect("magnitude_bias", {"bx_px_per_mag": 0.1})], ctx)
    with pytest.raises(MissingContextError, match="zenith_icrs"):
        predict([build_effect("refraction", {"r0_arcsec": 50})], ctx)


def test_attitude_collinear_effects_vanish_after_projection():
    """A detector roll and a clock offset (constant rate) are rigid rotations: the per-frame attitude
    fit absorbs them entirely; a radial distortion is not absorbed."""
    ctx = full_context()
    for name in ("boresight_rotation", "time_offset"):
        e = build_effect(name, {})
        raw = e.jacobian(ctx.x, ctx.y, ctx)
        assert np.abs(project_out(raw, ctx, "attitude")).max() < 1e-9 * np.abs(raw).max()
        assert np.isinf(parameter_sigma(e, ctx, 0.05)).all() or parameter_sigma(e, ctx, 0.05).min() > 1e6
    # time offset: the absorbed attitude is omega * 1e-3 rad per ms
    att = build_effect("time_offset", {}).attitude_jacobian(ctx)[:, :, 0]
    np.testing.assert_allclose(att, ctx.omega_rad_s * 1e-3, rtol=1e-6, atol=1e-15)
    radial = build_effect("radial_distortion", {})
    kept = np.linalg.norm(project_out(radial.jacobian(ctx.x, ctx.y, ctx), ctx, "attitude"))
    assert kept > 0.5 * np.linalg.norm(radial.jacobian(ctx.x, ctx.y, ctx))


def test_detection_limit_of_a_shift_without_nuisance_is_n_sigma_over_sqrt_n():
    ctx = full_context()
    lim = detection_limit(PrincipalPointOffset(), ctx, sigma_px=0.1, n_sigma=5.0, nuisance=None)
    assert lim["dx"] == pytest.approx(5.0 * 0.1 / np.sqrt(ctx.n), rel=1e-12)
    # with the attitude refitted a principal-point shift is almost invisible
    assert detection_limit(PrincipalPointOffset(), ctx, 0.1, 5.0)["dx"] > 20 * lim["dx"]


@pytest.mark.parametrize("name", PHYSICAL)
def test_signature_rms_is_the_rms_of_the_jacobian(name):
    ctx = full_context()
    e = build_effect(name, {})
    jac = e.jacobian(ctx.x, ctx.y, ctx)
    np.testing.assert_allclose(e.signature_rms_px(ctx), np.sqrt((jac**2).sum(1).mean(0)))
    if "image" in e.channels:
        assert np.all(e.signature_rms_px(ctx) > 0)
    else:
        assert np.all(e.signature_rms_px(ctx) == 0)


def test_context_take_selects_every_field():
    ctx = full_context()
    sub = ctx.take(np.arange(0, ctx.n, 3))
    assert sub.n == len(range(0, ctx.n, 3))
    np.testing.assert_array_equal(sub.magnitude, ctx.magnitude[::3])
    np.testing.assert_array_equal(sub.covariates["temperature_c"], ctx.covariates["temperature_c"][::3])
    np.testing.assert_allclose(sub.attitude.as_quat(), ctx.attitude.as_quat()[::3])


def _fields(ctx: EffectContext) -> dict:
    return {f.name: getattr(ctx, f.name) for f in dataclasses.fields(ctx)}


def _validated(ctx: EffectContext, **changes) -> EffectContext:
    """The context built again through the constructor's checks and broadcasting."""
    return EffectContext(**{**_fields(ctx), **changes})


def _assert_same_context(a: EffectContext, b: EffectContext) -> None:
    for k in _fields(a):
        va, vb = getattr(a, k), getattr(b, k)
        if k == "attitude":
            np.testing.assert_array_equal(va.as_quat(), vb.as_quat())
        elif k == "covariates":
            assert va.keys() == vb.keys()
            for name in va:
                np.testing.assert_array_equal(va[name], vb[name])
        elif isinstance(va, np.ndarray):
            assert va.dtype == vb.dtype and va.shape == vb.shape, k
            np.testing.assert_array_equal(va, vb)
        else:
            assert va is vb or va == vb, k


@pytest.mark.parametrize("index", ["ints", "repeated", "mask"])
def test_a_selection_is_the_context_built_from_the_selected_values_and_owns_them(index):
    """``take`` skips the constructor's checks (the source was checked): it must give what the
    constructor gives, in arrays of its own."""
    ctx = full_context(n=50)
    rng = np.random.default_rng(3)
    idx = {"ints": rng.permutation(50)[:20], "repeated": np.tile(np.arange(50), 5), "mask": rng.random(50) < 0.5}[index]
    sub = ctx.take(idx)
    picked = {k: (v[idx] if isinstance(v, np.ndarray) or k == "attitude" else v) for k, v in _fields(ctx).items()}
    picked["covariates"] = {name: c[idx] for name, c in ctx.covariates.items()}
    _assert_same_context(sub, EffectContext(**picked))
    for k in ("x", "y", "t_ns", "frame", "omega_rad_s", "unit_icrs"):
        assert not np.shares_memory(getattr(sub, k), getattr(ctx, k)), k


def test_a_scalar_selection_is_one_observation():
    ctx = full_context(n=10)
    one = ctx.take(3)
    assert one.n == 1 and one.unit_icrs.shape == (1, 3) and one.x[0] == ctx.x[3]


def test_new_positions_of_the_same_length_give_what_the_constructor_gives():
    ctx = full_context(n=40)
    x, y = ctx.x + 0.25, list(ctx.y - 1.0)
    moved = ctx.evolve(x=x, y=y, magnitude=ctx.magnitude + 1)
    _assert_same_context(moved, _validated(ctx, x=x, y=np.asarray(y), magnitude=ctx.magnitude + 1))
    x[0] = -1e9  # the caller's array changes; the context keeps its own copy
    assert moved.x[0] == ctx.x[0] + 0.25 and not np.shares_memory(moved.y, ctx.y)


def test_positions_of_another_length_broadcast_every_field_again():
    ctx = full_context(n=1).evolve(attitude=None)  # one rotation would not broadcast to four stars
    spread = ctx.evolve(x=np.arange(4.0), y=np.arange(4.0))
    assert spread.n == 4 and spread.unit_icrs.shape == (4, 3) and spread.t_ns.shape == (4,)
    with pytest.raises(TypeError, match="no field"):
        ctx.evolve(x=ctx.x, colour=1)


# ---------------------------------------------------------------------------- validation, doc
def test_unknown_parameter_lists_valid_ones():
    with pytest.raises(ValueError, match=r"k3.*valid parameters: k1, k2"):
        RadialDistortion(k3=0.1)


def test_out_of_bounds_and_non_numeric_rejected():
    with pytest.raises(ValueError, match="outside bounds"):
        PrincipalPointOffset(dx=1e6)
    with pytest.raises(ValueError, match="outside bounds"):
        RadialDistortion(k1=float("nan"))
    with pytest.raises(ValueError, match="must be a number"):
        RadialDistortion(k1="big")


def test_build_effect_unknown_name_lists_valid_names():
    with pytest.raises(UnknownEffectError, match=r"principal_point.*radial_distortion"):
        build_effect("coma", {})
    assert isinstance(UnknownEffectError("x"), ValueError)


def test_values_are_a_copy_and_defaults_fill_in():
    e = build_effect("radial_distortion", {"k1": 0.01})
    assert e.values == {"k1": 0.01, "k2": 0.0}
    e.values["k1"] = 5.0
    assert e.values["k1"] == 0.01
    assert e == RadialDistortion(k1=0.01) and e != RadialDistortion(k1=0.02)
    assert e.with_values(k2=0.5) == RadialDistortion(k1=0.01, k2=0.5)
    assert type(e).from_vector(e.vector) == e


def test_effect_parameter_validation():
    with pytest.raises(ValueError, match="default"):
        EffectParameter("a", "px", 5.0, 1.0, (-1.0, 1.0), "")
    with pytest.raises(ValueError, match="bounds"):
        EffectParameter("a", "px", 0.0, 1.0, (1.0, -1.0), "")
    with pytest.raises(ValueError, match="prior_scale"):
        EffectParameter("a", "px", 0.0, 0.0, (-1.0, 1.0), "")


def test_effects_doc_is_up_to_date():
    doc = ROOT / "docs" / "effects.md"
    assert doc.read_text() == render_markdown(), "regenerate: python -m rollingstar.sensors.effects.doc docs/effects.md"


# ------------------------------------------------------------------------ empirical shapes
def test_empirical_step_known_answer():
    """The step moves the chosen axis of the stars beyond the chosen coordinate, nothing else."""
    ctx = full_context(seed=3)
    x2, y2 = EFFECTS["empirical_step"](axis=1.0, across=0.0, at_px=400.0, size_px=0.3).apply(ctx.x, ctx.y, ctx)
    np.testing.assert_array_equal(x2, ctx.x)
    np.testing.assert_allclose(y2 - ctx.y, 0.3 * (np.asarray(ctx.x) > 400.0))
    with pytest.raises(ValueError, match="axis must be 0"):
        EFFECTS["empirical_step"](axis=0.5).apply(ctx.x, ctx.y, ctx)


@pytest.mark.parametrize("axis,along", [(0.0, 1.0), (1.0, 0.0)])
def test_empirical_ripple_known_answer_and_jacobian(axis, along):
    """The ripple is a sine of the chosen coordinate on the chosen axis; its Jacobian in period,
    amplitude and phase matches finite differences."""
    ctx = full_context(seed=4)
    values = {"axis": axis, "along": along, "period_px": 150.0, "amplitude_px": 0.2, "phase_rad": 0.4}
    eff = EFFECTS["empirical_ripple"](**values)
    x2, y2 = eff.apply(ctx.x, ctx.y, ctx)
    coord = np.asarray(ctx.y if along else ctx.x)
    moved, still = (y2 - ctx.y, x2 - ctx.x) if axis else (x2 - ctx.x, y2 - ctx.y)
    np.testing.assert_allclose(moved, 0.2 * np.sin(2 * np.pi * coord / 150.0 + 0.4))
    np.testing.assert_array_equal(still, 0.0)
    jac = eff.jacobian(ctx.x, ctx.y, ctx)
    for k, name in ((2, "period_px"), (3, "amplitude_px"), (4, "phase_rad")):
        h = 1e-6 * max(abs(values[name]), 1.0)
        xp, yp = EFFECTS["empirical_ripple"](**{**values, name: values[name] + h}).apply(ctx.x, ctx.y, ctx)
        xm, ym = EFFECTS["empirical_ripple"](**{**values, name: values[name] - h}).apply(ctx.x, ctx.y, ctx)
        fd = np.stack([xp - xm, yp - ym], axis=-1) / (2 * h)
        np.testing.assert_allclose(jac[:, :, k], fd, atol=1e-6)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_a_chain_resumed_where_it_changes_is_the_whole_chain_to_the_bit(seed):
    """``resume`` runs a chain from the effect where it differs from a traced one: that must be
    the whole chain's prediction to the bit, wherever the change is (a time effect included, which
    moves the context every later effect sees), and the trace must end on the traced chain's own."""
    rng = np.random.default_rng(seed)
    ctx = full_context(seed=seed % 7, n=30)
    names = list(rng.choice(PHYSICAL, size=rng.integers(1, 6), replace=False))
    chain = tuple(build_effect(n, random_values(EFFECTS[n], rng)) for n in names)
    trace = entering(chain, ctx)
    np.testing.assert_array_equal(np.stack(trace[-1]), np.stack(predict(chain, ctx)))
    for k, e in enumerate(ordered(chain)):
        changed = tuple(type(e)(**random_values(type(e), rng)) if c is e else c for c in chain)
        np.testing.assert_array_equal(np.stack(resume(changed, ctx, k, *trace[k])), np.stack(predict(changed, ctx)))
