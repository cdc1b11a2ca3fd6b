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

The other way round, :class:`GyroIntegrator` turns such samples back into the body angle between
any two times: the gyro history the estimators that use a gyro share.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rollingstar.sensors.conventions import NS_PER_S, S_PER_NS
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


class GyroIntegrator:
    """Body-angle history from gyro samples, for increments between arbitrary times.

    Sample ``i`` at ``t_i`` holds the mean rate over ``(t_{i-1}, t_i]`` (a rate-integrating gyro,
    as :func:`simulate_gyro` makes them); the first sample's interval length is taken from the next spacing
    (or ``default_period_s``). Minus the known bias, the rates are held constant over their
    intervals (zero-order hold) and also extrapolated beyond the first/last sample, so the angle
    ``Theta(t) = int omega`` is piecewise linear and its integral ``Psi(t)`` piecewise quadratic;
    both are exact for the held rates. Angles are summed as rotation vectors (small-angle: the
    rotation over one frame is arcseconds here; the Jacobian is first order anyway).
    """

    def __init__(self, bias_rad_s=(0.0, 0.0, 0.0), default_period_s: float = 0.01, keep_s: float = 2.0):
        self.bias = np.asarray(bias_rad_s, dtype=float).reshape(3)
        self.default_period_s = float(default_period_s)
        self.keep_ns = int(keep_s / S_PER_NS)
        self.origin_ns: int | None = None
        self.tau = np.zeros(0)  # knot times (s from origin), m + 1 of them
        self.rate = np.zeros((0, 3))  # m held rates, rate[j] on (tau[j], tau[j + 1]]
        self.theta = np.zeros((0, 3))  # Theta at the knots
        self.psi = np.zeros((0, 3))  # Psi at the knots

    def add(self, samples) -> None:
        """Append samples: ``samples.t_ns`` (m,) int64 and ``samples.omega_rad_s`` (m, 3), e.g. a frame's
        ``GyroSamples`` or a :class:`GyroRecord` (times must increase past the last one; older ones are ignored)."""
        t = np.asarray(samples.t_ns, dtype=np.int64)
        if t.size == 0:
            return
        w = np.asarray(samples.omega_rad_s, dtype=float).reshape(-1, 3) - self.bias
        if self.origin_ns is None:
            self.origin_ns = int(t[0])
        ts = (t - self.origin_ns) * S_PER_NS
        if self.tau.size:
            keep = ts > self.tau[-1]
            ts, w = ts[keep], w[keep]
            if ts.size == 0:
                return
            knots = np.concatenate([[self.tau[-1]], ts])
        else:
            first = ts[1] - ts[0] if ts.size > 1 else self.default_period_s
            knots = np.concatenate([[ts[0] - first], ts])
            self.tau = knots[:1]
            self.theta = np.zeros((1, 3))
            self.psi = np.zeros((1, 3))
        dt = np.diff(knots)[:, None]
        d_theta = np.cumsum(w * dt, axis=0)
        theta = self.theta[-1] + np.vstack([np.zeros((1, 3)), d_theta])
        # Psi(t_j) - Psi(t_{j-1}) = Theta(t_{j-1}) dt + omega dt^2 / 2
        d_psi = np.cumsum(theta[:-1] * dt + 0.5 * w * dt * dt, axis=0)
        self.tau = np.concatenate([self.tau, knots[1:]])
        self.rate = np.vstack([self.rate, w])
        self.theta = np.vstack([self.theta, theta[1:]])
        self.psi = np.vstack([self.psi, self.psi[-1] + d_psi])

    def trim(self, before_ns: int) -> None:
        """Forget intervals ending before ``before_ns - keep_s`` (Theta/Psi stay consistent)."""
        if self.origin_ns is None or self.rate.shape[0] < 2:
            return
        cut = (before_ns - self.origin_ns - self.keep_ns) * S_PER_NS
        j = int(np.searchsorted(self.tau, cut)) - 1
        j = min(max(j, 0), self.rate.shape[0] - 1)
        if j > 0:
            self.tau, self.theta, self.psi, self.rate = self.tau[j:], self.theta[j:], self.psi[j:], self.rate[j:]

    @property
    def empty(self) -> bool:
        return self.rate.shape[0] == 0

    def _locate(self, t_ns):
        ts = (np.asarray(t_ns, dtype=np.int64) - (self.origin_ns or 0)) * S_PER_NS
        j = np.clip(np.searchsorted(self.tau, ts, side="left"), 1, self.rate.shape[0]) - 1
        return j, (ts - self.tau[j])[..., None]

    def angle(self, t_ns) -> np.ndarray:
        """``Theta(t)`` (..., 3) rad; zeros when no sample was ever added."""
        t = np.asarray(t_ns)
        if self.empty:
            return np.zeros(t.shape + (3,))
        j, h = self._locate(t)
        return self.theta[j] + self.rate[j] * h

    def integral(self, t_ns) -> np.ndarray:
        """``Psi(t) = int Theta`` (..., 3) rad s."""
        t = np.asarray(t_ns)
        if self.empty:
            return np.zeros(t.shape + (3,))
        j, h = self._locate(t)
        return self.psi[j] + self.theta[j] * h + 0.5 * self.rate[j] * h * h

    def rate_at(self, t_ns) -> np.ndarray:
        """Held gyro rate (bias removed) at ``t`` (..., 3) rad/s."""
        t = np.asarray(t_ns)
        if self.empty:
            return np.zeros(t.shape + (3,))
        j, _ = self._locate(t)
        return self.rate[j]

    def window_mean(self, start_ns, exposure_ns: int) -> np.ndarray:
        """Mean of ``Theta`` over ``[start, start + exposure]``: ``(Psi(b) - Psi(a)) / exposure``."""
        start = np.asarray(start_ns, dtype=np.int64)
        return (self.integral(start + np.int64(exposure_ns)) - self.integral(start)) / (exposure_ns * S_PER_NS)

    def increment(self, t_from, t_to, exposure_ns: int | None = None) -> np.ndarray:
        """Body angle increment (..., 3) rad between two instants (``exposure_ns`` None), or between
        the means over two exposure windows starting at ``t_from`` / ``t_to`` (the quantity that
        moves a smeared spot's centre of gravity)."""
        if exposure_ns is None:
            return self.angle(t_to) - self.angle(t_from)
        # the two window means of window_mean, from one integral() call on the four instants
        a, b = np.broadcast_arrays(np.asarray(t_from, dtype=np.int64), np.asarray(t_to, dtype=np.int64))
        e = np.int64(exposure_ns)
        P = self.integral(np.stack([b + e, b, a + e, a]))
        return ((P[0] - P[1]) - (P[2] - P[3])) / (exposure_ns * S_PER_NS)
