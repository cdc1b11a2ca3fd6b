"""Speed of simulate -> run -> evaluate, per stage, in frames per second.

    .venv/bin/python benchmarks/speed.py [--centroid-frames 1000] [--image-frames 100] [--json]

Centroid level: the he2021b scenario (1024 x 1024, Hipparcos stars), baseline pipeline.
Image level: the he2021a scenario (1024 x 1024 rendered frames), baseline pipeline with `cog`.
Numbers are wall-clock on the machine that runs this; quote them with the machine.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.evaluate import evaluate_log
from rollingstar.pipelines.runner import run_pipeline
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
PASS_THROUGH_S = 2e-6  # per frame: below this a stage did no work on the frame


def measure(scenario: str, frames: int, tmp: Path) -> dict:
    cfg = load_scenario(ROOT / "configs" / "scenarios" / scenario)
    pipeline = load_pipeline(ROOT / "configs" / "pipelines" / "baseline.yaml")
    rec, res = tmp / f"{scenario}.mcap", tmp / f"{scenario}.out.mcap"
    t = time.perf_counter()
    simulate_to_log(cfg, rec, frames=frames, show_progress=False)
    t_sim = time.perf_counter() - t
    t = time.perf_counter()
    summary = run_pipeline(rec, pipeline, res, show_progress=False)
    t_run = time.perf_counter() - t
    t = time.perf_counter()
    evaluate_log(res)
    t_eval = time.perf_counter() - t
    # a stage that passes its input through (cog on a recording of centroids) takes ~nothing: None, not
    # a rate of millions of frames per second
    stages = {k: (frames / v if v / frames >= PASS_THROUGH_S else None) for k, v in summary.stage_seconds.items()}
    return {
        "scenario": scenario, "level": cfg.level, "frames": frames,
        "resolution": [cfg.sensor.width_px, cfg.sensor.height_px],
        "fps": {"simulate": frames / t_sim, "run (read+stages+write)": frames / t_run, "evaluate": frames / t_eval},
        "fps_per_pipeline_stage": stages,
        "recording_MiB": rec.stat().st_size / 2**20,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--centroid-frames", type=int, default=1000)
    ap.add_argument("--image-frames", type=int, default=100)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        results = [measure("he2021b.yaml", args.centroid_frames, Path(tmp)),
                   measure("he2021a.yaml", args.image_frames, Path(tmp))]
    machine = {"cpu_count": os.cpu_count(), "python": platform.python_version(), "machine": platform.machine()}
    if args.json:
        print(json.dumps({"machine": machine, "results": results}, indent=2))
        return
    print(f"machine: {machine}")
    for r in results:
        print(f"\n{r['scenario']} ({r['level']} level, {r['resolution'][0]}x{r['resolution'][1]}, {r['frames']} frames, "
              f"recording {r['recording_MiB']:.1f} MiB)")
        for k, v in r["fps"].items():
            print(f"  {k:<28s} {v:10.1f} frames/s")
        for k, v in r["fps_per_pipeline_stage"].items():
            text = f"{v:10.1f} frames/s" if v is not None else "  (passes its input through: nothing to do here)"
            print(f"    stage {k:<22s} {text}")


if __name__ == "__main__":
    main()
