"""Is the centroiders' 2 x 2 position covariance honest on smeared rolling-shutter images?

    rollingstar figures centroid-covariance [--quick] [--json] [--out docs]

Image-level simulation of the he2021a sensor (1024 x 1024, 44.9 ms exposure, 43.9 us line delay,
PSF sigma 1 px, Poisson + read noise, 12 bit; configs/scenarios/he2021a.yaml) rotating at 0, 1, 3,
6 and 10 deg/s about the camera x, y and z (boresight) axes, from random pointings. Every frame
goes through the ``cog`` centroider; each detection is matched to the catalogue star whose smear
it lies on, and compared with that star's true image position at the time the centroid refers to
(its own row's mid-exposure, ``t_ns``). The error is rotated into the frame of the star's true
image velocity (along and across the smear; x and y at rest) and normalised by the reported
covariance rotated into the same frame (``chi2/dof`` per axis: the mean of ``e_along^2 /
C_along`` and of ``e_across^2 / C_across``; 1 for an honest covariance), and, for comparison, by
the isotropic ``sigma_px^2``.

Excluded, and counted: stars whose smear passes within ``BLEND_PX`` of another star's (the two
spots blend) or within ``EDGE_PX`` of the detector edge (a streak cut by the edge). A star
detected as several spots (a faint streak broken by the threshold) counts each of its spots.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rollingstar.config import CONFIGS
from rollingstar.estimators.centroiders.cog import CogCentroider
from rollingstar.estimators.data import FrameData, SensorContext
from rollingstar.outputs import write_text
from rollingstar.pipelines.truth import true_positions
from rollingstar.progress import progress_bar
from rollingstar.sensors import build
from rollingstar.sensors.centroid_sim import solve_star_rows
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.scenario import ScenarioConfig, load_scenario
from rollingstar.sensors.simulate import ImageModel, StarTrackerSimulator

SCENARIO = CONFIGS / "scenarios" / "he2021a.yaml"
RATES_DEG_S = (0.0, 1.0, 3.0, 6.0, 10.0)
AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
BLEND_PX = 8.0  # smears closer than this blend into one spot
EDGE_PX = 4.0  # a smear closer than this to the detector edge is cut by it
MATCH_PX = 3.0  # a detection belongs to the star whose smear passes within this distance
VELOCITY_STEP_NS = 500_000  # central difference of the true image position
BAND = 0.15  # the target: chi2/dof within 1 +- BAND on every case and axis


@dataclass(frozen=True)
class Case:
    rate_deg_s: float
    axis: str

    @property
    def label(self) -> str:
        return "rest" if self.rate_deg_s == 0 else f"{self.rate_deg_s:g} deg/s about {self.axis}"


def cases() -> list[Case]:
    """Rest once, then every rate about every axis."""
    return [Case(0.0, "x")] + [Case(r, a) for r in RATES_DEG_S if r > 0 for a in AXES]


def _scenario(case: Case, pointing: int, seed: int) -> ScenarioConfig:
    """he2021a at the case's rate from a random pointing (uniform on the sky, random roll)."""
    rng = np.random.default_rng([seed, pointing])
    data = load_scenario(SCENARIO).model_dump()
    data["motion"]["rate_deg_s"] = tuple(case.rate_deg_s * np.asarray(AXES[case.axis]))
    data["motion"]["initial_attitude"] = {"ra_deg": float(rng.uniform(0, 360)),
                                          "dec_deg": float(np.degrees(np.arcsin(rng.uniform(-1, 1)))),
                                          "roll_deg": float(rng.uniform(-180, 180))}
    data["seed"] = int(rng.integers(2**31))
    return ScenarioConfig.model_validate(data)


def _simulator(cfg: ScenarioConfig, catalog) -> StarTrackerSimulator:
    camera = build.build_camera(cfg)
    return StarTrackerSimulator(camera=camera, timing=build.build_timing(cfg), catalog=catalog,
                                motion=build.build_motion(cfg), image_model=ImageModel(**cfg.image.model_dump()),
                                level="image", seed=cfg.seed)


def _truth_at(sim, unit: np.ndarray, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True image positions (n, 2) and velocities (n, 2, px/s) of directions ``unit`` at ``t_ns``."""
    t = np.asarray(t_ns, dtype=np.int64)
    pos = [np.column_stack(true_positions(sim.camera, (), sim.motion.attitude(tt), unit, tt))
           for tt in (t, t - VELOCITY_STEP_NS, t + VELOCITY_STEP_NS)]
    return pos[0], (pos[2] - pos[1]) / (2 * VELOCITY_STEP_NS * S_PER_NS)


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances (m, n) from points ``p`` (m, 2) to segments ``a``-``b`` (n, 2 each)."""
    ab = b - a
    L2 = np.maximum(np.sum(ab**2, axis=1), 1e-12)
    s = np.clip(np.einsum("mnk,nk->mn", p[:, None] - a[None], ab) / L2, 0.0, 1.0)
    closest = a[None] + s[..., None] * ab[None]
    return np.linalg.norm(p[:, None] - closest, axis=2)


def _smears_in_view(sim, t0_ns: int) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Catalogue ids and smear ends of every star near the field, at the time of its own
    centroid row (the simulator's row equation), also of those whose centroid lies just off the
    detector while their smear reaches onto it."""
    timing = sim.timing
    t_mid = np.int64(t0_ns + (timing.rows * timing.effective_line_delay_ns + timing.exposure_ns) // 2)
    boresight = sim.motion.attitude(np.array([t_mid]))[0].apply([0.0, 0.0, 1.0])
    speed = float(np.linalg.norm(sim.motion.angular_velocity(np.array([t_mid]))[0]))
    reach = speed * (timing.frame_period_ns * S_PER_NS) + 0.01
    idx = sim.catalog.cone(boresight, sim.camera.half_diagonal_rad + reach)
    unit = sim.catalog.unit_icrs[idx]
    x, y, _ = solve_star_rows(sim.camera, timing, sim.motion, (), unit, int(t0_ns))
    ok = np.isfinite(x) & np.isfinite(y)
    pos, vel = _truth_at(sim, unit[ok], timing.row_mid_exposure_ns(t0_ns, y[ok]))
    half = 0.5 * timing.exposure_ns * S_PER_NS
    return sim.catalog.ids[idx][ok], (pos - vel * half, pos + vel * half)


def _usable(sim, truth, ends: tuple[np.ndarray, np.ndarray], t0_ns: int) -> np.ndarray:
    """Truth stars whose smear is away from the edge and from every other star's smear (also of
    stars whose centroid is off the detector)."""
    a, b = ends
    H, W = sim.camera.height, sim.camera.width
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    inside = (lo[:, 0] >= EDGE_PX) & (lo[:, 1] >= EDGE_PX) & (hi[:, 0] <= W - 1 - EDGE_PX) & (hi[:, 1] <= H - 1 - EDGE_PX)
    n = len(truth)
    ids, (oa, ob) = _smears_in_view(sim, t0_ns)
    samples = a[:, None] + np.linspace(0, 1, 9)[None, :, None] * (b - a)[:, None]  # (n, 9, 2)
    d = _segment_distance(samples.reshape(-1, 2), oa, ob).reshape(n, 9, ids.size).min(axis=1)
    d[truth.catalog_id[:, None] == ids[None, :]] = np.inf  # a star's own smear
    return inside & (d.min(axis=1, initial=np.inf) > BLEND_PX)


def _frame_errors(sim, cog: CogCentroider, k: int) -> dict[str, np.ndarray]:
    """Per matched detection of frame ``k``: the error and the reported covariance in the smear's
    frame (along, across), the isotropic sigma, whether the star broke into several spots, its
    magnitude and smear length; and the counts of excluded stars."""
    frame = sim.frame(k)
    tr = frame.truth
    stars = cog.process(FrameData(index=k, t0_ns=frame.t0_ns, image=frame.image)).stars
    pos, vel = _truth_at(sim, tr.unit_icrs, tr.t_ns)
    half = 0.5 * sim.timing.exposure_ns * S_PER_NS
    ends = (pos - vel * half, pos + vel * half)
    usable = _usable(sim, tr, ends, frame.t0_ns)
    det = np.column_stack([stars.x, stars.y])
    dist = _segment_distance(det, *ends) if len(tr) and stars.n else np.zeros((stars.n, len(tr)))
    j = np.argmin(dist, axis=1) if len(tr) else np.zeros(stars.n, dtype=int)
    ok = (dist[np.arange(stars.n), j] < MATCH_PX) if len(tr) else np.zeros(stars.n, dtype=bool)
    ok &= usable[j] if len(tr) else ok
    i, j = np.flatnonzero(ok), j[ok]
    spots = np.bincount(j, minlength=len(tr))
    at, vt = _truth_at(sim, tr.unit_icrs[j], stars.t_ns[i])
    e = det[i] - at
    speed = np.linalg.norm(vt, axis=1)
    moving = speed * 2 * half > 0.05  # px of smear: below this the axes are x and y
    u = np.where(moving[:, None], vt / np.maximum(speed, 1e-300)[:, None], [1.0, 0.0])
    w = np.column_stack([-u[:, 1], u[:, 0]])
    C = np.stack([np.stack([stars.cov_xx[i], stars.cov_xy[i]], -1), np.stack([stars.cov_xy[i], stars.cov_yy[i]], -1)], -2)
    return {"e_along": np.sum(e * u, 1), "e_across": np.sum(e * w, 1),
            "c_along": np.einsum("ni,nij,nj->n", u, C, u), "c_across": np.einsum("ni,nij,nj->n", w, C, w),
            "c_cross": np.einsum("ni,nij,nj->n", u, C, w), "sigma_px": stars.sigma_px[i],
            "fragment": spots[j] > 1, "magnitude": tr.magnitude[j], "smear_px": speed * 2 * half,
            "saturated": stars.saturated[i],
            "excluded": np.array([int(np.sum(~usable))]), "unmatched": np.array([int(stars.n - ok.sum())])}


def simulate_case(case: Case, pointings: int, frames: int, seed: int, catalog=None,
                  advance=lambda n=1: None) -> dict[str, np.ndarray]:
    """Every matched detection of ``frames`` frames from each of ``pointings`` random pointings
    (``advance`` is called once per frame)."""
    catalog = catalog if catalog is not None else build.build_catalog(_scenario(case, 0, seed))
    parts = []
    for p in range(pointings):
        cfg = _scenario(case, p, seed)
        sim = _simulator(cfg, catalog)
        cog = CogCentroider()
        cog.setup(SensorContext.from_scenario(cfg, catalog=catalog))
        for k in range(frames):
            parts.append(_frame_errors(sim, cog, k))
            advance()
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def chi2_summary(d: dict[str, np.ndarray]) -> dict:
    """chi2/dof along and across with the reported covariance (and the standard error of each,
    the sample standard deviation of the normalised squares over sqrt(n)), the joint 2-D
    chi2/dof, and along and across with the isotropic sigma; for every matched detection
    (``all``) and for the stars detected as one spot (``single``)."""
    def chi(sel):
        n = int(sel.sum())
        if n == 0:
            return {"n": 0}
        ea, ec = d["e_along"][sel], d["e_across"][sel]
        ca, cc, cx, s2 = d["c_along"][sel], d["c_across"][sel], d["c_cross"][sel], d["sigma_px"][sel] ** 2
        det = ca * cc - cx**2
        full = (cc * ea**2 - 2 * cx * ea * ec + ca * ec**2) / det / 2
        za, zc = ea**2 / ca, ec**2 / cc
        return {"n": n, "along": float(np.mean(za)), "across": float(np.mean(zc)),
                "along_se": float(np.std(za) / np.sqrt(n)), "across_se": float(np.std(zc) / np.sqrt(n)),
                "joint": float(np.mean(full)), "along_sigma": float(np.mean(ea**2 / s2)),
                "across_sigma": float(np.mean(ec**2 / s2)),
                "rms_along_px": float(np.sqrt(np.mean(ea**2))), "rms_across_px": float(np.sqrt(np.mean(ec**2))),
                "reported_along_px": float(np.sqrt(np.mean(ca))), "reported_across_px": float(np.sqrt(np.mean(cc)))}

    frag = d["fragment"]
    return {"all": chi(np.ones(frag.size, dtype=bool)), "single": chi(~frag), "fragment_spots": int(frag.sum()),
            "excluded_stars": int(d["excluded"].sum()), "unmatched_spots": int(d["unmatched"].sum()),
            "smear_px_median": float(np.median(d["smear_px"])) if frag.size else float("nan")}


def _config(quick: bool) -> dict:
    """Pointings and frames per pointing per case; the cases (quick: rest and the fastest smear
    about x, where the threshold breaks faint smears)."""
    if quick:
        return {"pointings": 4, "frames": 6, "cases": [Case(0.0, "x"), Case(10.0, "x")]}
    return {"pointings": 12, "frames": 8, "cases": cases()}


def run_centroid_covariance(quick: bool = False, seed: int = 1, show_progress: bool = False) -> dict:
    """Every case's chi2 summary (:func:`chi2_summary`) and the set-up."""
    cfg = _config(quick)
    catalog = build.build_catalog(load_scenario(SCENARIO))
    rows = []
    total = len(cfg["cases"]) * cfg["pointings"] * cfg["frames"]
    with progress_bar("centroid covariance", total, show_progress) as advance:
        for case in cfg["cases"]:
            d = simulate_case(case, cfg["pointings"], cfg["frames"], seed, catalog, advance)
            rows.append({"rate_deg_s": case.rate_deg_s, "axis": case.axis, "label": case.label, **chi2_summary(d)})
    return {"quick": quick, "seed": seed, "pointings": cfg["pointings"], "frames": cfg["frames"],
            "band": BAND, "cases": rows}


def centroid_covariance_markdown(result: dict, command: str) -> str:
    """The table of :func:`run_centroid_covariance`'s result, with how it was measured."""
    lines = [
        "# Centroid covariance on smeared rolling-shutter images",
        "",
        f"Measured by `{command}` (seed {result['seed']}): {result['pointings']} random pointings x "
        f"{result['frames']} frames per case, he2021a sensor at image level (1024 x 1024, 44.9 ms exposure, "
        "43.9 us line delay, PSF sigma 1 px, Poisson + 5 e- read noise, gain 1 e-/ADU, 12 bit, Hipparcos Hp <= 6), "
        "the `cog` centroider with its defaults. Each detection is compared with the true position of the star it "
        "lies on at the time the centroid refers to (its row's mid-exposure); the error is rotated into the "
        "frame of the star's true image velocity (x, y at rest) and normalised by the reported 2 x 2 covariance "
        "rotated into the same frame (`chi2/dof`, 1 when honest), and by the isotropic `sigma_px` for comparison. "
        "Stars whose smear blends with another's or reaches the detector edge are left out (counted). "
        "Method and terms: `studies/centroid_covariance.py`, `estimators/centroiders/covariance.py`.",
        "",
        "| case | smear [px] | spots | pieces of broken smears | chi2/dof along | chi2/dof across | with sigma_px: along | across | "
        "RMS error along / across [px] | reported along / across [px] | left out |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    f = lambda v, d=2: "n/a" if v is None or not np.isfinite(v) else f"{v:.{d}f}"  # noqa: E731
    for r in result["cases"]:
        a = r["all"]
        if not a.get("n"):
            lines.append(f"| {r['label']} | {f(r['smear_px_median'], 1)} | 0 | | | | | | | | {r['excluded_stars']} |")
            continue
        lines.append(f"| {r['label']} | {f(r['smear_px_median'], 1)} | {a['n']} | {r['fragment_spots']} | "
                     f"**{f(a['along'])}** | **{f(a['across'])}** | {f(a['along_sigma'])} | {f(a['across_sigma'])} | "
                     f"{f(a['rms_along_px'], 3)} / {f(a['rms_across_px'], 3)} | "
                     f"{f(a['reported_along_px'], 3)} / {f(a['reported_across_px'], 3)} | {r['excluded_stars']} |")
    worst = max((abs(r["all"][k] - 1.0) for r in result["cases"] if r["all"].get("n") for k in ("along", "across")),
                default=float("nan"))
    lines += ["", f"Largest |chi2/dof - 1| over the cases and axes: {f(worst)} (target: {result['band']:g}).", ""]
    return "\n".join(lines + _broken_smears(result, f))


def _broken_smears(result: dict, f) -> list[str]:
    """The paragraph on the cases where the threshold broke faint smears into pieces."""
    rows = [r for r in result["cases"] if r["fragment_spots"] and r["single"].get("n")]
    if not rows:
        return []
    lines = ["## Broken smears", "",
             "At the fastest rates the faintest smears (Hp 5.5-6, under ~2 thresholds per pixel) break into two or "
             "three spots. Each piece is off the star by up to half the smear; `cog` finds the pieces of one smear "
             "(`estimators/centroiders/fragments.py`), widens each one's covariance along the smear by its offset "
             "from the pieces' common centre, and flags the frame `fragmented_stars:N`. The table above counts "
             "every piece; here the stars seen as one spot alone:", "",
             "| case | pieces | stars as one spot | chi2/dof along | across | RMS error along / across [px] |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        s = r["single"]
        lines.append(f"| {r['label']} | {r['fragment_spots']} | {s['n']} | {f(s['along'])} | {f(s['across'])} | "
                     f"{f(s['rms_along_px'], 3)} / {f(s['rms_across_px'], 3)} |")
    return lines + [""]


def plot_centroid_covariance(result: dict, out_dir: Path) -> Path:
    """chi2/dof along and across the smear against rate, per axis, with the covariance and with
    ``sigma_px``; the band 1 +- BAND shaded. Returns the PNG's path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    rest = [r for r in result["cases"] if r["rate_deg_s"] == 0 and r["all"].get("n")]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), sharey=True)
    for ax, key in zip(axes, ("along", "across")):
        for axis, color in zip(AXES, ("C0", "C1", "C2")):
            rows = rest + [r for r in result["cases"] if r["axis"] == axis and r["rate_deg_s"] > 0 and r["all"].get("n")]
            rate = [r["rate_deg_s"] for r in rows]
            ax.plot(rate, [r["all"][key] for r in rows], "o-", color=color, label=f"covariance, about {axis}")
            ax.plot(rate, [r["all"][f"{key}_sigma"] for r in rows], "x--", color=color, alpha=0.6,
                    label=f"sigma_px, about {axis}")
        ax.axhspan(1 - result["band"], 1 + result["band"], color="0.85", zorder=0)
        ax.set_yscale("log")
        ax.set_xlabel("rate [deg/s]")
        ax.set_title(f"{key} the smear")
    axes[0].set_ylabel("chi2 / dof")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    path = out_dir / "centroid_covariance.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def centroid_covariance_figures(out_dir: Path | None, quick: bool = False, seed: int = 1, as_json: bool = False) -> dict:
    """``rollingstar figures centroid-covariance [--quick] [--json] [--out docs]``: measure, print
    the table (or the JSON), and with ``out_dir`` write ``<out>/centroid-covariance.md``, ``.json``
    and ``<out>/img/centroid_covariance.png``."""
    command = f"rollingstar figures centroid-covariance{' --quick' if quick else ''} --seed {seed}" + (
        f" --out {out_dir}" if out_dir is not None else "")
    result = run_centroid_covariance(quick=quick, seed=seed, show_progress=not as_json)
    text = centroid_covariance_markdown(result, command)
    if out_dir is not None:
        out_dir = Path(out_dir)
        plot_centroid_covariance(result, out_dir / "img")
        write_text(out_dir / "centroid-covariance.md", text + "\n![chi2](img/centroid_covariance.png)\n")
        write_text(out_dir / "centroid-covariance.json", json.dumps(result, indent=1))
    print(json.dumps(result, indent=1) if as_json else text)
    return result
