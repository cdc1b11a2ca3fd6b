"""A tour of the rollingstar Python API: simulate, run, evaluate, compare two pipelines, diagnose.

    python examples/quickstart.py [--frames 40] [--out DIR]

Runs in about a minute on a laptop. Every step writes what the matching command line writes
(``rollingstar simulate``, ``run``, ``evaluate``, ``diagnose``), into ``DIR`` (default: a
temporary folder).
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import rollingstar as rs

# fu2022's star tracker turning at 1.4 deg/s: fast enough that the motion between rows decides how
# accurate an uncorrected attitude can be.
SCENARIO = "fu2022"


def tour(out: Path, frames: int) -> dict:
    # 1. A recording from a shipped scenario, given by name (a YAML path works too).
    rec = rs.simulate(SCENARIO, out / "rec.mcap", frames=frames, seed=1)
    print(f"simulated {rec.frames} frames, {rec.stars_per_frame_mean:.1f} stars per frame")

    # 2. Two shipped pipelines over it: the baseline (no rolling-shutter correction; tracking with a
    #    10 px gate, lost in space again whenever the stars leave it) and ls_rate (each frame's body
    #    rate from the stars' angular distances, the rolling-shutter correction it feeds, a 100 px gate).
    metrics = {}
    for name in ("baseline", "ls_rate"):
        summary = rs.run(name, rec.path, out / f"{name}.mcap")
        metrics[name] = rs.evaluate(summary.output)
        err = metrics[name]["attitude_error_arcsec"]
        print(f"{name:9s} {summary.valid_estimates}/{summary.attitude_estimates} valid, attitude RMSE "
              f"x {err['x_rmse']:.2f}  y {err['y_rmse']:.2f}  z {err['z_rmse']:.2f} arcsec")

    # 3. The recording read back: metadata, topics and the scenario it was made with.
    reader = rs.open_recording(rec.path)
    print(f"topics: {', '.join(sorted(reader.summary_info().topics))}")

    # 4. Diagnose the recording against its own scenario: nothing is left out, so nothing is named.
    report = rs.diagnose(rec.path, output=out / "diagnosis")
    print(f"diagnosis: {report['verdict']}")
    return {"metrics": metrics, "diagnosis": report}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        tour(args.out, args.frames)
        return
    with tempfile.TemporaryDirectory() as tmp:
        tour(Path(tmp), args.frames)


if __name__ == "__main__":
    main()
