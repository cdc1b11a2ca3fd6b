"""The diagnosis's prediction sends a star and its four position neighbours through the effect
chain in one call over 5n copies (``observations.predict``). That is right only if every effect
acts on each star alone: this checks it for every registered effect, and for all of them chained,
on a context with every field populated (several frames, a turning camera)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rollingstar.sensors.effects import EFFECTS
from rollingstar.sensors.effects.chain import predict as chain_predict
from tests.sensors.test_effects import full_context, random_values


def _values(cls, rng) -> dict:
    """Random parameter values; the empirical shapes' axis choices are whole numbers."""
    return {k: float(round(v)) if k in ("axis", "along", "across") else v for k, v in random_values(cls, rng).items()}


def _tiled(effects, ctx, offsets):
    n = ctx.n
    big = ctx.take(np.tile(np.arange(n), len(offsets)))
    big = big.evolve(x=big.x + np.repeat(offsets[:, 0], n), y=big.y + np.repeat(offsets[:, 1], n))
    return [np.reshape(a, (len(offsets), n)) for a in chain_predict(effects, big)]


def _one_by_one(effects, ctx, offsets):
    out = [chain_predict(effects, ctx.evolve(x=ctx.x + dx, y=ctx.y + dy)) for dx, dy in offsets]
    return [np.stack([o[k] for o in out]) for k in (0, 1)]


@pytest.mark.parametrize("name", sorted(EFFECTS) + ["all"])
def test_an_effect_sees_each_star_alone(name):
    rng = np.random.default_rng(4)
    classes = sorted(EFFECTS.items()) if name == "all" else [(name, EFFECTS[name])]
    effects = tuple(cls(**_values(cls, rng)) for _, cls in classes)
    ctx = full_context(n=60)
    offsets = np.array([[0.0, 0.0], [1e-3, 0.0], [-1e-3, 0.0], [0.0, 1e-3], [0.0, -1e-3]])
    for a, b in zip(_tiled(effects, ctx, offsets), _one_by_one(effects, ctx, offsets)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)


def test_predict_gives_the_same_attitude_jacobian_tiled_or_call_by_call(monkeypatch):
    """``predict`` itself, on a synthetic recording with every registered effect: the tiled chain
    (the default for this many stars) and the call-by-call chain (``TILED_MAX_STARS = 0``) agree."""
    from rollingstar.estimators.diagnosis import observations
    from rollingstar.sensors.effects.base import MissingContextError
    from tests.diagnosis.synthetic import synthetic

    rng = np.random.default_rng(6)
    obs, truth, camera, timing = synthetic(frames=4, stars=20, noise=False)
    effects = []
    for _, cls in sorted(EFFECTS.items()):  # those this recording's context can drive
        effect = cls(**_values(cls, rng))
        try:
            observations.predict(obs, truth, camera, timing, (effect,), attitude_jacobian=False)
        except MissingContextError:
            continue
        effects.append(effect)
    effects = tuple(effects)
    assert len(effects) >= 10 and obs.n <= observations.TILED_MAX_STARS
    tiled = observations.predict(obs, truth, camera, timing, effects)
    monkeypatch.setattr(observations, "TILED_MAX_STARS", 0)
    calls = observations.predict(obs, truth, camera, timing, effects)
    for a, b in ((tiled.x, calls.x), (tiled.y, calls.y), (tiled.att_jac, calls.att_jac)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)


def _same_context(a, b) -> None:
    """Every field of two effect contexts equal to the bit (arrays, rotations, the rest)."""
    import dataclasses

    for f in dataclasses.fields(a):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if f.name == "attitude":
            np.testing.assert_array_equal(va.as_quat(), vb.as_quat())
        elif f.name == "covariates":
            assert va.keys() == vb.keys()
        elif isinstance(va, np.ndarray):
            assert va.dtype == vb.dtype and va.shape == vb.shape, f.name
            np.testing.assert_array_equal(va, vb, err_msg=f.name)
        else:
            assert va is vb or va == vb, f.name


def test_the_kept_observation_fields_give_the_contexts_made_from_scratch():
    """``predict`` evolves contexts made once per observations (``observation_context``) instead of
    building each from the observations: the context and the tiled context must be, field by field
    and to the bit, what the constructor and ``take`` give; the pinhole part made once for many
    chains must predict as a fresh one does, and only for its own nuisance."""
    from dataclasses import replace

    from rollingstar.estimators.diagnosis import observations as O
    from rollingstar.sensors.effects.base import EffectContext
    from tests.diagnosis.synthetic import synthetic

    obs, truth, camera, timing = synthetic(frames=3, stars=15, noise=False)
    nuis = O.Nuisance(truth.attitude, truth.omega + 0.01)
    p = O.pinhole(obs, nuis, camera, timing)
    rot = O.camera_rotations(obs, nuis)
    fresh = EffectContext(camera=camera, x=p.ctx.x, y=p.ctx.y, t_ns=obs.t_ns, row=obs.y, t0_ns=obs.t0_ns[obs.frame],
                          frame=obs.frame, magnitude=obs.magnitude, vx=p.v[:, 0], vy=p.v[:, 1], omega_rad_s=p.omega,
                          attitude=rot, unit_icrs=obs.u_icrs, pm_rad_yr=obs.pm_rad_yr, timing=timing,
                          t_start_ns=int(obs.t0_ns.min()))
    _same_context(p.ctx, fresh)
    n, off = obs.n, O.POS_OFFSETS
    big = fresh.take(np.tile(np.arange(n), len(off)))
    _same_context(p.tiled, big.evolve(x=big.x + np.repeat(off[:, 0], n), y=big.y + np.repeat(off[:, 1], n)))
    effects = (EFFECTS["radial_distortion"](k1=3e-3), EFFECTS["rolling_shutter"](line_delay_error_us=2.0))
    for a, b in ((O.predict(obs, nuis, camera, timing, effects, start=p), O.predict(obs, nuis, camera, timing, effects)),
                 (O.fit_attitudes(obs, nuis, camera, timing, effects, start=p)[1],
                  O.fit_attitudes(obs, nuis, camera, timing, effects)[1])):
        for k in ("x", "y", "x_ideal", "w_cam", "att_jac", "vx"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    with pytest.raises(ValueError, match="another nuisance"):
        O.predict(obs, truth, camera, timing, effects, start=p)
    with pytest.raises(ValueError, match="another nuisance, camera"):
        O.predict(obs, nuis, replace(camera), timing, effects, start=p)


def test_one_set_of_observations_predicted_under_several_cameras_and_timings():
    """The observation fields are kept once per set of observations, whatever camera and timing a
    prediction uses: each prediction must be what the same observations give with nothing kept
    (a fresh copy), to the bit, on a recording that does not start at time zero."""
    from dataclasses import replace

    from rollingstar.estimators.diagnosis import observations as O
    from tests.diagnosis.synthetic import synthetic

    obs, truth, camera, timing = synthetic(frames=3, stars=15, noise=False)
    later = 7_000_000_123
    obs = replace(obs, t_ns=obs.t_ns + later, t0_ns=obs.t0_ns + later, t_ref_ns=obs.t_ref_ns + later)
    effects = (EFFECTS["rolling_shutter"](line_delay_error_us=2.0), EFFECTS["time_offset"](offset_ms=0.3))
    for cam in (camera, replace(camera, focal_length_m=camera.focal_length_m * 1.5), camera):
        for tim in (timing, replace(timing, line_delay_ns=timing.line_delay_ns * 2), None):
            if tim is None:
                chain = (EFFECTS["radial_distortion"](k1=3e-3),)
            else:
                chain = effects
            kept = O.predict(obs, truth, cam, tim, chain)
            fresh = O.predict(replace(obs), truth, cam, tim, chain)
            for k in ("x", "y", "att_jac"):
                np.testing.assert_array_equal(getattr(kept, k), getattr(fresh, k), err_msg=k)
            assert kept.ctx.t_start_ns == int(obs.t0_ns.min()) and kept.ctx.camera is cam and kept.ctx.timing is tim


def test_stars_the_model_cannot_place_weigh_nothing_in_the_attitude_fit():
    """Stars behind the camera have no predicted position; outside the fit's mask they must not
    stop it or move it: the attitudes are those fitted without them."""
    from dataclasses import replace

    from rollingstar.estimators.diagnosis import observations as O
    from tests.diagnosis.synthetic import synthetic

    obs, truth, camera, timing = synthetic(frames=3, stars=15, noise=False)
    behind = np.zeros(obs.n, bool)
    behind[::5] = True
    u = obs.u_icrs.copy()
    u[behind] = -u[behind]  # the antipode of the star: behind the camera
    obs = replace(obs, u_icrs=u)
    start = O.Nuisance(truth.attitude * Rotation.from_rotvec([[1e-4, -2e-4, 3e-4]] * obs.n_frames), truth.omega)
    with_them, pred = O.fit_attitudes(obs, start, camera, timing, mask=~behind)
    assert np.isnan(pred.x[behind]).all()
    without, _ = O.fit_attitudes(obs.take(~behind), start, camera, timing)
    np.testing.assert_allclose(with_them.attitude.as_quat(), without.attitude.as_quat(), rtol=0, atol=1e-14)
