"""Model the selected effects: nonlinear refit with uncertainties, and stability across subsets.

The selected effects' parameters ``theta`` are refitted with their nonlinear forward models by
variable projection (Golub & Pereyra 1973): for each trial ``theta`` every frame's attitude is
refitted by Gauss-Newton (:func:`observations.fit_attitudes`), and ``scipy.optimize.least_squares``
minimises the whitened residuals over ``theta`` alone. The Jacobian of these projected residuals
``J`` gives the covariance ``(J^T J)^-1`` (noise known, Gauss-Newton approximation), and hence the
1-sigma uncertainty of every parameter and their correlations.

Stability: the same refit on halves of the frames, on the inner and outer parts of the field and on
the slow and fast halves of image speed. Two subset estimates ``a, b`` agree when
``|a - b| / sqrt(sigma_a^2 + sigma_b^2) < 3`` for every parameter.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from estimators.diagnosis.library import Candidate
from estimators.diagnosis.observations import Nuisance, Observations, fit_attitudes

STABILITY_Z = 3.0


def chain_with(base_effects, candidates: list[Candidate], thetas: list[np.ndarray]) -> tuple:
    """The scenario's effects followed by the candidates at ``thetas`` (the chain orders by stage)."""
    return tuple(base_effects) + tuple(c.instance(t) for c, t in zip(candidates, thetas))


def split_theta(candidates: list[Candidate], z: np.ndarray) -> list[np.ndarray]:
    out, i = [], 0
    for c in candidates:
        m = len(c.parameters)
        out.append(c.defaults + c.scales * z[i:i + m])
        i += m
    return out


def refit(obs: Observations, nuis: Nuisance, camera, timing, base_effects, candidates: list[Candidate],
          mask: np.ndarray, theta0: list[np.ndarray] | None = None) -> dict:
    """Nonlinear refit of ``candidates`` (module doc) on the observations in ``mask``.

    Returns ``thetas`` (list per candidate), ``sigmas``, ``corr`` (correlation matrix of all
    parameters), the refitted ``nuisance`` and ``success``.
    """
    if not candidates:
        return {"thetas": [], "sigmas": [], "corr": np.zeros((0, 0)), "nuisance": nuis, "success": True, "cost": None}
    m = sum(len(c.parameters) for c in candidates)
    z0 = np.zeros(m) if theta0 is None else np.concatenate([(t - c.defaults) / c.scales for c, t in zip(candidates, theta0)])
    lo = np.concatenate([[(p.bounds[0] - p.default) / p.prior_scale for p in c.parameters] for c in candidates])
    hi = np.concatenate([[(p.bounds[1] - p.default) / p.prior_scale for p in c.parameters] for c in candidates])
    z0 = np.clip(z0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    state = {"nuis": nuis}
    sig = obs.sigma[mask]

    def resid(z):
        effects = chain_with(base_effects, candidates, split_theta(candidates, z))
        # always from the effect-free nuisance: the residual is then a function of z alone (no
        # hysteresis between evaluations, which finite differences and the trust region need)
        n2, pred = fit_attitudes(obs, nuis, camera, timing, effects, mask, iterations=4)
        state["nuis"] = n2
        r = np.concatenate([(obs.x[mask] - pred.x[mask]) / sig, (obs.y[mask] - pred.y[mask]) / sig])
        return np.nan_to_num(r, nan=1e6)

    try:
        res = least_squares(resid, z0, bounds=(lo, hi), method="trf", x_scale=1.0, diff_step=1e-4, max_nfev=60)
        z, jac, success, cost = res.x, res.jac, bool(res.success), float(2 * res.cost)
    except (ValueError, np.linalg.LinAlgError):  # a forward model that cannot be evaluated: report, not crash
        return {"thetas": split_theta(candidates, z0), "sigmas": [np.full(len(c.parameters), np.nan) for c in candidates],
                "corr": np.full((m, m), np.nan), "nuisance": nuis, "success": False, "cost": None}
    jtj = jac.T @ jac
    try:
        cov_z = np.linalg.inv(jtj)
    except np.linalg.LinAlgError:
        cov_z = np.linalg.pinv(jtj)
    sd_z = np.sqrt(np.clip(np.diag(cov_z), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_z / np.outer(sd_z, sd_z)
    scales = np.concatenate([c.scales for c in candidates])
    sig_theta = sd_z * scales
    out_s, i = [], 0
    for c in candidates:
        k = len(c.parameters)
        out_s.append(sig_theta[i:i + k])
        i += k
    resid(z)  # leave the nuisance at the solution
    return {"thetas": split_theta(candidates, z), "sigmas": out_s, "corr": corr, "nuisance": state["nuis"],
            "success": success, "cost": cost}


def subsets(obs: Observations, pred, camera, mask: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Pairs of disjoint training subsets: frame halves, inner/outer field, slow/fast image speed."""
    out = {}
    if obs.n_frames >= 4:
        first = obs.frame < obs.n_frames // 2
        out["halves (first/second frames)"] = (mask & first, mask & ~first)
    rad = np.hypot(pred.x - camera.cx, pred.y - camera.cy)
    med = np.median(rad[mask]) if mask.any() else 0.0
    out["field (inner/outer)"] = (mask & (rad <= med), mask & (rad > med))
    speed = np.hypot(pred.vx, pred.vy)
    if mask.any() and np.ptp(speed[mask]) > 1e-6 * max(np.max(speed[mask]), 1e-12):
        ms = np.median(speed[mask])
        out["rate (slow/fast image speed)"] = (mask & (speed <= ms), mask & (speed > ms))
    return out


def stability(obs: Observations, nuis: Nuisance, pred, camera, timing, base_effects, candidates: list[Candidate],
              thetas: list[np.ndarray], mask: np.ndarray) -> list[dict]:
    """Refit on each subset pair; per parameter the two values, sigmas and the z of their difference."""
    rows = []
    for label, (a, b) in subsets(obs, pred, camera, mask).items():
        if a.sum() < 10 or b.sum() < 10:
            continue
        fa = refit(obs, nuis, camera, timing, base_effects, candidates, a, thetas)
        fb = refit(obs, nuis, camera, timing, base_effects, candidates, b, thetas)
        for c, ta, sa, tb, sb in zip(candidates, fa["thetas"], fa["sigmas"], fb["thetas"], fb["sigmas"]):
            for j, p in enumerate(c.parameters):
                s = float(np.hypot(sa[j], sb[j]))
                z = float(abs(ta[j] - tb[j]) / s) if s > 0 and np.isfinite(s) else float("nan")
                rows.append({"subset": label, "effect": c.name, "param": p.name, "a": float(ta[j]), "sigma_a": float(sa[j]),
                             "b": float(tb[j]), "sigma_b": float(sb[j]), "z": z,
                             "stable": bool(np.isfinite(z) and z < STABILITY_Z) if np.isfinite(s) else None})
    return rows
