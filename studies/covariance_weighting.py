"""Does weighting the stars by their 2 x 2 position covariance improve the attitude of smeared frames?

    rollingstar figures covariance-weighting [--quick] [--json] [--out DIR] [--seed N]

Image-level simulation of the he2021a sensor (configs/scenarios/he2021a.yaml: 1024 x 1024, 44.9 ms
exposure, 43.9 us line delay, PSF sigma 1 px) rotating at 3 and 10 deg/s about the camera x axis
(a smear of 10 and 34 px), through the ``ls_rate`` pipeline (configs/pipelines/ls_rate.yaml: cog,
tracking, ls-rate, rate-correction, quest) twice on the same frames:

- *scalar*: ``star_covariance: false`` in ``ls-rate`` and ``quest``, every star weighted by its
  ``sigma_px`` (the isotropic equivalent ``sqrt(trace / 2)`` of its covariance);
- *2 x 2*: ``star_covariance: true``, every star weighted by its 2 x 2 covariance (ls-rate's GLS
  whitening, QUEST refined by Gauss-Newton, estimators/attitude/star_covariance.py).

Attitude error per axis (x, y cross-boresight, z about the boresight; arcsec RMSE, and the median
of the absolute error, over every valid estimate against the truth at its time). ``source`` says where the covariances come from:

- ``centroider``: the ``cog`` centroider's own ``cov_xx, cov_xy, cov_yy`` (noise propagation over
  the spot's pixels); a centroider that fills none leaves both runs identical, and the result says so
  (``stars_with_2x2`` 0);
- ``truth-smear``: each identified star's covariance set from the truth smear model before the rate
  stage: along the star's true image velocity ``v`` the variance of a streak of length
  ``L = |v| t_exposure`` over the PSF, ``psf^2 + L^2 / 12``, across it ``psf^2``, scaled so that
  ``trace / 2 = sigma_px^2`` (the scalar run's weight is unchanged: only the shape differs).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.config import CONFIGS
from rollingstar.estimators.data import FrameData, SensorContext, frame_camera
from rollingstar.estimators.plugin import Plugin
from rollingstar.estimators.rates.pso import image_velocity_px_s
from rollingstar.outputs import write_text
from rollingstar.pipelines.config import PipelineConfig, load_pipeline
from rollingstar.pipelines.runner import build_stages
from rollingstar.pipelines.simulate import build_simulator
from rollingstar.pipelines.stages import StagePipeline
from rollingstar.sensors.conventions import S_PER_NS, attitude_error_body_arcsec
from rollingstar.sensors.scenario import ScenarioConfig, load_scenario

SCENARIO = CONFIGS / "scenarios" / "he2021a.yaml"
PIPELINE = CONFIGS / "pipelines" / "ls_rate.yaml"
RATES_DEG_S = (3.0, 10.0)
WEIGHTED_KINDS = ("ls-rate", "quest")  # the stages whose weighting is switched
SOURCES = ("centroider", "truth-smear")


class TruthSmearCovariance(Plugin):
    """Sets every identified star's 2 x 2 covariance from the truth smear model (module docstring)."""

    role = "filter"
    name = "truth-smear-covariance"

    def __init__(self, omega_rad_s, exposure_s: float, psf_sigma_px: float):
        super().__init__()
        self.omega = np.asarray(omega_rad_s, dtype=float)
        self.exposure_s = float(exposure_s)
        self.psf2 = float(psf_sigma_px) ** 2

    def process(self, frame: FrameData) -> FrameData:
        s = frame.stars
        if s is None or s.n == 0:
            return frame
        vx, vy = image_velocity_px_s(frame_camera(frame, self.context), self.omega, s.x, s.y)
        length2 = (np.hypot(vx, vy) * self.exposure_s) ** 2
        along, across = self.psf2 + length2 / 12.0, np.full(s.n, self.psf2)
        th = np.arctan2(vy, vx)
        c, sn = np.cos(th), np.sin(th)
        scale = np.where(np.isfinite(s.sigma_px), s.sigma_px, np.nan) ** 2 / (0.5 * (along + across))
        xx = scale * (along * c * c + across * sn * sn)
        xy = scale * (along - across) * c * sn
        yy = scale * (along * sn * sn + across * c * c)
        return frame.evolve(stars=s.with_columns(cov_xx=xx, cov_xy=xy, cov_yy=yy))


def scenario(rate_deg_s: float, frames: int, seed: int) -> ScenarioConfig:
    cfg = load_scenario(SCENARIO)
    return cfg.model_copy(update={"frames": frames, "seed": seed,
                                  "motion": cfg.motion.model_copy(update={"rate_deg_s": (rate_deg_s, 0.0, 0.0)})})


def pipeline(star_covariance: bool) -> PipelineConfig:
    """The ls_rate pipeline with the weighting of its rate and attitude stages switched."""
    cfg = load_pipeline(PIPELINE)
    stages = [s.model_copy(update={"params": {**s.params, "star_covariance": star_covariance}})
              if s.kind in WEIGHTED_KINDS else s for s in cfg.stages]
    return cfg.model_copy(update={"stages": stages})


def run_case(cfg: ScenarioConfig, star_covariance: bool, source: str) -> dict:
    """One pipeline run over the simulated frames: attitude errors (n, 3) arcsec and star counts."""
    sim = build_simulator(cfg)
    context = SensorContext.from_scenario(cfg)
    stages = build_stages(pipeline(star_covariance), str(PIPELINE))
    if source == "truth-smear":
        rate = np.radians(np.asarray(cfg.motion.rate_deg_s, dtype=float))
        first_rate = next(i for i, s in enumerate(stages) if s.role == "rate")
        stages.insert(first_rate, TruthSmearCovariance(rate, sim.timing.exposure_ns * S_PER_NS, cfg.image.psf_sigma_px))
    for s in stages:
        s.setup(context)
    run = StagePipeline(stages, holds_centroids=False, context=context)
    ests, n_stars, n_2x2 = [], 0, 0
    for f in sim.frames(cfg.frames):
        for out in run.process(FrameData(index=f.index, t0_ns=f.t0_ns, image=f.image)):
            ests += [a for a in out.attitudes if a.valid]
            if out.stars is not None:
                ident = out.stars.identified
                n_stars += int(ident.sum())
                n_2x2 += int((ident & np.isfinite(out.stars.cov_xy) & (out.stars.cov_xy != 0)).sum())
    t = np.array([a.t_ns for a in ests], dtype=np.int64)
    err = (attitude_error_body_arcsec(sim.motion.attitude(t), Rotation.from_quat([a.q_xyzw for a in ests]))
           if ests else np.zeros((0, 3)))
    return {"err": err, "stars": n_stars, "stars_with_2x2": n_2x2}


def run_covariance_weighting(quick: bool = False, seed: int = 1, sources=SOURCES) -> dict:
    """Per source and rate: attitude RMSE per axis (arcsec), scalar vs 2 x 2 weighting (module docstring)."""
    frames, seeds = (15, 1) if quick else (40, 3)
    out = {"scenario": str(SCENARIO.name), "pipeline": str(PIPELINE.name), "frames_per_run": frames,
           "runs_per_rate": seeds, "seed": seed, "results": []}
    for source in sources:
        for rate in RATES_DEG_S:
            row = {"source": source, "rate_deg_s": rate}
            for key, full in (("scalar", False), ("2x2", True)):
                cases = [run_case(scenario(rate, frames, seed * 100 + k), full, source) for k in range(seeds)]
                err = np.concatenate([c["err"] for c in cases])
                row[key] = {"rmse_arcsec": np.sqrt(np.mean(err**2, axis=0)).tolist(),
                            "median_abs_arcsec": np.median(np.abs(err), axis=0).tolist(), "estimates": int(err.shape[0]),
                            "stars": sum(c["stars"] for c in cases),
                            "stars_with_2x2": sum(c["stars_with_2x2"] for c in cases)}
            out["results"].append(row)
    return out


def covariance_weighting_table(result: dict) -> str:
    lines = [f"attitude RMSE (arcsec), {result['scenario']} image level, {result['pipeline']}, "
             f"{result['runs_per_rate']} x {result['frames_per_run']} frames per rate, seed {result['seed']}",
             "source        rate   weighting  RMSE x   RMSE y   RMSE z  (median |e| x, y, z)  estimates  stars with 2x2"]
    for r in result["results"]:
        for key in ("scalar", "2x2"):
            d = r[key]
            x, y, z = d["rmse_arcsec"]
            mx, my, mz = d["median_abs_arcsec"]
            lines.append(f"{r['source']:<12} {r['rate_deg_s']:>4g}   {key:<9} {x:8.3f} {y:8.3f} {z:8.3f}  "
                         f"({mx:.3f}, {my:.3f}, {mz:.3f})  {d['estimates']:>6}    {d['stars_with_2x2']}/{d['stars']}")
    return "\n".join(lines)


def plot_covariance_weighting(result: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["results"]
    fig, axes = plt.subplots(1, len(rows), figsize=(3.2 * len(rows), 3.4), sharey=False, squeeze=False)
    for ax, r in zip(axes[0], rows):
        xs = np.arange(3)
        for k, (key, label) in enumerate((("scalar", "scalar sigma_px"), ("2x2", "2 x 2 covariance"))):
            ax.bar(xs + (k - 0.5) * 0.38, r[key]["rmse_arcsec"], width=0.38, label=label)
        ax.set_xticks(xs, ["x", "y", "z"])
        ax.set_yscale("log")  # cross-boresight and roll errors differ by an order of magnitude
        ax.set_title(f"{r['source']}, {r['rate_deg_s']:g} deg/s", fontsize=9)
        ax.set_ylabel("attitude RMSE (arcsec)")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def covariance_weighting_markdown(result: dict, command: str) -> str:
    """The page ``<out>/covariance-weighting.md``: what was measured, by which command, the table."""
    return "\n".join([
        "# Attitude accuracy: scalar sigma_px against the 2 x 2 star covariance", "",
        f"Measured by `{command}`. The `ls_rate` pipeline (ls-rate rolling-shutter correction, QUEST) on the "
        "he2021a sensor at image level; 'scalar' weights every star by its isotropic `sigma_px` "
        "(`star_covariance: false` in ls-rate and quest), '2x2' by the full covariance (the default). Covariance "
        "source 'centroider': what `cog` reports (docs/centroid-covariance.md); 'truth-smear': each star's true "
        "image velocity sets the covariance's shape, scaled to the same trace. Method: "
        "`studies/covariance_weighting.py`.", "",
        "```", covariance_weighting_table(result), "```", "",
        "![covariance weighting](img/covariance_weighting.png)", ""])


def write_covariance_weighting(result: dict, out_dir: Path, command: str) -> list[Path]:
    """``<out>/covariance_weighting.json`` (with the command), ``<out>/covariance-weighting.md`` and
    ``<out>/img/covariance_weighting.png``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    js = out_dir / "covariance_weighting.json"
    write_text(js, json.dumps({**result, "command": command}, indent=2) + "\n")
    md = out_dir / "covariance-weighting.md"
    write_text(md, covariance_weighting_markdown(result, command))
    return [js, md, plot_covariance_weighting(result, out_dir / "img" / "covariance_weighting.png")]
