"""Gyro history for the ``windowed`` centroider's prediction, compiled (liu2013 eqs 8-10 inputs).

:class:`FastGyroIntegrator` is :class:`rollingstar.sensors.gyro.GyroIntegrator` (same model, same
knot arrays ``tau``, ``rate``, ``theta``, ``psi``, same answers: tested to 1e-12) with its per-frame
:meth:`~FastGyroIntegrator.add` and :meth:`~FastGyroIntegrator.trim` compiled over preallocated
buffers, and :func:`gyro_increment` its ``increment`` compiled. Why: the numpy versions cost ~26 us
(``add``: a dozen concatenations and cumulative sums of one or two samples) and ~20 us
(``increment``) of fixed per-call overhead, together half of the ~0.1 ms a 20x windowed-vs-full-
frame speed-up leaves per frame (``benchmarks/windowed_speed.py``).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from rollingstar.estimators.data import GyroSamples
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.gyro import GyroIntegrator


@njit(cache=True, nogil=True)
def _append(tau, rate, theta, psi, m, ts, w):  # pragma: no cover - compiled
    """Append the samples (``ts`` s from the origin, ``w`` rates minus bias) newer than the last
    knot to the buffers holding ``m`` intervals; returns the new ``m``. GyroIntegrator.add's
    formulas in its order of operations: ``Theta_i = Theta_last + cumsum(w dt)``,
    ``Psi_i = Psi_last + cumsum(Theta_{i-1} dt + 0.5 w dt^2)``."""
    last = tau[m]
    th0 = theta[m].copy()
    ps0 = psi[m].copy()
    cs = np.zeros(3)
    cp = np.zeros(3)
    prev_t = last
    prev_th = th0.copy()
    for i in range(ts.shape[0]):
        if not ts[i] > last:
            continue
        dt = ts[i] - prev_t
        for a in range(3):
            cs[a] += w[i, a] * dt
            cp[a] += prev_th[a] * dt + 0.5 * w[i, a] * dt * dt
        m += 1
        tau[m] = ts[i]
        for a in range(3):
            rate[m - 1, a] = w[i, a]
            theta[m, a] = th0[a] + cs[a]
            psi[m, a] = ps0[a] + cp[a]
            prev_th[a] = theta[m, a]
        prev_t = ts[i]
    return m


class FastGyroIntegrator(GyroIntegrator):
    """:class:`~rollingstar.sensors.gyro.GyroIntegrator` with a compiled ``add`` and ``trim``
    (module docstring). ``tau``, ``rate``, ``theta``, ``psi`` are views of growing buffers."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._m = -1  # intervals held in the buffers; -1: buffers not set up (first add)

    def _views(self) -> None:
        m = self._m
        self.tau, self.rate = self._tau[:m + 1], self._rate[:m]
        self.theta, self.psi = self._theta[:m + 1], self._psi[:m + 1]

    def add(self, samples: GyroSamples) -> None:
        t = np.asarray(samples.t_ns, dtype=np.int64)
        if t.size == 0:
            return
        if self._m < 0:  # the first samples: the base class sets the origin and the first knot
            super().add(samples)
            m = self.rate.shape[0]
            cap = max(256, 2 * m)
            self._tau, self._rate = np.zeros(cap + 1), np.zeros((cap, 3))
            self._theta, self._psi = np.zeros((cap + 1, 3)), np.zeros((cap + 1, 3))
            self._tau[:m + 1], self._rate[:m] = self.tau, self.rate
            self._theta[:m + 1], self._psi[:m + 1] = self.theta, self.psi
            self._m = m
            self._views()
            return
        if self._m + t.size > self._rate.shape[0]:  # grow (amortised doubling)
            cap = 2 * (self._m + t.size)
            for name in ("_tau", "_theta", "_psi"):
                old = getattr(self, name)
                new = np.zeros((cap + 1,) + old.shape[1:])
                new[:self._m + 1] = old[:self._m + 1]
                setattr(self, name, new)
            rate = np.zeros((cap, 3))
            rate[:self._m] = self._rate[:self._m]
            self._rate = rate
        w = np.asarray(samples.omega_rad_s, dtype=float).reshape(-1, 3) - self.bias
        self._m = _append(self._tau, self._rate, self._theta, self._psi, self._m, (t - self.origin_ns) * S_PER_NS, w)
        self._views()

    def trim(self, before_ns: int) -> None:
        """As :meth:`GyroIntegrator.trim`, compacting the buffers."""
        if self._m < 2:
            return
        cut = (before_ns - self.origin_ns - self.keep_ns) * S_PER_NS
        j = min(max(int(np.searchsorted(self.tau, cut)) - 1, 0), self._m - 1)
        if j > 0:
            m = self._m
            self._tau[:m + 1 - j] = self._tau[j:m + 1].copy()
            self._theta[:m + 1 - j] = self._theta[j:m + 1].copy()
            self._psi[:m + 1 - j] = self._psi[j:m + 1].copy()
            self._rate[:m - j] = self._rate[j:m].copy()
            self._m = m - j
            self._views()


@njit(cache=True, nogil=True, error_model="numpy")
def gyro_increment(tau, psi, theta, rate, origin_ns, t_from, t_to, exposure_ns, exposure_mean):  # pragma: no cover
    """:meth:`rollingstar.sensors.gyro.GyroIntegrator.increment` compiled, (n, 3) rad, from the
    integrator's knot arrays (``tau``, ``psi``, ``theta``, ``rate``, ``origin_ns``): with
    ``exposure_mean`` the increment between the means of the body angle over the exposure windows
    (``exposure_ns`` long) starting at ``t_from`` and at ``t_to``,
    ``((Psi(b + e) - Psi(b)) - (Psi(a + e) - Psi(a))) / e``; else ``Theta(t_to) - Theta(t_from)``.
    Same formulas: on the knot interval ``j`` holding ``t`` (extrapolated beyond the ends),
    ``Theta(t) = theta_j + rate_j h``, ``Psi(t) = psi_j + theta_j h + rate_j h^2 / 2``; zeros
    when no sample was added. Why: the numpy method costs ~20 us of fixed overhead per call."""
    n = t_from.shape[0]
    m = rate.shape[0]
    out = np.zeros((n, 3))
    if m == 0:
        return out
    e = exposure_ns * S_PER_NS
    P = np.empty((4, 3))
    for k in range(n):
        if exposure_mean:
            times = (t_to[k] + exposure_ns, t_to[k], t_from[k] + exposure_ns, t_from[k])
            nq = 4
        else:
            times = (t_to[k], t_from[k], t_to[k], t_from[k])
            nq = 2
        for q in range(nq):
            ts = (times[q] - origin_ns) * S_PER_NS
            j = min(max(np.searchsorted(tau, ts), 1), m) - 1
            h = ts - tau[j]
            for a in range(3):
                if exposure_mean:
                    P[q, a] = psi[j, a] + theta[j, a] * h + 0.5 * rate[j, a] * h * h
                else:
                    P[q, a] = theta[j, a] + rate[j, a] * h
        for a in range(3):
            if exposure_mean:
                out[k, a] = ((P[0, a] - P[1, a]) - (P[2, a] - P[3, a])) / e
            else:
                out[k, a] = P[0, a] - P[1, a]
    return out
