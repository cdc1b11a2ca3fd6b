"""Figures of one evaluated run (``rollingstar evaluate --plots DIR``, ``rollingstar demo``).

- ``attitude_error.png``: the attitude error per camera axis against time, with the single-frame
  Cramér–Rao bounds as +-1 sigma lines (centroid level with the rate known, and with it unknown
  when the run estimated it; pixel level on image-level recordings);
- ``centroid_residuals.png``: the measured minus true star positions averaged over the cells of an
  ``CELLS x CELLS`` grid of the detector, one arrow per cell with stars (scaled, the scale drawn;
  the mean shows a systematic that the single stars' noise hides), row 0 at the top as on the image;
- ``rate_error.png``: the rate error per camera axis against time, with the bounds, when the run
  wrote rate estimates.

Each figure is written only when the run has the data it draws; a zero error draws as zero on a
linear axis (no logarithmic axes here).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from rollingstar.outputs import safe_output

_AXES = ("x", "y", "z")
CELLS = 8  # grid cells per detector side of the centroid-residual map


def pyplot():
    """matplotlib's pyplot on the Agg backend, imported on first use (a slow import that only
    figure-writing callers pay)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _bands(ax, bounds: list[tuple[dict | None, str]], axis: str, unit: str) -> None:
    for (values, label), style in zip(bounds, ("--", ":", "-.")):
        b = (values or {}).get(axis)
        if b:
            ax.axhline(b, color="k", ls=style, lw=1, label=f"{label} ±{b:.3g} {unit}")
            ax.axhline(-b, color="k", ls=style, lw=1)


def time_figure(curves: list[tuple[str, np.ndarray, np.ndarray]], bounds: list[tuple[dict | None, str]], unit: str,
                title: str, axes_words: dict):
    """Errors per camera axis against time, one panel per axis: ``curves`` of ``(label, t (n,), error
    (n, 3))``, each labelled with its RMSE, and ``bounds`` of ``(per-axis values, label)`` as +-1
    sigma lines."""
    plt = pyplot()
    fig, axs = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for k, (ax, a) in enumerate(zip(axs, _AXES)):
        for c, (label, t, err) in enumerate(curves):
            rmse = np.sqrt(np.mean(err[:, k] ** 2))
            ax.plot(t, err[:, k], ".-", ms=3, lw=0.8, color=f"C{k if len(curves) == 1 else c}",
                    label=f"{label + ': ' if label else ''}RMSE {rmse:.3g} {unit}")
        ax.axhline(0.0, color="0.6", lw=0.6)
        _bands(ax, bounds, a, unit)
        ax.set_ylabel(f"{a} ({unit})")
        ax.set_title(axes_words.get(a, a), fontsize=9, loc="left")
        ax.legend(fontsize=8, loc="upper right")
    axs[-1].set_xlabel("time since the first truth sample (s)")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def save(fig, path: Path, inputs=()) -> Path:
    """``fig`` as a PNG at ``path``, written beside it and renamed when complete."""
    with safe_output(path, inputs) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    pyplot().close(fig)
    return path


def _cell_means(x, y, dx, dy, size: tuple[int, int]):
    """Per occupied cell of the ``CELLS x CELLS`` grid: centre x, y, mean dx, dy and the star count."""
    w, h = size
    i = np.clip((x / w * CELLS).astype(int), 0, CELLS - 1)
    j = np.clip((y / h * CELLS).astype(int), 0, CELLS - 1)
    cell = j * CELLS + i
    n = np.bincount(cell, minlength=CELLS * CELLS)
    occupied = np.flatnonzero(n)
    mean = [np.bincount(cell, weights=v, minlength=CELLS * CELLS)[occupied] / n[occupied] for v in (x, y, dx, dy)]
    return (*mean, n[occupied])


def _quiver_figure(x, y, dx, dy, size: tuple[int, int], title: str):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 6.5))
    cx, cy, mx, my, n = _cell_means(x, y, dx, dy, size)
    norm = np.hypot(mx, my)
    scale_px = float(np.max(norm)) if norm.size and np.max(norm) > 0 else 1.0
    gain = 0.6 * (max(size) / CELLS) / scale_px  # the largest mean draws 60 % of a cell long
    q = ax.quiver(cx, cy, mx * gain, my * gain, norm, angles="xy", scale_units="xy", scale=1, cmap="viridis",
                  width=0.004)
    for xc, yc, k in zip(cx, cy, n):
        ax.annotate(str(k), (xc, yc), fontsize=6, color="0.5", ha="center", va="top", xytext=(0, -3),
                    textcoords="offset points")
    fig.colorbar(q, ax=ax, label="|mean error| in the cell (px)")
    ax.quiverkey(q, 0.85, -0.11, scale_px * gain, f"{scale_px:.2g} px", labelpos="E", coordinates="axes")
    ax.set_xlim(-0.5, size[0] - 0.5)
    ax.set_ylim(size[1] - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x = column (px)")
    ax.set_ylabel("y = row (px)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def evaluation_plots(metrics: dict, out_dir: str | Path, detector_size: tuple[int, int],
                     label: str = "", inputs=()) -> list[Path]:
    """Write the figures of ``metrics`` (an :func:`~rollingstar.pipelines.evaluate.evaluate_log`
    result made with ``series=True``) into ``out_dir``; returns the paths written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    s = metrics["series"]
    axes_words = metrics.get("axes", {})
    written = []
    if len(s["attitude_t_s"]):
        bounds = [(metrics.get("attitude_crb_arcsec"), "centroid-level bound"),
                  (metrics.get("pixel_crb_arcsec"), "pixel-level bound")]
        if len(s["rate_t_s"]):  # the run estimated the rate: the bound that holds it unknown too
            bounds.insert(1, (metrics.get("attitude_crb_rate_unknown_arcsec"), "centroid-level bound, rate unknown"))
        fig = time_figure([("", s["attitude_t_s"], s["attitude_error_arcsec"])], bounds, "arcsec",
                          f"{label} attitude error (estimate vs truth)".strip(), axes_words)
        written.append(save(fig, out_dir / "attitude_error.png", inputs))
    x, y, dx, dy = s["centroid"]
    if len(x):
        rms = float(np.sqrt(np.mean(dx**2 + dy**2)))
        fig = _quiver_figure(x, y, dx, dy, detector_size,
                             f"{label} centroid error (measured - true), mean per cell (grey: stars in it)\n"
                             f"{len(x)} stars, RMS {rms:.3g} px".strip())
        written.append(save(fig, out_dir / "centroid_residuals.png", inputs))
    if len(s["rate_t_s"]):
        fig = time_figure([("", s["rate_t_s"], s["rate_error_deg_s"])],
                          [(metrics.get("rate_crb_deg_s"), "centroid-level bound"),
                           (metrics.get("pixel_rate_crb_deg_s"), "pixel-level bound")], "deg/s",
                          f"{label} rate error (estimate vs truth)".strip(), axes_words)
        written.append(save(fig, out_dir / "rate_error.png", inputs))
    return written
