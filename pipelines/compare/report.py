"""``results.md`` (tables), ``report.html`` (the same tables and the figures) and ``img/*.png`` from ``results.json``.

Figures (matplotlib, Agg):

- ``img/error_vs_rate_<scenario>.png`` for every scenario with more than one variant: attitude error
  RMSE per axis, star-pair distance error RMSE and (when estimated) rate error RMSE per axis against
  the variant's ``|rate|`` or ``|(w_x, w_y)|`` (config ``plot_x``), one line per pipeline (mean over seeds, bars = std), the single-frame
  Cramér-Rao bounds dashed (centroid-level: the scenario's centroid sigma taken as given) and
  dotted (pixel-level: the information in the rendered pixels, image-level recordings);
- ``img/update_rate_vs_accuracy.png``: attitude updates per second against the attitude error
  (RMS over the three axes' RMSE), one marker per (variant, pipeline);
- ``img/cpu_time.png``: CPU time per frame of the run stage, per pipeline and scenario.
"""
from __future__ import annotations

import html
import re
from pathlib import Path

import numpy as np

AXES = ("x", "y", "z")


def _m(row: dict, key: str) -> tuple[float | None, float | None]:
    s = row["metrics"].get(key)
    return (None, None) if not s or s["mean"] is None else (s["mean"], s["std"])


def _fmt(mean, std=None, digits=3) -> str:
    if mean is None:
        return "n/a"
    text = f"{mean:.{digits}g}"
    return text + (f" ± {std:.2g}" if std and std > 1e-9 * abs(mean) else "")  # not float round-off


def _valid_percent(row: dict) -> str:
    """Frames with a valid attitude estimate (%, mean over seeds; :mod:`rollingstar.pipelines.outcomes`)."""
    valid, frames = _m(row, "outcomes.valid_frames")[0], _m(row, "outcomes.frames")[0]
    if valid is None:  # results written before the outcome counts: estimates per frame, at most every frame
        valid, frames = _m(row, "attitude_updates")[0], _m(row, "frames")[0]
        valid = None if valid is None or frames is None else min(valid, frames)
    return "n/a" if valid is None or not frames else f"{100.0 * valid / frames:.3g}"


def _flagged_percent(row: dict) -> str:
    """Flagged frames (%, mean over seeds) and the flags most frames carry, per reason (frames)."""
    flagged, frames = _m(row, "outcomes.flagged_frames")[0], _m(row, "outcomes.frames")[0]
    if flagged is None or not frames:
        return "n/a"
    prefix = "outcomes.flag_reasons."
    reasons = sorted(((s["mean"], k[len(prefix):]) for k, s in row["metrics"].items()
                      if k.startswith(prefix) and s["mean"]), reverse=True)
    top = ", ".join(f"{name} {n:.3g}" for n, name in reasons[:2]) + (", ..." if len(reasons) > 2 else "")
    return f"{100.0 * flagged / frames:.3g}" + (f" ({top})" if top else "")


TERMINAL_COLUMNS = ("variant", "pipeline", "valid (%)", "flagged (%)", "att. RMSE x / y / z (arcsec)",
                    "efficiency x / y / z",
                    "pixel efficiency x / y / z", "rate RMSE x / y / z (deg/s)", "CPU ms/frame")


def _informative(header: list[str], body: list[list[str]], columns) -> list[int]:
    """Indices of ``columns`` in ``header`` that are not n/a in every row."""
    keep = [header.index(c) for c in columns if c in header]
    return [k for k in keep if any(set(row[k].split(" / ")) != {"n/a"} for row in body)]


def terminal_tables(results: dict, columns=TERMINAL_COLUMNS) -> list[tuple[str, list[str], list[list[str]]]]:
    """The ``columns`` of :func:`tables` (default: the main ones, for the terminal), without the
    columns that are n/a in every row."""
    out = []
    for title, header, body in tables(results):
        keep = _informative(header, body, columns)
        out.append((title, [header[k] for k in keep], [[row[k] for k in keep] for row in body]))
    return out


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_")


def tables(results: dict) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, header, rows) per scenario."""
    out = []
    scenarios = list(dict.fromkeys(r["scenario"] for r in results["results"]))
    for sc in scenarios:
        rows = [r for r in results["results"] if r["scenario"] == sc]
        header = ["variant", "pipeline", "seeds", "valid (%)", "flagged (%)", "att. RMSE x / y / z (arcsec)",
                  "CRB x / y / z (arcsec)",
                  "efficiency x / y / z", "pixel CRB x / y / z (arcsec)", "pixel efficiency x / y / z",
                  "rate RMSE x / y / z (deg/s)", "rate CRB x / y / z (deg/s)", "pixel rate CRB x / y / z (deg/s)",
                  "pixel rate efficiency x / y / z", "pair dist. RMSE (px)", "updates (Hz)", "CPU ms/frame"]
        body = []
        for r in rows:
            def trio(prefix, suffix=""):
                return " / ".join(_fmt(*_m(r, f"{prefix}{a}{suffix}")) for a in AXES)
            cpu = r["timing"]["cpu_s_per_frame"]["mean"]
            body.append([
                r["variant"], r["pipeline"], str(len(r["seeds"])) + (f" ({len(r['errors'])} failed)" if r["errors"] else ""),
                _valid_percent(r), _flagged_percent(r),
                trio("attitude_error_arcsec.", "_rmse"), trio("attitude_crb_arcsec."), trio("efficiency.attitude_"),
                trio("pixel_crb_arcsec."), trio("efficiency_pixel.attitude_"),
                trio("rate_error_deg_s.", "_rmse"), trio("rate_crb_deg_s."), trio("pixel_rate_crb_deg_s."),
                trio("efficiency_pixel.rate_"),
                _fmt(*_m(r, "star_pair_distance_error_px.rmse")), _fmt(*_m(r, "update_rate_hz")),
                "n/a" if cpu is None else f"{1e3 * cpu:.3g}",
            ])
        out.append((sc, header, body))
    return out


# the pixel-level bound drawn beside each centroid-level one
_PIXEL_BOUND = {f"attitude_crb_arcsec.{a}": f"pixel_crb_arcsec.{a}" for a in AXES} | {
    f"rate_crb_deg_s.{a}": f"pixel_rate_crb_deg_s.{a}" for a in AXES}

_X_KEY = {"rate_norm": ("rate_norm_deg_s", "|rate| (deg/s)"), "rate_xy_norm": ("rate_xy_norm_deg_s", "|(w_x, w_y)| (deg/s)")}


def _pyplot():
    """matplotlib's pyplot on the Agg backend, imported on first use (a slow import that only
    figure-writing callers pay)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figures(results: dict, img_dir: Path) -> list[tuple[str, str]]:
    """Write the PNGs; returns (file name relative to the output dir, caption)."""
    img_dir.mkdir(parents=True, exist_ok=True)
    made = []
    rows = results["results"]
    x_key, x_label = _X_KEY[results["comparison"].get("plot_x", "rate_norm")]
    pipelines = list(dict.fromkeys(r["pipeline"] for r in rows))
    colours = {p: f"C{k % 10}" for k, p in enumerate(pipelines)}
    for sc in dict.fromkeys(r["scenario"] for r in rows):
        sub = [r for r in rows if r["scenario"] == sc]
        if len({r["variant"] for r in sub}) < 2:
            continue
        name = f"img/error_vs_rate_{_slug(sc)}.png"
        _error_vs_rate_figure(sc, sub, pipelines, colours, x_key, x_label, img_dir.parent / name)
        made.append((name, f"{sc}: error vs rate per axis"))
    _update_rate_figure(rows, pipelines, colours, img_dir / "update_rate_vs_accuracy.png")
    made.append(("img/update_rate_vs_accuracy.png", "update rate vs accuracy"))
    _cpu_time_figure(rows, pipelines, colours, img_dir / "cpu_time.png")
    made.append(("img/cpu_time.png", "CPU time per frame"))
    return made


def _error_vs_rate_figure(sc: str, sub: list[dict], pipelines: list[str], colours: dict, x_key: str, x_label: str,
                          path: Path) -> None:
    """Scenario ``sc``'s errors (and bounds) against the variants' rate, one panel per quantity."""
    plt = _pyplot()

    def _x_of(row: dict) -> float:
        return row[x_key]

    has_rate = any(_m(r, "rate_error_deg_s.x_rmse")[0] is not None for r in sub)
    nrows = 2 if has_rate else 1
    fig, axs = plt.subplots(nrows, 4, figsize=(16, 3.6 * nrows), squeeze=False)
    panels = [(axs[0][k], f"attitude_error_arcsec.{a}_rmse", f"attitude_crb_arcsec.{a}", f"attitude error {a} RMSE (arcsec)")
              for k, a in enumerate(AXES)]
    panels.append((axs[0][3], "star_pair_distance_error_px.rmse", None, "star-pair distance error RMSE (px)"))
    if has_rate:
        panels += [(axs[1][k], f"rate_error_deg_s.{a}_rmse", f"rate_crb_deg_s.{a}", f"rate error {a} RMSE (deg/s)")
                   for k, a in enumerate(AXES)]
        panels.append((axs[1][3], "rate_error_deg_s.rmse", None, "rate error |.| RMSE (deg/s)"))
    for ax, key, bound, title in panels:
        for p in pipelines:
            pr = sorted((r for r in sub if r["pipeline"] == p), key=_x_of)
            pts = [(_x_of(r), *_m(r, key)) for r in pr if _m(r, key)[0] is not None]
            if pts:
                _log_errorbar(ax, *map(np.array, zip(*pts)), colours[p], p)
            for bkey, style in ((bound, "--"), (_PIXEL_BOUND.get(bound), ":")):
                bpts = [(_x_of(r), _m(r, bkey)[0]) for r in pr
                        if bkey and _m(r, bkey)[0] is not None and _m(r, key)[0] is not None]
                if bpts:
                    bx, bm = zip(*bpts)
                    ax.plot(bx, bm, ls=style, lw=1, color=colours[p], alpha=0.7)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(x_label)
        if ax.has_data():
            ax.set_yscale("log")  # pipelines differ by orders of magnitude
        ax.grid(alpha=0.3)
    for ax in axs.flat:
        if not ax.has_data():
            ax.set_visible(False)
    axs[0][0].legend(fontsize=7)
    fig.suptitle(f"{sc}: error vs rate (mean ± std over seeds; dashed: single-frame Cramér–Rao bound, "
                 f"centroid-level; dotted: pixel-level)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _log_errorbar(ax, x, m, s, colour: str, label: str) -> None:
    """Means with std bars on a logarithmic axis, drawn honestly: a bar never reaches below zero (its
    lower arm stops at a tenth of the mean), and a mean of zero, which a log axis
    cannot place, is a hollow triangle on the axis' floor with the label "0"."""
    pos = m > 0
    lower = np.where(s < m, s, 0.9 * m)
    ax.errorbar(x[pos], m[pos], yerr=[lower[pos], s[pos]], marker="o", ms=3, capsize=2, color=colour, label=label)
    if (~pos).any():
        floor = ax.get_xaxis_transform()  # x in data, y in axes fraction
        ax.scatter(x[~pos], np.zeros((~pos).sum()) + 0.02, marker="v", facecolors="none", edgecolors=colour,
                   transform=floor, clip_on=False, zorder=3)
        for xi in x[~pos]:
            ax.annotate("0", (xi, 0.02), xycoords=floor, xytext=(4, 0), textcoords="offset points", fontsize=7,
                        color=colour)


def _update_rate_figure(rows: list[dict], pipelines: list[str], colours: dict, path: Path) -> None:
    """Attitude updates per second against the attitude error, one marker per (variant, pipeline)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for p in pipelines:
        pts = []
        for r in rows:
            if r["pipeline"] != p:
                continue
            e = [_m(r, f"attitude_error_arcsec.{a}_rmse")[0] for a in AXES]
            u = _m(r, "update_rate_hz")[0]
            if u is not None and all(v is not None for v in e):
                pts.append((u, float(np.sqrt(np.mean(np.square(e))))))
        if pts:
            ax.scatter(*zip(*pts), color=colours[p], label=p, s=18)
    ax.set_xlabel("attitude updates per second")
    ax.set_ylabel("attitude error, RMS of x/y/z RMSE (arcsec)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title("update rate vs accuracy (one point per scenario variant)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _cpu_time_figure(rows: list[dict], pipelines: list[str], colours: dict, path: Path) -> None:
    """CPU time per frame of the run stage, per pipeline and scenario (bars)."""
    plt = _pyplot()
    scen = list(dict.fromkeys(r["scenario"] for r in rows))
    fig, ax = plt.subplots(figsize=(max(6.5, 1.2 * len(scen) * max(1, len(pipelines)) * 0.4), 4.5))
    width = 0.8 / max(1, len(pipelines))
    for k, p in enumerate(pipelines):
        vals = []
        for sc in scen:
            cpu = [r["timing"]["cpu_s_per_frame"]["mean"] for r in rows
                   if r["scenario"] == sc and r["pipeline"] == p and r["timing"]["cpu_s_per_frame"]["mean"] is not None]
            vals.append(1e3 * float(np.mean(cpu)) if cpu else np.nan)
        ax.bar(np.arange(len(scen)) + k * width, vals, width, color=colours[p], label=p)
    ax.set_xticks(np.arange(len(scen)) + 0.4 - width / 2, scen, fontsize=8)
    ax.set_ylabel("CPU ms per frame (run stage, mean over variants)")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


_LEGEND = ("valid = frames with a valid attitude estimate; flagged = frames carrying a flag (a note, not a "
           "verdict), with the commonest flags and their frames per seed; CRB = single-frame Cramér–Rao bound, centroid-level "
           "(the scenario's centroid sigma taken as given); pixel CRB = the bound from the rendered pixels "
           "(image-level recordings); efficiency = RMSE / bound.")


def markdown(results: dict, images: list[tuple[str, str]], command: str) -> str:
    c = results["comparison"]
    lines = [f"# Comparison `{c['name']}`", "", c["description"], "", f"Command: `{command}`", "",
             f"Seeds: {c['seeds']}; mean ± std over seeds; {_LEGEND}", ""]
    for title, header, body in tables(results):
        lines += [f"## {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(row) + " |" for row in body]
        lines.append("")
    errors = [(r["pipeline"], r["variant"], e) for r in results["results"] for e in r["errors"]]
    if errors:
        lines += ["## Failed tasks", ""] + [f"- {p} on {v}: {e}" for p, v, e in errors] + [""]
    said = [(r["pipeline"], r["variant"], w) for r in results["results"] for w in r.get("warnings", ())]
    if said:
        lines += ["## Warnings", ""] + [f"- {p} on {v}: {w}" for p, v, w in said] + [""]
    lines += ["## Figures", ""] + [f"![{cap}]({name})" for name, cap in images]
    return "\n".join(lines) + "\n"


def html_report(results: dict, images: list[tuple[str, str]], command: str) -> str:
    c = results["comparison"]
    parts = ["<!doctype html><html><head><meta charset='utf-8'>",
             f"<title>rollingstar compare {html.escape(c['name'])}</title>",
             "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;font-size:12px}"
             "td,th{border:1px solid #ccc;padding:3px 6px;text-align:right}td:first-child,td:nth-child(2){text-align:left}"
             "img{max-width:100%}</style></head><body>",
             f"<h1>Comparison {html.escape(c['name'])}</h1><p>{html.escape(c['description'])}</p>",
             f"<p>Command: <code>{html.escape(command)}</code>; seeds {c['seeds']}; mean ± std over seeds; "
             f"{html.escape(_LEGEND)}</p>"]
    def figure(name: str, cap: str) -> str:
        return (f"<figure><img src='{html.escape(name)}' alt='{html.escape(cap)}'>"
                f"<figcaption>{html.escape(cap)}</figcaption></figure>")

    # the main figure first (errors against rate when the comparison sweeps the rate), then the tables
    lead = [im for im in images if im[0].startswith("img/error_vs_rate_")] or images[:1]
    parts += [figure(*im) for im in lead]
    for title, header, body in terminal_tables(results, columns=tables(results)[0][1] if results["results"] else ()):
        parts.append(f"<h2>{html.escape(title)}</h2><table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>")
        parts += ["<tr>" + "".join(f"<td>{html.escape(v)}</td>" for v in row) + "</tr>" for row in body]
        parts.append("</table>")
    rest = [im for im in images if im not in lead]
    if rest:
        parts.append("<h2>More figures</h2>")
        parts += [figure(*im) for im in rest]
    parts.append("</body></html>")
    return "\n".join(parts)
