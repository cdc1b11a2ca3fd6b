"""Step 4, verify: the fit improves, on data it never saw too, and the claims that follow.

Residual RMS and chi2/dof before and after on training and held-out data, the held-out residual
distribution, the gyro channel, a re-simulation with the input and the updated model
(:mod:`.resimulate`). Held-out data the final model leaves far outside a known noise count as an
unexplained mismatch. A model that does not lower the held-out chi-square is not named: its
effects become weak candidates. Every named effect carries its parameters, nonlinear drop-one
delta BIC, bootstrap inclusion, aliases and a confidence; the verdict says it in one sentence.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from rollingstar.estimators.diagnosis import gyro_channel, residuals, resimulate
from rollingstar.estimators.diagnosis.inputs import DiagnoseOptions, SensorModel
from rollingstar.estimators.diagnosis.library import Candidate, separating_experiment
from rollingstar.estimators.diagnosis.locating import Dataset, Location
from rollingstar.estimators.diagnosis.modelling import CHI2_Z_LIMIT, EffectModel, known_noise
from rollingstar.estimators.diagnosis.naming import Naming
from rollingstar.estimators.diagnosis.observations import Observations, Prediction, star_chi2, whitened_residuals

TIME_EFFECT_EXPERIMENT = ("a recording in which the tracker turns (constant rate, rate reversal): "
                          "time effects move stars only with motion")


@dataclass(frozen=True)
class BeforeAfter:
    """One statistic under the model as given (``before``) and with the named effects (``after``)."""

    before: float | None
    after: float | None


@dataclass(frozen=True, eq=False)
class FitQuality:
    """How well the model fits before and after the named effects, on training and held-out data."""

    train_rms_px: BeforeAfter  # residual RMS per axis
    heldout_rms_px: BeforeAfter
    train_chi2_dof: BeforeAfter
    heldout_chi2_dof: BeforeAfter
    heldout_distribution: dict | None  # Kolmogorov-Smirnov of held-out residuals / sigma against N(0, 1)
    gyro: dict | None  # the increment channel's chi2/dof before and after (training and held-out pairs)
    resimulation: dict | None  # :func:`.resimulate.resimulation_check`


@dataclass(frozen=True, eq=False)
class Verification:
    """The checks and the claims: what is named, what is ambiguous or weak, and the verdict."""

    quality: FitQuality
    evidence: list[dict]  # significant structure the final model leaves (training and held-out)
    heldout_confirms: bool  # the model lowers the held-out chi-square (image rows and gyro pairs)
    mismatch: bool
    effects: list[dict]  # the named effects: parameters, delta BIC, inclusion, aliases, confidence
    ambiguous: list[dict]  # pairs of candidates the data cannot tell apart, with the experiment that would
    absorbed: list[dict]  # candidates the per-frame attitude absorbs, with the experiment that would show them
    weak: list[dict]  # selected but not named (weak support, or no held-out improvement)
    rejected_on_heldout: list[str]
    named: list[Candidate]  # the effects the updated scenario enables
    thetas: list[np.ndarray]  # their parameters
    verdict: str
    isolated: np.ndarray  # held-out stars the final model misses alone, left out of the held-out test

    @property
    def unexplained(self) -> bool:
        return bool(self.evidence)


def verify(location: Location, naming: Naming, model: EffectModel, sensor: SensorModel, cands: dict[str, Candidate],
           options: DiagnoseOptions) -> Verification:
    """Held-out checks, the named effects' report rows, rejection without held-out improvement, verdict."""
    data = location.data
    isolated = isolated_misfits(data.obs, model.prediction, data.heldout)
    evidence = [*model.leftover_evidence, *heldout_evidence(data, model.prediction, isolated)]
    unexplained = bool(evidence)
    quality = fit_quality(location, model, sensor, options)
    confirms = heldout_confirms(data, quality)
    effects = [effect_row(c, th, sg, naming, model, unexplained, confirms)
               for c, th, sg in zip(model.chosen, model.fit["thetas"], model.fit["sigmas"])]
    ambiguous = ambiguity_rows(naming, cands)
    absorbed = absorbed_rows(naming, sensor, cands)
    mismatch, weak, named, thetas, rejected = bool(model.chosen) or unexplained, naming.weak, model.chosen, model.thetas, []
    if not confirms and effects:
        # a claim must hold up on data the fit never saw: a model that does not lower the held-out
        # chi-square is not named (its effects become weak candidates; the "after" numbers describe
        # that rejected model, and the updated scenario leaves it out)
        rejected = [e["name"] for e in effects]
        weak = [*weak, *({"name": e["name"], "delta_bic_nonlinear": e["delta_bic"],
                          "inclusion_probability": e["inclusion_probability"],
                          "inclusion_with_aliases": e.get("inclusion_with_aliases"),
                          "reason": "no held-out improvement", "params": e["params"]} for e in effects)]
        effects, ambiguous, mismatch, named, thetas = [], [], unexplained, [], []
    text = verdict(mismatch, [e["name"] for e in effects], ambiguous, evidence, rejected,
                   location.residuals["chi2_dof"], int(data.train.sum()))
    return Verification(quality, evidence, confirms, mismatch, effects, ambiguous, absorbed, weak, rejected,
                        named, thetas, text, isolated)


ISOLATED_P = 0.01  # family-wise chance that a noise draw among a set's stars is taken for an isolated misfit
MAX_ISOLATED_FRACTION = 0.01  # of a set's stars: more misfits than this (and than one) are a pattern


def isolated_misfits(obs: Observations, pred: Prediction, mask: np.ndarray) -> np.ndarray:
    """The stars of ``mask`` that alone contradict the noise model, when they are few: a star's
    chi-square (2 dof) beyond the Bonferroni level ``ISOLATED_P / n`` over the ``n`` stars, and at
    most ``max(1, MAX_ISOLATED_FRACTION n)`` such stars (a detector-edge or blended star, a hot
    pixel next to a star). More are not isolated: they are left in, as part of a pattern."""
    mask = np.asarray(mask, dtype=bool)
    n = int(mask.sum())
    if n == 0:
        return np.zeros(obs.n, dtype=bool)
    level = -2.0 * np.log(ISOLATED_P / n)  # chi2 with 2 dof: P(> c) = exp(-c / 2)
    out = mask & (star_chi2(obs, pred) > level)
    return out if out.sum() <= max(1, int(MAX_ISOLATED_FRACTION * n)) else np.zeros(obs.n, dtype=bool)


def heldout_evidence(data: Dataset, pred: Prediction, isolated: np.ndarray) -> list[dict]:
    """Held-out data the final model leaves far outside a known noise: a mismatch even when the
    training data show nothing (e.g. the only frames that could show an effect were held out).
    ``isolated``: the held-out stars :func:`isolated_misfits` finds, left out of the test (one star
    is not a systematic; the report lists them)."""
    out = []
    heldout = data.heldout & ~isolated
    for label, chi2, dof in heldout_chi2(data.obs, pred, heldout, data.heldout_frames_fitted, data.channel_heldout):
        scale = data.obs.noise_sigma_ln if label == "image" else 0.0  # the gyro rows' noise is the gyro's
        z = residuals.chi2_z(chi2, dof, scale) if dof > 0 else 0.0
        if known_noise(data) and z > CHI2_Z_LIMIT:
            out.append({"basis": f"held-out chi-square ({label})", "delta_chi2": chi2 - dof, "dof": dof,
                        "z": float(z), "significant": True})
    return out


def fit_quality(location: Location, model: EffectModel, sensor: SensorModel, options: DiagnoseOptions) -> FitQuality:
    """RMS and chi2/dof before and after, the held-out residual distribution, gyro channel, re-simulation."""
    data, pred0, pred1 = location.data, location.prediction, model.prediction
    obs, train, heldout = data.obs, data.train, data.heldout
    resim = resimulate.resimulation_check(
        obs, {"before": (sensor.effects, location.nuisance, pred0), "after": (model.effects, model.nuisance, pred1)},
        sensor.camera, sensor.timing, data.att_mask, sensor.moving, options.seed) if options.resimulate else None
    return FitQuality(
        train_rms_px=BeforeAfter(rms_px(obs, pred0, train), rms_px(obs, pred1, train)),
        heldout_rms_px=BeforeAfter(rms_px(obs, pred0, heldout), rms_px(obs, pred1, heldout)),
        train_chi2_dof=BeforeAfter(chi2_dof(obs, pred0, train, data.n_train_frames),
                                   chi2_dof(obs, pred1, train, data.n_train_frames)),
        heldout_chi2_dof=BeforeAfter(chi2_dof(obs, pred0, heldout, data.heldout_frames_fitted),
                                     chi2_dof(obs, pred1, heldout, data.heldout_frames_fitted)),
        heldout_distribution=heldout_distribution(obs, pred0, pred1, heldout),
        gyro=gyro_fit(data, location, pred1),
        resimulation=resim)


def gyro_fit(data: Dataset, location: Location, pred1: Prediction) -> dict | None:
    """Chi2/dof of the gyro increment rows before and after, training and held-out pairs; None without a gyro."""
    obs, chan, chan_out, pred0 = data.obs, data.obs.channel, data.channel_heldout, location.prediction
    if chan is None:
        return None

    def heldout_chi2_dof(p):
        return None if chan_out is None else float(np.sum(chan_out.residual(
            p.nuisance.attitude, obs.t_ref_ns, p.effects) ** 2)) / chan_out.rows

    return {"pairs": int(chan.pairs.size), "rows": chan.rows, "arw_rad_sqrt_s": chan.gyro.arw_rad_sqrt_s,
            "chi2_dof_before": location.gyro_chi2 / chan.rows,
            "chi2_dof_after": float(np.sum(gyro_channel.channel_rows(obs, pred1) ** 2)) / chan.rows,
            "heldout_pairs": 0 if chan_out is None else int(chan_out.pairs.size),
            "heldout_chi2_dof_before": heldout_chi2_dof(pred0),
            "heldout_chi2_dof_after": heldout_chi2_dof(pred1)}


def heldout_confirms(data: Dataset, quality: FitQuality) -> bool:
    """Whether the held-out chi-square (image rows and gyro pairs touching a held-out frame) drops."""
    hb, ha = quality.heldout_chi2_dof.before, quality.heldout_chi2_dof.after
    if hb is not None and ha is not None:  # chi-square sums over held-out image rows and gyro pairs
        n_img = max(2 * int(data.heldout.sum()) - 3 * data.heldout_frames_fitted, 1)
        hb, ha = hb * n_img, ha * n_img
        g = quality.gyro
        if g is not None and g["heldout_chi2_dof_before"] is not None:
            hb += g["heldout_chi2_dof_before"] * 3 * g["heldout_pairs"]
            ha += g["heldout_chi2_dof_after"] * 3 * g["heldout_pairs"]
    return bool(hb is None or ha is None or ha < hb)


def effect_row(c: Candidate, theta: np.ndarray, sigma: np.ndarray, naming: Naming, model: EffectModel,
               unexplained: bool, confirms: bool) -> dict:
    """The report of one named effect: parameters with sigmas, the evidence for it, its confidence."""
    params = {p.name: {"value": float(v), "sigma": float(s), "unit": p.unit} for p, v, s in zip(c.parameters, theta, sigma)}
    checked = [{"name": h, "corr": float(v)}
               for h, v in sorted(naming.correlations.get(c.name, {}).items(), key=lambda kv: -kv[1])]
    unstable = [s for s in model.stability if s["effect"] == c.name and s["stable"] is False]
    at_bound = [p.name for p, v in zip(c.parameters, theta) if v <= p.bounds[0] + 1e-9 * (p.bounds[1] - p.bounds[0])
                or v >= p.bounds[1] - 1e-9 * (p.bounds[1] - p.bounds[0])]
    origin = _pixel_origin(c, theta)
    doubts = [why for why, flag in (("residual structure left", unexplained),
                                    ("unstable across subsets", bool(unstable)),
                                    ("parameter at its bound", bool(at_bound)),
                                    ("no held-out improvement", not confirms),
                                    (origin, origin is not None)) if flag]
    return {"name": c.name, "params": params, "delta_bic": naming.delta_bic.get(c.name),
            "delta_bic_method": naming.delta_bic_method.get(c.name),
            "inclusion_probability": naming.selection["inclusion"].get(c.name),
            "inclusion_with_aliases": naming.pooled_inclusion.get(c.name), "aliases_checked": checked,
            "declared_aliases": [getattr(a, "other", str(a)) for a in c.aliases],
            "explanation": c.explanation, "stable": not unstable, "at_bound": at_bound,
            "confidence": "tentative" if doubts else "confident",
            "tentative_because": doubts}


# pixel-origin conventions a recording written elsewhere may use instead of docs/conventions.md's
# (x, y from 0 at the first pixel's centre): counted from 1, or from the first pixel's corner
PIXEL_ORIGINS = {(1.0, 1.0): "x, y counted from 1",
                 (-1.0, -1.0): "1 subtracted from x, y already counted from 0",
                 (0.5, 0.5): "x, y from the first pixel's corner, pixel centres at k + 0.5",
                 (-0.5, -0.5): "half a pixel subtracted from x, y already at the pixel centres"}


def _pixel_origin(c: Candidate, theta: np.ndarray) -> str | None:
    """The doubt that a principal-point shift is a pixel-origin convention: both offsets within 0.1 px
    of one of ``PIXEL_ORIGINS`` (a lens centred to a tenth of a pixel on a convention's value is
    far less likely than the convention)."""
    if c.name != "principal_point" or len(theta) != 2:
        return None
    for target, what in PIXEL_ORIGINS.items():
        if np.all(np.abs(np.asarray(theta, dtype=float) - target) <= 0.1):
            return (f"equal to a pixel-origin shift of ({target[0]:+g}, {target[1]:+g}) px ({what}; "
                    "docs/conventions.md counts from 0 at the first pixel's centre)")
    return None


def ambiguity_rows(naming: Naming, cands: dict[str, Candidate]) -> list[dict]:
    """Each unordered pair of candidates the data cannot tell apart once, with the separating experiment."""
    seen, rows = set(), []
    for a in naming.ambiguous:
        key = tuple(sorted((a["selected"], a["alternative"])))
        if key in seen:
            continue
        seen.add(key)
        rows.append({"candidates": list(key), "corr": a["corr"], "delta_bic_swap": a["delta_bic_swap"],
                     "separating_experiment": separating_experiment(cands[key[0]], cands[key[1]])})
    return rows


def absorbed_rows(naming: Naming, sensor: SensorModel, cands: dict[str, Candidate]) -> list[dict]:
    """Candidates the per-frame attitude absorbs, each with the experiment that would show it."""
    rows = []
    for name in naming.problem.absorbed:
        c = cands[name]
        declared = c.alias_of("attitude") or c.alias_of("rate")
        if declared is None and "time" in c.channels and not sensor.moving:
            text = TIME_EFFECT_EXPERIMENT
        else:
            text = separating_experiment(c, "attitude")
        rows.append({"name": name, "separating_experiment": text})
    return rows


def verdict(mismatch: bool, names: list[str], ambiguous: list[dict], evidence: list[dict], rejected: list[str],
            chi2_dof_before: float, n_train: int) -> str:
    """One sentence: no mismatch, or what is named, what cannot be told apart and what is left."""
    note = f"; not named, no held-out improvement: {', '.join(rejected)}" if rejected else ""
    if not mismatch:
        return ("no mismatch: the simulation explains the recording within its noise "
                f"(chi2/dof {chi2_dof_before:.3f} over {n_train} training stars){note}")
    parts = [note[2:]] if note else []
    if names:
        parts.append("named: " + ", ".join(names))
    for a in ambiguous:
        parts.append(f"cannot tell {a['candidates'][0]} from {a['candidates'][1]} (separate them with: {a['separating_experiment']})")
    if evidence:
        parts.append("unexplained systematic left (" + ", ".join(f"{e['basis']} z={e['z']:.1f}" for e in evidence) + ")")
    return "; ".join(parts)


def heldout_distribution(obs: Observations, pred0: Prediction, pred1: Prediction, m: np.ndarray) -> dict | None:
    """Kolmogorov-Smirnov test of the held-out residuals / sigma against N(0, 1), before and after.

    (The attitude of held-out frames is fitted to their own stars, which narrows the distribution
    slightly: 3 of 2 n dof per frame; the comparison before/after is what matters.)
    """
    if m.sum() < 5:
        return None
    out = {}
    for key, p in (("before", pred0), ("after", pred1)):
        w = whitened_residuals(obs, p)
        r = np.concatenate([w[m, 0], w[m, 1]])
        ks = stats.kstest(r, "norm")
        out[key] = {"ks_statistic": float(ks.statistic), "p_value": float(ks.pvalue), "std": float(np.std(r))}
    return out


def heldout_chi2(obs: Observations, pred: Prediction, heldout: np.ndarray, frames_fitted: int,
                 chan_out: gyro_channel.GyroChannel | None) -> list[tuple[str, float, int]]:
    """Chi-square and dof of the held-out data under ``pred``: image rows, and gyro pairs touching
    a held-out frame (when the recording has a gyro)."""
    out = []
    if heldout.any():
        c = float(np.sum(star_chi2(obs, pred)[heldout]))
        out.append(("image", c, int(2 * heldout.sum() - 3 * frames_fitted)))
    if chan_out is not None:
        e = chan_out.residual(pred.nuisance.attitude, obs.t_ref_ns, pred.effects)
        out.append(("gyro increments", float(e @ e), chan_out.rows))
    return out


def rms_px(obs: Observations, pred: Prediction, m: np.ndarray) -> float | None:
    """Residual RMS per axis (px) of the observations in ``m``; None when there are none."""
    if not m.any():
        return None
    return float(np.sqrt(np.mean(((obs.x - pred.x)[m] ** 2 + (obs.y - pred.y)[m] ** 2) / 2)))


def chi2_dof(obs: Observations, pred: Prediction, m: np.ndarray, frames_fitted: int) -> float | None:
    """Chi-square per degree of freedom of the observations in ``m`` (3 dof per fitted attitude)."""
    if not m.any():
        return None
    c = np.sum(star_chi2(obs, pred)[m])
    return float(c / max(2 * m.sum() - 3 * frames_fitted, 1))
