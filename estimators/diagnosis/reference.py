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
for an effect the stars see only through the attitude, the image residual depends on the attitude
and the effect only through their sum, so profiling the joint least squares (stars plus prior) over
the attitudes leaves exactly the weighted fit of ``a_k theta`` to ``e_k`` with covariance
``C_k + sigma_ref^2 I``. The candidates tested here are those the stars' selection set aside: the
ones the attitude absorbs, and the ones that even at their bounds would move the stars by less than
a sigma; for the latter the identity holds to the extent that their visible part is negligible.

Each candidate is fitted to ``e`` alone; a delta BIC above the diagnosis's margin, with its values
within their bounds, makes it *tested by the reference*, with its estimate and sigma. The
candidates then enter a joint model by forward selection under the stars' rules (:mod:`.selection`:
each step adds the one that lowers BIC most, while it does by more than the margin; pairs the data
cannot tell apart are reported), with one more: a set whose fit puts a candidate outside its bounds
is no explanation. The joint model's parameters go to the updated scenario. The chi-square of ``e``
with no effect checks that reference and fitted attitudes agree; the joint model's chi-square shows
how much of it the effects explain.
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
from rollingstar.estimators.diagnosis.selection import (
    ABSORBED_FRACTION,
    BIC_WINDOW,
    CORR_LIMIT,
    DECISIVE_SWAP_BIC,
    canonical_correlation,
)
from rollingstar.sensors.conventions import ARCSEC_TO_RAD

MISALIGNED = "a misaligned reference"
MISALIGNED_EXPERIMENT = ("a reference known to be aligned with the camera (a simulation's truth, a surveyed mount); "
                         "for a second tracker or an unsurveyed mount, --reference-mount-free fits the misalignment "
                         "and leaves this effect untested")


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
    rank_after: int = 0  # parameters the joint model determines
    ambiguous: list[dict] = field(default_factory=list)  # pairs the reference cannot tell apart
    mount: dict | None = None  # the reference's fitted misalignment, when it is free (:func:`reference_check`)

    @property
    def tested(self) -> list[str]:
        return [r["name"] for r in self.rows if r["tested"]]

    def as_json(self) -> dict:
        z = float(z_from_sf(stats.chi2.sf(self.chi2, self.dof))) if self.dof else None
        return {"sigma_arcsec": self.sigma_arcsec, "frames": self.frames, "chi2": self.chi2, "dof": self.dof,
                "z": z, "candidates": self.rows, "model": self.model_params,
                "chi2_after": self.chi2_after if self.model else self.chi2, "dof_after": self.dof - self.rank_after,
                "ambiguous": self.ambiguous, "mount": self.mount}


def reference_check(data, model, cands: dict[str, Candidate], names: list[str], reference: Rotation,
                    covered: np.ndarray, sigma_arcsec: float, min_delta_bic: float,
                    base: dict[str, dict] | None = None, mount_free: bool = False) -> ReferenceCheck:
    """Test the candidates ``names`` against ``reference`` (one attitude per frame at its reference
    time; frames where ``covered`` is False are left out). ``data``: the diagnosis's dataset,
    ``model``: the named model (its attitudes and prediction); ``base``: the scenario's effects
    (kind -> parameters), to which the values reported are added.

    ``mount_free``: the reference is not aligned with the camera (a second tracker, a mount): a
    constant rotation ``m`` (``R_ref = R_camera exp(m)``, camera axes) is fitted with every model,
    by projecting it out of ``e`` and of every candidate's rotations (Frisch-Waugh-Lovell: the same
    estimates as fitting it jointly), and reported. An effect that is a constant rotation (a
    boresight roll, over a narrow field a principal-point shift) then cannot be tested. Without it,
    such an effect is reported as not told apart from a misaligned reference."""
    obs, pred = data.obs, model.prediction
    sigma = sigma_arcsec * ARCSEC_TO_RAD
    e = (reference.inv() * model.nuisance.attitude).as_rotvec()  # (F, 3)
    cov = attitude_covariances(obs.frame, obs.n_frames, pred.att_jac, obs.sigma, data.att_mask, obs.cov)
    use = covered & np.all(np.isfinite(e), axis=1) & data.frame_has_train & np.all(np.isfinite(cov), axis=(1, 2))
    w = np.linalg.pinv(cov[use] + sigma**2 * np.eye(3), hermitian=True)  # (F', 3, 3)
    e = e[use]
    chi2 = float(np.einsum("ki,kij,kj->", e, w, e))
    aj = whiten(obs, pred.att_jac)
    idx = np.flatnonzero(data.att_mask)
    n_rows = 3 * int(use.sum())
    cols = {}
    for name in names:
        j = whiten(obs, cands[name].signature(pred.ctx, model.effects, pred.exposure_ns))
        a = absorbed_rotations(obs.frame[idx], obs.n_frames, aj[idx], j[idx])[use]  # (F', 3, p) rad per unit
        # a signature the recording cannot evaluate (times that place stars outside what the effect
        # models) determines nothing: a zero column, reported as not determined, never a NaN fit
        cols[name] = a if np.all(np.isfinite(a)) else np.zeros_like(a)
    e_given, cols_given, like = e, dict(cols), {}
    if mount_free:
        root = _whitening_root(w)
        like = {n: _like_a_constant(a, root) for n, a in cols.items()}
        e, cols = _without_mount(e, w), {n: _mount_projected(a, w) for n, a in cols.items()}
        chi2 = float(np.einsum("ki,kij,kj->", e, w, e))
    sel = _Selection(cols, w, e, cands, np.log(max(n_rows, 2)), base or {}, not mount_free, like)
    rows = [sel.alone(name, min_delta_bic) for name in names]
    chosen = sel.forward(names, min_delta_bic)
    out = ReferenceCheck(float(sigma_arcsec), int(use.sum()), chi2, n_rows - 3 * mount_free, rows)
    if mount_free:
        # the model's columns as given, less those the common rotation absorbs (zero when projected)
        given = {n: np.where(np.any(cols[n] != 0.0, axis=(0, 1)), cols_given[n], 0.0) for n in chosen}
        out = replace(out, mount=_mount(e_given, given, w, chosen))
    if not chosen:
        return out
    theta, inv, removed, rank = sel.fit(chosen)
    model, params, k = [], [], 0
    for name in chosen:
        c = cands[name]
        p = len(c.parameters)
        model.append((c, np.array([q.default for q in c.parameters]) + theta[k:k + p]))
        params.append({"name": name, "params": sel.params(name, theta[k:k + p], inv[k:k + p, k:k + p])})
        k += p
    return replace(out, model=model, model_params=params, chi2_after=max(chi2 - removed, 0.0), rank_after=rank,
                   ambiguous=sel.ambiguous(chosen, names))


def _without_mount(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``x`` (F', 3[, p]) less its weighted least-squares fit by one rotation common to every frame."""
    common = np.linalg.solve(w.sum(axis=0), np.einsum("kij,kj...->i...", w, x))
    return x - common


def _mount_projected(a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """A candidate's rotations ``a`` (F', 3, p) without the common rotation; a column the common
    rotation absorbs (numerically zero against its norm, ``ABSORBED_FRACTION``, as the stars'
    selection judges) is set to zero, so that the fit counts it as undetermined."""
    projected = _without_mount(a, w)
    norm = np.sqrt(np.einsum("kip,kij,kjp->p", a, w, a))
    kept = np.sqrt(np.einsum("kip,kij,kjp->p", projected, w, projected)) > ABSORBED_FRACTION * norm
    return np.where(kept, projected, 0.0)


def _constant(n_frames: int) -> np.ndarray:
    """The rotations (F', 3, 3) of one rotation common to every frame, per axis: the misalignment's."""
    return np.broadcast_to(np.eye(3), (n_frames, 3, 3))


def _like_a_constant(a: np.ndarray, root: np.ndarray) -> bool:
    """Whether rotations ``a`` (F', 3, p) are collinear with a constant one (canonical correlation
    above ``CORR_LIMIT`` of the whitened columns, ``root``: :func:`_whitening_root`): a free mount
    takes up nearly all of them."""
    return canonical_correlation(_whiten(a, root), _whiten(_constant(a.shape[0]), root)) > CORR_LIMIT


def _whitening_root(w: np.ndarray) -> np.ndarray:
    """``R`` (F', 3, 3) with ``w = R R^T``, from the eigen-decomposition, so that a singular ``w``
    has one too."""
    vals, vecs = np.linalg.eigh(w)
    return vecs * np.sqrt(np.clip(vals, 0.0, None))[:, None, :]


def _whiten(a: np.ndarray, root: np.ndarray) -> np.ndarray:
    """Rotations ``a`` (F', 3, p) whitened (``R^T a``), stacked over frames."""
    return np.einsum("kji,kjp->kip", root, a).reshape(-1, a.shape[2])


def _mount(e: np.ndarray, cols: dict[str, np.ndarray], w: np.ndarray, chosen: list[str]) -> dict:
    """The reference's misalignment ``m`` (``R_ref = R_camera exp(m)``, arcsec per camera axis) and
    its sigma: the common rotation (``-m``) fitted jointly with the model ``chosen`` (columns as
    given, not projected), its sigma marginal over the model's parameters."""
    design = np.concatenate([_constant(e.shape[0]), *(cols[n] for n in chosen)], axis=2)
    estimate, cov, _, _ = weighted_fit(design, w, e)
    sigma = np.sqrt(np.clip(np.diag(cov)[:3], 0.0, None))
    return {"rotation_arcsec": (-estimate[:3] / ARCSEC_TO_RAD).tolist(), "sigma_arcsec": (sigma / ARCSEC_TO_RAD).tolist()}


def weighted_fit(a: np.ndarray, w: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Weighted least squares of ``a theta`` (F', 3, p) to ``e`` (F', 3) with weights ``w`` (F', 3, 3):
    the estimate, its covariance, the chi-square it removes and the rank of the fit (the parameters
    the data determine; a pseudo-inverse leaves the others at zero with zero variance)."""
    normal = np.einsum("kip,kij,kjq->pq", a, w, a)
    rhs = np.einsum("kip,kij,kj->p", a, w, e)
    inv = np.linalg.pinv(normal, hermitian=True)
    theta = inv @ rhs
    rank = int(np.linalg.matrix_rank(normal, hermitian=True)) if normal.size else 0
    return theta, inv, float(rhs @ theta), rank


class _Selection:
    """Joint fits of sets of candidates to the attitude differences, and the choices made on them:
    the rules of the stars' selection (:mod:`.selection`), on ``e`` instead of the image residual.
    A fit that puts a candidate outside its bounds is no explanation: that candidate is not chosen,
    and not offered as an alternative, in that set."""

    def __init__(self, cols, w, e, cands, log_n: float, base: dict[str, dict], mount_fixed: bool = True,
                 like_the_mount: dict[str, bool] | None = None):
        self.cols, self.w, self.e, self.cands, self.log_n, self.base = dict(cols), w, e, cands, log_n, base
        self.mount_fixed, self.like_the_mount = mount_fixed, like_the_mount or {}
        self.root = _whitening_root(w)
        if mount_fixed:  # a misaligned reference, the alternative :meth:`ambiguous` offers every chosen effect
            self.cols[MISALIGNED] = _constant(e.shape[0])
        self._fits: dict[tuple, tuple] = {(): (np.zeros(0), np.zeros((0, 0)), 0.0, 0)}

    def fit(self, names) -> tuple[np.ndarray, np.ndarray, float, int]:
        key = tuple(names)
        if key not in self._fits:
            self._fits[key] = weighted_fit(np.concatenate([self.cols[n] for n in key], axis=2), self.w, self.e)
        return self._fits[key]

    def bic(self, names) -> float:
        """BIC up to a constant: the chi-square left plus ln(n) per determined parameter."""
        _, _, removed, rank = self.fit(names)
        return -removed + rank * self.log_n

    def within_bounds(self, names) -> bool:
        theta, k = self.fit(names)[0], 0
        for name in names:
            c = self.cands[name]
            value = np.array([q.default for q in c.parameters]) + theta[k:k + len(c.parameters)]
            if np.any(value < c.lower) or np.any(value > c.upper):
                return False
            k += len(c.parameters)
        return True

    def params(self, name: str, theta: np.ndarray, cov: np.ndarray) -> dict:
        """Each parameter's value in the updated scenario (the scenario's, else the default, plus
        ``theta``), sigma and unit."""
        given = self.base.get(name, {})
        return {p.name: {"value": float(given.get(p.name, p.default) + t), "sigma": float(np.sqrt(max(s, 0.0))),
                         "unit": p.unit} for p, t, s in zip(self.cands[name].parameters, theta, np.diag(cov))}

    def alone(self, name: str, min_delta_bic: float) -> dict:
        """The candidate fitted alone: tested when it lowers BIC by the margin within its bounds (an
        effect the free mount absorbs has nothing left to fit: rank 0, not tested)."""
        theta, inv, removed, rank = self.fit((name,))
        dbic = self.bic(()) - self.bic((name,))
        inside = self.within_bounds((name,))
        return {"name": name, "params": self.params(name, theta, inv), "delta_chi2": removed,
                "delta_bic": float(dbic), "within_bounds": inside, "determined": rank > 0,
                "like_the_mount": bool(self.like_the_mount.get(name, False)),
                "tested": bool(dbic > min_delta_bic and inside and rank > 0)}

    def forward(self, names: list[str], min_delta_bic: float) -> list[str]:
        """Forward selection: add the candidate that lowers BIC most, within bounds, while it lowers it
        by more than ``min_delta_bic``. Equal gains (collinear candidates) go to the first by name."""
        chosen: tuple[str, ...] = ()
        while True:
            best, best_gain = None, min_delta_bic
            for name in sorted(set(names) - set(chosen)):
                trial = (*chosen, name)
                gain = self.bic(chosen) - self.bic(trial)
                if gain > best_gain + 1e-9 * max(1.0, abs(best_gain)) and self.within_bounds(trial):
                    best, best_gain = name, gain
            if best is None:
                return list(chosen)
            chosen = (*chosen, best)

    def ambiguous(self, chosen: list[str], names: list[str]) -> list[dict]:
        """Pairs the reference cannot tell apart, as :func:`.selection.ambiguities` finds them: a
        chosen candidate and another whose swap for it costs less than ``BIC_WINDOW``, or that is
        collinear with it and whose swap is not decisive; two chosen candidates that are collinear."""
        rows, base = [], self.bic(chosen)
        for g in chosen:
            rest = [n for n in chosen if n != g]
            for h in (n for n in names if n not in chosen):
                swap = self.bic([*rest, h]) - base
                corr = canonical_correlation(self._whitened(g), self._whitened(h))
                if self.within_bounds([*rest, h]) and (swap < BIC_WINDOW or (corr > CORR_LIMIT and swap < DECISIVE_SWAP_BIC)):
                    rows.append(self._pair(g, h, corr, swap))
        for i, g in enumerate(chosen):
            for h in chosen[i + 1:]:
                corr = canonical_correlation(self._whitened(g), self._whitened(h))
                if corr > CORR_LIMIT:
                    rows.append(self._pair(g, h, corr, 0.0))
        if self.mount_fixed:  # a misaligned reference (a constant rotation) as the alternative, by the same rule
            for g in chosen:
                swap = self.bic([*(n for n in chosen if n != g), MISALIGNED]) - base
                corr = canonical_correlation(self._whitened(g), self._whitened(MISALIGNED))
                if swap < BIC_WINDOW or (corr > CORR_LIMIT and swap < DECISIVE_SWAP_BIC):
                    rows.append(self._pair(g, MISALIGNED, corr, swap))
        return rows

    def _pair(self, g: str, h: str, corr: float, swap: float) -> dict:
        experiment = MISALIGNED_EXPERIMENT if h == MISALIGNED else separating_experiment(self.cands[g], self.cands[h])
        return {"candidates": [g, h], "corr": corr, "delta_bic_swap": float(swap), "separating_experiment": experiment}

    def _whitened(self, name: str) -> np.ndarray:
        return _whiten(self.cols[name], self.root)
