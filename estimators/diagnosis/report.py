"""The diagnosis report for people: ``index.html`` with PNG plots, plus ``result.json``.

Plots (matplotlib, Agg): residual quiver maps before and after the fit (training stars, arrows
scaled so that the median before-fit residual is a tenth of the detector), residual against the
covariate that exposed the mismatch (binned means with 1-sigma bars, before and after), and the
held-out improvement (RMS and chi2/dof before/after, training vs held-out).
"""
from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from rollingstar.estimators.diagnosis.algorithm import Diagnosis
from rollingstar.estimators.diagnosis.residuals import (
    binned_structure,
    channels,
    covariates,
)


def _mpl():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _before_after(d: Diagnosis):
    """(label, prediction, colour) of the model as given and of the model with the named effects."""
    return (("before", d.location.prediction, "C0"), ("after", d.model.prediction, "C2"))


def quiver_maps(d: Diagnosis, path: Path) -> None:
    plt = _mpl()
    obs, cam, m = d.obs, d.sensor.camera, d.location.data.train
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.2), sharex=True, sharey=True)
    before = d.location.prediction
    r_before = np.hypot((obs.x - before.x)[m], (obs.y - before.y)[m])
    scale = max(np.median(r_before), 1e-9) / (0.1 * cam.width)  # px of residual per px of plot
    titles = ("before (simulation as given)", "after (selected effects)")
    for ax, title, (_, p, color) in zip(axes, titles, _before_after(d)):
        dx, dy = (obs.x - p.x)[m], (obs.y - p.y)[m]
        ax.quiver(p.x[m], p.y[m], dx, dy, angles="xy", scale_units="xy", scale=scale, width=0.002, color=color)
        rms = np.sqrt(np.mean((dx**2 + dy**2) / 2))
        ax.set_title(f"{title}\nRMS {rms:.4f} px per axis")
        ax.set_xlim(-0.5, cam.width - 0.5)
        ax.set_ylim(cam.height - 0.5, -0.5)
        ax.set_aspect("equal")
        ax.set_xlabel("x (column, px)")
    axes[0].set_ylabel("y (row, px)")
    fig.suptitle(f"training residuals (arrow of {np.median(r_before):.3g} px drawn as {0.1 * cam.width:.0f} px)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def covariate_plot(d: Diagnosis, path: Path) -> str | None:
    loc = d.location.residuals
    top = loc["_structure_full"][0] if loc["_structure_full"] else None
    if top is None:
        return None
    plt = _mpl()
    obs, cam, m = d.obs, d.sensor.camera, d.location.data.train
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for label, p, color in _before_after(d):
        cov = covariates(obs, p, cam)[top["covariate"]]
        ch = channels(obs, p, cam)[top["channel"]]
        s = binned_structure(cov[m], ch[m])
        if s["bin_centres"]:
            ax.errorbar(s["bin_centres"], s["bin_means"], yerr=s["bin_sigma"], fmt="o-", color=color,
                        label=f"{label} (structure z = {s['z']:.1f})", capsize=3)
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xlabel(top["covariate"])
    ax.set_ylabel(f"{top['channel']} residual / sigma (bin mean)")
    ax.set_title("residual vs the covariate that exposed the mismatch")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return top["covariate"]


def heldout_plot(result: dict, path: Path) -> None:
    plt = _mpl()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.8))
    labels = ["training", "held-out"]
    for ax, keys, ylabel in ((axes[0], ("train_rms", "heldout_rms"), "residual RMS per axis (px)"),
                             (axes[1], ("train_chi2_dof", "heldout_chi2_dof"), "chi2 / dof")):
        suffix = "_px" if ylabel.startswith("residual") else ""
        before = [result.get(f"{k}_before{suffix}") or np.nan for k in keys]
        after = [result.get(f"{k}_after{suffix}") or np.nan for k in keys]
        xs = np.arange(2)
        ax.bar(xs - 0.18, before, 0.36, label="before", color="C0")
        ax.bar(xs + 0.18, after, 0.36, label="after", color="C2")
        ax.set_xticks(xs, labels)
        ax.set_ylabel(ylabel)
        if suffix == "":
            ax.axhline(1.0, color="k", lw=0.8, ls="--")
    axes[0].legend()
    fig.suptitle("held-out improvement (effect parameters fitted on training data only)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _reference_section(ref: dict | None) -> list[str]:
    """The candidates tested against the reference attitude: each alone, then the joint model."""
    if not ref:
        return []
    joint = {m["name"]: m["params"] for m in ref["model"]}
    rows = [[c["name"], pn, _f(pv["value"]), _f(pv["sigma"]), pv["unit"], _f(c["delta_bic"]), c["within_bounds"],
             c["tested"], _f(joint[c["name"]][pn]["value"]) if c["name"] in joint else "not in it"]
            for c in ref["candidates"] for pn, pv in c["params"].items()]
    head = (f"<p>Against the reference attitude ({_f(ref['sigma_arcsec'])} arcsec per axis, {ref['frames']} frames): "
            f"chi2 {_f(ref['chi2'])} over {ref['dof']} dof without an effect, {_f(ref['chi2_after'])} over "
            f"{ref['dof_after']} with the joint model.</p>")
    out = [head, _table(rows, ["effect", "parameter", "value alone", "sigma alone", "unit", "delta BIC alone",
                               "within bounds", "tested", "value in the joint model"])]
    if ref["ambiguous"]:
        out.append(_table([[" / ".join(a["candidates"]), _f(a["corr"]), _f(a["delta_bic_swap"]), a["separating_experiment"]]
                           for a in ref["ambiguous"]], ["the reference cannot tell apart", "|corr|", "delta BIC swap",
                                                        "separating experiment"]))
    return out


def _table(rows: list[list], head: list[str]) -> str:
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_cell(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def _cell(v) -> str:
    """A table cell a reader can read: numbers rounded, no bare None/True/False, mappings as
    ``key value`` pairs instead of JSON."""
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return _f(v)
    if isinstance(v, dict):
        return ", ".join(f"{k.replace('_', ' ')} {_cell(x)}" for k, x in v.items())
    if isinstance(v, (list, tuple)):
        return ", ".join(_cell(x) for x in v)
    return str(v)


def _f(v, fmt="{:.4g}"):
    return "n/a" if v is None else fmt.format(v)


def _model_section(result: dict) -> list[str]:
    """Step 3 of the report: what is left after the named model (catch-all tests, the described
    shape, the noise check), stability and the updated scenario."""
    out = []
    out.append("<h2>3. Model</h2>")
    ue = result["unexplained_systematic"]
    out.append(_table([[t["basis"], _f(t["delta_chi2"]), t["dof"], _f(t["z"]), t["significant"]] for t in ue["tests"]],
                        ["generic basis on the residual left", "delta chi2", "dof", "z", "significant"]))
    desc = ue.get("description")
    if desc:
        out.append(f"<p><b>Outside the library:</b> {html.escape(desc['text'])}"
                     + (" Written to the updated scenario as an empirical correction." if desc.get("correction") else "") + "</p>")
        out.append(_table([[a["shape"], a.get("axis", ""), a.get("coordinate", ""), _f(a["bic"]), _f(a["z"])]
                             for a in desc["alternatives"]], ["shape tried (best of its kind)", "axis", "along", "BIC", "z"]))
    noise = result.get("noise_check")
    if noise:
        out.append(f"<p><b>Noise:</b> measured {_f(noise['factor'], '{:.3f}')} ± {_f(noise['factor_sigma'], '{:.3f}')} x the "
                     f"stated ({html.escape(noise['stated_source'])}, {noise['pairs']} star pairs in consecutive frames)"
                     + ("; applied." if noise["applied"] else "; consistent with the stated noise, not applied.") + "</p>")
    if result["stability"]:
        out.append(_table([[s["subset"], s["effect"], s["param"], _f(s["a"]), _f(s["sigma_a"]), _f(s["b"]), _f(s["sigma_b"]), _f(s["z"])]
                             for s in result["stability"]], ["subsets", "effect", "param", "a", "sigma a", "b", "sigma b", "z"]))
    if result.get("scenario_updated"):
        out.append(f"<p>Updated scenario: <code>{html.escape(Path(result['scenario_updated']).name)}</code></p>")
    return out


def write_report(result: dict, d: Diagnosis, out_dir: Path) -> Path:
    """Write ``index.html``, ``result.json`` (``result``: :func:`.algorithm.as_json` of ``d``) and
    the PNGs into ``out_dir``; returns the HTML path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    quiver_maps(d, out_dir / "residual_quiver.png")
    cov = covariate_plot(d, out_dir / "residual_vs_covariate.png")
    heldout_plot(result, out_dir / "heldout_improvement.png")
    (out_dir / "result.json").write_text(json.dumps(result, indent=2))
    loc = result["located"]
    parts = [f"<h1>rollingstar diagnose</h1><p><b>recording</b> {html.escape(result['recording'])}<br>"
             f"<b>simulation</b> {html.escape(str(result['sim']))}</p>",
             f"<h2>Verdict</h2><p>{html.escape(result['summary'])}</p><p><i>In one line:</i> {html.escape(result['verdict'])}</p>",
             "<h2>1. Locate</h2>",
             _table([["chi2 / dof (training)", _f(loc["chi2_dof"])], ["z of chi2 against the noise", _f(loc["z"])],
                     ["noise sigma (px)", f"{_f(result['noise']['sigma_px_median'])} ({result['noise']['source']})"],
                     ["strongest covariate", f"{loc['strongest_covariate']} ({loc['strongest_channel']}, z = {_f(loc['strongest_z'])})"],
                     ["worst field region (3x3)", loc["worst_region"]],
                     ["worst time span", loc["worst_time_span"]]], ["quantity", "value"]),
             _table([[s["covariate"], s["channel"], _f(s["chi2"]), s["dof"], _f(s["z"])] for s in loc["structure"]],
                    ["covariate", "channel", "chi2", "dof", "z"]),
             "<h2>2. Name</h2>",
             _table([[s["name"], _f(s["delta_bic"])] for s in result["screen"]], ["effect (alone)", "delta BIC"]),
             ]
    if result["effects"]:
        rows = []
        for e in result["effects"]:
            for pn, pv in e["params"].items():
                rows.append([e["name"], pn, _f(pv["value"]), _f(pv["sigma"]), pv["unit"], _f(e["delta_bic"]),
                             _f(e["inclusion_probability"]), e["confidence"]])
        parts.append(_table(rows, ["effect", "parameter", "value", "sigma", "unit", "delta BIC", "inclusion", "confidence"]))
        for e in result["effects"]:
            parts.append(f"<p><b>{html.escape(e['name'])}</b>: {html.escape(e['explanation'])}</p>")
    else:
        parts.append("<p>No effect improves BIC by the required margin.</p>")
    if result["ambiguous"]:
        parts.append(_table([[" / ".join(a["candidates"]), _f(a["corr"]), _f(a["delta_bic_swap"]), a["separating_experiment"]]
                             for a in result["ambiguous"]], ["cannot tell apart", "|corr|", "delta BIC swap", "separating experiment"]))
    if result["absorbed_by_attitude"] or result["not_testable"]:
        parts.append(_table([[a["name"], "absorbed by the per-frame attitude", a["separating_experiment"]] for a in result["absorbed_by_attitude"]]
                            + [[a["name"], "not testable", a["reason"]] for a in result["not_testable"]], ["effect", "status", "why / what would show it"]))
    parts += _reference_section(result.get("attitude_reference"))
    parts += _model_section(result)
    parts.append("<h2>4. The fit improves</h2>")
    parts.append(_table([["training", _f(result["train_rms_before_px"]), _f(result["train_rms_after_px"]),
                          _f(result["train_chi2_dof_before"]), _f(result["train_chi2_dof_after"])],
                         ["held-out", _f(result["heldout_rms_before_px"]), _f(result["heldout_rms_after_px"]),
                          _f(result["heldout_chi2_dof_before"]), _f(result["heldout_chi2_dof_after"])]],
                        ["data", "RMS before (px)", "RMS after (px)", "chi2/dof before", "chi2/dof after"]))
    rs = result.get("resimulation")
    if rs:
        parts.append(f"<p>Re-simulation ({html.escape(rs['method'])}; seed {rs['seed']}): recording vs re-simulated "
                     "normalised residuals under each model.</p>")
        parts.append(_table([[k, _f(rs[k]["rms_recording"]), _f(rs[k]["rms_resimulated"]), _f(rs[k]["ks_statistic"]),
                              _f(rs[k]["ks_p_value"]), _f(rs[k]["ad_statistic"]), _f(rs[k]["ad_p_value"])]
                             for k in ("before", "after") if k in rs],
                            ["model", "RMS recording (sigma)", "RMS re-simulated (sigma)", "KS D", "KS p", "AD", "AD p"]))
    parts.append('<img src="residual_quiver.png" alt="residual quiver maps before and after">')
    if cov:
        parts.append('<img src="residual_vs_covariate.png" alt="residual against the covariate">')
    parts.append('<img src="heldout_improvement.png" alt="held-out improvement">')
    style = "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse;margin:8px 0}" \
            "td,th{border:1px solid #ccc;padding:3px 6px;font-size:13px}img{max-width:100%}</style>"
    page = f"<!doctype html><html><head><meta charset='utf-8'><title>diagnose</title>{style}</head><body>{''.join(parts)}</body></html>"
    path = out_dir / "index.html"
    path.write_text(page)
    return path
