"""Effects: registry, parameter validation, identity at defaults, analytic Jacobians, known answers."""
from __future__ import annotations

import numpy as np
import pytest

from sensors.camera import PinholeCamera
from sensors.effects import EFFECTS, Effect, EffectParameter, UnknownEffectError, build_effect
from sensors.effects.principal_point import PrincipalPointOffset
from sensors.effects.radial_distortion import RadialDistortion

CAMERA = PinholeCamera(focal_length_m=24.09e-3, pixel_size_m=5.5e-6, width=1024, height=1024)


def _positions(n=200, seed=1):
    rng = np.random.default_rng(seed)
    return rng.uniform(-0.5, 1023.5, n), rng.uniform(-0.5, 1023.5, n), np.full(n, 123_456_789, dtype=np.int64)


def _nonzero_values(cls, seed=2):
    """Values well inside the bounds, a few prior scales from the defaults."""
    rng = np.random.default_rng(seed)
    out = {}
    for p in cls.parameters:
        lo, hi = p.bounds
        out[p.name] = float(np.clip(p.default + 3.0 * p.prior_scale * rng.uniform(-1, 1), lo, hi))
    return out


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_registry_entry_is_well_formed(name):
    cls = EFFECTS[name]
    assert issubclass(cls, Effect) and cls.name == name
    assert cls.parameters and all(isinstance(p, EffectParameter) for p in cls.parameters)
    assert len(set(cls.parameter_names())) == len(cls.parameters)
    assert len(cls.explanation) > 100  # a paragraph a user can read
    for alias in cls.aliases:
        assert type(build_effect(alias, {})) is cls


def test_aliases_are_unique_and_do_not_shadow_names():
    aliases = [a for cls in EFFECTS.values() for a in cls.aliases]
    assert len(aliases) == len(set(aliases))
    assert not set(aliases) & set(EFFECTS)


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_defaults_are_identity(name):
    x, y, t = _positions()
    effect = build_effect(name, {})
    x2, y2 = effect.apply(x, y, t, CAMERA)
    np.testing.assert_array_equal(x2, x)
    np.testing.assert_array_equal(y2, y)


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_jacobian_matches_finite_differences(name):
    cls = EFFECTS[name]
    x, y, t = _positions()
    values = _nonzero_values(cls)
    jac = cls(**values).jacobian(x, y, t, CAMERA)
    assert jac.shape == (x.size, 2, len(cls.parameters))
    for j, p in enumerate(cls.parameters):
        h = 1e-4 * p.prior_scale
        plus, minus = dict(values), dict(values)
        plus[p.name] += h
        minus[p.name] -= h
        xp, yp = cls(**plus).apply(x, y, t, CAMERA)
        xm, ym = cls(**minus).apply(x, y, t, CAMERA)
        fd = np.stack([(xp - xm) / (2 * h), (yp - ym) / (2 * h)], axis=-1)
        # central differences are exact for these polynomial models up to round-off (~1e-13 px / h)
        np.testing.assert_allclose(jac[:, :, j], fd, rtol=1e-6, atol=1e-6 * max(1.0, np.abs(fd).max()))


def test_radial_distortion_known_answer():
    f = CAMERA.focal_px
    xn, yn = 0.1, -0.05
    x, y = CAMERA.cx + f * xn, CAMERA.cy + f * yn
    r2 = xn**2 + yn**2
    k1, k2 = 0.02, -0.3
    xd, yd = RadialDistortion(k1=k1, k2=k2).apply(x, y, 0, CAMERA)
    scale = 1 + k1 * r2 + k2 * r2**2
    assert xd == pytest.approx(CAMERA.cx + f * xn * scale, abs=1e-9)
    assert yd == pytest.approx(CAMERA.cy + f * yn * scale, abs=1e-9)
    # the principal point is a fixed point; displacement is radial
    xc, yc = RadialDistortion(k1=k1, k2=k2).apply(CAMERA.cx, CAMERA.cy, 0, CAMERA)
    assert (xc, yc) == (CAMERA.cx, CAMERA.cy)
    assert (xd - x) * (y - CAMERA.cy) - (yd - y) * (x - CAMERA.cx) == pytest.approx(0.0, abs=1e-6)


def test_principal_point_shifts_every_position():
    x, y, t = _positions()
    xs, ys = PrincipalPointOffset(dx=2.5, dy=-1.25).apply(x, y, t, CAMERA)
    np.testing.assert_allclose(xs - x, 2.5, atol=1e-12)
    np.testing.assert_allclose(ys - y, -1.25, atol=1e-12)


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


def test_effect_parameter_validation():
    with pytest.raises(ValueError, match="default"):
        EffectParameter("a", "px", 5.0, 1.0, (-1.0, 1.0), "")
    with pytest.raises(ValueError, match="bounds"):
        EffectParameter("a", "px", 0.0, 1.0, (1.0, -1.0), "")
    with pytest.raises(ValueError, match="prior_scale"):
        EffectParameter("a", "px", 0.0, 0.0, (-1.0, 1.0), "")
