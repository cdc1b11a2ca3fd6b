"""The recording's noise against the noise the diagnosis was told: one factor, measured from the
frame-to-frame scatter of the same stars.

Every effect of the library moves a star's residual smoothly over the detector and in time. A star
seen in two consecutive frames sits at almost the same place, row time and image speed in both, so
the difference of its two whitened residuals cancels what such an effect does and keeps
``sqrt(2)`` times the white noise. Only pairs that moved less than ``MAX_SHIFT_FRACTION`` of the
detector between the frames count (consecutive images of unrelated scenes, or a fast slew, give
none), and the residuals are those of the model the diagnosis named, so that strong physics it
has modelled does not leak into the differences. The RMS of those differences over ``sqrt(2)`` is the factor by
which the stated noise is wrong, measured without modelling the physics first. Differences beyond
``CLIP`` robust sigmas (a rate reversal at that frame boundary, a wrong identification) are left
out; at 5 sigma that clips a normal sample's RMS by less than 0.01 %.

Each frame's attitude is fitted to its own stars, which takes part of their noise into the fit: a
residual's expected variance is ``1 - h`` of the noise's, with ``h`` the star's leverage on its
frame's attitude (half the trace of its 2 x 2 block of the hat matrix; 3 / (2 n) on average over
a frame of ``n`` stars, 17 % at 9 stars). Each difference is divided by its expected spread
(studentised residuals) before the scale is taken.

Every pair of consecutive frames is used; differences along one star's chain share an
observation (correlation -1/2 between neighbours), so the standard error of ``ln(factor)`` from
``m`` differences is ``sqrt(0.75 / m)`` instead of ``sqrt(0.5 / m)`` (variance of a mean of squares
with neighbour correlation rho^2 = 1/4: 1 + 2/4). Only training stars are used, so the held-out
test stays independent.

The factor is applied (every sigma and covariance scaled, and the diagnosis run again) when it is
beyond sampling (``NOISE_Z`` standard errors) and beyond ``MIN_CHANGE``: a noise model off by a
few per cent changes no decision. A recording whose smooth physics changes much between two frames
(a rate reversal at that frame boundary) contributes a few large differences; the clip leaves them out.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rollingstar.estimators.diagnosis.observations import Observations, Prediction, whiten, whitened_residuals

MAD_TO_SIGMA = 1.4826
CLIP = 5.0  # differences beyond this many robust sigmas are not noise
CHAIN_VARIANCE = 0.75  # m * var(ln s) from m differences along stars' chains (module doc)
MIN_DIFFERENCES = 40  # fewer differences (x and y of 20 pairs): the factor is not measured
NOISE_Z = 4.0  # two-sided p = 6e-5 of applying a factor to a recording whose stated noise is right
MIN_CHANGE = 0.05  # |ln factor| below this is not applied (5 %)
MAX_SHIFT_FRACTION = 1.0 / 32.0  # a pair's star moved less than this share of the detector's larger side


@dataclass(frozen=True)
class NoiseCheck:
    """The measured noise factor: recorded noise / stated noise."""

    factor: float
    sigma_ln: float  # standard error of ln(factor)
    pairs: int  # differences taken: a star seen in two consecutive frames (training stars)
    stated_source: str  # where the stated noise came from (the recording, the scenario)
    stated_sigma_px: float  # median stated sigma per axis
    applied: bool

    def as_json(self) -> dict:
        return {"factor": self.factor, "factor_sigma": self.factor * self.sigma_ln, "pairs": self.pairs,
                "stated_source": self.stated_source, "stated_sigma_px": self.stated_sigma_px, "applied": self.applied,
                "method": "RMS of the differences of the same star's studentised residuals in consecutive frames / sqrt(2)"}

    def sentence(self) -> str:
        """The noise-model mismatch in words (only meaningful when applied)."""
        return (f"noise-model mismatch: the recording's centroid noise is {self.factor:.2f} +- "
                f"{self.factor * self.sigma_ln:.2f} x the stated ({self.stated_source}), measured from "
                f"{self.pairs} stars seen in consecutive frames; not library physics, the diagnosis used the measured noise")


def measure(obs: Observations, pred: Prediction, use: np.ndarray, att_mask: np.ndarray, camera) -> NoiseCheck | None:
    """The noise factor of ``obs`` against ``pred`` over the stars ``use`` (None: too few pairs);
    ``att_mask``: the stars each frame's attitude was fitted to."""
    first, second = consecutive_pairs(obs, use)
    near = np.hypot(pred.x[second] - pred.x[first], pred.y[second] - pred.y[first]) \
        < MAX_SHIFT_FRACTION * max(camera.width, camera.height)
    first, second = first[near], second[near]
    if 2 * first.size < MIN_DIFFERENCES:
        return None
    w = whitened_residuals(obs, pred)
    spread = 1.0 - attitude_leverage(obs, pred, att_mask)
    diff = ((w[second] - w[first]) / np.sqrt(spread[first] + spread[second])[:, None]).ravel()
    robust = MAD_TO_SIGMA * float(np.median(np.abs(diff)))
    diff = diff[np.abs(diff) <= CLIP * robust]
    if diff.size < MIN_DIFFERENCES or robust <= 0.0:
        return None
    factor = float(np.sqrt(np.mean(diff**2)))
    # the attitude fit correlates the residuals of a frame's stars: the spread of the estimate grows
    # by about 1 + mean leverage (the share of each star's noise the attitude fit takes)
    sigma_ln = float(np.sqrt(CHAIN_VARIANCE / diff.size)) * (1.0 + float(np.mean(1.0 - spread[first])))
    big = abs(np.log(factor)) > max(NOISE_Z * sigma_ln, MIN_CHANGE)
    return NoiseCheck(factor, sigma_ln, int(first.size), obs.sigma_source, float(np.median(obs.sigma)), bool(big))


def attitude_leverage(obs: Observations, pred: Prediction, att_mask: np.ndarray) -> np.ndarray:
    """Each star's leverage on its frame's attitude fit (n,): half the trace of its 2 x 2 hat block
    (0 for stars the attitude was not fitted to)."""
    jac = whiten(obs, pred.att_jac)  # (n, 2, 3) in noise units, through the effect chain
    info = np.zeros((obs.n_frames, 3, 3))
    np.add.at(info, obs.frame[att_mask], np.einsum("nki,nkj->nij", jac[att_mask], jac[att_mask]))
    cov = np.linalg.pinv(info)[obs.frame]
    h = np.einsum("nki,nij,nkj->n", jac, cov, jac) / 2.0
    return np.where(att_mask, np.clip(h, 0.0, 0.9), 0.0)


def consecutive_pairs(obs: Observations, use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the same catalogue star in consecutive frames (both in ``use``)."""
    idx = np.flatnonzero(use & (obs.catalog_id >= 0))
    order = idx[np.lexsort((obs.frame[idx], obs.catalog_id[idx]))]
    a, b = order[:-1], order[1:]
    same = (obs.catalog_id[a] == obs.catalog_id[b]) & (obs.frame[b] == obs.frame[a] + 1)
    return a[same], b[same]


def scaled(obs: Observations, check: NoiseCheck) -> Observations:
    """``obs`` with every sigma (and covariance) scaled by the measured factor."""
    f = check.factor
    return replace(obs, sigma=obs.sigma * f, cov=None if obs.cov is None else obs.cov * f * f, noise_sigma_ln=check.sigma_ln,
                   sigma_source=f"{obs.sigma_source}, scaled by {f:.3g} (measured noise factor)")


def combined(first: NoiseCheck, again: NoiseCheck) -> NoiseCheck:
    """The factor against the stated noise when ``again`` was measured on observations scaled by
    ``first`` (when ``first`` was applied) or unscaled; its uncertainty is ``again``'s."""
    factor = (first.factor if first.applied else 1.0) * again.factor
    big = abs(np.log(factor)) > max(NOISE_Z * again.sigma_ln, MIN_CHANGE)
    return NoiseCheck(factor, again.sigma_ln, again.pairs, first.stated_source, first.stated_sigma_px, bool(big))


OVERSTATED_P = 1e-3  # lower-tail probability of the fit's chi-square below which the stated noise is said to be too large


def overstated(obs: Observations, pred: Prediction, kept: np.ndarray, frames_fitted: int, k: int) -> dict | None:
    """The stated noise against the final model's chi-square over every star it kept (training and
    held out), when the recording has no repeated stars to measure a factor from (a single image,
    unrelated scenes): a chi-square in its lower tail (below ``OVERSTATED_P``) says the stated
    noise is larger than the residuals show (as a table whose stated accuracy includes a few
    poorly fitted stars does). Held-out stars the model misses raise the sum, so a model that
    fails the held-out test is never called overfitted to noise here. Not applied: with a noise
    too large the tests lose sensitivity, they do not name more. ``frames_fitted``: the attitudes
    fitted to these stars; ``k``: the named effects' parameters. None outside that tail."""
    from scipy import stats

    dof = 2 * int(kept.sum()) - 3 * frames_fitted - k
    if dof < 10:
        return None
    c = float(np.sum(np.sum(whitened_residuals(obs, pred)[kept] ** 2, axis=1)))
    p = float(stats.chi2.cdf(c, dof))
    if p >= OVERSTATED_P:
        return None
    return {"factor": float(np.sqrt(c / dof)), "chi2": c, "dof": dof, "p": p}
