"""What a diagnosis is given besides the observations: its options and the simulation model.

The simulation model (:class:`SensorModel`) is what a scenario builds: the camera, the detector
timing, the effect chain the recording is compared against, and whether the scenario moves at all.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rollingstar.estimators.diagnosis.selection import MIN_DELTA_BIC
from rollingstar.sensors import build
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.scenario import ScenarioConfig
from rollingstar.sensors.timing import DetectorTiming

HELDOUT_FRACTION = 0.25


@dataclass(frozen=True)
class DiagnoseOptions:
    """How a diagnosis runs.

    ``heldout_fraction``: the share of frames (with fewer than 4 frames: of stars) held out before
    any fit; ``seed``: draws that split, the bootstrap resamples and the re-simulation noise;
    ``n_boot``: bootstrap resamples of the selection (0: none); ``min_delta_bic``: the BIC margin
    an effect must earn; ``stability``: refit on subsets; ``resimulate``: compare residual
    distributions with a re-simulation; ``show_progress``: show the progress of the pipeline run
    that produces the observations (used by the command layer, not by the algorithm);
    ``reference_sigma_arcsec``: the accuracy per axis of the recording's reference attitude, to
    test the effects the attitude absorbs against it (None: no reference used, :mod:`.reference`);
    ``reference_mount_free``: the reference is not aligned with the camera (a second tracker, an
    unsurveyed mount): its misalignment is fitted with every model.
    """

    heldout_fraction: float = HELDOUT_FRACTION
    seed: int = 0
    n_boot: int = 50
    min_delta_bic: float = MIN_DELTA_BIC
    stability: bool = True
    resimulate: bool = True
    show_progress: bool = False
    reference_sigma_arcsec: float | None = None
    reference_mount_free: bool = False


@dataclass(frozen=True, eq=False)
class SensorModel:
    """The simulation model a recording is diagnosed against: a scenario and what it builds."""

    scenario: ScenarioConfig
    camera: PinholeCamera
    timing: DetectorTiming
    effects: tuple  # the scenario's effect chain: the base every candidate effect is added to
    moving: bool  # whether the scenario declares any motion (:func:`scenario_moves`)


def sensor_model(scenario: ScenarioConfig, moving: bool | None = None) -> SensorModel:
    """Camera, timing, effect chain and motion flag of ``scenario`` (``moving``: the flag decided
    from the recording, :func:`sequence_moves`; None: the scenario's own, :func:`scenario_moves`)."""
    return SensorModel(scenario, build.build_camera(scenario), build.build_timing(scenario),
                       tuple(build.build_effects(scenario)), scenario_moves(scenario) if moving is None else moving)


MIN_SHARED_STARS = 3  # identified stars two consecutive frames share when they are one trajectory
SHARED_FRACTION = 0.8  # of the consecutive frame pairs
MOVING_NOISE_FRACTION = 0.5  # rolling-shutter displacement across a readout, in centroid sigmas
UNSTATED_NOISE_PX = 0.05  # the centroid sigma assumed here when the recording states none


def sequence_moves(obs, attitudes, camera, timing) -> bool:
    """Whether the recording's frames are one moving trajectory, whatever its scenario declares (a
    recording from another tool or a real tracker may declare no motion at all): at least
    ``SHARED_FRACTION`` of the consecutive frame pairs share ``MIN_SHARED_STARS`` identified stars
    (unrelated images share none), and the body rate their attitudes imply moves a star across one
    readout by more than ``MOVING_NOISE_FRACTION`` of the centroid noise (median over frames; a
    still sensor's rate from differenced attitudes is noise, and fitting it would only add noise)."""
    from rollingstar.estimators.diagnosis.noise import consecutive_pairs
    from rollingstar.estimators.diagnosis.observations import rates_from_attitudes

    if obs.n_frames < 2 or len(attitudes) != obs.n_frames:
        return False
    first, _ = consecutive_pairs(obs, np.ones(obs.n, dtype=bool))  # a star in frame k and in k + 1
    per_pair = np.bincount(obs.frame[first], minlength=obs.n_frames)[: obs.n_frames - 1]
    if np.mean(per_pair >= MIN_SHARED_STARS) < SHARED_FRACTION:
        return False
    _, _, rate = rates_from_attitudes(attitudes, obs.t_ref_ns)
    readout_s = timing.effective_line_delay_ns * S_PER_NS * camera.height
    shift_px = np.linalg.norm(rate, axis=1) * readout_s * camera.focal_px
    known = np.isfinite(obs.sigma)
    noise = float(np.median(obs.sigma[known])) if known.any() else UNSTATED_NOISE_PX
    return bool(np.median(shift_px) > MOVING_NOISE_FRACTION * noise)


def scenario_moves(scenario: ScenarioConfig) -> bool:
    """Whether the scenario declares any motion (rate, acceleration, segments with motion, jitter).

    A recording of a still sensor (or of unrelated scenes, such as imported single images) gets no
    rate from its attitude sequence: consecutive frames are not one trajectory.
    """
    m = scenario.motion
    vals = list(m.rate_deg_s) + list(m.accel_deg_s2)
    for seg in m.segments:
        vals += list(seg.rate_deg_s) + list(seg.accel_deg_s2)
    return any(v != 0 for v in vals) or bool(m.jitter)
