"""Shared fixtures: small simulated recordings made once per test session."""
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def real_data_dir() -> Path:
    """The shared real data (ROLLINGSTAR_REAL_DATA, default ../shared/data/real); skip when absent."""
    path = Path(os.environ.get("ROLLINGSTAR_REAL_DATA", ROOT.parent / "shared" / "data" / "real"))
    if not path.is_dir():
        pytest.skip(f"real data not found at {path} (set ROLLINGSTAR_REAL_DATA to the shared/data/real folder)")
    return path


@pytest.fixture(scope="session")
def small_recording(tmp_path_factory) -> Path:
    """20 frames of the he2021b scenario at centroid level."""
    from rollingstar.pipelines.simulate import simulate_to_log
    from rollingstar.sensors.scenario import load_scenario

    out = tmp_path_factory.mktemp("rec") / "he2021b_20.mcap"
    simulate_to_log(load_scenario(ROOT / "configs" / "scenarios" / "he2021b.yaml"), out, frames=20, show_progress=False)
    return out


@pytest.fixture(scope="session")
def small_output(tmp_path_factory, small_recording) -> Path:
    """The baseline pipeline's output over :func:`small_recording`."""
    from rollingstar.pipelines.config import load_pipeline
    from rollingstar.pipelines.runner import run_pipeline

    out = tmp_path_factory.mktemp("out") / "he2021b_20.out.mcap"
    run_pipeline(small_recording, load_pipeline(ROOT / "configs" / "pipelines" / "baseline.yaml"), out, show_progress=False)
    return out
