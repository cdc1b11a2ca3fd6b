"""fu2022 reproduction: single-frame PSO angular rate on the Table 1 sensor (centroid-level simulation).

Every trial: a random boresight (uniform on the sky) and roll, constant body rate, frame 0 simulated
by :class:`rollingstar.sensors.simulate.StarTrackerSimulator` (exact rolling shutter: each centroid is the star's
position at the mid-exposure of its own row; line delay 20 us, our assumption), Gaussian centroid
noise ``sigma`` per axis added here, the stars' times those of their *measured* rows, identities
from the truth (the paper assumes identified stars). Pointings with fewer than three stars brighter
than Mv 5.2 are redrawn (counted in the row notes). The estimator is ``pso-rate`` with the
parameters of ``configs/pipelines/fu2022.yaml`` unless a row says otherwise. Error = norm of
(estimated - true) (omega_x, omega_y) in deg/s (omega_z is assumed 0 by the method and is 0 here).

Random streams: trial ``k`` of condition ``c`` uses ``default_rng([seed, c, k])``; the PSO uses its
own ``default_rng([pso_seed, k])`` (frame index = k).
"""
from __future__ import annotations

import multiprocessing as mp
import time
from functools import lru_cache
from pathlib import Path

import numpy as np
import yaml

from rollingstar.config import CONFIGS
from rollingstar.estimators.data import FrameData, SensorContext, StarTable
from rollingstar.estimators.rates.pso import PsoRateEstimator, image_velocity_px_s
from rollingstar.progress import progress_bar
from rollingstar.sensors.conventions import DEG_TO_RAD, attitude_from_radec_roll
from rollingstar.sensors.motion import constant_rate
from rollingstar.sensors.scenario import load_scenario
from rollingstar.sensors.simulate import StarTrackerSimulator
from rollingstar.studies.reproduce import Row, paper_values

SCENARIO = CONFIGS / "scenarios" / "fu2022.yaml"
PIPELINE = CONFIGS / "pipelines" / "fu2022.yaml"
RATES = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 5.0)  # section 3.2 / Fig 11
FIELD_RATES = (0.5, 1.0, 3.0, 5.0)  # section 3.3 / Fig 14
SIGMAS = (0.01, 0.02, 0.03, 0.04, 0.05)  # Fig 12
# Line-delay sweep (us per row; the paper does not state it). 20: our default assumption (25.6 ms
# readout); 78.125: the 1280 rows read out over the 100 ms exposure, i.e. continuous rolling
# operation at 10 frames/s, the longest readout for which exposure and readout overlap in one frame
# period as the paper's Fig 4 draws; 156.25: readout 200 ms ("exposure time no more than 200 ms",
# sec 3.1); 39.06, 312.5 and 625 bracket them.
LINE_DELAYS_US = (20.0, 39.0625, 78.125, 156.25, 312.5, 625.0)
LINE_DELAYS_US_QUICK = (20.0, 78.125, 312.5)
# (key, omega deg/s, sigma px, paper quantity, statistic) of the sweep
SWEEP = (("fig9_noisy", (1, 1, 0), 0.02, "fig9_rate_error_median_noisy", "median"),
         ("fig11_x3", (3, 0, 0), 0.02, "fig11_max_error_x", "max"),
         ("fig12_0.01", (3, 0, 0), 0.01, "fig12_q3_error", "q3"),
         ("fig12_0.05", (3, 0, 0), 0.05, "fig12_q3_error", "q3"))


@lru_cache(maxsize=1)
def _setup():
    cfg = load_scenario(SCENARIO)
    ctx = SensorContext.from_scenario(cfg)
    with open(PIPELINE) as fh:
        pipe = yaml.safe_load(fh)
    params = next(s.get("params", {}) for s in pipe["stages"] if s["kind"] == "pso-rate")
    return cfg, ctx, dict(params)


def simulate_frame(ctx, omega_deg, sigma_px: float, rng: np.random.Generator, index: int,
                   magnitude_limit: float) -> tuple[FrameData, int]:
    """One identified centroid frame (>= 3 stars) at a random pointing; returns (frame, redraws)."""
    redraws = 0
    while True:
        att = attitude_from_radec_roll(rng.uniform(0, 360), np.degrees(np.arcsin(rng.uniform(-1, 1))),
                                       rng.uniform(-180, 180))
        sim = StarTrackerSimulator(ctx.camera, ctx.timing, ctx.catalog, constant_rate(att, np.asarray(omega_deg) * DEG_TO_RAD),
                                   magnitude_limit=magnitude_limit)
        tr = sim.frame(0).truth
        if len(tr) >= 3:
            break
        redraws += 1
    n = len(tr)
    x = tr.x + rng.normal(0.0, sigma_px, n) if sigma_px > 0 else tr.x.copy()
    y = tr.y + rng.normal(0.0, sigma_px, n) if sigma_px > 0 else tr.y.copy()
    t0 = 0
    stars = StarTable.build(x, y, ctx.timing.row_mid_exposure_ns(t0, y), ctx.timing.row_start_ns(t0, y),
                            flux=10 ** (-0.4 * tr.magnitude), catalog_id=tr.catalog_id, ref_icrs=tr.unit_icrs,
                            sigma_px=np.full(n, sigma_px))
    return FrameData(index=index, t0_ns=t0, stars=stars), redraws


def context_with_line_delay(ctx, line_delay_us: float | None):
    """The Table 1 context with another rolling-shutter line delay (None: the scenario's)."""
    if line_delay_us is None:
        return ctx
    t = ctx.timing
    timing = type(t)(mode=t.mode, exposure_ns=t.exposure_ns, line_delay_ns=int(round(line_delay_us * 1e3)), rows=t.rows)
    return type(ctx)(camera=ctx.camera, timing=timing, catalog=ctx.catalog, initial_attitude=ctx.initial_attitude,
                     centroid_sigma_px=ctx.centroid_sigma_px, bit_depth=ctx.bit_depth)


def run_condition(args) -> dict:
    """Monte Carlo of one condition: (cond_id, omega_deg, sigma, trials, seed, estimator overrides[, line delay us])."""
    cond_id, omega_deg, sigma, trials, seed, overrides = args[:6]
    cfg, ctx, params = _setup()
    ctx = context_with_line_delay(ctx, args[6] if len(args) > 6 else None)
    est = PsoRateEstimator(**{**params, **overrides})
    est.setup(ctx)
    true = np.asarray(omega_deg, dtype=float)[:2]
    err = np.empty((trials, 2))
    iters = np.empty(trials, dtype=int)
    redraws = 0
    for k in range(trials):
        frame, r = simulate_frame(ctx, omega_deg, sigma, np.random.default_rng([seed, cond_id, k]), k,
                                  cfg.catalog.magnitude_limit)
        redraws += r
        rate = est.process(frame).rate
        err[k] = np.degrees(rate.omega_rad_s[:2]) - true
        iters[k] = rate.iterations
    return {"err": err, "iters": iters, "redraws": redraws}


def _run_all(conds: list[tuple], workers: int) -> list[dict]:
    with progress_bar("fu2022 conditions", len(conds)) as advance:
        if workers <= 1:
            return [_advanced(run_condition(c), advance) for c in conds]
        _setup()  # load the catalogue once, inherited by the forked workers
        with mp.get_context("fork").Pool(workers) as pool:
            return [_advanced(r, advance) for r in pool.imap(run_condition, conds, chunksize=1)]


def _advanced(result, advance):
    advance()
    return result


def _norm(res: dict) -> np.ndarray:
    return np.hypot(res["err"][:, 0], res["err"][:, 1])


def velocity_field(ctx, omega_deg, step: int = 128):
    """Exact image velocity (px/s) on a grid of the detector (Figs 6-7)."""
    cam = ctx.camera
    gx, gy = np.meshgrid(np.arange(0, cam.width, step) + step / 2 - 0.5, np.arange(0, cam.height, step) + step / 2 - 0.5)
    vx, vy = image_velocity_px_s(cam, np.asarray(omega_deg) * DEG_TO_RAD, gx, gy)
    return gx, gy, vx, vy


def run(quick: bool, plots_dir: Path | None, seed: int) -> list[Row]:
    start = time.perf_counter()
    pv = paper_values("fu2022")
    cfg, ctx, params = _setup()
    n = 30 if quick else 500
    sig0 = float(cfg.noise.centroid_sigma_px)
    workers = 1 if quick else 2
    line_delays = LINE_DELAYS_US_QUICK if quick else LINE_DELAYS_US
    conds = _conditions(n, sig0, seed, line_delays)
    keys = list(conds)
    results = dict(zip(keys, _run_all([conds[k] for k in keys], workers)))
    elapsed = time.perf_counter() - start

    row = _row_maker(pv, seed, n)
    rows = _fig9_10_rows(row, results, params, sig0) + _fig11_12_14_rows(row, results, sig0, n)
    # Line-delay sweep: which line delay would the paper's bounds need?
    sweep = line_delay_sweep(results, line_delays)
    rows += _sweep_rows(row, sweep, line_delays, pv, n, seed)
    # Figs 6-7
    gx, gy, vx, vy = velocity_field(ctx, (0, 0, 1), step=8)
    rows.append(row("fig7_max_velocity_wz1", "wz = 1 deg/s, Table 1 detector", np.hypot(vx, vy).max(), unit="px/s",
                    trials=None, note="exact field of our camera model; = r_max * wz for a rotation about the boresight"))
    redraws = sum(r["redraws"] for r in results.values())
    total = sum(c[3] for c in conds.values())
    rows.append(Row("run_time", f"{total} trials in {len(conds)} conditions, {workers} process(es); "
                    f"{redraws} pointings with < 3 stars redrawn", None, elapsed, "s", "", total, seed))
    if plots_dir is not None:
        _plots(Path(plots_dir), ctx, results, RATES, FIELD_RATES, SIGMAS)
        _plot_sweep(Path(plots_dir), sweep, line_delays, pv)
    return rows


def _conditions(n: int, sig0: float, seed: int, line_delays) -> dict[str, tuple]:
    """Every Monte Carlo condition of the run by key: the arguments of :func:`run_condition`."""
    conds: dict[str, tuple] = {}

    def add(key, omega, sigma, overrides=None, trials=n, line_delay_us=None):
        conds[key] = (len(conds), tuple(omega), float(sigma), trials, seed, overrides or {}, line_delay_us)

    add("fig9_clean", (1, 1, 0), 0.0)
    add("fig9_noisy", (1, 1, 0), sig0)
    add("fig9_paper_linear", (1, 1, 0), 0.0, {"model": "linear", "reference": "frame_start"})
    for r in RATES:
        add(f"fig11_x_{r}", (r, 0, 0), sig0)
        add(f"fig11_y_{r}", (0, r, 0), sig0)
    for s in SIGMAS:
        add(f"fig12_{s}", (3, 0, 0), s)
    add("fig12_spread", (3, 0, 0), 0.05, {"selection": "spread"})
    add("fig12_all", (3, 0, 0), 0.05, {"n_stars": "all"})
    for r in FIELD_RATES:
        for kind, om in (("x", (r, 0, 0)), ("y", (0, r, 0)), ("xy", (r, r, 0))):
            if kind in ("x", "y") and f"fig11_{kind}_{r}" in conds:
                continue  # same condition as Fig 11: reuse those trials
            add(f"fig14_{kind}_{r}", om, sig0)
    for ld in line_delays:
        for key, om, sg, _, _ in SWEEP:
            add(f"ld_{ld}_{key}", om, sg, line_delay_us=ld)
    return conds


def _fig14(results: dict, kind: str, r) -> dict:
    """The trials of a Fig 14 condition (about x or y alone: those of Fig 11)."""
    return results[f"fig11_{kind}_{r}"] if kind in ("x", "y") else results[f"fig14_{kind}_{r}"]


def _row_maker(pv: dict, seed: int, n: int):
    """``row(qid, condition, ours, ...)``: a :class:`Row` of paper quantity ``qid`` (value and source
    from the paper's data file)."""
    def row(qid, condition, ours, unit="deg/s", trials=n, note=""):
        p = pv[qid]
        return Row(quantity=qid, condition=condition, paper=p["value"], ours=None if ours is None else float(ours),
                   unit=unit, source=p["source"], trials=trials, seed=seed, note=note)

    return row


def _fig9_10_rows(row, results: dict, params: dict, sig0: float) -> list[Row]:
    """Figs 9-10: rate error at wx = wy = 1 deg/s (clean, noisy, eqs as printed) and PSO generations."""
    base = f"pso-rate {params}; line delay 20 us (assumed); Mv <= 5.2"
    e = _norm(results["fig9_clean"])
    rows = [row("fig9_rate_error_max", "wx = wy = 1 deg/s, sigma 0", e.max(),
                note=f"median {np.median(e):.2g}, 95th pct {np.percentile(e, 95):.2g} deg/s; {base}"),
            row("fig9_rate_error_p95", "wx = wy = 1 deg/s, sigma 0", np.percentile(e, 95))]
    e = _norm(results["fig9_noisy"])
    rows.append(row("fig9_rate_error_median_noisy", f"wx = wy = 1 deg/s, sigma {sig0} px", np.median(e),
                    note=f"95th pct {np.percentile(e, 95):.2g}, max {e.max():.2g} deg/s"))
    e = _norm(results["fig9_paper_linear"])
    rows.append(row("fig9_rate_error_median_linear", "wx = wy = 1 deg/s, sigma 0, eqs 11-14 as printed (linear, t_ref = t0)",
                    np.median(e), note="the uniform-velocity pixel shift of eq 8 over T/2 + row delay biases the angles"))
    it = results["fig9_clean"]["iters"]
    rows.append(row("fig10_iterations_fraction_below_10", "wx = wy = 1 deg/s, sigma 0", np.mean(it < 10), unit="fraction",
                    note=f"median {np.median(it):.0f}; convergence = last generation moving the global best > "
                    f"{params.get('tolerance_deg_s', 1e-3)} deg/s"))
    rows.append(row("fig10_iterations_max", "wx = wy = 1 deg/s, sigma 0", it.max(), unit="generations"))
    return rows


def _fig11_12_14_rows(row, results: dict, sig0: float, n: int) -> list[Row]:
    """Figs 11, 12 and 14: rate error against the rate, the centroid noise and the motion (field test)."""
    rows = []
    for axis in ("x", "y"):
        errs = {r: _norm(results[f"fig11_{axis}_{r}"]) for r in RATES}
        rows.append(row(f"fig11_max_error_{axis}", f"about {axis}, 0.5-5 deg/s, sigma {sig0} px",
                        max(v.max() for v in errs.values()), trials=n * len(RATES),
                        note="per-rate max: " + ", ".join(f"{r}: {v.max():.2g}" for r, v in errs.items())))
        rows.append(row(f"fig11_q3_error_{axis}", f"about {axis}, 0.5-5 deg/s, sigma {sig0} px, worst rate",
                        max(np.percentile(v, 75) for v in errs.values()), trials=n * len(RATES),
                        note="per-rate Q3: " + ", ".join(f"{r}: {np.percentile(v, 75):.2g}" for r, v in errs.items())))
    for s in SIGMAS:
        e = _norm(results[f"fig12_{s}"])
        rows.append(row("fig12_q3_error", f"wx = 3 deg/s, sigma {s} px", np.percentile(e, 75),
                        note=f"median {np.median(e):.2g}, max {e.max():.2g}"))
    for variant, label in (("spread", "selection=spread"), ("all", "n_stars=all")):
        e = _norm(results[f"fig12_{variant}"])
        rows.append(row("fig12_q3_error", f"wx = 3 deg/s, sigma 0.05 px, {label}", np.percentile(e, 75),
                        note=f"median {np.median(e):.2g}, max {e.max():.2g}"))
    # Fig 14 (field test, reproduced in simulation)
    for kind in ("x", "y", "xy"):
        rm = {r: float(np.sqrt(np.mean(_fig14(results, kind, r)["err"] ** 2, axis=0)).max()) for r in FIELD_RATES}
        rows.append(row(f"fig14_rmse_{kind}", f"{kind} motion, 0.5-5 deg/s, sigma {sig0} px, worst axis and rate (eq 19)",
                        max(rm.values()), trials=n * len(FIELD_RATES),
                        note="per-rate RMSE: " + ", ".join(f"{r}: {v:.2g}" for r, v in rm.items())))
    return rows


def _sweep_rows(row, sweep: dict, line_delays, pv: dict, n: int, seed: int) -> list[Row]:
    """Per sweep quantity: ours at every line delay, then the line delay at which ours meets the paper."""
    rows = []
    for key, om, sg, qid, stat in SWEEP:
        cond = f"{_sweep_condition(om, sg)}, {stat} error"
        for ld in line_delays:
            rows.append(row(qid, f"{cond}, line delay {ld:g} us (readout {ld * 1280e-3:.1f} ms)", sweep[key][ld], trials=n))
        implied = implied_line_delay_us(line_delays, [sweep[key][ld] for ld in line_delays], pv[qid]["value"])
        rows.append(Row("implied_line_delay", f"{cond}: line delay at which ours meets the paper's {pv[qid]['value']} deg/s",
                        None, implied, "us", "ours (log-log interpolation of the sweep; nan: not reached within "
                        f"{line_delays[0]:g}-{line_delays[-1]:g} us)", n * len(line_delays), seed,
                        f"readout {implied * 1280e-3:.0f} ms for the 1280 rows" if np.isfinite(implied) else
                        f"1 / line delay extrapolation from {line_delays[-1]:g} us: "
                        f"{line_delays[-1] * sweep[key][line_delays[-1]] / pv[qid]['value']:.0f} us"))
    return rows


def _sweep_condition(om, sg) -> str:
    axes = " = ".join(f"w{a}" for a, v in zip("xyz", om) if v)
    return f"{axes} = {max(om):g} deg/s, sigma {sg:g} px"


def _statistic(err: np.ndarray, stat: str) -> float:
    return float({"median": np.median, "max": np.max, "q3": lambda e: np.percentile(e, 75)}[stat](err))


def line_delay_sweep(results: dict, line_delays) -> dict:
    """``{sweep key: {line delay us: statistic of |rate error| (deg/s)}}``."""
    return {key: {ld: _statistic(_norm(results[f"ld_{ld}_{key}"]), stat) for ld in line_delays}
            for key, _, _, _, stat in SWEEP}


def implied_line_delay_us(line_delays, errors, bound) -> float:
    """Line delay (us) at which ``errors`` (at ``line_delays``) first fall to ``bound``: linear
    interpolation in log-log between the bracketing sweep points; nan when the sweep never gets
    there (or the bound is not numeric). The noise-limited error falls as 1 / line delay (the rate
    is observed through the row-time differences), so log-log interpolation is the natural one."""
    if not isinstance(bound, (int, float)):
        return float("nan")
    ld = np.log(np.asarray(line_delays, dtype=float))
    e = np.log(np.maximum(np.asarray(errors, dtype=float), 1e-300))
    b = np.log(bound)
    if e[0] <= b:
        return float(line_delays[0])
    for k in range(1, ld.size):
        if e[k] <= b:
            f = (b - e[k - 1]) / (e[k] - e[k - 1])
            return float(np.exp(ld[k - 1] + f * (ld[k] - ld[k - 1])))
    return float("nan")


def _plot_sweep(out: Path, sweep: dict, line_delays, pv) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for k, (key, om, sg, qid, stat) in enumerate(SWEEP):
        c = f"C{k}"
        ax.plot(line_delays, [sweep[key][ld] for ld in line_delays], "o-", color=c,
                label=f"{_sweep_condition(om, sg)}: {stat}")
        ax.axhline(pv[qid]["value"], color=c, ls=":", lw=1)
    ld = np.asarray(line_delays, dtype=float)
    ax.plot(ld, sweep["fig12_0.01"][line_delays[0]] * ld[0] / ld, "k--", lw=0.8, label="1 / line delay")
    ax.axvline(78.125, color="grey", lw=0.8)
    ax.text(82, 0.05, "readout = exposure = 100 ms", rotation=90, fontsize=7, color="grey", transform=ax.get_xaxis_transform())
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("line delay (us per row)")
    ax.set_ylabel("|rate error| (deg/s)")
    ax.set_title("fu2022: rate error vs the unstated line delay (dotted: paper bounds)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "fu2022_line_delay.png", dpi=90)
    plt.close(fig)


def _pyplot():
    """matplotlib's pyplot on the Agg backend, imported only when plots are asked for."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _plots(out: Path, ctx, results, rates, field_rates, sigmas) -> None:
    out.mkdir(parents=True, exist_ok=True)
    _plot_velocity(out, ctx)
    _plot_errors(out, results, rates, field_rates, sigmas)


def _plot_velocity(out: Path, ctx) -> None:
    """Figs 6-7: image velocity fields of the Table 1 detector."""
    plt = _pyplot()
    # Fig 6: velocity fields for wx in (1, 5, 10), wz in (0, 0.05, 0.1) deg/s
    fig, axes = plt.subplots(3, 3, figsize=(12, 8), sharex=True, sharey=True)
    for i, wz in enumerate((0.0, 0.05, 0.1)):
        for j, wx in enumerate((1.0, 5.0, 10.0)):
            gx, gy, vx, vy = velocity_field(ctx, (wx, 0, wz))
            ax = axes[i, j]
            ax.quiver(gx, gy, vx, vy, angles="xy")
            ax.set_title(f"wx={wx:g}, wz={wz:g} deg/s", fontsize=9)
            ax.invert_yaxis()
    fig.suptitle("fu2022 Fig 6 (ours): image velocity field, Table 1 detector")
    fig.savefig(out / "fu2022_fig6.png", dpi=80)
    plt.close(fig)
    # Fig 7: wz = 1 deg/s direction and magnitude
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4))
    gx, gy, vx, vy = velocity_field(ctx, (0, 0, 1))
    a.quiver(gx, gy, vx, vy, angles="xy")
    a.invert_yaxis()
    a.set_title("direction, wz = 1 deg/s")
    gx, gy, vx, vy = velocity_field(ctx, (0, 0, 1), step=16)
    im = b.pcolormesh(gx, gy, np.hypot(vx, vy), shading="auto")
    b.invert_yaxis()
    fig.colorbar(im, ax=b, label="px/s")
    b.set_title("magnitude, wz = 1 deg/s")
    fig.savefig(out / "fu2022_fig7.png", dpi=80)
    plt.close(fig)


def _plot_errors(out: Path, results, rates, field_rates, sigmas) -> None:
    """Figs 9-12 and 14: the rate errors of the Monte Carlo conditions."""
    plt = _pyplot()
    # Fig 9 / 10
    r = results["fig9_clean"]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    a.plot(np.abs(r["err"][:, 0]), ".", label="|err wx|")
    a.plot(np.abs(r["err"][:, 1]), ".", label="|err wy|")
    a.axhline(0.002, color="r", ls="--", label="paper bound 0.002")
    a.set_yscale("log")
    a.set_xlabel("trial")
    a.set_ylabel("deg/s")
    a.legend()
    a.set_title("Fig 9 (ours): wx = wy = 1 deg/s, sigma 0")
    b.hist(r["iters"], bins=np.arange(0, 52, 2))
    b.set_xlabel("convergence generation")
    b.set_title("Fig 10 (ours)")
    fig.savefig(out / "fu2022_fig9_10.png", dpi=80)
    plt.close(fig)
    # Fig 11
    fig, axes = plt.subplots(1, 2, figsize=(12, 4), sharey=True)
    for ax, axis in zip(axes, ("x", "y")):
        ax.boxplot([_norm(results[f"fig11_{axis}_{r}"]) for r in rates], tick_labels=[str(r) for r in rates])
        ax.axhline(0.1, color="r", ls="--")
        ax.set_yscale("log")
        ax.set_xlabel(f"w{axis} (deg/s)")
        ax.set_title(f"Fig 11{'ab'[axis == 'y']} (ours): rotation about {axis}")
    axes[0].set_ylabel("|error| (deg/s)")
    fig.savefig(out / "fu2022_fig11.png", dpi=80)
    plt.close(fig)
    # Fig 12
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.boxplot([_norm(results[f"fig12_{s}"]) for s in sigmas], tick_labels=[str(s) for s in sigmas])
    ax.axhline(0.01, color="r", ls="--")
    ax.set_yscale("log")
    ax.set_xlabel("centroid noise sigma (px)")
    ax.set_ylabel("|error| (deg/s)")
    ax.set_title("Fig 12 (ours): wx = 3 deg/s")
    fig.savefig(out / "fu2022_fig12.png", dpi=80)
    plt.close(fig)
    # Fig 14
    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    panels = (("x", 0, "wx, wy = 0"), ("y", 1, "wy, wx = 0"), ("xy", 0, "wx, wx = wy"), ("xy", 1, "wy, wx = wy"))
    for ax, (kind, comp, title) in zip(axes.ravel(), panels):
        rmse = [np.sqrt(np.mean(_fig14(results, kind, r)["err"][:, comp] ** 2)) for r in field_rates]
        ax.plot(field_rates, rmse, "o-")
        ax.axhline(0.02, color="r", ls="--")
        ax.set_yscale("log")
        ax.set_title(f"Fig 14 (ours, simulated): {title}", fontsize=9)
        ax.set_xlabel("rate (deg/s)")
        ax.set_ylabel("RMSE (deg/s)")
    fig.tight_layout()
    fig.savefig(out / "fu2022_fig14.png", dpi=80)
    plt.close(fig)
