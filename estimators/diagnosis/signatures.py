"""The linear problem of the selection: whitened residuals and candidate signatures, attitude projected out.

Rows are the training observations' x residuals, then their y residuals, each divided by its
sigma, then (with a gyro) the whitened attitude-increment rows (:mod:`.gyro_channel`). Every frame's
attitude is projected out of the residual and of each signature (:func:`.selection.project_frames`):
what the attitude can absorb cannot name an effect.
"""
from __future__ import annotations

import numpy as np

from rollingstar.estimators.diagnosis import gyro_channel, selection
from rollingstar.estimators.diagnosis.library import Candidate
from rollingstar.estimators.diagnosis.observations import Observations, Prediction, whiten, whitened_residuals


def candidate_signatures(obs: Observations, pred: Prediction, cands: dict[str, Candidate], base_effects, mask):
    """Whitened, prior-scaled, attitude-projected signatures of every testable candidate (rows of ``mask``).

    Returns ``(projected, raw, untestable)``: name -> projected signature rows, name -> the same
    rows before the projection, and ``{"name", "reason"}`` of every candidate that cannot be tested.
    """
    aj = whiten(obs, pred.att_jac)
    groups, raw, untestable = {}, {}, []
    chan = obs.channel
    for name, c in cands.items():
        why = c.testable(pred.ctx, gyro=chan is not None)
        if why is not None:
            untestable.append({"name": name, "reason": why})
            continue
        try:
            j = c.signature(pred.ctx, base_effects, pred.exposure_ns)
        except (ValueError, TypeError, NotImplementedError) as exc:
            untestable.append({"name": name, "reason": f"signature not available: {exc}"})
            continue
        j = whiten(obs, j) * c.scales[None, None, :]
        p = selection.project_frames(obs.frame, obs.n_frames, aj, j)
        groups[name] = np.concatenate([p[mask, 0, :], p[mask, 1, :]])  # rows: all x residuals, then all y
        raw[name] = np.concatenate([j[mask, 0, :], j[mask, 1, :]])
        if chan is not None:  # then the attitude-increment rows (gyro_channel module doc)
            inc = gyro_channel.image_effect_signature(gyro_channel.absorbed_rotations(obs.frame, obs.n_frames, aj, j))
            if "gyro" in c.channels:
                inc = inc + gyro_channel.gyro_signature(c.instance(), chan.gyro, obs.t_ref_ns) * c.scales[None, None, :]
            g = chan.whiten(inc)
            groups[name] = np.concatenate([groups[name], g])
            raw[name] = np.concatenate([raw[name], g])
    return groups, raw, untestable


def whitened_residual(obs: Observations, pred: Prediction, mask) -> np.ndarray:
    """The residual rows of ``pred`` on ``mask``, whitened, attitude projected out, gyro rows appended."""
    aj = whiten(obs, pred.att_jac)
    r = whitened_residuals(obs, pred)[:, :, None]
    p = selection.project_frames(obs.frame, obs.n_frames, aj, r)[:, :, 0]
    return np.concatenate([p[mask, 0], p[mask, 1], gyro_channel.channel_rows(obs, pred)])


def linear_problem(obs: Observations, pred: Prediction, cands: dict[str, Candidate], chain, mask, blocks,
                   add_back: dict[str, np.ndarray] | None = None) -> tuple[selection.LinearProblem, list[dict]]:
    """The projected, whitened linear problem at the model ``chain`` (``pred`` its prediction).

    ``add_back`` (name -> prior-scaled parameter offsets) adds the selected effects' linear
    contributions back to the residual, so that the problem is the selection problem linearised
    at the fitted model (used for screening, bootstrap and aliases of the final model).
    Returns the problem and the untestable candidates.
    """
    groups, raw, untestable = candidate_signatures(obs, pred, cands, chain, mask)
    r = whitened_residual(obs, pred, mask)
    for name, z in (add_back or {}).items():
        if name in groups:
            r = r + groups[name] @ z
    reach = {n: np.maximum(c.upper - c.defaults, c.defaults - c.lower) / c.scales for n, c in cands.items()}
    return selection.build_problem(r, groups, blocks, raw, reach), untestable
