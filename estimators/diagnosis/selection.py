"""Name the physics left out: nuisance projection, screening, forward stepwise BIC, bootstrap, aliases.

The linearised problem. With whitened residuals ``r`` (each axis divided by its sigma) and, for
every effect group ``g``, its whitened signature ``X_g = d(x, y)/d(theta_g)`` at ``theta_g = 0``,
the model ``r = N a + sum_g X_g theta_g + e``, ``e ~ N(0, I)``, has the per-frame attitude ``a``
as nuisance ``N`` (the image-plane Jacobian of a small body rotation). Frisch-Waugh-Lovell: the
least-squares ``theta`` are those of the projected problem ``M r = sum_g M X_g theta_g`` with
``M = I - N (N^T N)^-1 N^T``, done frame by frame (``N`` is block diagonal).

With known noise, ``-2 log L = chi2 + const`` and ``BIC = chi2 + k ln n`` (Schwarz 1978). Forward
stepwise selection over effect *groups* adds, at each step, the group that lowers BIC most and
stops when no group lowers it by ``min_delta_bic`` (10: "very strong" evidence on the Kass &
Raftery 1995 scale). Bootstrap inclusion probabilities repeat the selection on recordings
resampled by whole frames (the unit the nuisance acts on). Two candidates are *ambiguous* when
swapping one for the other changes BIC by less than ``bic_window`` points, or when their projected
signatures have a canonical correlation above ``corr_limit`` (0.95) and the swap costs less than
``DECISIVE_SWAP_BIC``: the data cannot tell them apart, and the report names both and the
experiment that would. A swap of 10 would be decisive for a correctly specified model; between
signatures this collinear, a small misfit elsewhere (another effect, the noise model) moves the
comparison by more, so a tenfold margin is asked before a correlated pair counts as told apart.
Above it the pair is not reported as ambiguous, whatever the correlation: a swap costing
thousands of BIC points is an answer.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rollingstar.estimators.diagnosis.observations import frame_normal, solve_frames

MIN_DELTA_BIC = 10.0
BIC_WINDOW = 6.0
CORR_LIMIT = 0.95
DECISIVE_SWAP_BIC = 100.0  # a correlated pair whose swap costs this much is told apart (module doc)
ABSORBED_FRACTION = 1e-6  # projected signature numerically zero against its raw norm: the attitude absorbs it


def project_frames(frame: np.ndarray, n_frames: int, att_jac: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Remove from whitened ``cols`` (n, 2, m) their least-squares fit by each frame's rotation.

    ``att_jac`` (n, 2, 3) must be whitened the same way. Returns (n, 2, m). Vectorised over stars
    with per-frame normal equations (``np.add.at``).
    """
    a, b = frame_normal(frame, n_frames, att_jac, np.ones(frame.shape[0]), cols)
    coef = solve_frames(a, b)  # (F, 3, m)
    return cols - np.einsum("nki,nim->nkm", att_jac, coef[frame])


@dataclass
class LinearProblem:
    """The projected, whitened problem over the training observations.

    ``r`` (N,), ``groups[name]`` (N, m) with columns scaled by the parameters' prior scales,
    ``blocks`` (N,) the resampling unit (frame, or star for a single image), ``raw_norm[name]``
    the column norms before projection.
    """

    r: np.ndarray
    groups: dict[str, np.ndarray]
    blocks: np.ndarray
    raw_norm: dict[str, np.ndarray] = field(default_factory=dict)
    absorbed: list[str] = field(default_factory=list)

    @property
    def n(self) -> int:
        return int(self.r.shape[0])

    def subset(self, rows: np.ndarray) -> "LinearProblem":
        return LinearProblem(self.r[rows], {k: v[rows] for k, v in self.groups.items()}, self.blocks[rows],
                             self.raw_norm, list(self.absorbed))


def build_problem(r: np.ndarray, groups: dict[str, np.ndarray], blocks: np.ndarray,
                  raw: dict[str, np.ndarray] | None = None, reach: dict[str, np.ndarray] | None = None) -> LinearProblem:
    """Drop what the nuisance absorbs and make the problem.

    A column is absorbed when its projected norm is numerically zero against its raw norm
    (``ABSORBED_FRACTION``) or when, even at the parameter's bound (``reach``: the largest
    ``|theta - default|`` in prior-scale units), it would move the whitened data by less than one
    sigma in total. A group with every column absorbed is listed in ``absorbed``.
    """
    kept, absorbed, raw_norm = {}, [], {}
    for name, x in groups.items():
        pn = np.linalg.norm(x, axis=0)
        rn = np.linalg.norm(raw[name], axis=0) if raw is not None and name in raw else pn
        raw_norm[name] = rn
        keep = np.isfinite(pn) & (pn > ABSORBED_FRACTION * np.maximum(rn, 1e-300))
        if reach is not None and name in reach:
            keep &= pn * reach[name] >= 1.0
        if not keep.any():
            absorbed.append(name)
            continue
        kept[name] = x[:, keep] if not keep.all() else x
    return LinearProblem(r, kept, blocks, raw_norm, absorbed)


def lstsq_chi2(r: np.ndarray, x: np.ndarray) -> tuple[float, np.ndarray, int]:
    """Residual chi2, coefficients and rank of the least-squares fit of ``r`` by ``x``."""
    if x.shape[1] == 0:
        return float(r @ r), np.zeros(0), 0
    coef, _, rank, _ = np.linalg.lstsq(x, r, rcond=1e-10)
    res = r - x @ coef
    return float(res @ res), coef, int(rank)


def design(problem: LinearProblem, names) -> np.ndarray:
    cols = [problem.groups[n] for n in names]
    return np.hstack(cols) if cols else np.zeros((problem.n, 0))


def bic(problem: LinearProblem, names) -> float:
    """``chi2 + k ln n`` of the model with the effect groups ``names``."""
    chi2, _, rank = lstsq_chi2(problem.r, design(problem, names))
    return chi2 + rank * np.log(problem.n)


def screen(problem: LinearProblem) -> list[dict]:
    """Each group alone: its delta BIC against no effect, best first."""
    base = bic(problem, [])
    rows = [{"name": n, "delta_bic": float(base - bic(problem, [n]))} for n in problem.groups]
    return sorted(rows, key=lambda r: -r["delta_bic"])


def forward_stepwise(problem: LinearProblem, min_delta_bic: float = MIN_DELTA_BIC,
                     max_groups: int = 3) -> list[dict]:
    """Forward stepwise selection on BIC over groups (module doc); returns the steps taken."""
    selected: list[str] = []
    steps = []
    current = bic(problem, selected)
    while len(selected) < max_groups:
        best, best_bic = None, None
        for name in problem.groups:
            if name in selected:
                continue
            b = bic(problem, selected + [name])
            if best_bic is None or b < best_bic:
                best, best_bic = name, b
        if best is None or current - best_bic < min_delta_bic:
            break
        steps.append({"name": best, "delta_bic": float(current - best_bic)})
        selected.append(best)
        current = best_bic
    return steps


def bootstrap_selections(problem: LinearProblem, n_boot: int = 50, seed: int = 0,
                         min_delta_bic: float = MIN_DELTA_BIC) -> list[set[str]]:
    """The groups selected in each block-bootstrap resample."""
    rng = np.random.default_rng(seed)
    ids = np.unique(problem.blocks)
    rows_of = {b: np.flatnonzero(problem.blocks == b) for b in ids}
    out = []
    for _ in range(n_boot):
        pick = rng.choice(ids, size=ids.size, replace=True)
        rows = np.concatenate([rows_of[b] for b in pick])
        out.append({step["name"] for step in forward_stepwise(problem.subset(rows), min_delta_bic)})
    return out


def bootstrap_inclusion(problem: LinearProblem, n_boot: int = 50, seed: int = 0,
                        min_delta_bic: float = MIN_DELTA_BIC, sets: list[set[str]] | None = None) -> dict[str, float]:
    """Fraction of block-bootstrap resamples in which each group is selected."""
    sets = bootstrap_selections(problem, n_boot, seed, min_delta_bic) if sets is None else sets
    return {n: (sum(n in s for s in sets) / len(sets) if sets else 0.0) for n in problem.groups}


def pooled_inclusion(sets: list[set[str]], name: str, aliases) -> float:
    """Fraction of resamples selecting ``name`` or one of its ``aliases`` (effects the data cannot
    tell from it: the bootstrap then splits its votes among them, while the report names the
    ambiguity)."""
    pool = {name, *aliases}
    return sum(bool(pool & s) for s in sets) / len(sets) if sets else 0.0


def canonical_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Largest canonical correlation (cosine of the smallest principal angle) of two column spaces."""
    if a.shape[1] == 0 or b.shape[1] == 0:
        return 0.0
    qa, _ = np.linalg.qr(a)
    qb, _ = np.linalg.qr(b)
    return float(np.clip(np.linalg.svd(qa.T @ qb, compute_uv=False)[0], 0.0, 1.0))


def ambiguities(problem: LinearProblem, selected: list[str], candidates: list[str],
                bic_window: float = BIC_WINDOW, corr_limit: float = CORR_LIMIT) -> list[dict]:
    """Pairs (selected effect, alternative) the data cannot tell apart (module doc)."""
    out = []
    base = bic(problem, selected)
    for g in selected:
        rest = [s for s in selected if s != g]
        for h in candidates:
            if h == g or h in selected:
                continue
            corr = canonical_correlation(design(problem, [g]), design(problem, [h]))
            swap = bic(problem, rest + [h]) - base
            if swap < bic_window or (corr > corr_limit and swap < DECISIVE_SWAP_BIC):
                out.append({"selected": g, "alternative": h, "corr": corr, "delta_bic_swap": float(swap)})
    for i, g in enumerate(selected):  # two selected effects that trade off against each other
        for h in selected[i + 1:]:
            corr = canonical_correlation(design(problem, [g]), design(problem, [h]))
            if corr > corr_limit:
                out.append({"selected": g, "alternative": h, "corr": corr, "delta_bic_swap": 0.0})
    return out


def select(problem: LinearProblem, n_boot: int = 50, seed: int = 0, min_delta_bic: float = MIN_DELTA_BIC,
           bic_window: float = BIC_WINDOW, corr_limit: float = CORR_LIMIT) -> dict:
    """Screen, select, bootstrap and check aliases; one dict with every intermediate result."""
    screened = screen(problem)
    steps = forward_stepwise(problem, min_delta_bic)
    selected = [s["name"] for s in steps]
    sets = bootstrap_selections(problem, n_boot, seed, min_delta_bic) if n_boot > 0 else []
    inclusion = bootstrap_inclusion(problem, sets=sets) if n_boot > 0 else {}
    candidates = [s["name"] for s in screened]
    amb = ambiguities(problem, selected, candidates, bic_window, corr_limit)
    corr_table = {g: {h: canonical_correlation(design(problem, [g]), design(problem, [h]))
                      for h in candidates if h != g} for g in selected}
    return {"screen": screened, "steps": steps, "selected": selected, "inclusion": inclusion, "bootstrap_sets": sets,
            "ambiguous": amb, "correlations": corr_table, "absorbed": list(problem.absorbed)}
