
"""Windowed vs full-frame centroiding on the liu2013 frames, side by side in one run.

    .venv/bin/python benchmarks/windowed_speed.py [--frames 200] [--rounds 3] [--seed 1] [--json]

Frames: the liu2013 reproduction's (``studies/reproduce/liu2013.py``: 1000 x 1000 px, 12-bit,
two guide stars, 100 Hz, gyro-driven residual motion), rendered once. Centroiders, each set up
fresh per round and fed the frames in order with their gyro samples, exactly as
``configs/pipelines/liu2013_*.yaml`` configure them:

- ``cog``: the full-frame centroider (the baseline);
- ``windowed``: the default (compiled window kernel, tracked background);
- ``windowed kernel=numpy``: the vectorised numpy window pass with each window's own background
  (labelled "before");
- ``windowed batch=false``: one ``cog`` call per window (the original).

Two orders, both in the same run: ``sequential`` (each centroider runs over all frames on its own,
as in a pipeline: the other stages between two frames are small) and ``interleaved`` (every frame
goes through all four, the first one rotating, as in the reproduction: each call starts with
caches the others have flushed). Times are CPU time per ``process`` call (``time.process_time``,
one BLAS/OpenMP thread), windowed frames only, median over frames and rounds; ratios are
cog / windowed. Also reported, from the sequential runs: each path's centroid error against the
rendered spot positions (the simulator's truth, aberration shift included: the centroiders' own
error), std per axis over both guide stars and all windowed frames (cog: its spots within 2 px of
a star; its other detections are noise); and the largest and RMS
difference of the default's spot positions from the ``kernel=numpy`` path's (same frames, each
tracking its own windows).
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from rollingstar.estimators.data import FrameData, GyroSamples, SensorContext
from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.runner import build_stages
from rollingstar.sensors import build
from rollingstar.sensors.gyro import simulate_gyro
from rollingstar.sensors.scenario import load_scenario
from rollingstar.sensors.simulate import StarTrackerSimulator
from rollingstar.studies.reproduce import liu2013 as L

NAMES = ("cog", "windowed", "windowed kernel=numpy", "windowed batch=false")


def liu2013_frames(seed: int, frames: int):
    """The liu2013 reproduction's context and frames (FrameData with image and gyro samples)."""
    cfg = load_scenario(L.SCENARIO)
    camera, timing = build.build_camera(cfg), build.build_timing(cfg)
    sim_timing = type(timing)(mode="global", exposure_ns=L.EFFECTIVE_EXPOSURE_NS, line_delay_ns=0, rows=timing.rows,
                              frame_period_ns=timing.frame_period_ns)
    catalog, motion = build.build_catalog(cfg, camera), build.build_motion(cfg)
    nominal = np.asarray(cfg.catalog.positions_px, dtype=float)
    offsets = np.random.default_rng([seed, 2013]).normal(0.0, L.ABERRATION_SIGMA_PX, (frames, nominal.shape[0], 2))
    model = L.image_model(cfg)
    period = int(timing.frame_period_ns)
    sim = StarTrackerSimulator(camera, sim_timing, catalog, motion, effects=[L.AberrationJitter(offsets, nominal, 0, period)],
                               image_model=model, level="image", seed=seed)
    gyro = simulate_gyro(build.build_gyro(cfg), motion, -period, frames * period, seed)
    ctx = SensorContext.from_scenario(cfg, catalog)
    ctx = type(ctx)(camera=camera, timing=sim_timing, catalog=catalog, initial_attitude=ctx.initial_attitude,
                    bit_depth=model.bit_depth)
    out = []
    for k in range(frames):
        f = sim.frame(k)
        sel = (gyro.t_ns > f.t0_ns - period) & (gyro.t_ns <= f.t0_ns)
        out.append(FrameData(index=k, t0_ns=f.t0_ns, image=f.image, gyro=GyroSamples(gyro.t_ns[sel], gyro.omega_rad_s[sel]),
                             truth=f.truth))
    return ctx, out


def centroiders(ctx):
    full = build_stages(load_pipeline(L.PIPE_FULL), str(L.PIPE_FULL))[0]
    win = build_stages(load_pipeline(L.PIPE_WIN), str(L.PIPE_WIN))[0]
    params = win.params.model_dump()
    out = [full, win, type(win)(**{**params, "kernel": "numpy"}), type(win)(**{**params, "batch": False})]
    for c in out:
        c.setup(ctx)
    return dict(zip(NAMES, out))


def run(frames: int, rounds: int, seed: int) -> dict:
    from threadpoolctl import threadpool_limits

    ctx, fr = liu2013_frames(seed, frames)
    times = {order: {n: [] for n in NAMES} for order in ("sequential", "interleaved")}
    diffs = []
    errors = {n: [] for n in NAMES}
    with threadpool_limits(1):
        for rnd in range(rounds):
            # sequential: each centroider alone over all frames (order rotates between rounds)
            cs = centroiders(ctx)
            for j in range(len(NAMES)):
                name = NAMES[(rnd + j) % len(NAMES)]
                c = cs[name]
                pos = []
                for f in fr:
                    t = time.process_time()
                    out = c.process(f)
                    dt = time.process_time() - t
                    if name == "cog" or c.last_mode == "window":
                        times["sequential"][name].append(dt)
                    used = name == "cog" or c.last_mode == "window"
                    pos.append((out.stars.x.copy(), out.stars.y.copy(), used))
                    if used and f.index > 1:
                        tx, ty = f.truth.x, f.truth.y
                        for x, y in zip(out.stars.x, out.stars.y):  # error against the nearest rendered star
                            i = int(np.argmin(np.hypot(tx - x, ty - y)))
                            if np.hypot(tx[i] - x, ty[i] - y) < 2.0:  # cog's noise detections are not guide stars
                                errors[name].append((x - tx[i], y - ty[i]))
                cs[name] = pos
            for (xa, ya, wa), (xb, yb, wb) in zip(cs["windowed"][1:], cs["windowed kernel=numpy"][1:]):
                if wa and wb and xa.size == xb.size:
                    diffs.append(np.max(np.hypot(xa - xb, ya - yb)))
            # interleaved: every frame through all four, the first one rotating
            cs = centroiders(ctx)
            for k, f in enumerate(fr):
                for j in range(len(NAMES)):
                    name = NAMES[(k + j) % len(NAMES)]
                    t = time.process_time()
                    cs[name].process(f)
                    dt = time.process_time() - t
                    if name == "cog" or cs[name].last_mode == "window":
                        times["interleaved"][name].append(dt)
    res = {"frames": frames, "rounds": rounds, "seed": seed, "unit": "ms per frame (median CPU time)", "orders": {}}
    for order, per in times.items():
        med = {n: float(np.median(v[1:])) * 1e3 for n, v in per.items()}  # [1:]: drop the first windowed frame
        res["orders"][order] = {"ms": med, "ratio_cog_over": {n: med["cog"] / med[n] for n in NAMES[1:]}}
    d = np.asarray(diffs)
    res["default_vs_numpy_path_px"] = {"max": float(d.max()), "rms": float(np.sqrt(np.mean(d**2))), "frames": int(d.size)}
    res["centroid_error_std_px"] = {n: np.std(np.asarray(e), axis=0, ddof=1).tolist() for n, e in errors.items()}
    res["centroid_error_n"] = {n: len(e) for n, e in errors.items()}
    return res


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    res = run(a.frames, a.rounds, a.seed)
    if a.json:
        print(json.dumps(res, indent=2))
        return
    print(f"liu2013 frames: {a.frames} x {a.rounds} rounds, seed {a.seed}; {res['unit']}, windowed frames only")
    for order, r in res["orders"].items():
        print(f"  {order}:")
        for n in NAMES:
            ratio = "" if n == "cog" else f"   cog / this = {r['ratio_cog_over'][n]:.1f}x"
            print(f"    {n:24s} {r['ms'][n]:8.4f} ms{ratio}")
    print("  centroid error vs rendered position, std x / y (px):")
    for n in NAMES:
        sx, sy = res["centroid_error_std_px"][n]
        print(f"    {n:24s} {sx:.4f} / {sy:.4f}   ({res['centroid_error_n'][n]} spots)")
    d = res["default_vs_numpy_path_px"]
    print(f"  spot positions, default vs kernel=numpy: max {d['max']:.4f} px, RMS {d['rms']:.4f} px over {d['frames']} frames")


if __name__ == "__main__":
    main()
