"""Centroid-level rolling-shutter frames of the he2021a sensor under motion, for the identifier tests.

The simulator (``rollingstar.sensors.simulate``) places every star at its own row's mid-exposure
(solving the rolling-shutter fixed point itself); the image velocity each detection carries is the
true one (``image_velocity`` at the true rate) plus noise, standing for a streak centroider's.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from rollingstar.estimators.data import FrameData, GyroSamples, SensorContext, StarTable
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.catalog import StarCatalog
from rollingstar.sensors.effects.geometry import image_velocity
from rollingstar.sensors.motion import PiecewiseMotion, Segment
from rollingstar.sensors.simulate import StarTrackerSimulator
from rollingstar.sensors.timing import DetectorTiming

# he2021a (configs/scenarios/he2021a.yaml): 24.09 mm / 5.5 um, 1024 x 1024, 44.9 ms exposure, 43.9 us line delay
CAM = PinholeCamera(focal_length_m=0.02409, pixel_size_m=5.5e-6, width=1024, height=1024)
TIMING = DetectorTiming(mode="rolling", exposure_ns=44_900_000, line_delay_ns=43_900, rows=1024)
SIGMA_PX = 0.1
VELOCITY_SIGMA_PX_S = 2.0
_CONTEXTS: dict = {}


def he2021a_context(initial_attitude: Rotation | None = None) -> SensorContext:
    """Hipparcos to magnitude 6 at epoch 2025 without close doubles, as the scenario builds it."""
    if "catalog" not in _CONTEXTS:
        _CONTEXTS["catalog"] = StarCatalog.from_hipparcos(2025.0, 6.0).without_close_pairs(3 * CAM.ifov_rad)
    return SensorContext(camera=CAM, timing=TIMING, catalog=_CONTEXTS["catalog"], initial_attitude=initial_attitude,
                         centroid_sigma_px=SIGMA_PX)


def motion_frames(context: SensorContext, attitude: Rotation, rate_rad_s, frames: int, seed: int,
                  velocities: bool = True, alpha_rad_s2=(0.0, 0.0, 0.0), gyro_hz: float = 0.0):
    """Frames ``0 .. frames-1`` of a camera starting at ``attitude`` (t = 0) turning at ``rate_rad_s``
    (camera frame, plus ``alpha_rad_s2`` t): per frame ``(FrameData, true catalogue id of each
    detection, motion, noise-free (x, y, t_ns) of each detection)``; with ``gyro_hz`` the frame carries the true rate sampled since the previous frame."""
    motion = PiecewiseMotion(attitude, [Segment(10**12, np.asarray(rate_rad_s, dtype=float),
                                                np.asarray(alpha_rad_s2, dtype=float))])
    sim = StarTrackerSimulator(CAM, TIMING, context.catalog, motion, centroid_sigma_px=SIGMA_PX, seed=seed)
    rng = np.random.default_rng(seed)
    out = []
    for k in range(frames):
        f = sim.frame(k)
        c = f.centroids
        dist, j = cKDTree(np.column_stack([f.truth.x, f.truth.y])).query(np.column_stack([c["x"], c["y"]]))
        assert dist.max() < 10 * SIGMA_PX
        cols = {}
        if velocities:
            omega = motion.angular_velocity(np.asarray(c["t_ns"], dtype=np.int64))
            vx, vy = image_velocity(CAM, c["x"], c["y"], omega)
            cols = dict(vx=vx + rng.normal(0, VELOCITY_SIGMA_PX_S, vx.size), vy=vy + rng.normal(0, VELOCITY_SIGMA_PX_S, vy.size))
        det = StarTable.build(c["x"], c["y"], c["t_ns"], c["row_time_ns"], flux=c["flux"], sigma_px=SIGMA_PX, **cols)
        gyro = GyroSamples.empty()
        if gyro_hz:
            step = int(1e9 / gyro_hz)
            t = np.arange(f.t0_ns - TIMING.frame_period_ns + step, f.t0_ns + 1, step, dtype=np.int64)
            gyro = GyroSamples(t, motion.angular_velocity(t - step // 2))  # the mean rate over each interval
        true_xyt = (f.truth.x[j], f.truth.y[j], f.truth.t_ns[j])
        out.append((FrameData(index=k, t0_ns=f.t0_ns, stars=det, gyro=gyro), f.truth.catalog_id[j], motion, true_xyt))
    return out


def pointing(rng) -> Rotation:
    return Rotation.from_quat(rng.normal(size=4))
