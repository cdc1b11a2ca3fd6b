"""Model the selected effects: nonlinear refit with uncertainties, and stability across subsets.

The selected effects' parameters ``theta`` are refitted with their nonlinear forward models by
variable projection (Golub & Pereyra 1973): for each trial ``theta`` every frame's attitude is
refitted by Gauss-Newton (:func:`observations.fit_attitudes`), and ``scipy.optimize.least_squares``
minimises the whitened residuals over ``theta`` alone. The Jacobian of these projected residuals
``J`` gives the covariance ``(J^T J)^-1`` (noise known, Gauss-Newton approximation), and hence the
1-sigma uncertainty of every parameter and their correlations.

``J`` is Kaufman's (1975) variable-projection Jacobian: the effect columns at the refitted attitudes
(forward differences of the prediction with the attitudes held) with every frame's attitude
projected out, ``J = -M d pred / d z``. Differencing the whole projected residual instead would
refit every frame's attitude for every column (about five predictions each); the two agree to
first order. With a gyro channel the increment rows are differenced with each frame's attitude
moved by the rotation its training stars absorb of that column (the same first order).

Stability: the same refit on halves of the frames, on the inner and outer parts of the field and on
the slow and fast halves of image speed. Two subset estimates ``a, b`` agree when
``|a - b| / sqrt(sigma_a^2 + sigma_b^2) < 3`` for every parameter.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from rollingstar.estimators.diagnosis.gyro_channel import channel_rows
from rollingstar.estimators.diagnosis.library import Candidate
from rollingstar.estimators.diagnosis.observations import (
    Nuisance,
    Observations,
    Prediction,
    chain_positions,
    chain_trace,
    fit_attitudes,
    frame_normal,
    pinhole,
    predict,
    rates_from_attitudes,
    solve_frames,
    star_weights,
    whiten,
    whitened_residuals,
)
from rollingstar.estimators.diagnosis.selection import project_frames
from rollingstar.sensors.conventions import NS_PER_S
from rollingstar.sensors.effects.chain import ordered

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
    z0, lo, hi = _within_bounds(candidates, z0)
    state, start = {"nuis": nuis}, pinhole(obs, nuis, camera, timing)

    def resid(z):
        effects = chain_with(base_effects, candidates, split_theta(candidates, z))
        # always from the effect-free nuisance: the residual is then a function of z alone (no
        # hysteresis between evaluations, which finite differences and the trust region need)
        n2, pred = fit_attitudes(obs, nuis, camera, timing, effects, mask, iterations=4, start=start)
        state["nuis"], state["z"], state["pred"] = n2, np.array(z, copy=True), pred
        w = whitened_residuals(obs, pred, mask)
        r = np.concatenate([w[:, 0], w[:, 1], channel_rows(obs, pred)])  # + the gyro increment channel, when present
        return np.nan_to_num(r, nan=1e6)

    def jac(z):
        if state.get("z") is None or not np.array_equal(state["z"], z):
            resid(z)
        return projected_jacobian(obs, state["nuis"], camera, timing, base_effects, candidates, mask, z, hi, state["pred"])

    try:
        res = least_squares(resid, z0, jac=jac, bounds=(lo, hi), method="trf", x_scale=1.0, max_nfev=60)
        z, jac, success, cost = res.x, res.jac, bool(res.success), float(2 * res.cost)
    except (ValueError, np.linalg.LinAlgError):  # a forward model that cannot be evaluated: report, not crash
        return {"thetas": split_theta(candidates, z0), "sigmas": [np.full(len(c.parameters), np.nan) for c in candidates],
                "corr": np.full((m, m), np.nan), "nuisance": nuis, "success": False, "cost": None}
    out_s, corr = _sigmas_and_corr(_inverse_normal(jac), candidates)
    if state.get("z") is None or not np.array_equal(state["z"], z):
        resid(z)  # leave the nuisance at the solution (when the last evaluation was a trial elsewhere)
    return {"thetas": split_theta(candidates, z), "sigmas": out_s, "corr": corr, "nuisance": state["nuis"],
            "success": success, "cost": cost}


def projected_jacobian(obs: Observations, nuis: Nuisance, camera, timing, base_effects, candidates: list[Candidate],
                       mask: np.ndarray, z: np.ndarray, hi: np.ndarray, base: Prediction | None = None) -> np.ndarray:
    """Kaufman's Jacobian of :func:`refit`'s residual at ``z`` (module doc), ``nuis`` the attitudes
    refitted at ``z`` and ``base`` their prediction (made here when not given): rows as the
    residual (training x, training y, gyro increments).

    Image rows: ``-M d pred / d z``, the prediction differenced with the attitudes held and every
    frame's attitude projected out. Gyro increment rows (when the recording has them): the
    increments differenced with each frame's attitude moved by the rotation its training stars
    would absorb of that column (first order of the attitude refit), as the refit does.
    """
    thetas = split_theta(candidates, z)
    effects = chain_with(base_effects, candidates, thetas)
    base = predict(obs, nuis, camera, timing, effects) if base is None else base  # the residual's own prediction
    cols = np.empty((obs.n, 2, z.size))
    steps, chains = np.empty(z.size), []
    owner = np.repeat(np.arange(len(candidates)), [len(c.parameters) for c in candidates])
    first = np.concatenate([[0], np.cumsum([len(c.parameters) for c in candidates])])
    # a column's chain equals the base chain before its candidate: it runs from that candidate on
    trace = chain_trace(base, effects)
    place = {id(e): i for i, e in enumerate(ordered(effects))}
    for j in range(z.size):
        h = 1e-4 * max(1.0, abs(z[j]))
        zj = z[j] + h if z[j] + h <= hi[j] else z[j] - h
        steps[j] = zj - z[j]
        k, at = owner[j], len(base_effects) + owner[j]  # only candidate k's instance changes
        zk = z[first[k]:first[k + 1]].copy()
        zk[j - first[k]] = zj
        chains.append(effects[:at] + (candidates[k].instance(split_theta([candidates[k]], zk)[0]),) + effects[at + 1:])
        px, py = chain_positions(base, chains[-1], trace, place[id(effects[at])])
        cols[:, 0, j], cols[:, 1, j] = (px - base.x) / steps[j], (py - base.y) / steps[j]
    idx = np.flatnonzero(mask)
    aj = whiten(obs, base.att_jac[idx], idx)
    p = project_frames(obs.frame[idx], obs.n_frames, aj, whiten(obs, cols[idx], idx))
    rows = [-p[:, 0, :], -p[:, 1, :]]
    if obs.channel is not None:
        a, b = frame_normal(obs.frame, obs.n_frames, base.att_jac, star_weights(obs, mask), -cols)
        absorbed = solve_frames(a, b)  # (F, 3, m): each frame's attitude change per unit z
        chan = obs.channel
        inc = chan.increments(obs.t_ref_ns, effects)  # the integration is the costly part
        g0 = chan.residual(nuis.attitude, obs.t_ref_ns, increments=inc)
        on_gyro = np.concatenate([np.full(len(c.parameters), "gyro" in c.channels) for c in candidates])
        g = np.empty((g0.size, z.size))
        for j in range(z.size):  # the gyro is integrated again only for the effects that act on it
            att = nuis.attitude * Rotation.from_rotvec(absorbed[:, :, j] * steps[j])
            gj = chan.residual(att, obs.t_ref_ns, chains[j]) if on_gyro[j] else chan.residual(att, obs.t_ref_ns, increments=inc)
            g[:, j] = (gj - g0) / steps[j]
        rows.append(g)
    return np.nan_to_num(np.concatenate(rows))


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


# ------------------------------------------------------------------ joint refit with tied rates
def rate_operator(nuis: Nuisance, t_ref_ns: np.ndarray) -> np.ndarray:
    """``C`` (F, F-1) with ``omega = C @ steps``, ``steps_s = log(R_s^T R_{s+1}) / dt_s``.

    Per frame the finite-difference rate the nuisance fit chose (backward, forward or central,
    :func:`observations.rates_from_attitudes`) is recovered as the candidate closest to
    ``nuis.omega``; the operator then keeps that choice while the attitudes move.
    """
    f = len(t_ref_ns)
    c = np.zeros((f, max(f - 1, 0)))
    if f < 2:
        return c
    options = np.stack(rates_from_attitudes(nuis.attitude, t_ref_ns))  # (3, F, 3): bwd, fwd, central
    choice = np.argmin(np.linalg.norm(options - nuis.omega[None], axis=2), axis=0)
    k = np.arange(f)
    bwd = np.clip(k - 1, 0, f - 2)
    fwd = np.clip(k, 0, f - 2)
    for j, (wb, wf) in enumerate(((1.0, 0.0), (0.0, 1.0), (0.5, 0.5))):  # three candidates, not a per-frame loop
        sel = choice == j
        np.add.at(c, (k[sel], bwd[sel]), wb)
        np.add.at(c, (k[sel], fwd[sel]), wf)
    return c


def tied_rates(attitude, t_ref_ns: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Body rates ``C @ steps`` of an attitude sequence (see :func:`rate_operator`)."""
    f = len(t_ref_ns)
    if f < 2:
        return np.zeros((f, 3))
    dt = np.diff(t_ref_ns).astype(float) / NS_PER_S
    steps = (attitude[:-1].inv() * attitude[1:]).as_rotvec() / dt[:, None]
    return c @ steps


def joint_refit(obs: Observations, nuis: Nuisance, camera, timing, base_effects, candidates: list[Candidate],
                thetas: list[np.ndarray], mask: np.ndarray, moving: bool, max_nfev: int = 30) -> dict:
    """Joint nonlinear least squares over every frame's attitude and the effect parameters, with
    the rates tied to the attitudes; the covariance then carries the rate uncertainty.

    The variable-projection :func:`refit` holds each frame's rate fixed at the finite difference
    of the attitude sequence fitted *before* the effects were modelled, and its covariance treats
    those rates as exact. But within a frame a rate error is a time-proportional rotation that
    trades against every time-like effect (rolling shutter, smear, acceleration...), and the rate
    is itself estimated from the noisy attitudes. Here the parameters are ``x = (delta, z)``: a
    body rotation ``delta_k`` per frame with training stars (``R_k -> R_k Exp(delta_k)``) and the
    prior-scaled effect parameters ``z``; the rates are ``omega = C steps(R)``
    (:func:`rate_operator`, zero for a recording that does not move). Residuals are the whitened
    training residuals. Jacobian (Gauss-Newton, first order in the small inter-frame rotation)::

        d p_i / d delta_j = P_i [w_i]_x (1[k(i) = j] + dt_i (C D)_{k(i) j})
        D_{s j} = (1[j = s+1] - 1[j = s]) / dt_s                (d steps_s / d delta_j)

    (``P_i [w_i]_x`` the attitude Jacobian through the effect chain; ``R(t_i) = R_k Exp(omega_k dt_i)``
    makes a rate change a rotation ``dt_i d omega``) and central differences in ``z``. The
    covariance of ``z`` is the ``z`` block of ``(J^T J)^-1`` (noise known), i.e. the attitudes
    *and* the rates they imply are profiled out. Returns the same keys as :func:`refit`.
    """
    if not candidates:
        return {"thetas": [], "sigmas": [], "corr": np.zeros((0, 0)), "nuisance": nuis, "success": True, "cost": None}
    prob = _joint_problem(obs, nuis, camera, timing, base_effects, candidates, mask, moving)
    m, nf = prob.m, prob.nf
    z0 = np.concatenate([(t - cand.defaults) / cand.scales for cand, t in zip(candidates, thetas)])
    z0, lo, hi = _within_bounds(candidates, z0)
    x0 = np.concatenate([np.zeros(3 * nf), z0])
    lb = np.concatenate([np.full(3 * nf, -np.inf), lo])
    ub = np.concatenate([np.full(3 * nf, np.inf), hi])
    try:
        res = least_squares(prob.fun, x0, jac=prob.jac, bounds=(lb, ub), method="trf", x_scale="jac", max_nfev=max_nfev)
    except (ValueError, np.linalg.LinAlgError):
        return {"thetas": list(thetas), "sigmas": [np.full(len(cand.parameters), np.nan) for cand in candidates],
                "corr": np.full((m, m), np.nan), "nuisance": nuis, "success": False, "cost": None}
    out_s, corr = _sigmas_and_corr(_inverse_normal(prob.jac(res.x))[3 * nf:, 3 * nf:], candidates)
    n2, th = prob.state(res.x)
    return {"thetas": th, "sigmas": out_s, "corr": corr, "nuisance": n2, "success": bool(res.success),
            "cost": float(2 * res.cost), "rates_tied": prob.tied}


@dataclass(frozen=True, eq=False)
class _JointProblem:
    """The residuals and Jacobian of :func:`joint_refit` over ``x = (delta, z)``."""

    obs: Observations
    nuis: Nuisance  # the start: attitudes ``att0`` every ``delta`` rotates, and the untied rates
    camera: object
    timing: object
    base_effects: tuple
    candidates: list[Candidate]
    free: np.ndarray  # (F,) frames with training stars: the ones with a free rotation
    tied: bool  # rates follow the attitudes (a moving recording with >= 2 frames)
    c: np.ndarray | None  # :func:`rate_operator`, when tied
    cd: np.ndarray | None  # (F, F) d omega_k / d delta_j (times I3), when tied
    idx: np.ndarray  # the training observations
    dt_i: np.ndarray
    k_i: np.ndarray
    g_att: np.ndarray | None  # whitened d(increment rows)/d delta of the free frames, with a gyro

    @property
    def nf(self) -> int:
        return int(self.free.sum())

    @property
    def m(self) -> int:
        return sum(len(cand.parameters) for cand in self.candidates)

    def state(self, x):
        """The nuisance and per-candidate parameters of ``x``."""
        f, nf = self.obs.n_frames, self.nf
        rv = np.zeros((f, 3))
        rv[self.free] = x[:3 * nf].reshape(nf, 3)
        att = self.nuis.attitude * Rotation.from_rotvec(rv)
        omega = tied_rates(att, self.obs.t_ref_ns, self.c) if self.tied else self.nuis.omega
        return Nuisance(att, omega), split_theta(self.candidates, x[3 * nf:])

    def predict_at(self, nuis: Nuisance, thetas) -> Prediction:
        return predict(self.obs, nuis, self.camera, self.timing, chain_with(self.base_effects, self.candidates, thetas))

    def fun(self, x):
        """Whitened training residuals (x, then y), then the gyro increment rows."""
        obs, idx = self.obs, self.idx
        p = self.predict_at(*self.state(x))
        w = whitened_residuals(obs, p, idx)
        return np.nan_to_num(np.concatenate([w[:, 0], w[:, 1], channel_rows(obs, p)]), nan=1e6)

    def jac(self, x):
        """Rows as :meth:`fun`; columns the free frames' rotations, then ``z`` (joint_refit doc)."""
        n2, th = self.state(x)
        p = self.predict_at(n2, th)
        jd = self._attitude_columns(p)
        jz, gz = self._effect_columns(x, n2)
        full = np.concatenate([jd, jz], axis=2)
        rows = [full[:, 0, :], full[:, 1, :]]
        if self.obs.channel is not None:  # increment rows: d e / d delta (+I next frame, -I this frame), whitened
            rows.append(np.concatenate([self.g_att, gz], axis=1))
        return np.concatenate(rows)

    def _attitude_columns(self, p: Prediction) -> np.ndarray:
        """d(whitened residual)/d delta of the free frames, (N, 2, 3 nf), with the tied rates' share."""
        idx, k_i, f = self.idx, self.k_i, self.obs.n_frames
        aj = whiten(self.obs, p.att_jac[idx], idx)  # (N, 2, 3)
        jd = np.zeros((idx.size, 2, f, 3))
        jd[np.arange(idx.size), :, k_i, :] = aj
        if self.tied:
            jd += (aj[:, :, None, :] * (self.dt_i[:, None, None, None] * self.cd[k_i][:, None, :, None]))
        return -jd[:, :, self.free, :].reshape(idx.size, 2, 3 * self.nf)

    def _effect_columns(self, x, n2: Nuisance) -> tuple[np.ndarray, np.ndarray]:
        """Central differences in ``z``: image columns (N, 2, m) and gyro increment columns (rows, m)."""
        obs, idx, m, nf = self.obs, self.idx, self.m, self.nf
        chan = obs.channel
        jz = np.zeros((idx.size, 2, m))
        gz = np.zeros((0 if chan is None else chan.rows, m))
        for j in range(m):  # p columns by central differences (the effects' Jacobians are at theta only)
            h = 1e-3 * max(1.0, abs(x[3 * nf + j]))
            out, gout = [], []
            for s in (1.0, -1.0):
                zz = x[3 * nf:].copy()
                zz[j] += s * h
                pp = self.predict_at(n2, split_theta(self.candidates, zz))
                out.append(np.stack([pp.x[idx], pp.y[idx]], axis=-1))
                gout.append(channel_rows(obs, pp))
            jz[:, :, j] = whiten(obs, -(out[0] - out[1]) / (2 * h), idx)
            if chan is not None:
                gz[:, j] = (gout[0] - gout[1]) / (2 * h)
        return jz, gz


def _joint_problem(obs: Observations, nuis: Nuisance, camera, timing, base_effects, candidates: list[Candidate],
                   mask: np.ndarray, moving: bool) -> _JointProblem:
    """Set up :class:`_JointProblem`: free frames, the rate operator and its Jacobian, training rows."""
    f = obs.n_frames
    free = np.bincount(obs.frame[mask], minlength=f) > 0
    nf = int(free.sum())
    tied = bool(moving) and f >= 2
    c = rate_operator(nuis, obs.t_ref_ns) if tied else None
    cd = None
    if tied:
        dts = np.diff(obs.t_ref_ns).astype(float) / NS_PER_S
        d = np.zeros((f - 1, f))
        d[np.arange(f - 1), np.arange(f - 1)] = -1.0 / dts
        d[np.arange(f - 1), np.arange(1, f)] = 1.0 / dts
        cd = c @ d  # (F, F): d omega_k / d delta_j (times I3)
    idx = np.flatnonzero(mask)
    chan = obs.channel
    g_att = None if chan is None else chan.attitude_rows(f).reshape(chan.rows, f, 3)[:, free, :].reshape(chan.rows, 3 * nf)
    return _JointProblem(obs, nuis, camera, timing, tuple(base_effects), candidates, free, tied, c, cd, idx,
                         obs.dt_s()[idx], obs.frame[idx], g_att)


def _within_bounds(candidates: list[Candidate], z0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Prior-scaled parameter bounds ``lo, hi`` of ``candidates``, and ``z0`` moved just inside them."""
    lo = np.concatenate([[(p.bounds[0] - p.default) / p.prior_scale for p in c.parameters] for c in candidates])
    hi = np.concatenate([[(p.bounds[1] - p.default) / p.prior_scale for p in c.parameters] for c in candidates])
    return np.clip(z0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo)), lo, hi


def _inverse_normal(jac: np.ndarray) -> np.ndarray:
    """``(J^T J)^-1`` of a whitened Jacobian (pseudo-inverse when singular): the parameter covariance."""
    jtj = jac.T @ jac
    try:
        return np.linalg.inv(jtj)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(jtj)


def _sigmas_and_corr(cov_z: np.ndarray, candidates) -> tuple[list[np.ndarray], np.ndarray]:
    """Per-candidate 1-sigma in parameter units (scaled ``z``) and the correlation matrix of ``cov_z``."""
    sd_z = np.sqrt(np.clip(np.diag(cov_z), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_z / np.outer(sd_z, sd_z)
    sig_theta = sd_z * np.concatenate([c.scales for c in candidates])
    bounds = np.cumsum([0] + [len(c.parameters) for c in candidates])
    return [sig_theta[a:b] for a, b in zip(bounds[:-1], bounds[1:])], corr
