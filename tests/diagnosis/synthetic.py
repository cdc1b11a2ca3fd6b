"""A synthetic recording built directly from the diagnosis forward model (no simulator, no pipeline).

Stars at random pixels of every frame, a constant body rate, per-star times from the rolling
shutter timing; observed positions = :func:`rollingstar.estimators.diagnosis.observations.predict` under the
true attitude, rate and effects, plus Gaussian noise. Self-consistent by construction, so the
estimators' statistical properties (bias, interval coverage) can be checked against the truth.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.estimators.diagnosis.observations import (
    Nuisance,
    Observations,
    predict,
)
from rollingstar.sensors import build
from rollingstar.studies.bench.discrepancy import base_scenario


def synthetic(effects=(), frames: int = 12, stars: int = 25, rate_deg_s=(1.0, 0.0, 0.0), sigma: float = 0.05,
              seed: int = 0, period_s: float = 0.1, noise: bool = True):
    """Returns (obs, truth Nuisance, camera, timing)."""
    rng = np.random.default_rng(seed)
    cfg = base_scenario(frames)
    camera, timing = build.build_camera(cfg), build.build_timing(cfg)
    t0 = (np.arange(frames) * period_s * 1e9).astype(np.int64)
    t_ref = np.array([timing.frame_reference_ns(int(t)) for t in t0], dtype=np.int64)
    omega = np.deg2rad(np.asarray(rate_deg_s, dtype=float))
    r0 = Rotation.from_euler("xyz", rng.uniform(0, 2 * np.pi, 3))
    att = r0 * Rotation.from_rotvec(np.outer((t_ref - t_ref[0]) / 1e9, omega))
    frame = np.repeat(np.arange(frames), stars)
    x = rng.uniform(20, camera.width - 20, frame.size)
    y = rng.uniform(20, camera.height - 20, frame.size)
    t = np.concatenate([timing.row_mid_exposure_ns(int(t0[k]), np.round(y[frame == k]).astype(int)) for k in range(frames)])
    dt = (t - t_ref[frame]) / 1e9
    rot = att[frame] * Rotation.from_rotvec(omega[None] * dt[:, None])
    u = rot.apply(camera.unproject(x, y))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    n = frame.size
    obs = Observations(frame=frame, x=x, y=y, sigma=np.full(n, sigma), t_ns=t.astype(np.int64), u_icrs=u,
                       magnitude=rng.uniform(2, 6, n), catalog_id=np.arange(n), flux=np.ones(n),
                       frame_index=np.arange(frames), t0_ns=t0, t_ref_ns=t_ref)
    truth = Nuisance(att, np.tile(omega, (frames, 1)))
    p = predict(obs, truth, camera, timing, tuple(effects))
    from dataclasses import replace

    e = rng.normal(0, sigma, (2, n)) if noise else np.zeros((2, n))
    obs = replace(obs, x=p.x + e[0], y=p.y + e[1])
    return obs, truth, camera, timing
