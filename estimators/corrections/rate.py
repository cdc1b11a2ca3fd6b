"""Rolling-shutter correction with a body rate: every star moved to one reference time.

A star measured at pixel ``(x_i, y_i)`` refers to its own time ``t_i`` (the StarTable ``t_ns``: for a
raw centroid the mid-exposure of its row). With the body turning at the constant rate ``omega``
(camera frame) its direction at the reference time ``t_ref`` is ``Exp(omega (t_i - t_ref)) w_i``
(``w(t) = R(t)^T u``, ``R(t + s) = R(t) Exp(omega s)``, ``w_i = unproject(x_i, y_i)``), re-projected
to the corrected pixel. ``model="linear"`` applies fu2022 eqs 11-14 instead: the uniform pixel shift
``x_i - v_x (t_i - t_ref)``, ``y_i - v_y (t_i - t_ref)`` with eq 8's ``v = (F omega_y, -F omega_x)``
(see :mod:`rollingstar.estimators.rates.pso`).

The rate is the frame's ``frame.rate``, set by a rate stage earlier in the pipeline (``pso-rate``,
``ls-rate`` or any other). For pipelines without one the correction can run a rate estimator
itself (``estimator``); the kinds ``pso-correction`` and ``ls-correction`` are aliases of this
plugin with ``estimator`` set (see :data:`rollingstar.pipelines.registry.ALIASES`).
"""
from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from rollingstar.estimators.corrections.base import Correction
from rollingstar.estimators.data import FrameData, RateEstimate, frame_camera
from rollingstar.estimators.rates.base import RateEstimator, Reference, reference_time_ns
from rollingstar.estimators.rates.pso import PsoRateEstimator, corrected_positions
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.so3 import rotate_at_rate, rotate_by_rotvec

FLAG = "rate_invalid"


def rate_estimator_class(kind: str) -> type[RateEstimator]:
    """The rate estimator class of ``kind`` (``pso-rate`` or ``ls-rate``) for ``estimator``."""
    if kind == "pso-rate":
        return PsoRateEstimator
    # imported on use: ls_rate loads its numba kernels (~0.5 s), which pipelines without it skip
    from rollingstar.estimators.rates.ls_rate import LsRateEstimator

    return LsRateEstimator


class RateCorrectionParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    model: Literal["rotation", "linear"] = Field(
        default="rotation", description="'rotation': each star's direction rotated exactly to t_ref; "
        "'linear': fu2022 eqs 11-14 pixel shift (omega_x, omega_y only).")
    rotation_form: Literal["axis-angle", "rotation-vector"] = Field(
        default="axis-angle", description="How model 'rotation' evaluates Exp(omega dt) w (rollingstar.sensors.so3): "
        "'axis-angle' (rotate_at_rate) or 'rotation-vector' (rotate_by_rotvec); equal to rounding, "
        "pso-correction uses 'rotation-vector'.")
    reference: Reference = Field(
        default="frame_mid", description="t_ref: 'frame_start' = row 0 exposure start; 'frame_mid' = mid-exposure "
        "of the middle row. Also the reference of the estimator's rate.")
    estimator: Literal["pso-rate", "ls-rate"] | None = Field(
        default=None, description="Rate estimator this stage runs itself when the frame has no valid rate "
        "(pipelines without a rate stage); None: such frames are left uncorrected.")
    estimator_params: dict[str, Any] = Field(
        default={}, description="Parameters of the estimator, except reference (and pso-rate's model), which "
        "are this stage's.")
    reuse_rate: bool = Field(
        default=True, description="Use the frame's valid rate when there is one; False: always run the estimator.")

    @model_validator(mode="after")
    def _check_estimator(self):
        if self.estimator is None:
            if self.estimator_params or not self.reuse_rate:
                raise ValueError("estimator_params and reuse_rate false need an estimator")
            return self
        shared = sorted(set(self.estimator_params) & {"reference", "model"})
        if shared:
            raise ValueError(f"estimator_params: {shared} are set on the correction (the estimator shares them)")
        try:
            rate_estimator_class(self.estimator).Params(**self.all_estimator_params())
        except ValidationError as err:
            raise ValueError(f"estimator_params of {self.estimator}: {err}") from None
        return self

    def all_estimator_params(self) -> dict:
        """The estimator's parameters: ``estimator_params`` plus this stage's ``reference`` (and ``model``
        when the estimator takes one: pso-rate's loss moves the stars with the correction's model)."""
        fields = rate_estimator_class(self.estimator).Params.model_fields
        return {**self.estimator_params, **{k: getattr(self, k) for k in ("reference", "model") if k in fields}}


def _usable(rate: RateEstimate | None) -> bool:
    return rate is not None and rate.valid and bool(np.all(np.isfinite(np.asarray(rate.omega_rad_s, dtype=float))))


class RateCorrection(Correction):
    """Rolling-shutter correction with ``frame.rate``: every star moved to ``t_ref`` (module docstring).

    Moves **every** star of ``frame.stars`` (identified or not) with the frame's valid, finite rate
    (all three axes for ``model="rotation"``, x and y for ``"linear"``) and sets ``t_ns = t_ref`` for
    each. With ``estimator``, frames without such a rate (or every frame, ``reuse_rate: false``) get
    ``frame.rate`` from that estimator first (with ``estimator_params``). A frame whose rate is
    missing or invalid, or that has no star table, is returned uncorrected (each star keeps its own
    ``t_ns``) with flag ``rate_invalid``. Pixels are moved with the frame's camera
    (:func:`~rollingstar.estimators.data.frame_camera`); ``sigma_px`` and the 2 x 2 ``cov_*`` are kept
    (the map is a near-rigid shift over one frame; the rate's uncertainty is not added).
    """

    name = "rate-correction"
    Params = RateCorrectionParams

    @property
    def needs(self) -> frozenset[str]:
        """``frame.rate`` from an earlier rate stage; with ``estimator``, identified stars to estimate it from."""
        return frozenset({"rate"} if self.params.estimator is None else {"identified"})

    @property
    def provides(self) -> frozenset[str]:
        """Stars at one time; with ``estimator`` also ``frame.rate``."""
        return Correction.provides | ({"rate"} if self.params.estimator is not None else set())

    def setup(self, context) -> None:
        super().setup(context)
        self._estimator = None
        if self.params.estimator is not None:
            self._estimator = rate_estimator_class(self.params.estimator)(**self.params.all_estimator_params())
            self._estimator.setup(context)

    def process(self, frame: FrameData) -> FrameData:
        p = self.params
        if self._estimator is not None and not (p.reuse_rate and _usable(frame.rate)):
            frame = self._estimator.process(frame)
        stars = frame.stars
        if not _usable(frame.rate) or stars is None:
            return frame.evolve() if FLAG in frame.flags else frame.flagged(FLAG)
        omega = np.asarray(frame.rate.omega_rad_s, dtype=float)
        t_ref = reference_time_ns(p.reference, frame.t0_ns, self.context.timing)
        dt = (stars.t_ns - np.int64(t_ref)).astype(float) * S_PER_NS
        cam = frame_camera(frame, self.context)
        if p.model == "linear":
            x, y = corrected_positions(cam, omega, stars.x, stars.y, dt)
        else:
            w = cam.unproject(stars.x, stars.y)
            if p.rotation_form == "axis-angle":
                u = rotate_at_rate(omega, w, dt)
            else:
                u = rotate_by_rotvec(omega[None, :] * dt[:, None], w)
            x, y, _ = cam.project(u)
        new = stars.with_columns(x=x, y=y, t_ns=np.full(stars.n, t_ref, dtype=np.int64))
        return frame.evolve(stars=new)
