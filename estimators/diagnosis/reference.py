"""Effects the per-frame attitude absorbs, tested against a reference attitude the recording carries.

An effect whose image displacement a rotation of the frame reproduces (a boresight roll, a clock
offset at a constant rate, a principal-point shift over a small field) cannot be told from the
attitude by the stars alone: the diagnosis lists it as not testable. A recording that also carries
a reference attitude (a simulation's truth, a second tracker, a surveyed mount) of stated accuracy
``sigma_ref`` per axis makes it testable. The attitude fitted to frame ``k`` under the named model
differs from the reference by ``e_k = log(R_ref,k^-1 R_k)``; to first order that is the rotation
``a_k theta`` the frame absorbed of the effect (the per-frame least-squares rotation of the
effect's whitened image Jacobian, :func:`.gyro_channel.absorbed_rotations`), plus the attitude
fit's error (covariance ``C_k`` from the stars) and the reference's (``sigma_ref^2 I``).

This is the reference used as a prior of covariance ``sigma_ref^2 I`` on every frame's attitude:
for an effect the stars cannot see, the image residual depends on the attitude and the effect only
through their sum, so profiling the joint least squares (stars plus prior) over the attitudes leaves
exactly the weighted fit of ``a_k theta`` to ``e_k`` with covariance ``C_k + sigma_ref^2 I``.

Each absorbed candidate is fitted to ``e`` alone by weighted least squares over the frames; a
delta BIC above the diagnosis's margin makes it *tested by the reference*, with its estimate and
sigma. The tested candidates then enter a joint model by forward selection (each step adds the one
that lowers the chi-square most, while its delta BIC clears the margin): its parameters, fitted
together, go to the updated scenario. The chi-square of ``e`` with no effect checks that reference
and fitted attitudes agree; the joint model's chi-square shows how much of it the effects explain.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats
from scipy.spatial.transform import Rotation

from rollingstar.estimators.diagnosis.gyro_channel import absorbed_rotations, attitude_covariances
from rollingstar.estimators.diagnosis.library import Candidate, separating_experiment
from rollingstar.estimators.diagnosis.observations import whiten
from rollingstar.estimators.diagnosis.residuals import z_from_sf
from rollingstar.estimators.diagnosis.selection import BIC_WINDOW, CORR_LIMIT, DECISIVE_SWAP_BIC, canonical_correlation
from rollingstar.sensors.conventions import ARCSEC_TO_RAD


@dataclass(frozen=True)
class ReferenceCheck:
    """The fitted attitudes against the reference, and each absorbed candidate tested on them."""

    sigma_arcsec: float
    frames: int
    chi2: float  # of the attitude differences with no effect
    dof: int
    rows: list[dict]  # per candidate: name, params, delta_chi2, delta_bic, tested
    model: list[tuple[Candidate, np.ndarray]] = field(default_factory=list)  # jointly fitted: (candidate, values)
    model_params: list[dict] = field(default_factory=list)  # per model candidate: name, params (value, sigma, unit)
    chi2_after: float | None = None  # of the attitude differences with the joint model
    ambiguous: list[dict] = field(default_factory=list)  # pairs the reference cannot tell apart

    @property
    def tested(self) -> list[str]:
        return [r["name"] for r in self.rows if r["tested"]]

    def as_json(self) -> dict:
        z = float(z_from_sf(stats.chi2.sf(self.chi2, self.dof))) if self.dof else None
        n_par = sum(len(c.parameters) for c, _ in self.model)
        return {"sigma_arcsec": self.sigma_arcsec, "frames": self.frames, "chi2": self.chi2, "dof": self.dof,
                "z": z, "candidates": self.rows, "model": self.model_params,
                "chi2_after": self.chi2_after if self.model else self.chi2, "dof_after": self.dof - n_par,
                "ambiguous": self.ambiguous}


def reference_check(data, model, cands: dict[str, Candidate], names: list[str], reference: Rotation,
                    covered: np.ndarray, sigma_arcsec: float, min_delta_bic: float) -> ReferenceCheck:
    """Test the candidates ``names`` against ``reference`` (one attitude per frame at its reference
    time; frames where ``covered`` is False are left out). ``data``: the diagnosis's dataset,
    ``model``: the named model (its attitudes and prediction)."""
    obs, pred = data.obs, model.prediction
    sigma = sigma_arcsec * ARCSEC_TO_RAD
    e = (reference.inv() * model.nuisance.attitude).as_rotvec()  # (F, 3)
    cov = attitude_covariances(obs.frame, obs.n_frames, pred.att_jac, obs.sigma, data.att_mask, obs.cov)
    use = covered & np.all(np.isfinite(e), axis=1) & data.frame_has_train
    w = np.linalg.pinv(cov[use] + sigma**2 * np.eye(3), hermitian=True)  # (F', 3, 3)
    e = e[use]
    chi2 = float(np.einsum("ki,kij,kj->", e, w, e))
    aj = whiten(obs, pred.att_jac)
    idx = np.flatnonzero(data.att_mask)
    n_rows = 3 * int(use.sum())
    cols = {}
    for name in names:
        j = whiten(obs, cands[name].signature(pred.ctx, model.effects, pred.exposure_ns))
        cols[name] = absorbed_rotations(obs.frame[idx], obs.n_frames, aj[idx], j[idx])[use]  # (F', 3, p) rad per unit
    rows = []
    for name in names:
        c = cands[name]
        theta, inv, delta = weighted_fit(cols[name], w, e)
        dbic = delta - len(c.parameters) * np.log(max(n_rows, 2))
        rows.append({"name": name, "params": _params(c.parameters, theta, inv), "delta_chi2": delta,
                     "delta_bic": float(dbic), "tested": bool(dbic > min_delta_bic)})
    chosen = _forward(cols, w, e, [r["name"] for r in rows if r["tested"]], cands, n_rows, min_delta_bic)
    out = ReferenceCheck(float(sigma_arcsec), int(use.sum()), chi2, n_rows, rows)
    if not chosen:
        return out
    theta, inv, delta = weighted_fit(np.concatenate([cols[n] for n in chosen], axis=2), w, e)
    model, params, k = [], [], 0
    for name in chosen:
        c = cands[name]
        p = len(c.parameters)
        model.append((c, np.array([q.default for q in c.parameters]) + theta[k:k + p]))
        params.append({"name": name, "params": _params(c.parameters, theta[k:k + p], inv[k:k + p, k:k + p])})
        k += p
    amb = _ambiguous(cols, w, e, chosen, out.tested, cands, n_rows)
    return replace(out, model=model, model_params=params, chi2_after=max(chi2 - delta, 0.0), ambiguous=amb)


def weighted_fit(a: np.ndarray, w: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted least squares of ``a theta`` (F', 3, p) to ``e`` (F', 3) with weights ``w`` (F', 3, 3):
    the estimate, its covariance and the chi-square it removes."""
    normal = np.einsum("kip,kij,kjq->pq", a, w, a)
    rhs = np.einsum("kip,kij,kj->p", a, w, e)
    inv = np.linalg.pinv(normal, hermitian=True)
    theta = inv @ rhs
    return theta, inv, float(rhs @ theta)


def _forward(cols: dict[str, np.ndarray], w: np.ndarray, e: np.ndarray, tested: list[str],
             cands: dict[str, Candidate], n_rows: int, min_delta_bic: float) -> list[str]:
    """Forward selection among the ``tested`` candidates: add the one whose joint fit removes the most
    chi-square, while that gain less its BIC penalty stays above ``min_delta_bic``."""
    chosen: list[str] = []
    removed = 0.0
    while True:
        gains = {}
        for name in (n for n in tested if n not in chosen):
            a = np.concatenate([cols[n] for n in [*chosen, name]], axis=2)
            gains[name] = weighted_fit(a, w, e)[2] - removed
        best = max(gains, key=gains.get, default=None)
        if best is None or gains[best] - len(cands[best].parameters) * np.log(max(n_rows, 2)) <= min_delta_bic:
            return chosen
        chosen.append(best)
        removed += gains[best]


def _ambiguous(cols: dict[str, np.ndarray], w: np.ndarray, e: np.ndarray, chosen: list[str], tested: list[str],
               cands: dict[str, Candidate], n_rows: int) -> list[dict]:
    """Pairs (chosen, other tested candidate) the reference cannot tell apart, by the rule the stars'
    selection uses (:func:`.selection.ambiguities`): swapping one for the other costs less than
    ``BIC_WINDOW``, or their whitened signatures are collinear and the swap is not decisive."""
    def bic(names: list[str]) -> float:
        a = np.concatenate([cols[n] for n in names], axis=2)
        return -weighted_fit(a, w, e)[2] + a.shape[2] * np.log(max(n_rows, 2))

    root = np.linalg.cholesky(w)  # w = L L^T: L^T a whitens a frame's rows
    def whitened(name: str) -> np.ndarray:
        return np.einsum("kji,kjp->kip", root, cols[name]).reshape(-1, cols[name].shape[2])

    rows, base = [], bic(chosen)
    for g in chosen:
        rest = [n for n in chosen if n != g]
        for h in (n for n in tested if n not in chosen):
            swap = bic([*rest, h]) - base
            corr = canonical_correlation(whitened(g), whitened(h))
            if swap < BIC_WINDOW or (corr > CORR_LIMIT and swap < DECISIVE_SWAP_BIC):
                rows.append({"candidates": [g, h], "corr": corr, "delta_bic_swap": float(swap),
                             "separating_experiment": separating_experiment(cands[g], cands[h])})
    return rows


def _params(parameters, theta: np.ndarray, cov: np.ndarray) -> dict:
    """Each parameter's value (its default plus ``theta``), sigma and unit."""
    return {p.name: {"value": float(p.default + t), "sigma": float(np.sqrt(max(s, 0.0))), "unit": p.unit}
            for p, t, s in zip(parameters, theta, np.diag(cov))}
