"""results.json: per (scenario variant, pipeline) the evaluate metrics over seeds and their spread.

Layout::

    {"comparison": {...config summary...},
     "results": [{"scenario", "variant", "params", "rate_deg_s", "pipeline", "seeds",
                  "metrics": {"attitude_error_arcsec.x_rmse": {"mean", "std", "min", "max", "n"}, ...},
                  "per_seed": [{"seed", "metrics": {...flat...}} | {"seed", "error"}],
                  "timing": {"cpu_s_per_frame": {...}, "wall_s_per_frame": {...}, "stage_s_per_frame": {...}}}],
     "run": {"executor", "workers", "wall_time_s", "tasks", "pipeline_runs", "profile", ...}}

A task is one (variant, seed) simulation with every pipeline run on it; ``aggregate`` takes the
pipeline runs (rows of :func:`rollingstar.pipelines.compare.tasks.run_task`) in any order.

Metrics are the flattened (dotted) numbers of ``evaluate_log`` (efficiency = RMSE / Cramér-Rao bound
included); ``std`` is the sample standard deviation over seeds (0 with one seed). Everything but
``timing`` and ``run`` is a deterministic function of the config: :func:`deterministic_view`.
"""
from __future__ import annotations

import math

import numpy as np

from rollingstar.pipelines.compare.config import Comparison


def flatten(metrics: dict, prefix: str = "") -> dict[str, float | None]:
    """Nested evaluate dict -> ``{"a.b": number or None}`` (numbers only)."""
    out: dict[str, float | None] = {}
    for key, value in metrics.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, name + "."))
        elif value is None or isinstance(value, (int, float)) and not isinstance(value, bool):
            out[name] = None if value is None or not math.isfinite(value) else float(value)
    return out


def spread(values: list[float | None]) -> dict:
    v = np.array([x for x in values if x is not None], dtype=float)
    if v.size == 0:
        return {"mean": None, "std": None, "min": None, "max": None, "n": 0}
    return {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
            "min": float(v.min()), "max": float(v.max()), "n": int(v.size)}


#: Metrics a run writes only when non-zero (a seed without a flag has no key for it): a seed that ran
#: and lacks one counted zero, so that every seed enters the mean.
COUNTS = ("outcomes.flag_reasons.", "outcomes.invalid_reasons.")


def aggregate(comp: Comparison, pipeline_runs: list[dict], run_info: dict) -> dict:
    by_key: dict[tuple[str, str], list[dict]] = {}
    for r in pipeline_runs:
        by_key.setdefault((r["variant"], r["pipeline"]), []).append(r)
    rows = []
    for v in comp.variants:
        for p in v.pipelines:
            runs = sorted(by_key.get((v.label, p), []), key=lambda r: r["seed"])
            flat = [flatten(r["metrics"]) if "metrics" in r else None for r in runs]
            keys = sorted({k for f in flat if f is not None for k in f})
            metrics = {k: spread([f.get(k, 0 if k.startswith(COUNTS) else None) if f is not None else None
                                  for f in flat]) for k in keys}
            per_seed = [{"seed": r["seed"], "metrics": f} if f is not None else {"seed": r["seed"], "error": r["error"]}
                        for r, f in zip(runs, flat)]
            timed = [r["timing"] for r in runs if "timing" in r]
            stages = sorted({s for t in timed for s in t["stage_s_per_frame"]})
            timing = {
                "cpu_s_per_frame": spread([t["cpu_s_per_frame"] for t in timed]),
                "wall_s_per_frame": spread([t["wall_s_per_frame"] for t in timed]),
                "stage_s_per_frame": {s: spread([t["stage_s_per_frame"].get(s) for t in timed]) for s in stages},
            }
            row = {
                "scenario": v.scenario, "variant": v.label, "params": v.params, "rate_deg_s": v.rate_deg_s,
                "rate_norm_deg_s": float(np.linalg.norm(v.rate_deg_s)),
                "rate_xy_norm_deg_s": float(np.linalg.norm(v.rate_deg_s[:2])), "frames": v.config.frames,
                "pipeline": p, "seeds": [r["seed"] for r in runs], "metrics": metrics, "per_seed": per_seed,
                "errors": [f"seed {r['seed']}: {r['error']}" for r in runs if "error" in r],
                "timing": timing,
            }
            # the sentences evaluate adds beside its numbers (flatten keeps numbers only)
            said = [f"seed {r['seed']}: {r['metrics']['truth_convention']}" for r in runs
                    if "truth_convention" in r.get("metrics", {})]
            rows.append({**row, "warnings": said} if said else row)
    cfg = comp.config
    return {
        "comparison": {"name": cfg.name, "description": cfg.description, "source": comp.source,
                       "seeds": cfg.seed_list(), "pipelines": comp.pipeline_paths,
                       "variants": [v.label for v in comp.variants], "plot_x": cfg.plot_x},
        "results": rows,
        "run": run_info,
    }


def deterministic_view(results: dict) -> dict:
    """results.json without the machine-dependent parts (``timing`` per row, ``run``)."""
    return {"comparison": results["comparison"],
            "results": [{k: v for k, v in row.items() if k != "timing"} for row in results["results"]]}
