"""The attitude motion model shared by ``mekf`` and ``gtsam``: gyro-driven, or constant rate.

Both estimators use one kinematic model, ``R(t + dt) = R(t) Exp((u - beta) dt)`` (body-frame
rate, docs/conventions.md), with a state ``beta`` that follows a random walk:

- ``gyro``: ``u`` is the gyro rate (rate-integrating samples, zero-order hold between samples)
  and ``beta`` the gyro bias (Lefferts, Markley & Shuster 1982; Markley & Crassidis 2014
  sec. 6.4/7.2). Attitude noise: the gyro's angle random walk ``sigma_v``; bias noise: its rate
  random walk ``sigma_u``.
- ``constant_rate`` (no gyro in the recording): ``u = 0``, so ``beta = -omega`` is minus the body
  rate, and the random walk of ``beta`` is the white angular-acceleration noise of a
  constant-angular-velocity (nearly-constant-rate) prior; ``sigma_v`` is a small attitude model
  noise. The same equations then give the constant-rate motion prior without a second model.

This module holds the parameters (units in the names) and their conversion to SI.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from pydantic import Field

from rollingstar.estimators.attitude.observations import ObservationParams
from rollingstar.sensors.conventions import ARCSEC_TO_RAD, DEG_TO_RAD, S_PER_HOUR


class MotionModelParams(ObservationParams):
    motion_model: Literal["auto", "gyro", "constant_rate"] = Field(
        default="auto", description="'gyro': propagate with the frames' gyro samples and estimate the gyro bias; "
        "'constant_rate': nearly-constant angular velocity, rate estimated; 'auto': gyro when gyro samples arrived "
        "up to the first frame with identified stars.")
    gyro_arw_deg_sqrt_h: float = Field(default=0.01, ge=0, description="gyro: angle random walk (deg/sqrt(h)).")
    gyro_rrw_deg_h_sqrt_h: float = Field(default=0.1, ge=0, description="gyro: bias (rate) random walk (deg/h/sqrt(h)).")
    gyro_bias_sigma_deg_h: float = Field(default=100.0, gt=0, description="gyro: prior 1-sigma of the bias (deg/h).")
    rate_sigma_deg_s: float = Field(default=1.0, gt=0, description="constant_rate: prior 1-sigma of the rate (deg/s).")
    angular_accel_noise_deg_s_sqrt_s: float = Field(
        default=1e-3, ge=0, description="constant_rate: white angular-acceleration noise density of the rate random "
        "walk (deg/s/sqrt(s)).")
    attitude_noise_arcsec_sqrt_s: float = Field(
        default=0.1, ge=0, description="constant_rate: attitude model noise density (arcsec/sqrt(s)).")


@dataclass(frozen=True)
class MotionNoise:
    """SI noise of the model: attitude noise density ``sigma_v`` (rad/sqrt(s)), random-walk density
    of ``beta`` ``sigma_u`` (rad/s/sqrt(s)) and the prior 1-sigma of ``beta`` (rad/s)."""

    mode: str
    sigma_v: float
    sigma_u: float
    beta_sigma: float


def motion_noise(p: MotionModelParams, mode: str) -> MotionNoise:
    """Convert the parameters of ``mode`` ('gyro' or 'constant_rate') to SI."""
    if mode == "gyro":
        return MotionNoise(mode, p.gyro_arw_deg_sqrt_h * DEG_TO_RAD / 60.0,
                           p.gyro_rrw_deg_h_sqrt_h * DEG_TO_RAD / S_PER_HOUR / 60.0,
                           p.gyro_bias_sigma_deg_h * DEG_TO_RAD / S_PER_HOUR)
    if mode == "constant_rate":
        return MotionNoise(mode, p.attitude_noise_arcsec_sqrt_s * ARCSEC_TO_RAD,
                           p.angular_accel_noise_deg_s_sqrt_s * DEG_TO_RAD, p.rate_sigma_deg_s * DEG_TO_RAD)
    raise ValueError(f"unknown motion model {mode!r}")


def resolve_mode(p: MotionModelParams, has_gyro: bool) -> str:
    """The motion model in use: the configured one, or for 'auto' gyro exactly when samples exist."""
    if p.motion_model != "auto":
        return p.motion_model
    return "gyro" if has_gyro else "constant_rate"
