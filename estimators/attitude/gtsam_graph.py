"""Factor-graph pieces of the ``gtsam`` attitude smoother (GTSAM >= 4.3 Python wrapper).

Variables: ``r<i>`` a ``Rot3`` per attitude state (camera-to-ICRS, ``v_icrs = R v_cam``, the
project convention and GTSAM's ``nRb``), ``b<k>`` a ``Vector3`` per frame segment (the gyro bias,
or minus the body rate under the constant-rate model, see :mod:`rollingstar.estimators.attitude.motion_model`).

Factors:

- star ``i`` at state ``s``: ``AttitudeFactorRot3(r_s, nRef = r_i, model, bMeasured = b_i)`` with
  error ``nRef.error(R b_i)`` (the 2-vector of the measured direction rotated to ICRS in the
  tangent plane of the catalogue direction, rad), isotropic 1-sigma ``sigma_i``, or the star's
  2 x 2 direction covariance when the frame's stars carry anisotropic ones (optionally wrapped in
  a Huber M-estimator);
- between consecutive states ``s -> s'`` in segment ``k``: ``AHRSFactor(r_s, r_s', b_k, pim)``
  with ``pim`` the ``PreintegratedAhrsMeasurements`` of the gyro over ``[t_s, t_s']`` (one
  zero-order-hold step of the mean rate, from :class:`GyroIntegrator`) or of a zero rate
  (constant-rate model); its prediction ``R_s' = R_s Exp((omega_meas - b) dt)`` and covariance
  ``sigma_v^2 dt`` (GTSAM's gyroscope covariance is a noise density, rad^2/s);
- between consecutive segments: ``BetweenFactorVector(b_k, b_k', 0, sigma_u sqrt(dt))`` (random
  walk), and a prior ``PriorFactorVector(b_0, 0, beta_sigma)`` on the first.
"""
from __future__ import annotations

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["rot_key", "bias_key", "star_factors", "ahrs_factor", "bias_walk_factor", "bias_prior_factor",
           "to_rot3", "rotation_of", "rotation_params"]

SIGMA_FLOOR = 1e-12  # GTSAM needs a positive definite preintegration covariance


def rot_key(i: int) -> int:
    return gtsam.symbol("r", int(i))


def bias_key(k: int) -> int:
    return gtsam.symbol("b", int(k))


def to_rot3(R: Rotation) -> gtsam.Rot3:
    return gtsam.Rot3(R.as_matrix())


def rotation_of(rot3: gtsam.Rot3) -> Rotation:
    return Rotation.from_matrix(rot3.matrix())


def star_factors(key: int, body: np.ndarray, ref: np.ndarray, sigma_rad: np.ndarray, huber_k: float | None = None,
                 cov_rad2: np.ndarray | None = None, basis: np.ndarray | None = None, R_lin: Rotation | None = None):
    """One ``AttitudeFactorRot3`` per star (the GTSAM API builds factors one by one).

    Noise model: isotropic ``sigma_rad``; or, with ``cov_rad2`` (m, 2, 2), each star's tangent-plane
    covariance in the basis ``basis`` (m, 3, 2) perpendicular to its measured ``b``
    (:mod:`rollingstar.estimators.attitude.star_covariance`), carried to the factor's error
    ``nRef.basis()^T R b``: ``M Sigma M^T`` with ``M = B^T R E`` (``B`` GTSAM's basis of the catalogue
    direction, ``R = R_lin`` the state's initial value; at the solution ``R b ~ r`` and ``M`` is a
    2-D rotation, so an arcsecond-level error of ``R_lin`` changes the model by ~1e-5 relative).
    """
    out = []
    for i, (b, r, s) in enumerate(zip(body, ref, sigma_rad)):
        n_ref = gtsam.Unit3(np.asarray(r, dtype=float))
        if cov_rad2 is None:
            model = gtsam.noiseModel.Isotropic.Sigma(2, float(s))
        else:
            M = n_ref.basis().T @ R_lin.as_matrix() @ basis[i]
            C = M @ cov_rad2[i] @ M.T
            model = gtsam.noiseModel.Gaussian.Covariance(0.5 * (C + C.T))
        if huber_k is not None:
            model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k), model)
        out.append(gtsam.AttitudeFactorRot3(key, n_ref, model, gtsam.Unit3(np.asarray(b, dtype=float))))
    return out


def rotation_params(sigma_v: float) -> gtsam.PreintegratedRotationParams:
    p = gtsam.PreintegratedRotationParams()
    p.setGyroscopeCovariance(max(sigma_v, SIGMA_FLOOR) ** 2 * np.eye(3))
    return p


def ahrs_factor(key_i: int, key_j: int, key_b: int, omega_mean: np.ndarray, dt: float,
                params: gtsam.PreintegratedRotationParams) -> gtsam.AHRSFactor:
    """``AHRSFactor`` over ``dt`` seconds of the measured mean rate ``omega_mean`` (zeros: constant rate)."""
    pim = gtsam.PreintegratedAhrsMeasurements(params, np.zeros(3))
    pim.integrateMeasurement(np.asarray(omega_mean, dtype=float), float(dt))
    return gtsam.AHRSFactor(key_i, key_j, key_b, pim)


def bias_walk_factor(key_a: int, key_b: int, dt: float, sigma_u: float) -> gtsam.BetweenFactorVector:
    sigma = max(sigma_u * np.sqrt(max(dt, 0.0)), SIGMA_FLOOR)
    return gtsam.BetweenFactorVector(key_a, key_b, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, sigma))


def bias_prior_factor(key: int, sigma: float) -> gtsam.PriorFactorVector:
    return gtsam.PriorFactorVector(key, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, float(sigma)))
