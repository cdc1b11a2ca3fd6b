"""Star-vector observations of one frame for the sequential estimators (``mekf``, ``gtsam``).

Each identified star gives a camera-frame unit vector ``b_i = camera.unproject(x_i, y_i)``
(he2021b eq 2; ``camera`` the frame's, :func:`rollingstar.estimators.data.frame_camera`), its
catalogue direction ``r_i`` (ICRS) and an isotropic angular 1-sigma ``sigma_i = sigma_px_i / focal_px``
rad (the pixel's angular size at the principal point; the off-axis foreshortening, about 1 % at
the edge of a 10 deg field, is neglected as in ``quest``). When a star of the frame carries a 2 x 2
position covariance that is not isotropic (and ``star_covariance`` is on), every star also gets the
exact 2 x 2 covariance of its direction in the tangent plane (``direction``,
:mod:`rollingstar.estimators.attitude.star_covariance`), which the estimators then use instead of
``sigma_i``; ``sigma_i`` is then the isotropic equivalent ``sqrt(trace(C_i) / 2) / focal_px``.
The observation refers to the time its position refers to, ``t_ns`` (for raw rolling-shutter
centroids the mid-exposure of the star's own row, ``row_time_ns + exposure / 2``; after a
correction stage the common time it moved the star to), so that the measurement model
``b_i = R(t_i)^T r_i`` holds without any rolling-shutter correction.

Stars are sorted by time and grouped into *states*: stars whose times differ by at most
``merge_ns`` share one state (one attitude estimate); with ``merge_ns = 0`` only stars at the
same instant share a state (e.g. all stars of a global-shutter frame).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import ConfigDict, Field

from rollingstar.estimators.attitude.robust import RobustParams
from rollingstar.estimators.attitude.star_covariance import (
    DirectionCovariance,
    anisotropic_covariance,
    direction_covariance,
    isotropic_sigma_px,
    tangent_basis,
)
from rollingstar.estimators.data import StarTable

__all__ = ["StarObservations", "star_observations", "ObservationParams", "tangent_basis"]


class ObservationParams(RobustParams):
    """Star-measurement parameters shared by the sequential attitude estimators (and the robust gate, robust.py)."""

    model_config = ConfigDict(extra="forbid")

    sigma_px: float | None = Field(
        default=None, gt=0, description="1-sigma centroid error (px) for stars whose sigma_px is NaN; None: the "
        "sensor context's centroid_sigma_px, else 0.05 px.")
    use_star_sigma: bool = Field(default=True, description="Use each star's own sigma_px when finite.")
    star_covariance: bool = Field(
        default=True, description="Weight each star by its 2 x 2 position covariance (cov_xx, cov_xy, cov_yy) when a "
        "star of the frame carries one that is not isotropic; False: by the scalar sigma_px alone.")
    merge_us: float = Field(
        default=0.0, ge=0.0, description="Stars whose times differ by at most this (microseconds) share one attitude "
        "state; 0: one state per distinct star time (per star on a rolling-shutter frame).")


@dataclass(frozen=True)
class StarObservations:
    """Identified stars of a frame sorted by time: ``t_ns`` (n,), camera unit vectors ``body``
    (n, 3), ICRS unit vectors ``ref`` (n, 3), angular sigma ``sigma_rad`` (n,), and the states:
    ``state_t_ns`` (m,) (the time of each state = the mean of its stars' times) and
    ``state_of`` (n,) the state of each star. ``direction``: the stars' 2 x 2 tangent-plane
    covariances (same order) when the frame's stars carry anisotropic ones, else None (module docstring)."""

    t_ns: np.ndarray
    body: np.ndarray
    ref: np.ndarray
    sigma_rad: np.ndarray
    state_t_ns: np.ndarray
    state_of: np.ndarray
    direction: DirectionCovariance | None = None

    @property
    def n(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def n_states(self) -> int:
        return int(self.state_t_ns.shape[0])

    def state_slices(self) -> list[slice]:
        """Star index range of each state (stars are sorted, so a state's stars are contiguous)."""
        bounds = np.searchsorted(self.state_of, np.arange(self.n_states + 1))
        return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def star_observations(stars: StarTable | None, camera, sigma_px: float, use_star_sigma: bool = True,
                      merge_ns: int = 0, star_covariance: bool = True) -> tuple[StarObservations, int]:
    """The frame's usable identified stars as observations, and how many identified stars were
    dropped for non-finite position or reference."""
    if stars is None or stars.n == 0:
        sel = StarTable.empty()
    else:
        sel = stars.take(stars.identified)
    finite = np.isfinite(sel.x) & np.isfinite(sel.y) & np.isfinite(sel.ref_icrs).all(axis=1)
    dropped = int((~finite).sum())
    sel = sel.take(finite)
    order = np.argsort(sel.t_ns, kind="stable")
    sel = sel.take(order)
    cov_px = anisotropic_covariance(sel, sigma_px, use_star_sigma, star_covariance)
    direction = None
    if cov_px is None:
        sig = np.full(sel.n, float(sigma_px))
        if use_star_sigma:
            sig = np.where(np.isfinite(sel.sigma_px) & (sel.sigma_px > 0), sel.sigma_px, sig)
        body = camera.unproject(sel.x, sel.y).reshape(-1, 3)
        body = body / np.linalg.norm(body, axis=1, keepdims=True)
    else:
        sig = isotropic_sigma_px(cov_px)
        direction = direction_covariance(camera, sel.x, sel.y, cov_px)
        body = direction.body
    ref = sel.ref_icrs / np.linalg.norm(sel.ref_icrs, axis=1, keepdims=True)
    t = sel.t_ns.astype(np.int64)
    state_t, state_of = _states(t, merge_ns)
    obs = StarObservations(t_ns=t, body=body, ref=ref, sigma_rad=sig / float(camera.focal_px),
                           state_t_ns=state_t, state_of=state_of, direction=direction)
    return obs, dropped


def _states(t: np.ndarray, merge_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """The states of time-sorted star times ``t``: each state's time (the rounded mean of its stars')
    and the state of every star; a new state starts where the time steps by more than ``merge_ns``."""
    new_state = np.concatenate([[True], np.diff(t) > merge_ns]) if t.size else np.zeros(0, dtype=bool)
    state_of = np.cumsum(new_state) - 1
    m = int(new_state.sum())
    if m:
        base = int(t[0])
        counts = np.bincount(state_of, minlength=m)
        mean = np.bincount(state_of, weights=(t - base).astype(float), minlength=m) / counts
        state_t = base + np.rint(mean).astype(np.int64)
    else:
        state_t = np.zeros(0, dtype=np.int64)
    return state_t, state_of.astype(np.int64)
