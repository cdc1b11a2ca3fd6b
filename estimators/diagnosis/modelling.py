"""Step 3, model: the named effects' parameters, their uncertainties and what is left unexplained.

The final parameters and sigmas come from a joint fit with the rates tied to the attitudes
(:func:`.refit.joint_refit`); stability refits on subsets of the data (:func:`.refit.stability`);
the residual left is tested against generic bases (:mod:`.catchall`) and, with a known noise,
against its chi-square. :func:`updated_scenario` writes the named effects into the scenario.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rollingstar.config import validate
from rollingstar.estimators.diagnosis import catchall, residuals, selection
from rollingstar.estimators.diagnosis import refit as refit_mod
from rollingstar.estimators.diagnosis.inputs import DiagnoseOptions, SensorModel
from rollingstar.estimators.diagnosis.library import Candidate
from rollingstar.estimators.diagnosis.locating import Dataset
from rollingstar.estimators.diagnosis.naming import Naming
from rollingstar.estimators.diagnosis.observations import (
    Nuisance,
    Prediction,
    fit_nuisance,
    whiten,
)
from rollingstar.estimators.diagnosis.signatures import whitened_residual
from rollingstar.sensors.scenario import ScenarioConfig

CHI2_Z_LIMIT = 5.0  # a chi-square this many sigma beyond its dof is a mismatch the model leaves


@dataclass(frozen=True, eq=False)
class EffectModel:
    """The named effects modelled: parameters, the fit under them, and the structure they leave."""

    chosen: list[Candidate]
    fit: dict  # thetas, sigmas, corr (joint refit when it ran), success of the variable-projection refit
    effects: tuple  # the scenario's chain with the named effects at their fitted parameters
    nuisance: Nuisance
    prediction: Prediction
    stability: list[dict]  # :func:`refit.stability` rows (empty when not run)
    leftover_tests: list[dict]  # :func:`catchall.residual_structure`: generic bases on the residual left
    leftover_evidence: list[dict]  # the significant ones, and a total chi-square beyond a known noise

    @property
    def thetas(self) -> list[np.ndarray]:
        return self.fit["thetas"]


def model_effects(data: Dataset, naming: Naming, sensor: SensorModel, options: DiagnoseOptions) -> EffectModel:
    """Joint refit of the named effects, stability across subsets, tests of the residual left."""
    named = naming.model
    fit, effects, nuis1, pred1 = named.fit, named.effects, named.nuisance, named.prediction
    chosen = named.chosen
    if chosen:
        # final estimate and covariance with the rates tied to the attitudes (refit.joint_refit):
        # the variable-projection refit holds the rates fixed and its sigmas ignore their error
        jf = refit_mod.joint_refit(data.obs, fit["nuisance"], sensor.camera, sensor.timing, sensor.effects, chosen,
                                   fit["thetas"], data.train, sensor.moving)
        if jf["cost"] is not None:
            fit = {**fit, "thetas": jf["thetas"], "sigmas": jf["sigmas"], "corr": jf["corr"], "joint_success": jf["success"]}
            effects = refit_mod.chain_with(sensor.effects, chosen, fit["thetas"])
            nuis1, pred1 = fit_nuisance(data.obs, jf["nuisance"], sensor.camera, sensor.timing, effects,
                                        data.att_mask, sensor.moving)
    tests, evidence = leftover_structure(data, pred1, sensor, chosen)
    model = EffectModel(chosen, fit, effects, nuis1, pred1, [], tests, evidence)
    return with_stability(data, model, sensor) if options.stability else model


def with_stability(data: Dataset, model: EffectModel, sensor: SensorModel) -> EffectModel:
    """``model`` with its stability rows: the named effects refitted on subsets (:func:`.refit.stability`)."""
    if not model.chosen:
        return model
    stab = refit_mod.stability(data.obs, model.nuisance, model.prediction, sensor.camera, sensor.timing, sensor.effects,
                               model.chosen, model.fit["thetas"], data.train)
    return replace(model, stability=stab)


def leftover_structure(data: Dataset, pred: Prediction, sensor: SensorModel,
                       chosen: list[Candidate]) -> tuple[list[dict], list[dict]]:
    """Generic bases (:mod:`.catchall`) on the training residual ``pred`` leaves; the significant ones
    and, when the noise is known, a total chi-square beyond :data:`CHI2_Z_LIMIT` are evidence."""
    obs, train = data.obs, data.train
    bases = catchall.generic_bases(obs, pred, sensor.camera)
    aj = whiten(obs, pred.att_jac)
    gproj = {}
    for name, g in bases.items():
        p = selection.project_frames(obs.frame, obs.n_frames, aj, whiten(obs, g))
        gproj[name] = np.concatenate([p[train, 0, :], p[train, 1, :],
                                      np.zeros((obs.channel.rows if obs.channel is not None else 0, p.shape[2]))])
    left = catchall.residual_structure(whitened_residual(obs, pred, train), gproj)
    after_stats = residuals.chi2_stats(obs, pred, train, 3 * data.n_train_frames + sum(len(c.parameters) for c in chosen))
    evidence = [row for row in left if row["significant"]]
    if after_stats["z"] > CHI2_Z_LIMIT and known_noise(data):
        evidence.append({"basis": "total chi-square", "delta_chi2": after_stats["chi2"] - after_stats["dof"],
                         "dof": after_stats["dof"], "z": after_stats["z"], "significant": True})
    return left, evidence


def known_noise(data: Dataset) -> bool:
    """Whether the noise comes from the recording or the scenario (not estimated from the residuals)."""
    return data.obs.sigma_source.startswith(("recording", "scenario"))


def updated_scenario(scenario: ScenarioConfig, chosen: list[Candidate], thetas: list[np.ndarray]) -> ScenarioConfig:
    """The input scenario with the selected effects enabled (a kind already present gets base + delta)."""
    effects = [dict(e.model_dump()) for e in scenario.effects]
    for c, th in zip(chosen, thetas):
        delta = {p.name: float(v - p.default) for p, v in zip(c.parameters, th)}
        for e in effects:
            if e["kind"] == c.name:
                e["params"] = {p.name: float(e["params"].get(p.name, p.default)) + delta[p.name] for p in c.parameters}
                break
        else:
            effects.append(c.scenario_entry(th))
    data = scenario.model_dump(mode="json")
    data["effects"] = effects
    if chosen:
        data["description"] = (scenario.description + "\n" if scenario.description else "") + \
            "updated by rollingstar diagnose: " + ", ".join(c.name for c in chosen)
    return validate(ScenarioConfig, data, "<updated scenario>")
