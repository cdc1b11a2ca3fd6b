"""Simulate a recording: scenario config -> sensor objects -> simulator -> MCAP log.

Source -> sink, one frame at a time: the simulator produces a frame (truth and measurements), the
writer appends it. Truth attitude is logged densely (``truth_rate_hz``) so that evaluation can
interpolate it at any estimate's own time.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rollingstar.config import to_yaml, validate
from rollingstar.logs.records import AttitudeSamples, GyroSamples, arrays_to_stars
from rollingstar.logs.topics import (
    TOPIC_CENTROIDS,
    TOPIC_GYRO,
    TOPIC_IMAGE,
    TOPIC_TRUTH_ATTITUDE,
    TOPIC_TRUTH_STARS,
)
from rollingstar.logs.writer import RECORDING, LogWriter
from rollingstar.outputs import PARTIAL_SUFFIX, safe_output
from rollingstar.pipelines.interrupt import Interrupted, stop_on_sigint
from rollingstar.progress import progress_bar
from rollingstar.sensors import build
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.gyro import simulate_gyro
from rollingstar.sensors.scenario import ScenarioConfig
from rollingstar.sensors.simulate import ImageModel, StarTrackerSimulator


@dataclass(frozen=True)
class SimulationSummary:
    path: str
    frames: int
    level: str
    stars_per_frame_mean: float
    duration_s: float


def build_simulator(cfg: ScenarioConfig) -> StarTrackerSimulator:
    camera = build.build_camera(cfg)
    image_model = ImageModel(**cfg.image.model_dump()) if cfg.level == "image" else None
    return StarTrackerSimulator(
        camera=camera,
        timing=build.build_timing(cfg),
        catalog=build.build_catalog(cfg, camera),
        motion=build.build_motion(cfg),
        effects=build.build_effects(cfg),
        centroid_sigma_px=cfg.noise.centroid_sigma_px,
        image_model=image_model,
        level=cfg.level,
        seed=cfg.seed,
        zenith_icrs=build.build_zenith(cfg),
        covariates=build.build_covariates(cfg),
    )


def truth_sample_times(t0_ns: int, period_ns: int, rate_hz: float) -> np.ndarray:
    """Truth attitude sample times covering ``[t0, t0 + period)``, at least 16 per frame."""
    n = max(16, int(np.ceil(period_ns * S_PER_NS * rate_hz)))
    return t0_ns + (np.arange(n, dtype=np.int64) * period_ns) // n


def simulate_to_log(cfg: ScenarioConfig, output: str | Path, frames: int | None = None, seed: int | None = None,
                    show_progress: bool = True, compression: str = "zstd", inputs: Iterable[str | Path] = ()
                    ) -> SimulationSummary:
    """Simulate ``frames`` frames of ``cfg`` into the MCAP file ``output`` (chunks compressed with
    ``compression``: zstd, lz4 or none; the content does not depend on it).

    ``output`` is written through :func:`rollingstar.outputs.safe_output`: refused when it is one of
    ``inputs`` (the scenario file), replaced only when complete, kept as ``<output>.partial`` when
    the simulation fails or is interrupted."""
    if frames is not None or seed is not None:
        update = {k: v for k, v in (("frames", frames), ("seed", seed)) if v is not None}
        cfg = validate(ScenarioConfig, {**cfg.model_dump(mode="json"), **update}, f"{cfg.name} with {update}")
    sim = build_simulator(cfg)
    motion = sim.motion
    timing = sim.timing
    n_frames = cfg.frames
    period = int(timing.frame_period_ns)
    gyro_model = build.build_gyro(cfg)
    gyro = None
    if gyro_model is not None:
        gyro = simulate_gyro(gyro_model, motion, timing.frame_start_ns(0) - period, timing.frame_start_ns(n_frames), cfg.seed)
        gyro = dataclasses.replace(gyro, omega_rad_s=sim.apply_gyro(gyro.t_ns, gyro.omega_rad_s))  # gyro effects
    star_counts = []
    with safe_output(output, inputs, replaces=RECORDING) as tmp, stop_on_sigint() as stop, \
            LogWriter(tmp, kind="simulation", metadata={"scenario": {"yaml": to_yaml(cfg)}},
                      compression=compression) as writer, \
            progress_bar(f"simulate {cfg.name}", n_frames, show_progress) as advance:
        for frame in sim.frames(n_frames):
            if stop.requested:  # SIGINT: end at a frame boundary with a finalised log
                break
            t0 = int(frame.t0_ns)
            if gyro is not None:
                sel = (gyro.t_ns > t0 - period) & (gyro.t_ns <= t0)
                if sel.any():
                    w = gyro.omega_rad_s[sel]
                    writer.write_json(TOPIC_GYRO, GyroSamples(t_ns=gyro.t_ns[sel].tolist(), x=w[:, 0].tolist(),
                                                              y=w[:, 1].tolist(), z=w[:, 2].tolist()), t0)  # published at the frame boundary (>= 0 even when the
                    # gyro period does not divide the frame period and the last sample precedes t0)
            times = truth_sample_times(t0, period, cfg.truth_rate_hz)
            q = motion.attitude(times).as_quat()
            w = motion.angular_velocity(times)
            writer.write_json(TOPIC_TRUTH_ATTITUDE, AttitudeSamples(
                t_ns=times.tolist(), qx=q[:, 0].tolist(), qy=q[:, 1].tolist(), qz=q[:, 2].tolist(), qw=q[:, 3].tolist(),
                wx=w[:, 0].tolist(), wy=w[:, 1].tolist(), wz=w[:, 2].tolist()), int(times[0]))
            tr = frame.truth
            writer.write_json(TOPIC_TRUTH_STARS, arrays_to_stars(
                frame.index, t0, x=tr.x, y=tr.y, t_ns=tr.t_ns, row_time_ns=tr.row_time_ns,
                catalog_id=tr.catalog_id, ref_icrs=tr.unit_icrs, magnitude=tr.magnitude), t0)
            if frame.image is not None:
                writer.write_image(TOPIC_IMAGE, frame.image, t0)
            else:
                c = frame.centroids
                writer.write_json(TOPIC_CENTROIDS, arrays_to_stars(
                    frame.index, t0, x=c["x"], y=c["y"], t_ns=c["t_ns"], row_time_ns=c["row_time_ns"],
                    flux=c.get("flux"), sigma_px=np.full(len(c["x"]), cfg.noise.centroid_sigma_px)), t0)
            star_counts.append(len(tr.x))
            advance()
        writer.close()
        if stop.requested:
            raise Interrupted(f"interrupted: {output}{PARTIAL_SUFFIX} holds the {len(star_counts)} of {n_frames} "
                              f"frame(s) simulated before SIGINT; {output} was not written")
    return SimulationSummary(str(output), n_frames, cfg.level, float(np.mean(star_counts)) if star_counts else 0.0,
                             n_frames * period * S_PER_NS)
