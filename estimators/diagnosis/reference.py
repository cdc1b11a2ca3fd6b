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

Each absorbed candidate is fitted to ``e`` alone by weighted least squares over the frames; a
delta BIC above the diagnosis's margin makes it *tested by the reference*, with its estimate and
sigma. The chi-square of ``e`` with no effect checks that reference and fitted attitudes agree.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.spatial.transform import Rotation

from rollingstar.estimators.diagnosis.gyro_channel import absorbed_rotations, attitude_covariances
from rollingstar.estimators.diagnosis.library import Candidate
from rollingstar.estimators.diagnosis.observations import whiten
from rollingstar.estimators.diagnosis.residuals import z_from_sf
from rollingstar.sensors.conventions import ARCSEC_TO_RAD


@dataclass(frozen=True)
class ReferenceCheck:
    """The fitted attitudes against the reference, and each absorbed candidate tested on them."""

    sigma_arcsec: float
    frames: int
    chi2: float  # of the attitude differences with no effect
    dof: int
    rows: list[dict]  # per candidate: name, params, delta_chi2, delta_bic, tested

    @property
    def tested(self) -> list[str]:
        return [r["name"] for r in self.rows if r["tested"]]

    def as_json(self) -> dict:
        z = float(z_from_sf(stats.chi2.sf(self.chi2, self.dof))) if self.dof else None
        return {"sigma_arcsec": self.sigma_arcsec, "frames": self.frames, "chi2": self.chi2, "dof": self.dof,
                "z": z, "candidates": self.rows}


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
    rows = []
    for name in names:
        c = cands[name]
        j = whiten(obs, c.signature(pred.ctx, model.effects, pred.exposure_ns))
        a = absorbed_rotations(obs.frame[idx], obs.n_frames, aj[idx], j[idx])[use]  # (F', 3, p) rad per unit
        normal = np.einsum("kip,kij,kjq->pq", a, w, a)
        rhs = np.einsum("kip,kij,kj->p", a, w, e)
        inv = np.linalg.pinv(normal, hermitian=True)
        theta = inv @ rhs
        delta = float(rhs @ theta)
        dbic = delta - len(c.parameters) * np.log(max(3 * int(use.sum()), 2))
        params = {p.name: {"value": float(p.default + t), "sigma": float(np.sqrt(max(s, 0.0))), "unit": p.unit}
                  for p, t, s in zip(c.parameters, theta, np.diag(inv))}
        rows.append({"name": name, "params": params, "delta_chi2": delta, "delta_bic": float(dbic),
                     "tested": bool(dbic > min_delta_bic)})
    return ReferenceCheck(float(sigma_arcsec), int(use.sum()), chi2, 3 * int(use.sum()), rows)
