"""Attitude error with 0-3 planted false matches per frame, every attitude solver, robust gate vs plain.

    .venv/bin/python benchmarks/outliers.py [--frames 30] [--seed 1] [--json out.json] [--markdown out.md]

Scene and planting: :mod:`rollingstar.studies.outlier_bench` (he2021b Table 2 stars, 0.05 deg/s, 0.05 px).
Printed: RMS attitude error (arcsec, rotation angle of truth^-1 * estimate) per solver, gate
(``robust: none | ransac | huber``, threshold 3 px) and number of false matches, and the ratio of
each error to the same solver's clean (0 false matches, no gate) error. The table is in
docs/reliability.md.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")


def markdown(rows: list[dict], command: str) -> str:
    clean = {r["solver"]: r["rms_arcsec"] for r in rows if r["false_matches"] == 0 and r["gate"] == "none"}
    ks = sorted({r["false_matches"] for r in rows})
    lines = [f"`{command}`", "",
             "| solver | gate | " + " | ".join(f"{k} false: RMS arcsec (x clean)" for k in ks) + " |",
             "|---|---|" + "---|" * len(ks)]
    for solver in dict.fromkeys(r["solver"] for r in rows):
        for gate in dict.fromkeys(r["gate"] for r in rows):
            cells = []
            for k in ks:
                r = next(r for r in rows if r["solver"] == solver and r["gate"] == gate and r["false_matches"] == k)
                cells.append(f"{r['rms_arcsec']:.4g} ({r['rms_arcsec'] / clean[solver]:.3g})")
            lines.append(f"| {solver} | {gate} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--markdown", type=Path)
    args = ap.parse_args()
    # imported here, after the thread-count variables above are set: BLAS reads them when numpy loads
    from rollingstar.progress import progress_bar
    from rollingstar.studies.outlier_bench import SOLVERS, measure

    command = f".venv/bin/python benchmarks/outliers.py --frames {args.frames} --seed {args.seed}"
    with progress_bar("outliers", 4 * len(SOLVERS) * 3, True) as advance:
        rows = measure(n_frames=args.frames, seed=args.seed, root=ROOT, advance=advance)
    text = markdown(rows, command)
    print(text)
    if args.json:
        args.json.write_text(json.dumps({"command": command, "rows": rows}, indent=2))
    if args.markdown:
        args.markdown.write_text(text)


if __name__ == "__main__":
    main()
