"""Speed of the `cog` centroider against a plain frame.sum() pass and tetra3rs' extractor.

    .venv/bin/python benchmarks/centroid_speed.py [--repeats 30] [--json]

Frames: a 1024 x 1024 uint16 frame rendered by the he2021a scenario's image simulator, and (when
the shared real data is present: ROLLINGSTAR_REAL_DATA, default ../shared/data/real) the eight
1024 x 768 16-bit tetra3 sky images. Each timing is the minimum over ``--repeats`` calls (the
least disturbed run on a shared machine); ratios are to ``frame.sum()`` of the same frame. The
cost of the edge term (estimators/centroiders/edge.py: spots cut by the detector edge) is ``cog``
median with ``edge_sigma`` on minus off, interleaved call by call, with the number of cut spots.
tetra3rs runs single-threaded (``threads=1``) so that the comparison is per core.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from rollingstar.estimators.centroiders.cog import CogCentroider
from rollingstar.estimators.data import FrameData, SensorContext
from rollingstar.pipelines.simulate import build_simulator
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.scenario import load_scenario
from rollingstar.sensors.timing import DetectorTiming

ROOT = Path(__file__).resolve().parents[1]


def best_ms(fn, repeats: int) -> float:
    fn()
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best * 1e3


def simulated_frame() -> np.ndarray:
    cfg = load_scenario(ROOT / "configs" / "scenarios" / "he2021a.yaml")
    sim = build_simulator(cfg)
    return np.asarray(sim.frame(0).image)


def real_frames() -> list[tuple[str, np.ndarray]]:
    from PIL import Image

    base = Path(os.environ.get("ROLLINGSTAR_REAL_DATA", ROOT.parent / "shared" / "data" / "real")) / "tetra3"
    return [(p.stem, np.asarray(Image.open(p))) for p in sorted(base.glob("*.tiff"))]


def measure(name: str, img: np.ndarray, repeats: int) -> dict:
    import tetra3rs

    H, W = img.shape
    cam = PinholeCamera(focal_length_m=0.035, pixel_size_m=6.9e-6, width=W, height=H)
    ctx = SensorContext(camera=cam, timing=DetectorTiming(mode="global", exposure_ns=1_000_000, line_delay_ns=0, rows=H),
                        catalog=None)
    frame = FrameData(index=0, t0_ns=0, image=img)
    row = {"frame": name, "shape": [H, W], "sum_ms": best_ms(lambda: img.sum(), repeats)}
    for bg in ("median", "tiles", "map"):
        c = CogCentroider(background=bg, max_sharpness=0.9 if bg == "map" else None)
        c.setup(ctx)
        row[f"cog_{bg}_ms"] = best_ms(lambda: c.process(frame), repeats)
        row[f"cog_{bg}_spots"] = c.process(frame).stars.n
    on, off = CogCentroider(), CogCentroider(edge_sigma=False)
    on.setup(ctx)
    off.setup(ctx)
    t_on, t_off = np.inf, np.inf
    for _ in range(repeats):  # interleaved: the same machine state for both
        t_on = min(t_on, best_ms(lambda: on.process(frame), 1))
        t_off = min(t_off, best_ms(lambda: off.process(frame), 1))
    row["edge_term_ms"] = t_on - t_off
    row["cut_spots"] = sum(int(f.split(":")[1]) for f in on.process(frame).flags if f.startswith("edge_truncated_stars:"))
    ext = tetra3rs.CentroidExtractor()
    row["tetra3rs_ms"] = best_ms(lambda: ext.extract(img, threads=1), repeats)
    row["tetra3rs_spots"] = len(ext.extract(img, threads=1).centroids)
    for k in ("cog_median_ms", "cog_tiles_ms", "cog_map_ms", "tetra3rs_ms"):
        row[k.replace("_ms", "_over_sum")] = row[k] / row["sum_ms"]
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    frames = [("he2021a simulated 1024x1024", simulated_frame())] + real_frames()
    rows = [measure(name, img, args.repeats) for name, img in frames]
    if args.json:
        print(json.dumps({"machine": platform.processor() or platform.machine(), "rows": rows}, indent=1))
        return
    print(f"machine: {platform.machine()} {os.cpu_count()} cpu(s); min of {args.repeats} calls, ms (x frame.sum())")
    print(f"{'frame':34s} {'sum':>6s} {'cog median':>17s} {'cog tiles':>17s} {'cog map':>17s} {'tetra3rs':>17s} "
          f"{'edge term (cut spots)':>22s}")
    for r in rows:
        cells = [f"{r[k + '_ms']:6.2f} ({r[k + '_over_sum']:4.1f}x)" for k in ("cog_median", "cog_tiles", "cog_map", "tetra3rs")]
        print(f"{r['frame'][:34]:34s} {r['sum_ms']:6.2f} " + " ".join(f"{c:>17s}" for c in cells)
              + f" {r['edge_term_ms']:+8.3f} ms ({r['cut_spots']:2d})")


if __name__ == "__main__":
    main()
