"""Centroid-level simulator speed: no effect, one effect, every library effect switched on, side by side.

    .venv/bin/python benchmarks/effects_speed.py [--frames 200] [--json]

Scenario: he2021b (1024 x 1024, Hipparcos stars, rolling shutter) with a 1 deg/s multi-axis rate,
a ground site (elevation 40 deg) and a temperature covariate so that every effect has its context;
each effect at one prior scale. Reports simulated frames per second of each case and its ratio to no effect
(wall clock on the machine that runs it; quote the ratio, it is what transfers between machines).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from rollingstar.config import validate
from rollingstar.pipelines.simulate import build_simulator
from rollingstar.sensors.effects import EFFECTS
from rollingstar.sensors.scenario import ScenarioConfig, load_scenario

ROOT = Path(__file__).resolve().parents[1]


def scenario(names) -> ScenarioConfig:
    data = load_scenario(ROOT / "configs" / "scenarios" / "he2021b.yaml").model_dump(mode="json")
    data["motion"].update(rate_deg_s=[0.5, -0.7, 0.5], segments=[], jitter=[])
    data["environment"] = {"elevation_deg": 40.0, "covariates": {"temperature_c": {"offset": 25.0, "slope_per_h": 5.0}}}
    data["level"] = "centroid"
    data["effects"] = [
        {"kind": name, "params": {p.name: p.default + p.prior_scale for p in EFFECTS[name].parameters}}
        for name in names
    ]
    return validate(ScenarioConfig, data, "he2021b + effects")


def measure(frames: int) -> dict:
    out = {}
    cases = (("no effect", ()), ("rolling_shutter", ("rolling_shutter",)),
             ("radial_distortion", ("radial_distortion",)), (f"all {len(EFFECTS)} effects", tuple(EFFECTS)))
    for label, names in cases:
        sim = build_simulator(scenario(names))
        sim.frame(0)  # catalogue load and caches
        t = time.perf_counter()
        stars = sum(len(sim.frame(k).truth) for k in range(frames))
        out[label] = {"frames_per_s": frames / (time.perf_counter() - t), "stars_per_frame": stars / frames}
    base = out["no effect"]["frames_per_s"]
    return {"frames": frames, "results": out,
            "speed_ratio_vs_none": {k: v["frames_per_s"] / base for k, v in out.items() if k != "no effect"}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    r = measure(args.frames)
    if args.json:
        print(json.dumps(r, indent=2))
        return
    for k, v in r["results"].items():
        ratio = r["speed_ratio_vs_none"].get(k)
        tail = f"  speed ratio vs none {ratio:.2f}" if ratio is not None else ""
        print(f"{k:<18s} {v['frames_per_s']:8.1f} frames/s  ({v['stars_per_frame']:.1f} stars/frame){tail}")


if __name__ == "__main__":
    main()
