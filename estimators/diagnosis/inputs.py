"""What a diagnosis is given besides the observations: its options and the simulation model.

The simulation model (:class:`SensorModel`) is what a scenario builds: the camera, the detector
timing, the effect chain the recording is compared against, and whether the scenario moves at all.
"""
from __future__ import annotations

from dataclasses import dataclass

from rollingstar.estimators.diagnosis.selection import MIN_DELTA_BIC
from rollingstar.sensors import build
from rollingstar.sensors.camera import PinholeCamera
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
    test the effects the attitude absorbs against it (None: no reference used, :mod:`.reference`).
    """

    heldout_fraction: float = HELDOUT_FRACTION
    seed: int = 0
    n_boot: int = 50
    min_delta_bic: float = MIN_DELTA_BIC
    stability: bool = True
    resimulate: bool = True
    show_progress: bool = False
    reference_sigma_arcsec: float | None = None


@dataclass(frozen=True, eq=False)
class SensorModel:
    """The simulation model a recording is diagnosed against: a scenario and what it builds."""

    scenario: ScenarioConfig
    camera: PinholeCamera
    timing: DetectorTiming
    effects: tuple  # the scenario's effect chain: the base every candidate effect is added to
    moving: bool  # whether the scenario declares any motion (:func:`scenario_moves`)


def sensor_model(scenario: ScenarioConfig) -> SensorModel:
    """Camera, timing, effect chain and motion flag of ``scenario``."""
    return SensorModel(scenario, build.build_camera(scenario), build.build_timing(scenario),
                       tuple(build.build_effects(scenario)), scenario_moves(scenario))


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
