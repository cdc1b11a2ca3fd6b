"""Step 2, name: which library effects the recording shows.

Forward-stepwise BIC on the linear problem at the model as given (:mod:`.selection`), refined with
the nonlinear model (:func:`select_nonlinear`: backward elimination by nonlinear delta BIC, forward
steps on the problem re-linearised at the fitted model). Then the selection statistics on the
problem linearised at the fitted model: screening, bootstrap inclusion, aliases. An effect is named
only when it wins the majority of bootstrap resamples (inclusion pooled over the candidates the
data cannot tell from it) and still earns its BIC margin nonlinearly; otherwise it is reported as
a weak candidate and the rest refitted.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from rollingstar.estimators.diagnosis import gyro_channel, selection
from rollingstar.estimators.diagnosis import refit as refit_mod
from rollingstar.estimators.diagnosis.inputs import DiagnoseOptions, SensorModel
from rollingstar.estimators.diagnosis.library import Candidate
from rollingstar.estimators.diagnosis.locating import Dataset, Location
from rollingstar.estimators.diagnosis.observations import (
    Nuisance,
    Prediction,
    fit_attitudes,
    fit_nuisance,
    star_chi2,
)
from rollingstar.estimators.diagnosis.signatures import linear_problem

MIN_INCLUSION = 0.5
MAX_ROUNDS = 3  # rounds of nonlinear backward / linear forward refinement
WALD_SLACK = 4.0  # an effect whose Wald delta BIC is this many times the margin is kept without a refit


@dataclass(frozen=True, eq=False)
class NonlinearFit:
    """Named effects refitted nonlinearly (:func:`refit.refit`), with the attitudes and rates
    refitted under the resulting effect chain."""

    names: list[str]
    chosen: list[Candidate]
    fit: dict  # :func:`refit.refit`: thetas, sigmas, corr, nuisance, success, cost
    effects: tuple  # the scenario's chain with the named effects at their fitted parameters
    nuisance: Nuisance
    prediction: Prediction


@dataclass(frozen=True, eq=False)
class Naming:
    """What the Name step decided, and the statistics it decided on."""

    model: NonlinearFit  # the named effects
    rounds: list[dict]  # nonlinear refinement: ``{"dropped", "delta_bic_nonlinear"}`` or ``{"added"}``
    problem: selection.LinearProblem  # linearised at the fitted model, the selected effects added back
    selection: dict  # :func:`selection.select` on ``problem``: screen, steps, inclusion, bootstrap sets
    pooled_inclusion: dict[str, float]  # bootstrap inclusion pooled over each selected effect's aliases
    weak: list[dict]  # selected effects not named (weak bootstrap support or nonlinear delta BIC)
    delta_bic: dict[str, float]  # drop-one delta BIC of every named effect (:func:`drop_one_delta_bic`)
    ambiguous: list[dict]  # named effects the data cannot tell from another candidate
    correlations: dict[str, dict[str, float]]  # canonical correlation of each named effect with every screened one
    delta_bic_method: dict[str, str] = field(default_factory=dict)  # "refit" (nonlinear) or "wald", per effect


def name_effects(location: Location, sensor: SensorModel, cands: dict[str, Candidate],
                 options: DiagnoseOptions) -> Naming:
    """Select, refine nonlinearly, test the selection at the fitted model, drop weak effects."""
    data, nuis0 = location.data, location.nuisance
    blocks = data.blocks()
    first = selection.forward_stepwise(location.problem, options.min_delta_bic)
    refits = Refits(data, sensor, nuis0)
    model, rounds = select_nonlinear(refits, cands, [st["name"] for st in first], blocks, options)
    # the selection statistics on the problem linearised at the final model, selected effects added back
    problem, _ = linear_problem(data.obs, model.prediction, cands, model.effects, data.train, blocks,
                                add_back={c.name: (th - c.defaults) / c.scales for c, th in zip(model.chosen, model.fit["thetas"])})
    sel = selection.select(problem, n_boot=options.n_boot, seed=options.seed, min_delta_bic=options.min_delta_bic)
    drop_one, method = drop_one_delta_bic(refits, model.chosen, model.fit, options.min_delta_bic)
    pooled = pooled_inclusion(problem, sel, model.names)
    weak = [n for n in model.names if (options.n_boot > 0 and pooled[n] < MIN_INCLUSION)
            or drop_one.get(n, 0.0) < options.min_delta_bic]  # or no longer earning its place nonlinearly
    weak_rows = []
    if weak:
        weak_rows = [{"name": n, "delta_bic_nonlinear": drop_one.get(n), "inclusion_probability": sel["inclusion"].get(n),
                      "inclusion_with_aliases": pooled[n]} for n in weak]
        model = refit_named(refits, cands, [n for n in model.names if n not in weak])
        drop_one, method = drop_one_delta_bic(refits, model.chosen, model.fit, options.min_delta_bic)
    screened = [row["name"] for row in sel["screen"]]
    correlations = {g: {h: selection.canonical_correlation(selection.design(problem, [g]), selection.design(problem, [h]))
                        for h in screened if h != g} for g in model.names if g in problem.groups}
    return Naming(model, rounds, problem, sel, pooled, weak_rows, drop_one,
                  selection.ambiguities(problem, model.names, screened), correlations, method)


def pooled_inclusion(problem: selection.LinearProblem, sel: dict, names: list[str]) -> dict[str, float]:
    """Bootstrap inclusion of each selected effect pooled over the candidates the data cannot tell
    from it (those split the votes)."""
    alias_of = {n: [h for h in problem.groups if h != n and n in problem.groups
                    and selection.canonical_correlation(selection.design(problem, [n]), selection.design(problem, [h]))
                    > selection.CORR_LIMIT] for n in names}
    return {n: selection.pooled_inclusion(sel["bootstrap_sets"], n, alias_of[n]) for n in names}


class Refits:
    """The nonlinear refits of one naming, each made once.

    Within one :func:`name_effects` the data, sensor model and starting nuisance are fixed, so a
    refit is decided by the effects and the parameters it starts from. Backward elimination's last
    pass and :func:`drop_one_delta_bic` refit the same subsets from the same fit; the second asks
    here and gets the first's answer (a refit is deterministic).
    """

    def __init__(self, data: Dataset, sensor: SensorModel, nuis0: Nuisance):
        self.data, self.sensor, self.nuis0 = data, sensor, nuis0
        self.fits: dict[tuple, dict] = {}

    def __call__(self, chosen: list[Candidate], warm: dict | None = None) -> dict:
        """:func:`refit_chi2` of ``chosen`` from ``warm`` (name -> theta; the others from their defaults)."""
        starts = [np.asarray(warm[c.name], dtype=float).tobytes() if warm and c.name in warm else None for c in chosen]
        key = tuple(zip((c.name for c in chosen), starts))
        if key not in self.fits:
            self.fits[key] = refit_chi2(self.data, self.sensor, self.nuis0, chosen, warm)
        return self.fits[key]


def refit_chi2(data: Dataset, sensor: SensorModel, nuis0: Nuisance, chosen: list[Candidate],
               warm: dict | None = None) -> dict:
    """Nonlinear refit on the training data; ``warm`` (name -> theta) starts parameters from a previous fit.

    Without effects, ``cost`` is the chi-square of the model as given with the attitudes refitted.
    """
    obs, mask = data.obs, data.train
    theta0 = None if not warm else [warm.get(c.name, c.defaults) for c in chosen]
    fit = refit_mod.refit(obs, nuis0, sensor.camera, sensor.timing, sensor.effects, chosen, mask, theta0)
    if fit["cost"] is None:
        _, pred = fit_attitudes(obs, nuis0, sensor.camera, sensor.timing, sensor.effects, mask)
        fit["cost"] = float(np.sum(star_chi2(obs, pred)[mask]) + np.sum(gyro_channel.channel_rows(obs, pred) ** 2))
    return fit


def with_nuisance(data: Dataset, sensor: SensorModel, nuis0: Nuisance, names: list[str], chosen: list[Candidate],
                  fit: dict) -> NonlinearFit:
    """The fitted effects as a chain, the attitudes and rates refitted under it (from ``nuis0``)."""
    chain = refit_mod.chain_with(sensor.effects, chosen, fit["thetas"])
    nuis1, pred1 = fit_nuisance(data.obs, nuis0, sensor.camera, sensor.timing, chain, data.att_mask, sensor.moving)
    return NonlinearFit(names, chosen, fit, chain, nuis1, pred1)


def refit_named(refits: Refits, cands: dict[str, Candidate], names: list[str]) -> NonlinearFit:
    """Refit the effects ``names`` from their defaults."""
    chosen = [cands[n] for n in names]
    return with_nuisance(refits.data, refits.sensor, refits.nuis0, names, chosen, refits(chosen))


def select_nonlinear(refits: Refits, cands: dict[str, Candidate], names: list[str], blocks: np.ndarray,
                     options: DiagnoseOptions) -> tuple[NonlinearFit, list[dict]]:
    """Refine a linear selection with the nonlinear model: backward elimination by nonlinear
    delta BIC, then forward stepwise on the problem re-linearised at the fitted model; repeat
    until nothing changes (at most :data:`MAX_ROUNDS`). Returns the fit and the changes made.

    The linearised forward step can overstate what an effect earns: it re-adds an effect the
    nonlinear refit then drops again. An effect dropped twice is not offered again, and the
    refinement stops when the elimination comes back to a set of effects an earlier round's
    elimination ended with (a cycle, in which every further round repeats one already made); that
    set, which the nonlinear test accepted, is the result. An effect dropped once still comes back
    when the model has changed so that it earns its place."""
    data, sensor, nuis0 = refits.data, refits.sensor, refits.nuis0
    rounds, kept, drops, added = [], set(), Counter(), False
    for _ in range(MAX_ROUNDS):
        fit = refits([cands[n] for n in names])
        names, fit, dropped = backward_eliminate(refits, cands, names, fit, options.min_delta_bic)
        rounds += dropped
        drops.update(d["dropped"] for d in dropped)
        model = with_nuisance(data, sensor, nuis0, names, [cands[n] for n in names], fit)
        if frozenset(names) in kept:
            if added:  # what the forward step added was dropped again: a cycle
                rounds.append({"cycle": sorted(names)})
            return model, rounds
        kept.add(frozenset(names))
        others = {k: c for k, c in cands.items() if k not in names and drops[k] < 2}
        prob, _ = linear_problem(data.obs, model.prediction, others, model.effects, data.train, blocks)
        steps = selection.forward_stepwise(prob, options.min_delta_bic)
        if steps:
            names = names + [st["name"] for st in steps]
            rounds.append({"added": [st["name"] for st in steps]})
        if not dropped and not steps:
            return model, rounds
        added = bool(steps)
    return refit_named(refits, cands, names), rounds


def backward_eliminate(refits: Refits, cands: dict[str, Candidate], names: list[str], fit: dict,
                       min_delta_bic: float) -> tuple[list[str], dict, list[dict]]:
    """Drop, one at a time, an effect whose nonlinear delta BIC is below the margin.

    Candidates are tried in the order of their Wald delta BIC (from the full fit's covariance, no
    refit): the first whose refit without it costs less than ``min_delta_bic`` is dropped. An effect
    whose Wald delta BIC exceeds ``WALD_SLACK`` x the margin is not refitted: it earns its place by a
    wide margin, and each refit is a nonlinear fit of every other effect and attitude.

    Returns the names kept, their fit, and ``{"dropped", "delta_bic_nonlinear"}`` per effect dropped.
    """
    dropped = []
    while len(names) > 1:
        chosen = [cands[n] for n in names]  # the names fit["thetas"] belong to
        warm = {c.name: t for c, t in zip(chosen, fit["thetas"])}
        worst = None
        for n, wald in wald_delta_bic(chosen, fit, refits.data.n_residuals):
            if wald >= WALD_SLACK * min_delta_bic:
                break
            f = refits([cands[m] for m in names if m != n], warm)
            d = f["cost"] - fit["cost"] - len(cands[n].parameters) * np.log(refits.data.n_residuals)
            if d < min_delta_bic:
                worst, worst_bic, worst_fit = n, d, f
                break
        if worst is None:
            break
        names = [m for m in names if m != worst]
        fit = worst_fit
        dropped.append({"dropped": worst, "delta_bic_nonlinear": float(worst_bic)})
    return names, fit, dropped


def wald_delta_bic(chosen: list[Candidate], fit: dict, n_residuals: int) -> list[tuple[str, float]]:
    """Each effect's Wald delta BIC, ``dtheta^T C^-1 dtheta - p ln N`` from the fit's covariance,
    ascending; an effect without a finite covariance comes first (-inf: refit it)."""
    if not chosen:
        return []
    sig = np.concatenate([np.asarray(s, dtype=float) for s in fit["sigmas"]])
    cov = np.asarray(fit["corr"], dtype=float) * np.outer(sig, sig)
    out, i = [], 0
    for c, theta in zip(chosen, fit["thetas"]):
        k = len(c.parameters)
        block, d = cov[i:i + k, i:i + k], np.asarray(theta, dtype=float) - c.defaults
        i += k
        if not np.all(np.isfinite(block)):
            out.append((c.name, -np.inf))
            continue
        out.append((c.name, float(d @ np.linalg.pinv(block) @ d) - k * np.log(n_residuals)))
    return sorted(out, key=lambda nw: nw[1])


def drop_one_delta_bic(refits: Refits, chosen: list[Candidate], fit: dict,
                       min_delta_bic: float) -> tuple[dict[str, float], dict[str, str]]:
    """Delta BIC of each selected effect: chi2 without it minus chi2 with all, minus its penalty,
    and how it was computed.

    By a nonlinear refit without it ("refit") when its Wald delta BIC (:func:`wald_delta_bic`) is
    below ``WALD_SLACK`` x the margin (where the decision is made); beyond, the Wald value itself
    ("wald"): the effect earns its place either way and each refit is a nonlinear fit of every
    other effect."""
    out, method = {}, {}
    warm = {c.name: t for c, t in zip(chosen, fit["thetas"])}
    n_res = refits.data.n_residuals
    wald = dict(wald_delta_bic(chosen, fit, n_res))
    for c in chosen:
        if wald[c.name] >= WALD_SLACK * min_delta_bic:
            out[c.name], method[c.name] = wald[c.name], "wald"
            continue
        rest = [d for d in chosen if d is not c]
        f = refits(rest, warm)
        out[c.name] = float(f["cost"] - fit["cost"] - len(c.parameters) * np.log(n_res))
        method[c.name] = "refit"
    return out, method
