"""``rollingstar diagnose`` on the real creusot recordings: per image and jointly per lens folder.

    .venv/bin/python benchmarks/creusot_diagnosis.py [--json out.json] [--markdown out.md] [--markdown-image out.md]

Each astrometry.net corr folder is imported with ``rollingstar import corr`` (a pinhole from
``log.json``'s field of view, nothing else; centroid sigma = the corr table's RMS residual) and
diagnosed with ``--sim`` omitted (the importer's model). Single images hold out 25 % of their
stars; the joint recordings (one frame per image of a folder) hold out whole images. The real
data path is ``ROLLINGSTAR_REAL_DATA`` (default ``../shared/data/real``); never copied here.

Per recording: the lens projection (searched only when the field is wide enough to tell
projections apart), the named effects, the measured noise factor, what is left unexplained (its
described shape), the held-out RMS after the named model against astrometry.net's own in-sample
residual on the held-out stars' tables (:func:`heldout_bar`: a single image's table residual, the
importer's sigma; for a joint recording, that of the images held out; target: not above it), and
the CPU seconds of the whole diagnosis (import excluded, pipeline run included). The summary also
lists the recordings above that residual by more than their held-out stars' own scatter allows
(:func:`above_beyond_scatter`).

A held-out RMS is larger than an in-sample one by construction (the fit did not see those stars),
so the in-sample residual is not a like-for-like bar. The fair one is also reported:
astrometry.net's model class (a TAN WCS with SIP distortion of order 2) fitted to the diagnosis's
own training stars and scored on the same held-out stars (``anet_class.py`` beside this script:
the model, why it is fitted by hand, and how joint recordings share one lens). Both use the stars
the diagnosis kept (after its gross-outlier rejection), whose held-out set it reports.

Every recording is also imported with ``--centroids image`` (each star measured again on the PNG
the table was made from, with its covariance: ``rollingstar.estimators.centroiders.remeasure``) and
diagnosed the same way; its table (``--markdown-image``) sets the held-out RMS after against the
same bar, astrometry.net's in-sample residual of its own positions.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from anet_class import fit_class  # beside this script (run as ``python benchmarks/creusot_diagnosis.py``)
from scipy import stats

from rollingstar.estimators.centroiders.remeasure import remeasure_stars
from rollingstar.logs.importers.corr import find_corr_folders, import_corr, pointing_centres
from rollingstar.pipelines.diagnose import DiagnoseOptions, diagnose_recording

ROOT = Path(__file__).resolve().parents[1]
GROUPS = ("16mm_checker_2", "16mm_checker_calib/distorted", "16mm_checker_calib/undistorted",
          "8mm_checker_calib/distorted", "8mm_checker_calib/undistorted")


def creusot_dir() -> Path:
    return Path(os.environ.get("ROLLINGSTAR_REAL_DATA", ROOT.parent / "shared" / "data" / "real")) / "creusot"


def summarise(label: str, scope: str, res: dict) -> dict:
    effects = [{"name": e["name"], "params": {k: (v["value"], v["sigma"], v["unit"]) for k, v in e["params"].items()},
                "delta_bic": e["delta_bic"], "inclusion": e["inclusion_probability"], "confidence": e["confidence"],
                "at_bound": e.get("at_bound", [])} for e in res["effects"]]
    return {"recording": label, "scope": scope, "stars": res["split"]["train_observations"] + res["split"]["heldout_observations"],
            "heldout_stars": res["split"]["heldout_observations"],
            "heldout_frames_fitted": res["split"]["heldout_frames"] if res["split"]["unit"] == "frames" else 0,
            "frames": res["split"]["frames"], "sigma_px": res["noise"]["sigma_px_median"],
            "chi2_dof_before": res["located"]["chi2_dof"], "chi2_dof_after": res["train_chi2_dof_after"],
            "strongest_covariate": res["located"]["strongest_covariate"], "mismatch": res["mismatch"],
            "effects": effects, "weak": res.get("weak_candidates", []), "ambiguous": res["ambiguous"],
            "unexplained": res["unexplained_systematic"]["present"],
            "heldout_rms_before_px": res["heldout_rms_before_px"], "heldout_rms_after_px": res["heldout_rms_after_px"],
            "projection": res["projection"], "noise_check": res.get("noise_check"),
            "description": (res["unexplained_systematic"].get("description") or {}).get("text"),
            "verdict": res["verdict"], "summary": res["summary"]}


def anet_class(d) -> dict:
    """astrometry.net's model class fitted to the diagnosis ``d``'s training stars, scored on its held-out ones."""
    obs, cam = d.obs, d.sensor.camera  # the stars the diagnosis kept, ``obs.heldout`` its split
    fit = fit_class(obs.frame, np.column_stack([obs.x, obs.y]), obs.u_icrs, obs.heldout, cam.focal_px, (cam.cx, cam.cy))
    if fit is None:
        return {"anet_class_heldout_rms_px": None, "anet_class_train_rms_px": None, "anet_class_params": None}
    return {"anet_class_heldout_rms_px": fit.heldout_rms_px, "anet_class_train_rms_px": fit.train_rms_px,
            "anet_class_params": fit.n_params}


def timed(label: str, scope: str, rec: Path, opts: DiagnoseOptions) -> dict:
    start = time.process_time()
    res, d = diagnose_recording(rec, options=opts)
    cpu = time.process_time() - start
    return {**summarise(label, scope, res), **anet_class(d), "anet_bar_px": heldout_bar(rec, d), "cpu_s": cpu}


def heldout_bar(rec: Path, d) -> float | None:
    """astrometry.net's in-sample residual (RMS per axis) on the held-out stars' own tables: each
    held-out image's table residual, pooled over the diagnosis's held-out stars (for a single
    image, its table's residual; for a joint recording, that of the images held out, not of the
    whole folder). None when a held-out table has no residual."""
    tables = pointing_centres(rec)
    obs = d.obs
    images, stars = np.unique(obs.frame_index[obs.frame[obs.heldout]], return_counts=True)
    rms = [tables[int(k)]["residual_rms_px"] for k in images]
    if not images.size or any(r is None for r in rms):
        return None
    return float(np.sqrt(np.sum(stars * np.square(rms)) / stars.sum()))


def run(seed: int = 0) -> tuple[list[dict], list[dict]]:
    """The rows of every recording with astrometry.net's positions, and with the stars measured
    again on the images (``rollingstar import corr --centroids image``)."""
    base = creusot_dir()
    rows, image_rows = [], []
    opts = DiagnoseOptions(seed=seed)
    with tempfile.TemporaryDirectory() as tmp:
        for group in GROUPS:
            folder = base / group
            subs = [(f"{group}/{sub.relative_to(folder)}", "image", sub) for sub in find_corr_folders(folder)]
            for label, scope, source in [*subs, (group, "joint", folder)]:
                rec = Path(tmp) / f"{label.replace('/', '_')}.mcap"
                import_corr(source, rec)
                rows.append(timed(label, scope, rec, opts))
                rec = rec.with_name(f"{rec.stem}_image.mcap")
                import_corr(source, rec, remeasure_stars)
                image_rows.append({**remeasured(rec), **timed(label, scope, rec, opts)})
    return rows, image_rows


def remeasured(rec: Path) -> dict:
    """How many of the recording's stars were measured again on their images, and the PSF sigmas."""
    frames = pointing_centres(rec).values()
    done = [f["remeasured"] for f in frames]
    return {"measured": sum(d["measured"] for d in done), "listed": sum(f["n_stars"] for f in frames),
            "psf_sigma_px": [d.get("psf_sigma_px") for d in done if d["image"]],
            "psf_measured": [d.get("psf_measured") for d in done if d["image"]]}


def markdown(rows: list[dict]) -> str:
    def f(v, fmt="{:.3g}"):
        return "n/a" if v is None else fmt.format(v)

    def eff(r):
        if not r["effects"]:
            weak = ", ".join(f"{w['name']} (incl. {f(w['inclusion_probability'], '{:.2f}')})" for w in r["weak"])
            return "none" + (f"; weak: {weak}" if weak else "")
        parts = []
        for e in r["effects"]:
            ps = ", ".join(f"{k} = {f(v[0])} ± {f(v[1])}{' (at bound)' if k in e['at_bound'] else ''}"
                           for k, v in e["params"].items())
            tag = "" if e["confidence"] == "confident" else ", tentative"
            parts.append(f"{e['name']} ({ps}; ΔBIC {f(e['delta_bic'], '{:.0f}')}, incl. {f(e['inclusion'], '{:.2f}')}{tag})")
        return "; ".join(parts)

    def proj(r):
        p = r["projection"]
        if p is None:
            return "not searched"
        if not p.get("searched", True):  # a narrow field far off the model: only the declared lens fitted
            focal = p["candidates"][p["named"]]["focal_px"]
            return "not searched; lens fitted" + (f", focal {focal:.0f} px (declared {p['declared_focal_px']:.0f})"
                                                  if p["refocused"] else "")
        return p["named"] if p["named"] == p["declared"] else f"**{p['named']}** (declared {p['declared']})"

    def noise(r):
        n = r["noise_check"]
        return "n/a" if n is None else (f"{n['factor']:.2f} ± {n['factor_sigma']:.2f}" + (" (applied)" if n["applied"] else ""))

    def ratio(r):
        a, s = r["heldout_rms_after_px"], r["anet_bar_px"]
        return "n/a" if a is None or not s else f"{a / s:.2f}"

    lines = ["| recording | scope | frames | stars | a.net residual = sigma (px) | projection | named | noise factor | ambiguous | "
             "unexplained | held-out RMS before → after (px) | after / a.net | a.net class held out (px) | CPU s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        amb = "; ".join(" / ".join(a["candidates"]) for a in r["ambiguous"]) or "-"
        left = (r["description"] or "yes") if r["unexplained"] else "-"
        lines.append(f"| {r['recording']} | {r['scope']} | {r['frames']} | {r['stars']} | {f(r['sigma_px'])} | {proj(r)} | "
                     f"{eff(r)} | {noise(r)} | {amb} | {left} | "
                     f"{f(r['heldout_rms_before_px'], '{:.3f}')} → {f(r['heldout_rms_after_px'], '{:.3f}')} | {ratio(r)} | "
                     f"{f(r['anet_class_heldout_rms_px'], '{:.3f}')} | {f(r['cpu_s'], '{:.2f}')} |")
    cpu = [r["cpu_s"] for r in rows]
    lines += ["", *against(rows, "anet_bar_px", "astrometry.net's in-sample residual", beyond_scatter=True),
              *against(rows, "anet_class_heldout_rms_px", "astrometry.net's model class held out the same way "
                       "(TAN + SIP order 2 fitted to the same training stars, scored on the same held-out stars)")]
    lines.append(f"- CPU seconds per diagnosis: median {np.median(cpu):.2f}, maximum {np.max(cpu):.2f} ({len(rows)} recordings)")
    return "\n".join(lines)


def markdown_image(rows: list[dict], table_rows: list[dict]) -> str:
    """The recordings with the stars measured again on their images, against astrometry.net's own
    in-sample residual of the same table and against the diagnosis of the table's positions
    (``table_rows``, the same recordings)."""
    def f(v, fmt="{:.3g}"):
        return "n/a" if v is None else fmt.format(v)

    def psf(r):
        return ", ".join(f"{s:.2f}" + ("" if m else " (default)") for s, m in zip(r["psf_sigma_px"], r["psf_measured"]))

    lines = ["| recording | scope | stars measured again | PSF sigma (px) | stated sigma, median (px) | named | "
             "training chi2/dof after | held-out RMS after (px) | a.net residual, held-out images (px) | after / a.net | "
             "CPU s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        named = ", ".join(e["name"] for e in r["effects"]) or "none"
        ratio = (f"{r['heldout_rms_after_px'] / r['anet_bar_px']:.2f}"
                 if r["heldout_rms_after_px"] is not None and r["anet_bar_px"] else "n/a")
        lines.append(f"| {r['recording']} | {r['scope']} | {r['measured']} of {r['listed']} | {psf(r)} | "
                     f"{f(r['sigma_px'])} | {named} | {f(r['chi2_dof_after'])} | {f(r['heldout_rms_after_px'], '{:.3f}')} | "
                     f"{f(r['anet_bar_px'])} | {ratio} | {f(r['cpu_s'], '{:.2f}')} |")
    cpu = [r["cpu_s"] for r in rows]
    table = {r["recording"]: r["heldout_rms_after_px"] for r in table_rows}
    pairs = [(r["recording"], r["heldout_rms_after_px"], table.get(r["recording"])) for r in rows]
    pairs = [(k, a, b) for k, a, b in pairs if a is not None and b is not None]
    not_lower = [k for k, a, b in pairs if a >= b]
    lines += ["", *against(rows, "anet_bar_px", "astrometry.net's in-sample residual, stars measured again",
                           beyond_scatter=True),
              f"- held-out RMS after lower than with the tables' positions: {len(pairs) - len(not_lower)} of "
              f"{len(pairs)} recordings (not lower: {', '.join(not_lower) or 'none'})",
              f"- CPU seconds per diagnosis: median {np.median(cpu):.2f}, maximum {np.max(cpu):.2f} ({len(rows)} recordings)"]
    return "\n".join(lines)


def against(rows: list[dict], key: str, what: str, beyond_scatter: bool = False) -> list[str]:
    """Summary lines: on how many recordings the held-out RMS after is at or below ``row[key]``
    (described as ``what``), overall and per lens, with the median ratio per lens; rows without
    either number count in neither. ``beyond_scatter``: also those above it by more than their
    held-out stars' own scatter allows (:func:`above_beyond_scatter`)."""
    def ratios(of):
        return [r["heldout_rms_after_px"] / r[key] for r in of if r["heldout_rms_after_px"] is not None and r[key]]

    lines = [f"- held-out RMS after at or below {what}: {sum(x <= 1.0 for x in ratios(rows))} of "
             f"{len(ratios(rows))} recordings"]
    for lens in sorted({lens_of(r) for r in rows}):
        x = ratios([r for r in rows if lens_of(r) == lens])
        median = f"{np.median(x):.2f}" if x else "n/a"
        lines.append(f"  - {lens}: {sum(v <= 1.0 for v in x)} of {len(x)}, median ratio {median}")
    if beyond_scatter:
        scored = [r for r in rows if r["heldout_rms_after_px"] is not None and r[key]]
        above = [r["recording"] for r in scored if above_beyond_scatter(r, key)]
        lines.append(f"  - above it by more than the held-out stars' own scatter allows (one-sided "
                     f"{BEYOND_SCATTER_P:.1%}): {len(above)} of {len(scored)} ({', '.join(above) or 'none'})")
        missed = [r for r in scored if r["heldout_rms_after_px"] > r[key]]
        also = [r["recording"] for r in missed if (r["anet_class_heldout_rms_px"] or 0.0) > r[key]]
        lines.append(f"  - of the {len(missed)} above it, above it also with astrometry.net's own model class held out "
                     f"the same way: {len(also)} ({', '.join(also) or 'none'})")
    return lines


BEYOND_SCATTER_P = 0.025


def above_beyond_scatter(row: dict, key: str) -> bool:
    """Whether the held-out RMS after exceeds ``row[key]`` by more than sampling allows: if the
    held-out residuals had an RMS per axis of ``row[key]``, the sum of squares over the m held-out
    stars' 2m coordinates would be ``row[key]^2 chi2(2m - 3f)``, f the held-out images whose
    attitude is fitted to their own stars (3 of their coordinates absorbed each, as the
    diagnosis's held-out chi-square counts them); True when the measured one lies beyond its
    one-sided ``BEYOND_SCATTER_P`` point. The model's own fitted error, which makes a held-out RMS
    larger still, is not allowed for: a recording is counted here more readily than it should be,
    never less."""
    m, dof = row["heldout_stars"], 2 * row["heldout_stars"] - 3 * row.get("heldout_frames_fitted", 0)
    ratio2 = (row["heldout_rms_after_px"] / row[key]) ** 2
    return dof > 0 and float(stats.chi2.sf(2 * m * ratio2, dof)) < BEYOND_SCATTER_P


def lens_of(row: dict) -> str:
    """The lens of a recording, the first part of its folder name (``8mm``, ``16mm``)."""
    return row["recording"].split("_", 1)[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--markdown", type=Path)
    ap.add_argument("--markdown-image", type=Path, help="the table of the stars measured again on the images")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if not creusot_dir().is_dir():
        raise SystemExit(f"real data not found at {creusot_dir()} (set ROLLINGSTAR_REAL_DATA)")
    rows, image_rows = run(args.seed)
    if args.json:
        args.json.write_text(json.dumps({"table": rows, "image": image_rows}, indent=2))
    md, md_image = markdown(rows), markdown_image(image_rows, rows)
    if args.markdown:
        args.markdown.write_text(md + "\n")
    if args.markdown_image:
        args.markdown_image.write_text(md_image + "\n")
    print(md, md_image, sep="\n\n")


if __name__ == "__main__":
    main()
