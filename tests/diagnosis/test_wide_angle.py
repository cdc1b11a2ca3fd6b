"""``rollingstar diagnose`` on a 100 deg fisheye (equidistant projection) simulated at centroid level:
with the projection declared, a lens distortion is named and fitted as on a narrow field; with a
pinhole declared for the same nominal field, the projection is named first (with its focal
length) and the distortion after it; a model off beyond what the projection search spans is
refused with what to fix (exit 2), not a traceback."""
from __future__ import annotations

import json
import math

import pytest
from typer.testing import CliRunner

from rollingstar.cli import app
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.scenario import load_scenario

SIGMA_PX = 0.05
K1 = 0.01


def _scenario(projection: str, focal_px: float, effects: str = "") -> str:
    return f"""name: fisheye
level: centroid
sensor: {{focal_length_mm: {focal_px * 5.5e-3:.6f}, pixel_size_um: 5.5, width_px: 1024, height_px: 1024,
          projection: {projection}}}
shutter: {{mode: rolling, exposure_ms: 50.0, line_delay_us: 49.0}}
catalog: {{source: hipparcos, magnitude_limit: 4.0, epoch_year: 2025.0}}
motion:
  initial_attitude: {{ra_deg: 83.8, dec_deg: -5.4, roll_deg: 0.0}}
  rate_deg_s: [0.5, 0.0, 0.0]
noise: {{centroid_sigma_px: {SIGMA_PX}}}
frames: 12
seed: 3
{effects}"""


@pytest.fixture(scope="module")
def fisheye(tmp_path_factory):
    d = tmp_path_factory.mktemp("fisheye")
    half = math.radians(50.0)  # 100 deg across the 1024 px width
    base, pinhole, truth = d / "base.yaml", d / "pinhole.yaml", d / "truth.yaml"
    base.write_text(_scenario("equidistant", 512 / half))
    pinhole.write_text(_scenario("perspective", 512 / math.tan(half)))  # the same nominal field through a pinhole
    truth.write_text(_scenario("equidistant", 512 / half, f"effects: [{{kind: radial_distortion, params: {{k1: {K1}}}}}]\n"))
    rec = d / "truth.mcap"
    simulate_to_log(load_scenario(truth), rec, show_progress=False)
    return {"dir": d, "base": base, "pinhole": pinhole, "rec": rec}


def test_a_fisheye_distortion_is_named_with_the_projection_declared(fisheye):
    res = CliRunner().invoke(app, ["diagnose", "--sim", str(fisheye["base"]), "--recording", str(fisheye["rec"]),
                                   "-o", str(fisheye["dir"] / "report"), "--json", "-q"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    named = {e["name"]: e for e in out["effects"]}
    assert set(named) == {"radial_distortion"}, out["verdict"]
    k1 = named["radial_distortion"]["params"]["k1"]
    assert abs(k1["value"] - K1) < 4 * k1["sigma"], k1
    # held out (RMS per axis): from the distortion's pull (~0.5 px here) down to the noise's sigma
    assert out["heldout_rms_before_px"] > 5 * SIGMA_PX
    assert out["heldout_rms_after_px"] < 1.2 * SIGMA_PX


def test_a_pinhole_declared_for_a_fisheye_gets_the_projection_named_then_the_distortion(fisheye):
    res = CliRunner().invoke(app, ["diagnose", "--sim", str(fisheye["pinhole"]), "--recording", str(fisheye["rec"]),
                                   "-o", str(fisheye["dir"] / "report_pinhole"), "--json", "-q"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    proj = out["projection"]
    assert proj["declared"] == "perspective" and proj["named"] == "equidistant" and out["mismatch"]
    truth_focal = 512 / math.radians(50.0)
    assert abs(proj["candidates"]["equidistant"]["focal_px"] / truth_focal - 1) < 1e-3
    # the other laws fit worse than their focal length and k1 can make up: named by a wide margin
    runner_up = sorted(c["chi2_dof"] for p, c in proj["candidates"].items() if p != "equidistant")[0]
    assert runner_up > 5 * proj["candidates"]["equidistant"]["chi2_dof"]
    assert out["verdict"].startswith("lens projection: equidistant, not the declared perspective")
    assert proj["heldout_rms_px"]["perspective"] > 100 * proj["heldout_rms_px"]["equidistant"]
    named = {e["name"]: e for e in out["effects"]}
    assert set(named) == {"radial_distortion"}
    k1 = named["radial_distortion"]["params"]["k1"]
    assert abs(k1["value"] - K1) < 4 * k1["sigma"], k1
    assert out["heldout_rms_after_px"] < 1.2 * SIGMA_PX


def test_a_narrow_field_makes_no_projection_search():
    """Over a 13 deg field every projection differs from the pinhole by a theta^3 term a k1
    absorbs, far below the noise: none could be named, and none is searched."""
    from rollingstar.estimators.diagnosis.projection import distinguishable
    from rollingstar.sensors.camera import PinholeCamera

    narrow = PinholeCamera(focal_length_m=0.02409, pixel_size_m=5.5e-6, width=1024, height=1024)
    assert not distinguishable(narrow, 0.05)
    wide = PinholeCamera(focal_length_m=512 / math.tan(math.radians(50.0)) * 5.5e-6, pixel_size_m=5.5e-6, width=1024,
                         height=1024)
    assert distinguishable(wide, 0.05)


def test_a_model_off_beyond_the_search_is_refused_with_what_to_fix(fisheye):
    """A focal length twice the lens's: beyond the focal-length freedom of the projection search
    and the library's focal-length effect, so the stars stay beyond the outlier gate, and the
    command says which parts of the sensor model to check."""
    off = fisheye["dir"] / "off.yaml"
    off.write_text(_scenario("equidistant", 2 * 512 / math.radians(50.0)))
    res = CliRunner().invoke(app, ["diagnose", "--sim", str(off), "--recording", str(fisheye["rec"]),
                                   "-o", str(fisheye["dir"] / "report_off"), "--json", "-q"])
    assert res.exit_code == 2, res.output
    assert "sensor model is far from the recording's" in res.output and "focal length" in res.output
    assert "Traceback" not in res.output
