"""The regression gate: this run's results.json against a stored baseline, per metric, with tolerances.

Gated metrics (mean over seeds) and the direction that is worse:

- lower is better: attitude error RMSE per axis, rate error RMSE (norm and per axis), star-pair
  distance and centroid error RMSE, invalid attitude estimates, flagged frames;
- higher is better: attitude updates, identified stars per frame.

A metric is worse when it moved in its bad direction by more than ``abs + rel * |baseline|``;
tolerances come from the comparison config's ``tolerances`` (fnmatch patterns on the dotted metric
name, the most specific, i.e. longest, matching pattern wins), default ``rel = 0.02``. A number that became
null, a (variant, pipeline) of the baseline missing from this run, or a task that now fails also
count as worse. Timings are never gated (they depend on the machine).
"""
from __future__ import annotations

import json
from fnmatch import fnmatch
from pathlib import Path

from rollingstar.config import excerpt
from rollingstar.errors import UserError
from rollingstar.pipelines.compare.config import Task, Tolerance

LOWER_IS_BETTER = ("attitude_error_arcsec.?_rmse", "rate_error_deg_s.rmse", "rate_error_deg_s.?_rmse",
                   "star_pair_distance_error_px.rmse", "centroid_error_px.rmse", "invalid_attitude_estimates",
                   "flagged_frames")
HIGHER_IS_BETTER = ("attitude_updates", "identified_stars_per_frame")
DEFAULT_TOLERANCE = Tolerance(rel=0.02, abs=0.0)


def load_baseline(path: str | Path, tasks: list[Task] | None = None) -> dict:
    """A baseline results.json, checked before any task runs: JSON of the right shape, at least one
    result, and (given this comparison's ``tasks``) only (variant, pipeline) pairs this comparison
    produces -- a baseline of another comparison would otherwise pass or fail for the wrong reason."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: baseline file not found (generate it with `rollingstar compare CONFIG -o DIR` "
                        "and copy DIR/results.json)")
    try:
        data = json.loads(path.read_text())
    except (ValueError, RecursionError) as exc:
        raise UserError(f"{path}: baseline is not JSON of a results.json: {excerpt(str(exc), 200)}") from None
    if not isinstance(data, dict) or not isinstance(data.get("results"), list):
        raise UserError(f"{path}: not a results.json of `rollingstar compare` (no 'results' list)")
    if not data["results"]:
        raise UserError(f"{path}: the baseline holds no results: nothing to gate against")
    for k, row in enumerate(data["results"]):
        if not (isinstance(row, dict) and isinstance(row.get("variant"), str) and isinstance(row.get("pipeline"), str)
                and isinstance(row.get("metrics"), dict)
                and all(isinstance(v, dict) for v in row["metrics"].values())):
            raise UserError(f"{path}: results[{k}]: expected {{variant: str, pipeline: str, metrics: {{name: "
                            f"{{mean: ...}}}}}}, got {excerpt(row, 120)}")
    if tasks is not None:
        produced = {(t.variant, name) for t in tasks for name, _ in t.pipelines}
        foreign = sorted({(r["variant"], r["pipeline"]) for r in data["results"]} - produced)
        if foreign:
            listed = "; ".join(f"{p} on {v}" for v, p in foreign[:5]) + (" ..." if len(foreign) > 5 else "")
            raise UserError(f"{path}: {len(foreign)} baseline result(s) that this comparison does not produce "
                            f"({listed}): a baseline of another comparison config?")
    return data


def _direction(metric: str) -> int:
    """+1 when larger is worse, -1 when smaller is worse, 0 when not gated."""
    if any(fnmatch(metric, p) for p in LOWER_IS_BETTER):
        return 1
    if any(fnmatch(metric, p) for p in HIGHER_IS_BETTER):
        return -1
    return 0


def _tolerance(metric: str, tolerances: dict[str, Tolerance]) -> Tolerance:
    matches = [p for p in tolerances if fnmatch(metric, p)]
    return tolerances[max(matches, key=len)] if matches else DEFAULT_TOLERANCE


def compare_to_baseline(current: dict, baseline: dict, tolerances: dict[str, Tolerance]) -> list[str]:
    """One line per metric that got worse (empty: no regression)."""
    now = {(r["variant"], r["pipeline"]): r for r in current["results"]}
    worse = []
    for base in baseline["results"]:
        key = (base["variant"], base["pipeline"])
        where = f"{base['pipeline']} on {base['variant']}"
        row = now.get(key)
        if row is None:
            worse.append(f"{where}: missing from this run (in the baseline)")
            continue
        if row.get("errors") and not base.get("errors"):
            worse.append(f"{where}: now fails: {'; '.join(row['errors'])}")
        for metric, stats in sorted(base["metrics"].items()):
            sign = _direction(metric)
            b = stats.get("mean")
            if sign == 0 or b is None:
                continue
            c = row["metrics"].get(metric, {}).get("mean")
            if c is None:
                worse.append(f"{where}: {metric}: {b:.6g} in the baseline, now missing (null)")
                continue
            tol = _tolerance(metric, tolerances)
            allowed = tol.abs + tol.rel * abs(b)
            if sign * (c - b) > allowed:
                change = f"{(c - b) / abs(b):+.1%}" if b else f"{c - b:+.6g}"
                worse.append(f"{where}: {metric}: {b:.6g} -> {c:.6g} ({change}; tolerance abs {tol.abs:g} + rel {tol.rel:g})")
    return worse
