"""Re-simulate a recording with a scenario's forward model and compare residual distributions.

Step 4 of the diagnosis: if the updated scenario describes the sensor, a recording simulated from
it must leave residuals distributed like the real recording's under the same model; the input
scenario, missing the physics, must not. The re-simulation keeps everything the recording fixes
-- its identified stars (catalogue directions), their times, the per-frame attitudes and rates the
diagnosis fitted, the recording's sigmas -- and draws fresh Gaussian centroid noise (seeded)::

    (x, y)_sim = chain(project(R(t_i)^T u_i)) + sigma_i n_i,     n_i ~ N(0, I)

(the forward model of :func:`rollingstar.estimators.diagnosis.observations.predict`, i.e. the scenario's
effect chain; for a constant rate within a frame it is the simulator's model, see
:mod:`rollingstar.sensors.effects.chain`). Both recordings then go through the same nuisance fit (attitude,
rates from the attitude sequence) under the model, and their normalised residuals
``(obs - model) / sigma`` (both axes, every star) are compared by the two-sample
Kolmogorov-Smirnov test (``scipy.stats.ks_2samp``) and the k-sample Anderson-Darling test
(``scipy.stats.anderson_ksamp``, more sensitive in the tails; its p-value is floored at 0.001 and
capped at 0.25 by scipy). Done for the input scenario ("before") and the updated one ("after").
Working at the recording's own stars and attitudes makes this possible for imported real data too
(whose declared scenario has no motion or sky that could be simulated image by image).
"""
from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
from scipy import stats

from rollingstar.estimators.diagnosis.observations import (
    Nuisance,
    Observations,
    fit_nuisance,
    predict,
    whitened_residuals,
)


def normalised_residuals(obs: Observations, pred) -> np.ndarray:
    """``(obs - model) / sigma`` of every star (whitened by its 2 x 2 covariance when it carries one), x then y, (2 n,)."""
    r = whitened_residuals(obs, pred)
    return np.concatenate([r[:, 0], r[:, 1]])


def resimulated(obs: Observations, nuis: Nuisance, camera, timing, effects, seed: int) -> Observations:
    """The recording's observations re-drawn from the model (module doc), fresh noise from ``seed``."""
    p = predict(obs, nuis, camera, timing, tuple(effects))
    rng = np.random.default_rng([seed, 1729])
    if obs.cov is None:
        return replace(obs, x=p.x + rng.normal(0.0, obs.sigma), y=p.y + rng.normal(0.0, obs.sigma))
    d = np.einsum("nij,nj->ni", np.linalg.cholesky(obs.cov), rng.normal(size=(obs.n, 2)))
    return replace(obs, x=p.x + d[:, 0], y=p.y + d[:, 1])


def compare(a: np.ndarray, b: np.ndarray) -> dict:
    """Two-sample KS and Anderson-Darling of residual samples ``a`` (recording) and ``b`` (re-simulation)."""
    ks = stats.ks_2samp(a, b)
    with warnings.catch_warnings():  # scipy warns when the p-value is outside its table (floored / capped)
        warnings.simplefilter("ignore")
        ad = stats.anderson_ksamp([a, b])
    return {"ks_statistic": float(ks.statistic), "ks_p_value": float(ks.pvalue),
            "ad_statistic": float(ad.statistic), "ad_p_value": float(ad.significance_level),
            "rms_recording": float(np.sqrt(np.mean(a * a))), "rms_resimulated": float(np.sqrt(np.mean(b * b))),
            "n": int(a.size)}


def resimulation_check(obs: Observations, models: dict, camera, timing, att_mask, moving: bool, seed: int = 0) -> dict:
    """For each named model ``{label: (effects, nuisance, prediction)}`` (the recording's fit under
    that model): re-simulate, refit the nuisance, compare residual distributions (module doc)."""
    out = {"method": "re-simulated at the recording's stars, times and fitted attitudes/rates with the model's "
                     "effect chain and fresh Gaussian noise at the recording's sigma; nuisance refitted; "
                     "normalised residuals compared (two-sample Kolmogorov-Smirnov, Anderson-Darling)",
           "seed": int(seed)}
    for label, (effects, nuis, pred) in models.items():
        sim = resimulated(obs, nuis, camera, timing, effects, seed)
        _, p_sim = fit_nuisance(sim, nuis, camera, timing, tuple(effects), att_mask, moving)
        out[label] = compare(normalised_residuals(obs, pred), normalised_residuals(sim, p_sim))
    return out
