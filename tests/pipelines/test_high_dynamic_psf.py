"""The high-dynamic pipeline on a camera whose PSF is twice the simulator's default width (a
defocused star tracker), with nothing in the pipeline told so: the streak centroider and the
pixel step measure the width from the stars, and the errors stay at the pixel-level bound
(`pytest -s` prints the efficiencies)."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.config import CONFIGS
from rollingstar.logs import LogReader
from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.evaluate import evaluate_log
from rollingstar.pipelines.runner import run_pipeline
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.scenario import load_scenario

pytestmark = pytest.mark.long_study


@pytest.mark.parametrize("rate_deg_s", [0.5, 6.0])
def test_a_psf_twice_the_default_is_measured_and_the_bound_is_reached(tmp_path, rate_deg_s):
    cfg = load_scenario(CONFIGS / "scenarios" / "he2021a.yaml")
    cfg = cfg.model_copy(update={"frames": 20, "seed": 4,
                                 "motion": cfg.motion.model_copy(update={"rate_deg_s": (rate_deg_s, 0.0, 0.0)}),
                                 "image": cfg.image.model_copy(update={"psf_sigma_px": 2.0})})
    rec, out = tmp_path / "rec.mcap", tmp_path / "out.mcap"
    simulate_to_log(cfg, rec, show_progress=False)
    summary = run_pipeline(rec, load_pipeline(CONFIGS / "pipelines" / "high_dynamic.yaml"), out, show_progress=False)
    assert summary.valid_estimates == 20
    psf = [m.data["psf_sigma_px"] for m in LogReader(out).messages("/estimate/frame")]  # written per frame
    assert all(p is not None and abs(p / 2.0 - 1) < 0.03 for p in psf), psf
    m = evaluate_log(out)
    eff = [m["efficiency_pixel"][f"{k}_{a}"] for k in ("attitude", "rate") for a in "xyz"]
    print(f"\nPSF 2 px at {rate_deg_s} deg/s: efficiency against the pixel-level bound, attitude x / y / z "
          f"{eff[0]:.2f} / {eff[1]:.2f} / {eff[2]:.2f}, rate {eff[3]:.2f} / {eff[4]:.2f} / {eff[5]:.2f}; "
          f"{m['identified_stars_per_frame']:.1f} stars identified per frame; PSF measured {psf[0]:.3f} px")
    assert np.all(np.array(eff) < 1.6), eff
