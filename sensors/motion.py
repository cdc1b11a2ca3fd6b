"""Attitude truth: camera-to-ICRS rotation and body rate evaluable exactly at any integer-ns time.

Kinematics convention: ``R(t + dt) = R(t) * Exp(omega dt)`` with ``omega`` the angular velocity in
the camera (body) frame, so ``R^T dR/dt = [omega]x``.

Piecewise motion: on segment ``i`` starting at ``t_i`` with attitude ``R_i``, body rate ``omega_i``
and body angular acceleration ``alpha_i``, with ``tau = t - t_i`` (seconds)::

    theta(tau) = omega_i tau + alpha_i tau^2 / 2          (body-frame rotation vector)
    R(t)       = R_i * Exp(theta(tau))
    omega(t)   = J_r(theta) * (omega_i + alpha_i tau)       (exact body rate)

where ``J_r`` is the right Jacobian of SO(3) (:func:`so3_right_jacobian`). When ``alpha`` is
parallel to ``omega`` (or zero) ``J_r(theta) theta_dot = theta_dot`` and this is the familiar
constant-axis rotation. Segment start attitudes are chained exactly,
``R_{i+1} = R_i * Exp(theta_i(duration_i))``; no numerical integration is involved.

Jitter on top of a base motion, ``phi(t) = sum_k A_k sin(2 pi f_k t + p_k)``::

    R(t)     = R_base(t) * Exp(phi(t))
    omega(t) = Exp(phi)^T omega_base(t) + J_r(phi) phi_dot(t)

Times are differenced in integer nanoseconds before conversion to float seconds, so evaluation
far from the reference time loses no precision in ``tau``.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.sensors.conventions import NS_PER_S
from rollingstar.sensors.so3 import cross, skew

_SERIES_THRESHOLD = 0.1  # |theta| below which (|t| - sin|t|)/|t|^3 uses its Taylor series


def _right_jacobian_coefficients(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``a(x) = (1 - cos x) / x^2`` and ``b(x) = (x - sin x) / x^3``, accurate for all x >= 0."""
    a = 0.5 * np.sinc(x / (2.0 * np.pi)) ** 2  # 2 sin^2(x/2) / x^2: no cancellation
    x2 = x * x
    series = 1.0 / 6.0 - x2 / 120.0 + x2**2 / 5040.0 - x2**3 / 362880.0 + x2**4 / 39916800.0
    small = x < _SERIES_THRESHOLD
    xs = np.where(small, 1.0, x)
    b = np.where(small, series, (xs - np.sin(xs)) / xs**3)
    return a, b


def so3_right_jacobian(theta: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3), (..., 3) -> (..., 3, 3)::

        J_r(theta) = I - a(|theta|) [theta]x + b(|theta|) [theta]x^2,
        a(x) = (1 - cos x) / x^2 = 0.5 * (sin(x/2) / (x/2))^2,
        b(x) = (x - sin x) / x^3  (Taylor series 1/6 - x^2/120 + x^4/5040 - ... for x < 0.1),

    so that ``Exp(theta + d) ~= Exp(theta) Exp(J_r(theta) d)`` and the body rate of
    ``Exp(theta(t))`` is ``J_r(theta) theta_dot``.
    """
    th = np.asarray(theta, dtype=float)
    if th.shape[-1:] != (3,):
        raise ValueError(f"theta: expected shape (..., 3), got {th.shape}")
    x = np.linalg.norm(th, axis=-1)
    a, b = _right_jacobian_coefficients(x)
    k = skew(th)
    k2 = th[..., :, None] * th[..., None, :] - (x * x)[..., None, None] * np.eye(3)  # [theta]x^2
    return np.eye(3) - a[..., None, None] * k + b[..., None, None] * k2


def _right_jacobian_apply(theta: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``J_r(theta) v`` for (n, 3) stacks without forming matrices:
    ``v - a theta x v + b (theta (theta . v) - |theta|^2 v)``."""
    x2 = theta[:, 0] ** 2 + theta[:, 1] ** 2 + theta[:, 2] ** 2
    a, b = _right_jacobian_coefficients(np.sqrt(x2))
    dot = theta[:, 0] * v[:, 0] + theta[:, 1] * v[:, 1] + theta[:, 2] * v[:, 2]
    return v - a[:, None] * cross(theta, v) + b[:, None] * (theta * dot[:, None] - x2[:, None] * v)


def _matvec(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``m @ v`` for stacks (n, 3, 3) x (n, 3), as explicit element-wise sums so the result for a
    time does not depend on how many other times are evaluated with it."""
    return m[:, :, 0] * v[:, 0:1] + m[:, :, 1] * v[:, 1:2] + m[:, :, 2] * v[:, 2:3]


def compose_rotations(a: Rotation, b: Rotation) -> Rotation:
    """``a * b`` (apply ``b`` first) via the vectorised Hamilton product of scalar-last quaternions.

    Equivalent to scipy's ``Rotation.__mul__`` (to rounding), several times faster for large stacks.
    """
    p, q = a.as_quat(), b.as_quat()
    px, py, pz, pw = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qx, qy, qz, qw = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.stack(
        [
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
            pw * qw - px * qx - py * qy - pz * qz,
        ],
        axis=-1,
    )
    return Rotation.from_quat(out)


def _as_time_array(t_ns) -> tuple[np.ndarray, bool]:
    """Integer-ns times as a 1-D int64 array, and whether the input was a scalar."""
    t = np.asarray(t_ns)
    if t.ndim > 1:
        raise ValueError(f"t_ns: expected a scalar or 1-D array of integer ns, got shape {t.shape}")
    if t.dtype.kind not in "iu":
        if t.dtype.kind != "f" or not np.all(np.isfinite(t)) or np.any(t != np.round(t)):
            raise ValueError(f"t_ns: expected integer nanoseconds, got dtype {t.dtype}")
    return np.atleast_1d(t).astype(np.int64), t.ndim == 0


def _as_vec3(value, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: expected a finite 3-vector, got {value!r}")
    return v


class AttitudeMotion:
    """Base class: subclasses implement ``_attitude(t) -> Rotation`` and ``_omega(t) -> (n, 3)``
    for a 1-D int64 array ``t``; the public methods handle scalar and array inputs."""

    def attitude(self, t_ns) -> Rotation:
        """Camera-to-ICRS attitude at ``t_ns``: a Rotation of length n for an (n,) array, a single
        Rotation for a scalar."""
        t, scalar = _as_time_array(t_ns)
        r = self._attitude(t)
        return r[0] if scalar else r

    def angular_velocity(self, t_ns) -> np.ndarray:
        """Body-frame angular velocity (rad/s) at ``t_ns``: (n, 3) for an array, (3,) for a scalar."""
        t, scalar = _as_time_array(t_ns)
        w = self._omega(t)
        return w[0] if scalar else w

    def _attitude(self, t: np.ndarray) -> Rotation:  # pragma: no cover - abstract
        raise NotImplementedError

    def _omega(self, t: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError


@dataclass(frozen=True, eq=False)
class Segment:
    """A piece of motion: ``duration_ns`` (> 0), body rate at its start and constant body
    angular acceleration (see the module docstring for the exact law)."""

    duration_ns: int
    omega_rad_s: np.ndarray
    alpha_rad_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        if isinstance(self.duration_ns, bool) or not isinstance(self.duration_ns, (int, np.integer)) or self.duration_ns <= 0:
            raise ValueError(f"duration_ns: expected a positive integer number of ns, got {self.duration_ns!r}")
        object.__setattr__(self, "duration_ns", int(self.duration_ns))
        object.__setattr__(self, "omega_rad_s", _as_vec3(self.omega_rad_s, "omega_rad_s"))
        object.__setattr__(self, "alpha_rad_s2", _as_vec3(self.alpha_rad_s2, "alpha_rad_s2"))


class PiecewiseMotion(AttitudeMotion):
    """Consecutive :class:`Segment` s from ``start_ns`` with attitude ``initial`` at ``start_ns``.

    After the last segment its law continues (``tau`` keeps growing); before ``start_ns`` the first
    segment's law extends backwards (negative ``tau``).
    """

    def __init__(self, initial: Rotation, segments: list[Segment], start_ns: int = 0):
        if not isinstance(initial, Rotation) or not initial.single:
            raise ValueError(f"initial: expected a single scipy Rotation, got {initial!r}")
        segments = list(segments)
        if not segments:
            raise ValueError("segments: expected at least one Segment, got none")
        if not all(isinstance(s, Segment) for s in segments):
            raise ValueError("segments: expected a list of Segment objects")
        if isinstance(start_ns, bool) or not isinstance(start_ns, (int, np.integer)):
            raise ValueError(f"start_ns: expected an integer number of ns, got {start_ns!r}")
        self.initial = initial
        self.segments = tuple(segments)
        self.start_ns = int(start_ns)

    @functools.cached_property
    def segment_starts_ns(self) -> np.ndarray:
        """Start time of each segment (int64 ns)."""
        durations = np.array([s.duration_ns for s in self.segments], dtype=np.int64)
        return np.int64(self.start_ns) + np.concatenate([[0], np.cumsum(durations)[:-1]]).astype(np.int64)

    @functools.cached_property
    def _omega0(self) -> np.ndarray:
        return np.stack([s.omega_rad_s for s in self.segments])

    @functools.cached_property
    def _alpha(self) -> np.ndarray:
        return np.stack([s.alpha_rad_s2 for s in self.segments])

    @functools.cached_property
    def _start_attitudes(self) -> Rotation:
        """Exact chain ``R_{i+1} = R_i * Exp(theta_i(duration_i))`` (one step per segment)."""
        tau = np.array([s.duration_ns for s in self.segments], dtype=float) / NS_PER_S
        steps = Rotation.from_rotvec(self._omega0 * tau[:, None] + 0.5 * self._alpha * tau[:, None] ** 2)
        quats = [self.initial.as_quat()]
        current = self.initial
        for i in range(len(self.segments) - 1):
            current = current * steps[i]
            quats.append(current.as_quat())
        return Rotation.from_quat(np.stack(quats))

    def _locate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Segment index, elapsed time tau (s), and rotation vector theta(tau) for each time."""
        starts = self.segment_starts_ns
        idx = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(starts) - 1)
        tau = (t - starts[idx]).astype(float) / NS_PER_S
        theta = self._omega0[idx] * tau[:, None] + 0.5 * self._alpha[idx] * tau[:, None] ** 2
        return idx, tau, theta

    def _attitude(self, t: np.ndarray) -> Rotation:
        idx, _, theta = self._locate(t)
        return compose_rotations(self._start_attitudes[idx], Rotation.from_rotvec(theta))

    def _omega(self, t: np.ndarray) -> np.ndarray:
        idx, tau, theta = self._locate(t)
        theta_dot = self._omega0[idx] + self._alpha[idx] * tau[:, None]
        return _right_jacobian_apply(theta, theta_dot)


class JitterMotion(AttitudeMotion):
    """Sinusoidal body-frame jitter on a base motion (module docstring equations).

    ``amplitude_rad`` (k, 3), ``frequency_hz`` (k,), ``phase_rad`` (k, 3) (default zeros);
    the sinusoids' time origin is ``epoch_ns`` (default 0): ``t = (t_ns - epoch_ns) / 1e9``.
    """

    def __init__(self, base: AttitudeMotion, amplitude_rad, frequency_hz, phase_rad=None, epoch_ns: int = 0):
        if not isinstance(base, AttitudeMotion):
            raise ValueError(f"base: expected an AttitudeMotion, got {type(base).__name__}")
        amp = np.atleast_2d(np.asarray(amplitude_rad, dtype=float))
        freq = np.atleast_1d(np.asarray(frequency_hz, dtype=float))
        if amp.ndim != 2 or amp.shape[1] != 3 or not np.all(np.isfinite(amp)):
            raise ValueError(f"amplitude_rad: expected finite values of shape (k, 3), got shape {amp.shape}")
        k = amp.shape[0]
        if freq.shape != (k,) or not np.all(np.isfinite(freq)) or np.any(freq < 0):
            raise ValueError(f"frequency_hz: expected {k} finite non-negative frequencies, got {frequency_hz!r}")
        phase = np.zeros((k, 3)) if phase_rad is None else np.atleast_2d(np.asarray(phase_rad, dtype=float))
        if phase.shape != (k, 3) or not np.all(np.isfinite(phase)):
            raise ValueError(f"phase_rad: expected finite values of shape ({k}, 3), got shape {phase.shape}")
        if isinstance(epoch_ns, bool) or not isinstance(epoch_ns, (int, np.integer)):
            raise ValueError(f"epoch_ns: expected an integer number of ns, got {epoch_ns!r}")
        self.base = base
        self.amplitude_rad = amp
        self.frequency_hz = freq
        self.phase_rad = phase
        self.epoch_ns = int(epoch_ns)

    def _phi(self, t: np.ndarray, derivative: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """Jitter rotation vector phi (n, 3) and, if asked, its time derivative (n, 3)."""
        s = (t - np.int64(self.epoch_ns)).astype(float) / NS_PER_S
        w = 2.0 * np.pi * self.frequency_hz  # (k,)
        arg = w[None, :, None] * s[:, None, None] + self.phase_rad[None]  # (n, k, 3)
        phi = np.einsum("kj,nkj->nj", self.amplitude_rad, np.sin(arg))
        if not derivative:
            return phi, None
        return phi, np.einsum("kj,nkj->nj", self.amplitude_rad * w[:, None], np.cos(arg))

    def _attitude(self, t: np.ndarray) -> Rotation:
        phi, _ = self._phi(t)
        return compose_rotations(self.base._attitude(t), Rotation.from_rotvec(phi))

    def _omega(self, t: np.ndarray) -> np.ndarray:
        phi, phi_dot = self._phi(t, derivative=True)
        exp_phi_t = np.swapaxes(Rotation.from_rotvec(phi).as_matrix(), -1, -2)
        return _matvec(exp_phi_t, self.base._omega(t)) + _right_jacobian_apply(phi, phi_dot)


def inertial_hold(initial: Rotation, start_ns: int = 0) -> PiecewiseMotion:
    """Constant attitude ``initial`` at all times."""
    return PiecewiseMotion(initial, [Segment(NS_PER_S, np.zeros(3))], start_ns)


def constant_rate(initial: Rotation, omega_rad_s, start_ns: int = 0) -> PiecewiseMotion:
    """``R(t) = initial * Exp(omega (t - start))`` at all times."""
    return PiecewiseMotion(initial, [Segment(NS_PER_S, omega_rad_s)], start_ns)


def constant_acceleration(initial: Rotation, omega0_rad_s, alpha_rad_s2, start_ns: int = 0) -> PiecewiseMotion:
    """``R(t) = initial * Exp(omega0 tau + alpha tau^2 / 2)``, ``tau = t - start``, at all times."""
    return PiecewiseMotion(initial, [Segment(NS_PER_S, omega0_rad_s, alpha_rad_s2)], start_ns)
