"""Reproduction of He et al. 2021b (Sensors 21, 5724): REQUEST updates every 1/3/5 stars of a
rolling-shutter frame (Table 3, Figs 8-13) and the Star1000 case (Table 4, Figs 15-18).

Set-up (our choices where the paper is silent, stated in ``docs/reproductions/he2021b.md``):

- Table 1 sensor, 15 stars starting at the Table 2 positions read as *pixels* (scenario
  ``configs/scenarios/he2021b_table2.yaml``), rotation 0.05 deg/s about the camera x axis,
  300 frames (10 Hz), centroid-level simulation with 0.05 px Gaussian centroid noise per axis.
- Pipeline: tracking identifier + ``request`` (``estimators/attitude/request.py``) with the true
  rate (``rate_source: truth``), ``forgetting`` 1 (the paper's eqs 30-31) unless stated. The
  stages are driven in-process exactly as ``pipelines.runner`` drives them (no MCAP I/O); the
  attitude error is evaluated as ``pipelines.evaluate`` does, at each estimate's own ``t_ns``.
- Monte Carlo: ``trials`` noise realisations, scenario seeds ``seed, seed + 1, ...``; RMSE pooled
  over every valid update of every trial.
- Fig 12 "global exposure": the same scenario with a global shutter, QUEST once per frame.
- Star1000 (Table 4): its sensor, 8 synthetic stars evenly spread over the rows (the experiment's
  star simulator field is not given), 0.1 deg/s, 30 frames = 6 s at 5 Hz.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from estimators.attitude.quest import QuestSolver
from estimators.attitude.request import RequestSolver
from estimators.data import FrameData, StarTable, TruthSamples
from estimators.identifiers.tracking import TrackingIdentifier
from pipelines import build
from pipelines.config import load_scenario
from pipelines.reproduce import Row, paper_values
from pipelines.simulate import build_simulator, truth_sample_times
from pipelines.truth import attitude_crb_rad2
from sensors.conventions import RAD_TO_ARCSEC, attitude_error_body_arcsec

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs" / "scenarios"
AXES = ("x", "y", "z")
GROUPS = (1, 3, 5)
STAR1000_GROUPS = (4, 2, 1)
# 8 synthetic Star1000 stars, one per 128-row band, columns spread over the detector (our choice).
STAR1000_POSITIONS = [(180.0, 60.0), (820.0, 190.0), (430.0, 320.0), (690.0, 450.0),
                      (120.0, 580.0), (900.0, 700.0), (350.0, 830.0), (610.0, 960.0)]


@dataclass
class Runs:
    """Errors (arcsec, (N, 3)) and times of the valid updates of one configuration over trials."""

    err: list
    t_ns: list
    n_updates: list
    n_invalid: list
    frames: int
    period_s: float

    def rmse(self) -> np.ndarray:
        e = np.concatenate(self.err)
        return np.sqrt(np.mean(e**2, axis=0))

    def rmse_per_trial(self) -> np.ndarray:
        return np.array([np.sqrt(np.mean(e**2, axis=0)) for e in self.err])

    def max_abs(self) -> np.ndarray:
        return np.max(np.abs(np.concatenate(self.err)), axis=0)

    def updates_per_frame(self) -> float:
        return float(np.mean(self.n_updates)) / self.frames

    def rate_hz(self) -> float:
        return float(np.mean(self.n_updates)) / (self.frames * self.period_s)


def table2_scenario(rate_deg_s: float, frames: int, seed: int, sigma_px: float = 0.05, mode: str = "rolling"):
    cfg = load_scenario(CONFIG_DIR / "he2021b_table2.yaml")
    return cfg.model_copy(update={
        "frames": frames, "seed": seed,
        "motion": cfg.motion.model_copy(update={"rate_deg_s": (rate_deg_s, 0.0, 0.0)}),
        "noise": cfg.noise.model_copy(update={"centroid_sigma_px": sigma_px}),
        "shutter": cfg.shutter.model_copy(update={"mode": mode}),
    })


def star1000_scenario(frames: int, seed: int, sigma_px: float = 0.05):
    cfg = load_scenario(CONFIG_DIR / "star1000.yaml")
    return cfg.model_copy(update={
        "frames": frames, "seed": seed,
        "catalog": cfg.catalog.model_copy(update={"source": "synthetic", "positions_px": STAR1000_POSITIONS, "magnitude": 4.0}),
        "noise": cfg.noise.model_copy(update={"centroid_sigma_px": sigma_px}),
    })


def simulate(cfg):
    """Input frames (centroid tables, truth samples as the runner would pass them) and the truth motion."""
    sim = build_simulator(cfg)
    context = build.build_context(cfg)
    period = int(sim.timing.frame_period_ns)
    frames, crb = [], []
    for f in sim.frames(cfg.frames):
        c = f.centroids
        stars = StarTable.build(c["x"], c["y"], c["t_ns"], c["row_time_ns"], flux=c["flux"],
                                sigma_px=np.full(len(c["x"]), cfg.noise.centroid_sigma_px))
        times = truth_sample_times(f.t0_ns, period, cfg.truth_rate_hz)
        truth = TruthSamples(times, sim.motion.attitude(times).as_quat(), sim.motion.angular_velocity(times))
        frames.append(FrameData(index=f.index, t0_ns=f.t0_ns, stars=stars, truth=truth))
        if len(f.truth) >= 2 and cfg.noise.centroid_sigma_px > 0:
            w = sim.motion.attitude(f.truth.t_ns).inv().apply(f.truth.unit_icrs)
            crb.append(np.diag(attitude_crb_rad2(context.camera, w, cfg.noise.centroid_sigma_px)))
    crb_arcsec = np.sqrt(np.mean(crb, axis=0)) * RAD_TO_ARCSEC if crb else np.full(3, np.nan)
    return frames, sim.motion, context, period * 1e-9, crb_arcsec


def run_stages(stages, frames, context):
    """Drive the stages as ``pipelines.runner`` does (process in order, then ``update_prior``)."""
    for s in stages:
        s.setup(context)
    out = []
    for frame in frames:
        for s in stages:
            frame = s.process(frame)
        for s in stages:
            upd = getattr(s, "update_prior", None)
            if upd is not None:
                upd(frame)
        out.append(frame)
    return out


def identify(frames, context):
    """Identify every frame once (tracking identifier, prior advanced by a per-frame QUEST, as the
    runner would) and return the identified frames without attitudes, to feed several solvers.

    The matches do not depend on which solver advances the prior here (15 stars, < 1 px motion
    between frames, 10 px gate); this saves re-running the identifier for every configuration."""
    out = run_stages([TrackingIdentifier(gate_px=10.0), QuestSolver()], frames, context)
    return [f.evolve(attitudes=(), flags=()) for f in out]


def attitude_errors(out_frames, motion):
    ests = [a for f in out_frames for a in f.attitudes]
    valid = [a for a in ests if a.valid]
    t = np.array([a.t_ns for a in valid], dtype=np.int64)
    q = np.array([a.q_xyzw for a in valid])
    err = attitude_error_body_arcsec(motion.attitude(t), Rotation.from_quat(q)) if len(valid) else np.zeros((0, 3))
    return err, t, len(valid), len(ests) - len(valid)


def _collect(runs: dict, key, out_frames, motion, frames, period_s):
    err, t, nv, ni = attitude_errors(out_frames, motion)
    r = runs.setdefault(key, Runs([], [], [], [], frames, period_s))
    r.err.append(err)
    r.t_ns.append(t)
    r.n_updates.append(nv)
    r.n_invalid.append(ni)


def request_stages(group, rate_source="truth", forgetting=1.0, **kw):
    return [RequestSolver(group_size=group, rate_source=rate_source, forgetting=forgetting, **kw)]


def measure(quick: bool, seed: int) -> dict:
    """Every measurement of the reproduction (the rows and the plots are made from this)."""
    n_frames = 60 if quick else 300
    trials = 3 if quick else 10
    rates = (0.0, 0.1, 0.2) if quick else (0.0, 0.05, 0.1, 0.15, 0.2)
    rate_trials = 2 if quick else 5
    star_trials = 3 if quick else 10
    res: dict = {"frames": n_frames, "trials": trials, "rate_trials": rate_trials, "star_trials": star_trials,
                 "rates": rates, "seed": seed, "table": {}, "rate": {}, "star": {}, "crb": []}
    start = time.perf_counter()
    cpu_start = time.process_time()
    for i in range(trials):
        frames, motion, ctx, period_s, crb = simulate(table2_scenario(0.05, n_frames, seed + i))
        frames = identify(frames, ctx)
        res["crb"].append(crb)
        for g in GROUPS:
            for rho in (1.0, 0.5):
                out = run_stages(request_stages(g, forgetting=rho), frames, ctx)
                _collect(res["table"], (g, rho), out, motion, n_frames, period_s)
        out = run_stages(request_stages("frame", forgetting=0.0), frames, ctx)
        _collect(res["table"], ("frame", 0.0), out, motion, n_frames, period_s)
        gframes, gmotion, gctx, _, _ = simulate(table2_scenario(0.05, n_frames, seed + i, mode="global"))
        out = run_stages([QuestSolver()], identify(gframes, gctx), gctx)
        _collect(res["table"], ("global", None), out, gmotion, n_frames, period_s)
    for rate in rates:
        for i in range(rate_trials):
            frames, motion, ctx, period_s, _ = simulate(table2_scenario(rate, n_frames, seed + i))
            frames = identify(frames, ctx)
            for g in GROUPS:
                out = run_stages(request_stages(g), frames, ctx)
                _collect(res["rate"], (rate, g, "truth"), out, motion, n_frames, period_s)
            out = run_stages(request_stages(5, rate_source="fixed"), frames, ctx)  # no correction, no propagation
            _collect(res["rate"], (rate, 5, "zero"), out, motion, n_frames, period_s)
    for i in range(star_trials):
        frames, motion, ctx, period_s, _ = simulate(star1000_scenario(30, seed + i))
        frames = identify(frames, ctx)
        for g in STAR1000_GROUPS:
            out = run_stages(request_stages(g), frames, ctx)
            _collect(res["star"], g, out, motion, 30, period_s)
    res["seconds"] = time.perf_counter() - start
    res["cpu_seconds"] = time.process_time() - cpu_start
    res["crb"] = np.sqrt(np.mean(np.square(res["crb"]), axis=0))
    return res


def rows_from(res: dict) -> list[Row]:
    pv = paper_values("he2021b")
    seed, T, F = res["seed"], res["trials"], res["frames"]
    rows: list[Row] = []
    cond = f"0.05 deg/s, {F} frames, 0.05 px, rate truth"
    for g in GROUPS:
        r = res["table"][(g, 1.0)]
        rm, sp = r.rmse(), r.rmse_per_trial().std(axis=0)
        for k, ax in enumerate(AXES):
            rows.append(Row(f"rmse_{ax}_per{g}", cond + ", forgetting 1 (eqs 30-31)", pv["table3_rmse_arcsec"][f"per{g}"][ax],
                            float(rm[k]), "arcsec", pv["table3_rmse_arcsec"]["source"], T, seed,
                            f"trial-to-trial std {sp[k]:.3g}"))
    for g in GROUPS:
        rm = res["table"][(g, 0.5)].rmse()
        for k, ax in enumerate(AXES):
            rows.append(Row(f"rmse_{ax}_per{g}", cond + ", forgetting 0.5", pv["table3_rmse_arcsec"][f"per{g}"][ax],
                            float(rm[k]), "arcsec", pv["table3_rmse_arcsec"]["source"], T, seed, "sensitivity: fading memory"))
    for g in GROUPS:
        r = res["table"][(g, 1.0)]
        rows.append(Row(f"updates_per_frame_per{g}", "15 stars per frame", pv["updates_per_frame"][f"per{g}"],
                        r.updates_per_frame(), "1/frame", pv["updates_per_frame"]["source"], T, seed,
                        f"invalid estimates over all trials: {sum(r.n_invalid)}"
                        + (" (the first update of each run: one star does not fix the attitude)" if g == 1 else "")))
        rows.append(Row(f"update_rate_per{g}", "frame period 100.176 ms", pv["update_rate_hz"][f"per{g}"], r.rate_hz(), "Hz",
                        pv["update_rate_hz"]["source"], T, seed))
    for g in GROUPS:
        mx = res["table"][(g, 1.0)].max_abs()
        for k, ax in enumerate(AXES):
            rows.append(Row(f"max_error_{ax}_per{g}", cond, pv["fig8_10_max_error_arcsec"][f"per{g}"][ax], float(mx[k]),
                            "arcsec", pv["fig8_10_max_error_arcsec"]["source"], T, seed))
    glob, per5, frame = res["table"][("global", None)].rmse(), res["table"][(5, 1.0)].rmse(), res["table"][("frame", 0.0)].rmse()
    for k, ax in enumerate(AXES):
        rows.append(Row(f"global_rmse_{ax}", "global shutter, QUEST once per frame, 15 stars", pv["fig12_global_vs_rolling"]["statement"],
                        float(glob[k]), "arcsec", pv["fig12_global_vs_rolling"]["source"], T, seed,
                        f"ours rolling per-5 {per5[k]:.3g}; rolling once per frame (forgetting 0) {frame[k]:.3g}"))
        rows.append(Row(f"crb_{ax}", "single frame, 15 stars, 0.05 px", None, float(res["crb"][k]), "arcsec", "ours (Cramér-Rao bound)", T, seed))
    r_hi = max(res["rates"])
    xy = max(float(res["rate"][(r_hi, g, "truth")].rmse()[k]) for g in GROUPS for k in (0, 1))
    src = pv["fig11_at_0p2_deg_s"]["source"]
    rt = res["rate_trials"]
    rows.append(Row("rmse_xy_max_over_groups", f"{r_hi} deg/s, rate truth", pv["fig11_at_0p2_deg_s"]["xy_all"], xy, "arcsec", src, rt, seed))
    rows.append(Row("rmse_z_per1", f"{r_hi} deg/s, rate truth", pv["fig11_at_0p2_deg_s"]["z_per1"],
                    float(res["rate"][(r_hi, 1, "truth")].rmse()[2]), "arcsec", src, rt, seed))
    for rate in res["rates"]:
        rows.append(Row("rmse_z_per5", f"{rate} deg/s, rate truth", None, float(res["rate"][(rate, 5, "truth")].rmse()[2]),
                        "arcsec", src, rt, seed))
        rows.append(Row("rmse_z_per5_no_rate", f"{rate} deg/s, zero rate (no correction, no propagation)", None,
                        float(res["rate"][(rate, 5, "zero")].rmse()[2]), "arcsec", src, rt, seed))
    s = pv["star1000"]
    st = res["star_trials"]
    for g in STAR1000_GROUPS:
        r = res["star"][g]
        mx = r.max_abs()
        rows.append(Row(f"star1000_updates_per_frame_per{g}", "8 stars, 0.1 deg/s", s["updates_per_frame"][f"per{g}"],
                        r.updates_per_frame(), "1/frame", s["source"], st, seed))
        rows.append(Row(f"star1000_update_rate_per{g}", "frame period 200.0 ms", s["update_rate_hz"][f"per{g}"], r.rate_hz(), "Hz",
                        s["source"], st, seed))
        rows.append(Row(f"star1000_updates_6s_per{g}", "30 frames", s["total_updates_6s"][f"per{g}"], float(np.mean(r.n_updates)),
                        "updates", s["source"], st, seed, f"invalid per run: {np.mean(r.n_invalid):.3g}"))
        for k, ax in enumerate(AXES[:2]):
            rows.append(Row(f"star1000_max_error_{ax}_per{g}", "8 stars, 0.1 deg/s, 0.05 px", s["max_error_arcsec"][f"per{g}"][ax],
                            float(mx[k]), "arcsec", s["source"], st, seed, f"rmse {r.rmse()[k]:.3g}"))
    rows.append(Row("run time", "quick" if res["frames"] < 300 else "full", None, float(res["cpu_seconds"]), "s (CPU)",
                    "ours", None, seed, f"wall clock {res['seconds']:.1f} s"))
    return rows


def run(quick: bool, plots_dir: Path | None, seed: int) -> list[Row]:
    res = measure(quick, seed)
    rows = rows_from(res)
    if plots_dir is not None:
        plot(res, Path(plots_dir))
    return rows


# ----------------------------------------------------------------------------------- plots
def plot(res: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pv = paper_values("he2021b")
    out.mkdir(parents=True, exist_ok=True)
    # Table 3 bars
    fig, axs = plt.subplots(1, 3, figsize=(12, 3.6))
    for k, ax in enumerate(AXES):
        paper = [pv["table3_rmse_arcsec"][f"per{g}"][ax] for g in GROUPS]
        ours = [res["table"][(g, 1.0)].rmse()[k] for g in GROUPS]
        ours05 = [res["table"][(g, 0.5)].rmse()[k] for g in GROUPS]
        xs = np.arange(3)
        axs[k].bar(xs - 0.27, paper, 0.27, label="paper")
        axs[k].bar(xs, ours05, 0.27, label="ours, forgetting 0.5")
        axs[k].bar(xs + 0.27, ours, 0.27, label="ours, forgetting 1")
        axs[k].set_xticks(xs, [f"per {g}" for g in GROUPS])
        axs[k].set_yscale("log")
        axs[k].set_title(f"{ax.upper()}-axis RMSE (arcsec)")
    axs[0].legend(fontsize=8)
    fig.suptitle("he2021b Table 3: RMSE vs stars per update (0.05 deg/s)")
    fig.tight_layout()
    fig.savefig(out / "he2021b_table3.png", dpi=110)
    plt.close(fig)
    # Figs 8-10: error series of trial 0
    fig, axs = plt.subplots(3, 3, figsize=(12, 8), sharex=True)
    for row, g in enumerate((5, 3, 1)):
        r = res["table"][(g, 1.0)]
        t = (r.t_ns[0] - r.t_ns[0][0]) * 1e-9
        for k, ax in enumerate(AXES):
            axs[row, k].plot(t, r.err[0][:, k], lw=0.5)
            axs[row, k].set_title(f"per {g} star(s), {ax.upper()}", fontsize=9)
    for k in range(3):
        axs[2, k].set_xlabel("time (s)")
    axs[1, 0].set_ylabel("attitude error (arcsec)")
    fig.suptitle("he2021b Figs 8-10: attitude error, 0.05 deg/s, forgetting 1 (trial 0)")
    fig.tight_layout()
    fig.savefig(out / "he2021b_fig8_10.png", dpi=110)
    plt.close(fig)
    # Fig 11: RMSE vs rate
    fig, axs = plt.subplots(1, 3, figsize=(12, 3.6))
    for k, ax in enumerate(AXES):
        for g in GROUPS:
            axs[k].plot(res["rates"], [res["rate"][(r, g, "truth")].rmse()[k] for r in res["rates"]], "o-", label=f"per {g}")
        axs[k].plot(res["rates"], [res["rate"][(r, 5, "zero")].rmse()[k] for r in res["rates"]], "k--", label="per 5, zero rate")
        axs[k].set_xlabel("rate (deg/s)")
        axs[k].set_yscale("log")
        axs[k].set_title(f"{ax.upper()}-axis RMSE (arcsec)")
    axs[0].legend(fontsize=8)
    fig.suptitle("he2021b Fig 11: RMSE vs angular rate")
    fig.tight_layout()
    fig.savefig(out / "he2021b_fig11.png", dpi=110)
    plt.close(fig)
    # Fig 12: global vs rolling per 5
    fig, axs = plt.subplots(1, 3, figsize=(12, 3.6))
    for k, ax in enumerate(AXES):
        for key, lab in (((5, 1.0), "rolling per 5"), (("global", None), "global, QUEST per frame")):
            r = res["table"][key]
            axs[k].plot((r.t_ns[0] - r.t_ns[0][0]) * 1e-9, r.err[0][:, k], lw=0.6, label=lab)
        axs[k].set_title(f"{ax.upper()} (arcsec)")
        axs[k].set_xlabel("time (s)")
    axs[0].legend(fontsize=8)
    fig.suptitle("he2021b Fig 12: global exposure vs rolling shutter per 5 stars (trial 0)")
    fig.tight_layout()
    fig.savefig(out / "he2021b_fig12.png", dpi=110)
    plt.close(fig)
    # Figs 15-17: Star1000 error series; Fig 18 update counts (and Fig 13)
    fig, axs = plt.subplots(3, 3, figsize=(12, 8), sharex=True)
    for row, g in enumerate(STAR1000_GROUPS):
        r = res["star"][g]
        t = (r.t_ns[0] - r.t_ns[0][0]) * 1e-9
        for k, ax in enumerate(AXES):
            axs[row, k].plot(t, r.err[0][:, k], ".-", lw=0.5, ms=2)
            axs[row, k].set_title(f"Star1000 per {g} star(s), {ax.upper()}", fontsize=9)
    for k in range(3):
        axs[2, k].set_xlabel("time (s)")
    fig.suptitle("he2021b Figs 15-17: Star1000, 8 stars, 0.1 deg/s (trial 0)")
    fig.tight_layout()
    fig.savefig(out / "he2021b_fig15_17.png", dpi=110)
    plt.close(fig)
    fig, axs = plt.subplots(1, 2, figsize=(10, 3.6))
    lab = [f"per {g}" for g in GROUPS] + ["global"]
    ours = [res["table"][(g, 1.0)].rate_hz() for g in GROUPS] + [res["table"][("global", None)].rate_hz()]
    paper = [pv["update_rate_hz"][f"per{g}"] for g in GROUPS] + [10]
    xs = np.arange(4)
    axs[0].bar(xs - 0.2, paper, 0.4, label="paper")
    axs[0].bar(xs + 0.2, ours, 0.4, label="ours")
    axs[0].set_xticks(xs, lab)
    axs[0].set_title("Fig 13: update rate (Hz), Table 1 sensor")
    axs[0].legend(fontsize=8)
    lab = [f"per {g}" for g in STAR1000_GROUPS] + ["global"]
    ours = [float(np.mean(res["star"][g].n_updates)) for g in STAR1000_GROUPS] + [30]
    paper = [pv["star1000"]["total_updates_6s"][f"per{g}"] for g in STAR1000_GROUPS] + [30]
    axs[1].bar(xs - 0.2, paper, 0.4, label="paper")
    axs[1].bar(xs + 0.2, ours, 0.4, label="ours")
    axs[1].set_xticks(xs, lab)
    axs[1].set_title("Fig 18: attitude updates within 6 s, Star1000")
    fig.tight_layout()
    fig.savefig(out / "he2021b_fig13_18.png", dpi=110)
    plt.close(fig)
