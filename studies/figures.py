"""Figures of the foundation: measured on every run, written to docs/foundation.md with plots.

    rollingstar figures foundation [--quick] [--json] [--out docs]

1. Static he2021b sensor: attitude error per axis next to the Cramér–Rao bound of the geometry.
2. Rolling shutter visible and exact: star-pair distance error of the baseline (no correction)
   versus rate about camera x, rolling vs global shutter, against the first-order prediction
   v * dy * line_delay; the row time of every simulated star equals t0 + round(y * line_delay).
3. Image level, he2021a sensor: `cog` centroid error at rest; rendered smear length at 1 deg/s
   against omega * exposure * focal / pixel.
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from rollingstar.config import CONFIGS
from rollingstar.logs.reader import LogReader
from rollingstar.logs.topics import TOPIC_TRUTH_STARS
from rollingstar.outputs import write_text
from rollingstar.pipelines.config import PipelineConfig, load_pipeline
from rollingstar.pipelines.evaluate import evaluate_log
from rollingstar.pipelines.runner import run_pipeline
from rollingstar.pipelines.simulate import build_simulator, simulate_to_log
from rollingstar.sensors.scenario import ScenarioConfig, load_scenario
from rollingstar.studies.real_data import real_data_markdown, run_real_data, write_real_data_docs

SCENARIOS = CONFIGS / "scenarios"
BASELINE = CONFIGS / "pipelines" / "baseline.yaml"


def _with(cfg: ScenarioConfig, **changes) -> ScenarioConfig:
    """A copy of ``cfg`` with nested fields replaced, e.g. ``motion__rate_deg_s=(1, 0, 0)``."""
    data = cfg.model_dump()
    for key, value in changes.items():
        node = data
        *parents, leaf = key.split("__")
        for p in parents:
            node = node[p]
        node[leaf] = value
    return ScenarioConfig.model_validate(data)


def _simulate_run_evaluate(cfg: ScenarioConfig, pipeline: PipelineConfig, tmp: Path, tag: str) -> tuple[dict, Path]:
    rec, out = tmp / f"{tag}.mcap", tmp / f"{tag}.out.mcap"
    simulate_to_log(cfg, rec, show_progress=False)
    run_pipeline(rec, pipeline, out, show_progress=False)
    return evaluate_log(out), rec


def static_vs_crb(frames: int, seed: int, tmp: Path) -> dict:
    cfg = _with(load_scenario(SCENARIOS / "he2021b.yaml"), motion__rate_deg_s=(0.0, 0.0, 0.0), frames=frames, seed=seed)
    m, _ = _simulate_run_evaluate(cfg, load_pipeline(BASELINE), tmp, "static")
    a, crb = m["attitude_error_arcsec"], m["attitude_crb_arcsec"]
    return {
        "frames": frames, "seed": seed, "stars_per_frame": m["identified_stars_per_frame"],
        "rmse_arcsec": [a["x_rmse"], a["y_rmse"], a["z_rmse"]],
        "crb_arcsec": [crb["x"], crb["y"], crb["z"]],
        "efficiency": [a[f"{k}_rmse"] / crb[k] for k in "xyz"],
    }


def _predicted_pair_rms(rec: Path, cfg: ScenarioConfig) -> float:
    """First-order prediction of the uncorrected pair error: v_y * (y_i - y_j) * line_delay."""
    rate = np.radians(cfg.motion.rate_deg_s[0])
    v = rate * cfg.sensor.focal_length_mm / (cfg.sensor.pixel_size_um * 1e-3)  # px/s along y at the centre
    ld = cfg.shutter.line_delay_us * 1e-6 if cfg.shutter.mode == "rolling" else 0.0
    diffs = []
    for stars in LogReader(rec).stars(TOPIC_TRUTH_STARS).values():
        y = stars["y"]
        i, j = np.triu_indices(len(y), k=1)
        dy = y[i] - y[j]
        diffs.append(np.abs(dy) * v * ld * np.abs(dy) / np.maximum(np.abs(dy), 1e-12))
    # the pair distance changes by the projection of the relative shift onto the pair direction;
    # we report the simpler bound |v dy ld| (shift along y) as the seeds do.
    return float(np.sqrt(np.mean(np.concatenate(diffs) ** 2))) if diffs else float("nan")


SWEEP_GATE_PX = 25.0  # at 3 deg/s stars move 11 px between t = 0 (the prior) and frame 0's mid-time


def rolling_sweep(rates: list[float], frames: int, seed: int, tmp: Path) -> dict:
    base = load_scenario(SCENARIOS / "he2021b.yaml")
    baseline = load_pipeline(BASELINE)
    stages = [s.model_copy(update={"params": {**s.params, "gate_px": SWEEP_GATE_PX}}) if s.kind == "tracking" else s
              for s in baseline.stages]
    pipeline = baseline.model_copy(update={"stages": stages})
    rows = []
    row_time_max_err = 0
    for rate in rates:
        row = {"rate_deg_s": rate}
        for mode in ("rolling", "global"):
            cfg = _with(base, motion__rate_deg_s=(rate, 0.0, 0.0), shutter__mode=mode, frames=frames, seed=seed)
            m, rec = _simulate_run_evaluate(cfg, pipeline, tmp, f"sweep_{mode}_{rate}")
            row[mode] = {
                "pair_rmse_px": m["star_pair_distance_error_px"]["rmse"],
                "pair_max_px": m["star_pair_distance_error_px"]["max"],
                "attitude_rmse_arcsec": [m["attitude_error_arcsec"][f"{k}_rmse"] for k in "xyz"],
            }
            if mode == "rolling":
                row["rolling"]["predicted_shift_rms_px"] = _predicted_pair_rms(rec, cfg)
                row_time_max_err = max(row_time_max_err, _row_time_error_ns(rec, cfg))
        rows.append(row)
    rolling = np.array([r["rolling"]["pair_rmse_px"] for r in rows])
    r = np.asarray(rates)
    slope = float(np.polyfit(r, rolling, 1)[0]) if len(r) > 1 else float("nan")
    return {"frames": frames, "seed": seed, "rows": rows, "rolling_slope_px_per_deg_s": slope,
            "row_time_max_error_ns": int(row_time_max_err)}


def _row_time_error_ns(rec: Path, cfg: ScenarioConfig) -> int:
    ld_ns = round(cfg.shutter.line_delay_us * 1000)
    worst = 0
    for s in LogReader(rec).stars(TOPIC_TRUTH_STARS).values():
        expected = s["t0_ns"] + np.rint(s["y"] * ld_ns).astype(np.int64)
        worst = max(worst, int(np.max(np.abs(s["row_time_ns"] - expected), initial=0)))
    return worst


def image_level(frames: int, seed: int, tmp: Path) -> dict:
    base = load_scenario(SCENARIOS / "he2021a.yaml")
    static = _with(base, motion__rate_deg_s=(0.0, 0.0, 0.0), frames=frames, seed=seed)
    m, _ = _simulate_run_evaluate(static, load_pipeline(BASELINE), tmp, "image_static")
    smear = smear_length(_with(base, motion__rate_deg_s=(1.0, 0.0, 0.0), seed=seed))
    return {"frames": frames, "seed": seed, "cog_centroid_rmse_px": m["centroid_error_px"]["rmse"],
            "cog_centroid_max_px": m["centroid_error_px"]["max"],
            "identified_stars_per_frame": m["identified_stars_per_frame"],
            "attitude_rmse_arcsec": [m["attitude_error_arcsec"][f"{k}_rmse"] for k in "xyz"], "smear": smear}


def smear_length(cfg: ScenarioConfig) -> dict:
    """Rendered streak length of isolated stars from the noiseless image, second-moment method.

    A uniform streak of length L convolved with a Gaussian PSF (sigma) and integrated over square
    pixels has variance ``L^2 / 12 + sigma^2 + 1 / 12`` along the motion (the last term is the
    pixel's own box), so ``L = sqrt(12 (var - sigma^2 - 1/12))``.
    """
    sim = build_simulator(cfg)
    frame = sim.frame(0)
    img = sim.star_electrons(0)
    sigma = cfg.image.psf_sigma_px
    omega = np.radians(np.linalg.norm(cfg.motion.rate_deg_s))
    expected = omega * cfg.shutter.exposure_ms * 1e-3 * cfg.sensor.focal_length_mm / (cfg.sensor.pixel_size_um * 1e-3)
    half = int(np.ceil(expected / 2 + 6 * sigma))
    lengths = []
    xs, ys = frame.truth.x, frame.truth.y
    for i in range(len(xs)):  # a handful of stars per frame: measurement code, not a hot path
        others = np.hypot(xs - xs[i], ys - ys[i])
        others[i] = np.inf
        r0, c0 = int(round(ys[i])), int(round(xs[i]))
        if others.min() < 4 * half or not (half <= r0 < img.shape[0] - half and half <= c0 < img.shape[1] - half):
            continue
        patch = img[r0 - half:r0 + half + 1, c0 - half:c0 + half + 1]
        rows = np.arange(-half, half + 1, dtype=float)
        profile = patch.sum(axis=1)
        mean = (profile * rows).sum() / profile.sum()
        var = (profile * (rows - mean) ** 2).sum() / profile.sum()
        lengths.append(np.sqrt(12 * max(var - sigma**2 - 1.0 / 12.0, 0.0)))
    ld = cfg.shutter.line_delay_us * 1e-6
    v = expected / (cfg.shutter.exposure_ms * 1e-3)
    measured = float(np.median(lengths)) if lengths else float("nan")
    return {"rate_deg_s": float(np.degrees(omega)), "expected_px": float(expected), "measured_px": measured,
            "relative_error": measured / expected - 1.0, "stars_measured": len(lengths),
            "rolling_stretch_factor": 1.0 / (1.0 - v * ld)}


def run_foundation(quick: bool = False, seed: int = 1) -> dict:
    frames_static = 30 if quick else 300
    frames_sweep = 10 if quick else 50
    frames_image = 5 if quick else 30
    rates = [0.0, 1.0, 3.0] if quick else [0.0, 0.25, 0.5, 1.0, 2.0, 3.0]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        return {
            "quick": quick,
            "static_vs_crb": static_vs_crb(frames_static, seed, tmp),
            "rolling_shutter": rolling_sweep(rates, frames_sweep, seed, tmp),
            "image_level": image_level(frames_image, seed, tmp),
        }


def plot_foundation(result: dict, out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    s = result["static_vs_crb"]
    fig, ax = plt.subplots(figsize=(5, 3.2))
    idx = np.arange(3)
    ax.bar(idx - 0.18, s["rmse_arcsec"], 0.36, label="baseline RMSE")
    ax.bar(idx + 0.18, s["crb_arcsec"], 0.36, label="Cramér–Rao bound")
    ax.set_xticks(idx, ["x", "y", "z (boresight)"])
    ax.set_yscale("log")
    ax.set_ylabel("attitude error [arcsec]")
    ax.set_title(f"static he2021b sensor, {s['frames']} frames")
    ax.legend()
    fig.tight_layout()
    paths.append(out_dir / "foundation_static_crb.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    rs = result["rolling_shutter"]
    rates = [r["rate_deg_s"] for r in rs["rows"]]
    fig, ax = plt.subplots(figsize=(5, 3.2))
    ax.plot(rates, [r["rolling"]["pair_rmse_px"] for r in rs["rows"]], "o-", label="rolling shutter, no correction")
    ax.plot(rates, [r["global"]["pair_rmse_px"] for r in rs["rows"]], "s-", label="global shutter")
    ax.plot(rates, [r["rolling"]["predicted_shift_rms_px"] for r in rs["rows"]], "k--", label="first order |v Δy Δt| (RMS)")
    ax.set_xlabel("rate about camera x [deg/s]")
    ax.set_ylabel("star-pair distance error RMS [px]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out_dir / "foundation_pair_distance.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)
    return paths


def foundation_markdown(result: dict, command: str) -> str:
    s, rs, im = result["static_vs_crb"], result["rolling_shutter"], result["image_level"]
    f = lambda v, d=3: "n/a" if v is None else f"{v:.{d}f}"  # noqa: E731
    lines = [
        "# Foundation figures",
        "",
        f"Measured by `{command}` (seed {s['seed']}); every number below comes from that run.",
        "Plots: `docs/img/foundation_*.png`.",
        "",
        "## 1. Static attitude error against the Cramér–Rao bound",
        "",
        f"he2021b Table 1 sensor, omega = 0, centroid level, 0.05 px centroid noise, real Hipparcos stars "
        f"(Hp <= 6; pairs imaged closer than 8 px removed, they blend), {s['frames']} frames, {f(s['stars_per_frame'], 1)} identified stars per frame; "
        "baseline pipeline (tracking, none, QUEST). The bound is the inverse Fisher information of the "
        "pixel measurements of each frame's stars, averaged over frames (`pipelines/truth.py`).",
        "",
        "| axis | RMSE [arcsec] | Cramér–Rao bound [arcsec] | RMSE / bound |",
        "|---|---|---|---|",
    ]
    for k, axis in enumerate(("x", "y", "z (boresight)")):
        lines.append(f"| {axis} | {f(s['rmse_arcsec'][k])} | {f(s['crb_arcsec'][k])} | {f(s['efficiency'][k], 2)} |")
    lines += [
        "",
        "![static](img/foundation_static_crb.png)",
        "",
        "## 2. The rolling shutter is visible and exact",
        "",
        f"Baseline pipeline (no rolling-shutter correction), he2021b sensor (49 us line delay, 50 ms exposure), rate about "
        f"the camera x axis (stars move across rows), {rs['frames']} frames per point, tracking gate {SWEEP_GATE_PX:g} px "
        "(the first frame's stars are 11 px from the t = 0 prior at 3 deg/s). The pair-distance error of the "
        "rolling shutter grows linearly with rate (he2021a section 3, our translation: 'before correction the star-pair distance error is "
        "linear in the angular rate'); with a global shutter it stays at the noise floor.",
        "",
        "| rate [deg/s] | rolling: pair RMSE [px] | rolling: pair max [px] | first-order RMS |v Δy Δt| [px] | global: pair RMSE [px] | rolling: attitude RMSE x/y/z [arcsec] |",
        "|---|---|---|---|---|---|",
    ]
    for r in rs["rows"]:
        a = r["rolling"]["attitude_rmse_arcsec"]
        lines.append(f"| {r['rate_deg_s']:g} | {f(r['rolling']['pair_rmse_px'])} | {f(r['rolling']['pair_max_px'])} | "
                     f"{f(r['rolling']['predicted_shift_rms_px'])} | {f(r['global']['pair_rmse_px'])} | "
                     f"{f(a[0], 2)} / {f(a[1], 2)} / {f(a[2], 2)} |")
    lines += [
        "",
        f"Slope of the rolling-shutter pair error: {f(rs['rolling_slope_px_per_deg_s'])} px per deg/s. "
        "(The first-order column is the RMS shift along y between the two stars' exposure times; the pair "
        "distance only sees its component along the pair direction, hence the measured error is smaller.)",
        "",
        f"Row times in the centroid-level truth: the largest |row_time - (t0 + round(y * line_delay))| over every star of "
        f"every rolling-shutter recording above is **{rs['row_time_max_error_ns']} ns**.",
        "",
        "![pair distance](img/foundation_pair_distance.png)",
        "",
        "## 3. Image level (he2021a sensor)",
        "",
        f"omega = 0, {im['frames']} rendered 1024 x 1024 frames (PSF sigma 1 px, 12-bit, Poisson + read noise), "
        f"{f(im['identified_stars_per_frame'], 1)} identified stars per frame: `cog` centroid error RMS "
        f"**{f(im['cog_centroid_rmse_px'])} px** (max {f(im['cog_centroid_max_px'])} px) against the true positions; "
        f"QUEST attitude RMSE x/y/z {f(im['attitude_rmse_arcsec'][0], 2)} / {f(im['attitude_rmse_arcsec'][1], 2)} / "
        f"{f(im['attitude_rmse_arcsec'][2], 2)} arcsec.",
        "",
        f"Smear at {im['smear']['rate_deg_s']:g} deg/s about x (motion along the columns): expected omega * exposure * "
        f"focal / pixel = {f(im['smear']['expected_px'])} px; rendered (noiseless image, second moment minus PSF, median "
        f"of {im['smear']['stars_measured']} isolated stars) {f(im['smear']['measured_px'])} px: "
        f"**{100 * im['smear']['relative_error']:+.2f} %**. Motion along the readout direction stretches a streak by "
        f"1 / (1 - v * line_delay) = {im['smear']['rolling_stretch_factor']:.5f} (the rolling shutter's own signature).",
        "",
    ]
    return "\n".join(lines)


def write_foundation_docs(result: dict, docs_dir: Path, command: str) -> Path:
    plot_foundation(result, docs_dir / "img")
    path = docs_dir / "foundation.md"
    write_text(path, foundation_markdown(result, command))
    write_text(docs_dir / "foundation.json", json.dumps(result, indent=2))
    return path


def real_data_figures(out_dir: Path | None, as_json: bool = False, repeats: int = 3) -> dict:
    """``rollingstar figures real-data [--out docs]``: :func:`rollingstar.studies.real_data.run_real_data`,
    written to ``<out>/real-data.md``, ``.json`` and PNGs."""
    command = "rollingstar figures real-data" + (f" --out {out_dir}" if out_dir is not None else "")
    result = run_real_data(repeats=repeats, show_progress=not as_json)
    if out_dir is not None:
        write_real_data_docs(result, Path(out_dir), command)
    if as_json:
        print(json.dumps(result, indent=1, default=str))
    elif out_dir is None:
        print(real_data_markdown(result, command))
    return result
