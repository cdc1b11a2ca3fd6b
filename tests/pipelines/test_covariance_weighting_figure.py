"""The covariance-weighting figure's pieces: the truth smear model and the switched pipeline."""
from __future__ import annotations

import numpy as np

from rollingstar.estimators.data import FrameData, SensorContext, StarTable
from rollingstar.estimators.rates.pso import image_velocity_px_s
from rollingstar.pipelines.runner import build_stages
from rollingstar.studies.covariance_weighting import (
    PIPELINE,
    TruthSmearCovariance,
    pipeline,
    scenario,
)


def test_truth_smear_covariance_is_long_along_the_image_velocity_with_the_stars_trace():
    cfg = scenario(10.0, 2, 1)
    ctx = SensorContext.from_scenario(cfg)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 1023, 20), rng.uniform(0, 1023, 20)
    sigma = rng.uniform(0.05, 0.3, 20)
    omega = np.radians([10.0, 0.0, 0.0])
    stage = TruthSmearCovariance(omega, 0.0449, 1.0)
    stage.setup(ctx)
    out = stage.process(FrameData(index=0, t0_ns=0, stars=StarTable.build(x, y, 0, sigma_px=sigma))).stars
    C = np.stack([np.stack([out.cov_xx, out.cov_xy], -1), np.stack([out.cov_xy, out.cov_yy], -1)], -2)
    np.testing.assert_allclose(0.5 * np.trace(C, axis1=1, axis2=2), sigma**2, rtol=1e-12)  # the scalar weight kept
    ev, V = np.linalg.eigh(C)
    vx, vy = image_velocity_px_s(ctx.camera, omega, x, y)
    v = np.column_stack([vx, vy]) / np.hypot(vx, vy)[:, None]
    assert np.allclose(np.abs(np.einsum("ni,ni->n", V[:, :, 1], v)), 1.0, atol=1e-9)  # long axis along the smear
    length = np.hypot(vx, vy) * 0.0449
    np.testing.assert_allclose(ev[:, 1] / ev[:, 0], 1.0 + length**2 / 12.0, rtol=1e-9)  # streak over a 1 px PSF


def test_the_pipeline_switches_only_the_weighting_of_the_rate_and_attitude_stages():
    for full in (False, True):
        stages = build_stages(pipeline(full), str(PIPELINE))
        switched = {s.name: s.params.star_covariance for s in stages if hasattr(s.params, "star_covariance")}
        assert switched == {"ls-rate": full, "quest": full}
