"""Real-sky figures of issue 4 (docs/real-data.md): every tetra3 and creusot image, measured now.

    .venv/bin/python benchmarks/real_data.py [--out docs] [--repeats 3] [--json]

Needs the shared real data (ROLLINGSTAR_REAL_DATA, default ../shared/data/real). See
rollingstar.studies/real_data.py for what is measured.
"""
from __future__ import annotations

import argparse
import json
import sys

from rollingstar.errors import UserError
from rollingstar.studies.real_data import (
    real_data_markdown,
    run_real_data,
    write_real_data_docs,
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="write <out>/real-data.md, real-data.json and img/real_*.png")
    ap.add_argument("--repeats", type=int, default=3, help="timings are the minimum of this many calls")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    command = ".venv/bin/python benchmarks/real_data.py" + (f" --out {args.out}" if args.out else "") + \
        (f" --repeats {args.repeats}" if args.repeats != 3 else "")
    try:
        result = run_real_data(repeats=args.repeats)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.out:
        print(f"wrote {write_real_data_docs(result, args.out, command)}")
    if args.json:
        print(json.dumps(result, indent=1))
    elif not args.out:
        print(real_data_markdown(result, command))
    return 0


if __name__ == "__main__":
    sys.exit(main())
