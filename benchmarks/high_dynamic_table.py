"""The summary table of docs/high-dynamic.md from the high-dynamic sweep's results.

    rollingstar compare configs/compare/high_dynamic.yaml -o docs/comparison/high_dynamic --workers 2
    .venv/bin/python benchmarks/high_dynamic_table.py docs/comparison/high_dynamic/results.json

Per rotation axis and rate: each pipeline's valid frames (per cent of all frames) and its
efficiency against the pixel-level bound (RMSE / bound, attitude x / y / z, then rate x / y / z;
the baseline fits no rate), means over the seeds; then the sweep's summary lines for
``high_dynamic``.
"""
from __future__ import annotations

import argparse
import json
import math
import re

PIPELINES = ("high_dynamic", "ls_rate", "baseline")
AXES = ("x", "y", "z")


def _mean(metric) -> float | None:
    if isinstance(metric, dict):
        return metric.get("mean")
    return metric


def _valid(metrics: dict) -> float:
    """Fraction of frames with a valid attitude (results without the outcome counts: frames less
    invalid estimates, one estimate per frame)."""
    if "outcomes.valid_frames" in metrics:
        return _mean(metrics["outcomes.valid_frames"]) / _mean(metrics["outcomes.frames"])
    return 1.0 - _mean(metrics["invalid_attitude_estimates"]) / _mean(metrics["frames"])


def _fmt(value: float | None) -> str:
    """Two significant digits, trailing zeros kept (1.0, 0.90); whole numbers from 100 on."""
    if value is None:
        return "n/a"
    if abs(value) >= 99.5:
        return f"{value:.0f}"
    rounded = float(f"{value:.2g}")
    if rounded == 0:
        return "0"
    return f"{rounded:.{max(0, 1 - math.floor(math.log10(abs(rounded))))}f}"


def _cell(metrics: dict, with_rate: bool) -> str:
    valid = 100.0 * _valid(metrics)
    names = [f"attitude_{a}" for a in AXES] + ([f"rate_{a}" for a in AXES] if with_rate else [])
    eff = [_mean(metrics.get(f"efficiency_pixel.{n}")) for n in names]
    text = [_fmt(e) for e in eff]
    att = " / ".join(text[:3])
    return f"{valid:.3g} %, {att}" + (f", {' / '.join(text[3:])}" if with_rate else "")


def table(results: list[dict]) -> str:
    rows = {}
    for r in results:
        rate = r["rate_deg_s"]
        axis = next((a for a, v in zip(AXES, rate) if v), "x")
        rows.setdefault((axis, max(abs(v) for v in rate)), {})[r["pipeline"]] = r["metrics"]
    lines = ["| about | deg/s | high_dynamic: valid, eff. | ls_rate: valid, eff. | baseline: valid, eff. (attitude) |",
             "|---|---|---|---|---|"]
    for (axis, rate), by in sorted(rows.items()):
        cells = [_cell(by[p], p != "baseline") if p in by else "-" for p in PIPELINES]
        lines.append(f"| {axis} | {rate:g} | " + " | ".join(cells) + " |")
    hd = [by["high_dynamic"] for by in rows.values() if "high_dynamic" in by]
    worst = max(_mean(m[f"efficiency_pixel.{k}_{a}"]) for m in hd for k in ("attitude", "rate") for a in AXES)
    valid = min(_valid(m) for m in hd)
    lines += ["", f"- high_dynamic: valid frames from a cold start at least {100 * valid:.3g} % at every rate and axis",
              f"- high_dynamic: efficiency at most {worst:.3g} on any axis, attitude or rate"]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", help="results.json of `rollingstar compare configs/compare/high_dynamic.yaml`")
    args = ap.parse_args()
    with open(args.results) as f:
        results = json.load(f)["results"]
    print(table([r for r in results if re.match(r"about_", r["variant"])] or results))


if __name__ == "__main__":
    main()
