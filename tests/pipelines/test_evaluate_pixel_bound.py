"""evaluate's pixel-level bound on an image-level recording: finite, and the RMS of the frame bounds
computed independently from the simulator's own truth (motion model, catalogue magnitudes)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rollingstar.logs.reader import LogReader
from rollingstar.logs.topics import TOPIC_EST_ATTITUDE, TOPIC_TRUTH_STARS
from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.evaluate import _star_magnitudes, evaluate_log
from rollingstar.pipelines.runner import run_pipeline
from rollingstar.pipelines.simulate import build_simulator, simulate_to_log
from rollingstar.sensors import build
from rollingstar.sensors.conventions import RAD_TO_ARCSEC
from rollingstar.sensors.image_sim import ImageModel
from rollingstar.sensors.pixel_crb import FrameDetector, frame_crb
from rollingstar.sensors.scenario import load_scenario
from rollingstar.sensors.timing import DetectorTiming

ROOT = Path(__file__).resolve().parents[2]
FRAMES = 4


@pytest.fixture(scope="module")
def he2021a(tmp_path_factory):
    """Four he2021a frames (image level, 1 deg/s about x) and the he2021a pipeline's output."""
    cfg = load_scenario(ROOT / "configs" / "scenarios" / "he2021a.yaml")
    tmp = tmp_path_factory.mktemp("pixel_bound")
    simulate_to_log(cfg, tmp / "rec.mcap", frames=FRAMES, show_progress=False)
    run_pipeline(tmp / "rec.mcap", load_pipeline(ROOT / "configs" / "pipelines" / "he2021a.yaml"), tmp / "out.mcap",
                 show_progress=False)
    return cfg, tmp / "out.mcap"


def _independent_bounds(cfg, out) -> tuple[np.ndarray, np.ndarray]:
    """RMS over the frames with a valid estimate of the frame bound at the estimate's time, from the
    simulator's truth: attitude (arcsec) and rate (deg/s) per axis."""
    sim = build_simulator(cfg.model_copy(update={"frames": FRAMES}))
    timing: DetectorTiming = sim.timing
    model = ImageModel(**cfg.image.model_dump())
    det = FrameDetector.from_image_model(model, timing.exposure_ns, timing.effective_line_delay_ns)
    estimates = [m.data for m in LogReader(out).messages([TOPIC_EST_ATTITUDE]) if m.data["valid"]]
    att, rate = [], []
    for a in estimates:
        frame, t_ref = sim.frame(a["frame"]), a["t_ns"]
        cov = frame_crb(sim.camera, sim.motion.attitude(t_ref), sim.motion.angular_velocity(t_ref),
                        frame.truth.unit_icrs, model.star_electrons(frame.truth.magnitude, timing.exposure_ns),
                        (frame.t0_ns - t_ref) * 1e-9, det)
        att.append(np.diag(cov)[:3])
        rate.append(np.diag(cov)[3:])
    return np.sqrt(np.mean(att, axis=0)) * RAD_TO_ARCSEC, np.degrees(np.sqrt(np.mean(rate, axis=0)))


def test_evaluate_reports_the_pixel_bound_of_the_frames_true_stars(he2021a):
    cfg, out = he2021a
    m = evaluate_log(out)
    assert m["attitude_updates"] == FRAMES
    pixel = np.array([m["pixel_crb_arcsec"][a] for a in "xyz"])
    pixel_rate = np.array([m["pixel_rate_crb_deg_s"][a] for a in "xyz"])
    assert np.all(np.isfinite(pixel)) and np.all(pixel > 0) and np.all(np.isfinite(pixel_rate))
    att, rate = _independent_bounds(cfg, out)
    np.testing.assert_allclose(pixel, att, rtol=1e-4)
    np.testing.assert_allclose(pixel_rate, rate, rtol=1e-4)
    centroid_level = np.array([m["attitude_crb_arcsec"][a] for a in "xyz"])
    assert np.all(np.isfinite(centroid_level))  # the given-sigma bound is reported at image level too
    rmse = np.array([m["attitude_error_arcsec"][f"{a}_rmse"] for a in "xyz"])
    np.testing.assert_allclose([m["efficiency_pixel"][f"attitude_{a}"] for a in "xyz"], rmse / pixel)


def test_a_centroid_level_recording_has_no_pixel_bound(small_output):
    m = evaluate_log(small_output)
    assert m["pixel_crb_arcsec"] == {"x": None, "y": None, "z": None}
    assert m["efficiency_pixel"]["attitude_x"] is None
    assert m["attitude_crb_arcsec"]["x"] is not None


def test_magnitudes_missing_from_the_truth_are_taken_from_the_catalogue(he2021a):
    cfg, out = he2021a
    tru = next(iter(LogReader(out).stars(TOPIC_TRUTH_STARS).values()))
    carried = _star_magnitudes(tru, lambda: None)  # the truth carries them: no catalogue needed
    looked_up = _star_magnitudes({**tru, "magnitude": None}, lambda: build.build_catalog(cfg))
    np.testing.assert_allclose(looked_up, carried)
    assert np.all(carried <= cfg.catalog.magnitude_limit)
