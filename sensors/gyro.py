"""Rate-integrating gyro: samples of the body rate with scale, bias, random walks and white noise.

Sample ``k = 0, 1, ...`` is at ``t_k = start + round(k * 1e9 / rate_hz)`` ns (all ``t_k <= end``).
Each sample integrates the exact motion over ``[t_{k-1}, t_k]`` (``t_{-1}`` from the same formula,
so the intervals tile time without gaps or overlaps), ``dt_k = t_k - t_{k-1}``::

    true_k  = Log(R(t_{k-1})^T R(t_k)) / dt_k                (exact interval-average body rate)
    bias_k  = b0 + K sqrt(dt) * sum_{j=1..k} n_j             (rate random walk, n_j ~ N(0, I))
    meas_k  = (1 + s) * true_k + bias_k + (N / sqrt(dt)) m_k (angle random walk, m_k ~ N(0, I))

with ``dt = 1 / rate_hz`` the nominal period, ``s`` the per-axis scale-factor error, ``N`` the
angle random walk (rad/sqrt(s)) and ``K`` the rate random walk (rad/s/sqrt(s)).

Noise is drawn in fixed blocks of 4096 samples, block ``b`` from
``np.random.default_rng([seed, b])`` (white noise first, then walk steps), so a record is
deterministic for a seed and extending ``end_ns`` leaves the earlier samples unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rollingstar.sensors.conventions import NS_PER_S
from rollingstar.sensors.motion import AttitudeMotion, compose_rotations

NOISE_BLOCK = 4096


def _vec3(value, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: expected a finite 3-vector, got {value!r}")
    return v


@dataclass(frozen=True, eq=False)
class GyroModel:
    """Gyro error model (see module docstring): sample rate, constant bias ``b0`` (rad/s),
    angle random walk ``N`` (rad/sqrt(s)), rate random walk ``K`` (rad/s/sqrt(s)), and
    fractional per-axis scale-factor error (e.g. 100e-6 for 100 ppm)."""

    rate_hz: float
    bias_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    arw_rad_sqrt_s: float = 0.0
    rrw_rad_s_sqrt_s: float = 0.0
    scale_factor: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ValueError(f"rate_hz: expected a positive finite sample rate, got {self.rate_hz!r}")
        if self.rate_hz > NS_PER_S:
            raise ValueError(f"rate_hz: expected at most 1e9 Hz (1 ns sampling), got {self.rate_hz!r}")
        for name in ("arw_rad_sqrt_s", "rrw_rad_s_sqrt_s"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: expected a finite non-negative noise density, got {value!r}")
        object.__setattr__(self, "rate_hz", float(self.rate_hz))
        object.__setattr__(self, "bias_rad_s", _vec3(self.bias_rad_s, "bias_rad_s"))
        object.__setattr__(self, "scale_factor", _vec3(self.scale_factor, "scale_factor"))

    @property
    def period_s(self) -> float:
        """Nominal sample interval ``dt = 1 / rate_hz``."""
        return 1.0 / self.rate_hz

    @property
    def white_sigma_rad_s(self) -> float:
        """Per-sample white rate-noise sigma ``N / sqrt(dt)``."""
        return self.arw_rad_sqrt_s / np.sqrt(self.period_s)

    @property
    def bias_step_sigma_rad_s(self) -> float:
        """Per-sample bias random-walk step sigma ``K sqrt(dt)``."""
        return self.rrw_rad_s_sqrt_s * np.sqrt(self.period_s)


@dataclass(frozen=True, eq=False)
class GyroRecord:
    """Simulated samples: times (m,) int64 ns; measured, true interval-average rate and total
    bias, each (m, 3) rad/s in the camera frame."""

    t_ns: np.ndarray
    omega_rad_s: np.ndarray
    true_omega_rad_s: np.ndarray
    bias_rad_s: np.ndarray

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


def sample_times_ns(rate_hz: float, start_ns: int, k) -> np.ndarray:
    """``start + round(k * 1e9 / rate_hz)`` as int64 (k may be negative)."""
    k = np.asarray(k, dtype=np.int64)
    return np.int64(start_ns) + np.rint(k.astype(float) * NS_PER_S / rate_hz).astype(np.int64)


def _noise(seed: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Standard-normal white (m, 3) and walk-step (m, 3) draws, block-wise from ``[seed, block]``."""
    n_blocks = -(-m // NOISE_BLOCK)
    white = np.empty((n_blocks * NOISE_BLOCK, 3))
    walk = np.empty((n_blocks * NOISE_BLOCK, 3))
    for b in range(n_blocks):  # one draw per 4096-sample block
        rng = np.random.default_rng([seed, b])
        sl = slice(b * NOISE_BLOCK, (b + 1) * NOISE_BLOCK)
        white[sl] = rng.standard_normal((NOISE_BLOCK, 3))
        walk[sl] = rng.standard_normal((NOISE_BLOCK, 3))
    return white[:m], walk[:m]


def simulate_gyro(model: GyroModel, motion: AttitudeMotion, start_ns: int, end_ns: int, seed: int) -> GyroRecord:
    """Gyro samples from ``start_ns`` to ``end_ns`` (inclusive) of ``motion`` (module docstring)."""
    if not isinstance(model, GyroModel):
        raise ValueError(f"model: expected a GyroModel, got {type(model).__name__}")
    if not isinstance(motion, AttitudeMotion):
        raise ValueError(f"motion: expected an AttitudeMotion, got {type(motion).__name__}")
    for name, value in (("start_ns", start_ns), ("end_ns", end_ns), ("seed", seed)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise ValueError(f"{name}: expected an integer, got {value!r}")
    if end_ns < start_ns:
        raise ValueError(f"end_ns: expected >= start_ns ({start_ns}), got {end_ns}")
    if seed < 0:
        raise ValueError(f"seed: expected a non-negative integer, got {seed}")

    k_max = int(np.floor((end_ns - start_ns) * model.rate_hz / NS_PER_S)) + 1
    k = np.arange(-1, k_max + 1, dtype=np.int64)
    t_all = sample_times_ns(model.rate_hz, start_ns, k)
    m = int(np.count_nonzero(t_all[1:] <= end_ns))
    t_prev, t = t_all[:m], t_all[1 : m + 1]

    delta = compose_rotations(motion.attitude(t_prev).inv(), motion.attitude(t)).as_rotvec()
    true = delta / ((t - t_prev).astype(float) / NS_PER_S)[:, None]

    white, walk = _noise(int(seed), m)
    steps = model.bias_step_sigma_rad_s * walk
    steps[:1] = 0.0  # bias_0 = b0: the walk starts at the first sample
    bias = model.bias_rad_s + np.cumsum(steps, axis=0)
    meas = (1.0 + model.scale_factor) * true + bias + model.white_sigma_rad_s * white
    return GyroRecord(t_ns=t, omega_rad_s=meas, true_omega_rad_s=true, bias_rad_s=bias)
