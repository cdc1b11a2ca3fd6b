"""Attitude smoother ``gtsam``: a factor graph over Rot3 states at the stars' own exposure times.

Factor graph (GTSAM, Dellaert & Kaess, "Factor graphs for robot perception", 2017; the factors in
:mod:`rollingstar.estimators.attitude.gtsam_graph`):

- one ``Rot3`` state per star time (rolling shutter: every star of a frame refers to its own row's
  mid-exposure ``t_ns``; stars within ``merge_us`` share a state, see :mod:`observations`). We chose
  states at the stars' times over states at frame times with the stars interpolated on the manifold:
  it needs no interpolation model inside the star factors (the motion model between states carries
  it, exactly like the gyro does), every estimate is at a time a star was seen (the update rate of
  he2021b's per-star REQUEST), and the chain stays sparse (tridiagonal in time);
- each identified star: an ``AttitudeFactorRot3`` (body vector from the unprojection by the frame's
  camera, :func:`~rollingstar.estimators.data.frame_camera`, reference ``ref_icrs``, 1-sigma
  ``sigma_px / focal_px``; when the frame's stars carry anisotropic 2 x 2 position covariances, each
  star's exact 2 x 2 direction covariance, :mod:`rollingstar.estimators.attitude.star_covariance`);
- between consecutive states: an ``AHRSFactor`` of ``PreintegratedAhrsMeasurements`` of the gyro
  (bias estimated, one bias per frame segment with a random walk), or, without a gyro, of a zero
  rate with the "bias" standing for minus the body rate: a nearly-constant-angular-velocity motion
  prior (rate per frame segment, white angular-acceleration random walk), see
  :mod:`rollingstar.estimators.attitude.motion_model`.

Modes:

- ``batch``: Levenberg-Marquardt over the whole recording. :meth:`process` buffers and returns a
  provisional causal estimate (the frame's QUEST solution, which the runner does not write but
  feeds to the identifier's prior); :meth:`finish` solves and returns every frame.
- ``fixed-lag``: GTSAM's ``BatchFixedLagSmoother`` (``fixed_lag_backend: batch``, default: LM
  over the window, marginalising older states into a linear prior) or
  ``IncrementalFixedLagSmoother`` (``isam2``, relinearising every update: GTSAM's default 0.1 rad
  threshold would never relinearise arcsecond corrections). A frame is released (:meth:`release`)
  once the newest state is ``lag_s`` past its last star, with the estimate of that update (a frame
  that a long gap would marginalise first is released just before). Under the gyro model a frame
  enters the graph once the gyro samples cover its stars (they arrive with the next frame).
  Measured (``benchmarks/he2021b_attitude.py --seeds 3``, he2021b Table 2 stars, lag 1 s): both
  backends give the same errors to 1e-3 arcsec; ISAM2 costs 14.6 ms of CPU per frame against 26.8.
  The default stays ``batch``: the incremental smoother's marginalisation is known to fail on some
  Bayes-tree shapes (borglab/gtsam#1638, #1795: "known to have problems", segfaults), and a crash
  loses the run, while 27 ms per 100 ms frame keeps up in real time.

Outputs per state: an :class:`AttitudeEstimate` at the state's time with the marginal covariance
of the state (GTSAM's ``Rot3`` tangent is the body frame: ``R_true = R Exp(d)``, the project's
camera-frame error) when ``covariance`` is on, and the gyro bias of its segment (gyro model);
``frame.rate`` (when no earlier stage set it) at the frame's last state, ``omega_meas - b``.
Frames without identified stars get an invalid estimate with the reason; an unobservable graph
(e.g. a single star in the whole recording) makes every estimate invalid with GTSAM's reason; when
GTSAM cannot factor the marginals (extreme noise ratios, see ``_marginals``) the estimates carry no
covariance and the frame is flagged ``covariance_unavailable``.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Literal

import gtsam
import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from rollingstar.estimators.attitude.base import AttitudeSolver
from rollingstar.estimators.attitude.gtsam_graph import (
    ahrs_factor,
    bias_key,
    bias_prior_factor,
    bias_walk_factor,
    rot_key,
    rotation_of,
    rotation_params,
    star_factors,
    to_rot3,
)
from rollingstar.estimators.attitude.motion_model import (
    MotionModelParams,
    motion_noise,
    resolve_mode,
)
from rollingstar.estimators.attitude.observations import (
    StarObservations,
    star_observations,
)
from rollingstar.estimators.attitude.robust import apply_robust
from rollingstar.estimators.attitude.wahba import quest, quest_covariance
from rollingstar.estimators.data import AttitudeEstimate, FrameData, RateEstimate, default_sigma_px, frame_camera
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.gyro import GyroIntegrator

__all__ = ["GtsamSmoother", "GtsamParams"]


class GtsamParams(MotionModelParams):
    mode: Literal["batch", "fixed-lag"] = Field(
        default="batch", description="'batch': Levenberg-Marquardt over the whole recording (results at the end); "
        "'fixed-lag': a frame is final once the newest star is lag_s later.")
    lag_s: float = Field(default=1.0, gt=0, description="fixed-lag: smoothing window (s).")
    fixed_lag_backend: Literal["batch", "isam2"] = Field(
        default="batch", description="fixed-lag: GTSAM BatchFixedLagSmoother ('batch') or IncrementalFixedLagSmoother ('isam2').")
    covariance: bool = Field(default=True, description="Compute the marginal covariance of every state.")
    huber_k: float | None = Field(
        default=None, gt=0, description="Huber M-estimator threshold (in sigmas) on the star factors; None: Gaussian.")
    max_iterations: int = Field(default=50, ge=1, description="Levenberg-Marquardt iteration limit (batch mode and "
                                "the batch fixed-lag backend).")
    max_chi2_dof: float = Field(default=100.0, gt=1, description="batch: a solution whose chi-square per residual "
                                "exceeds this is reported as not converged (all estimates invalid).")


@dataclass
class _Block:
    """One frame and its part of the graph (states ``first .. first + m - 1``, segment ``segment``)."""

    frame: FrameData
    obs: StarObservations
    reason: str = ""
    first: int = -1
    segment: int = -1
    init: list = field(default_factory=list)

    @property
    def m(self) -> int:
        return self.obs.n_states


class GtsamSmoother(AttitudeSolver):
    """Factor-graph attitude smoother over Rot3 states at the stars' own times (GTSAM); batch
    Levenberg-Marquardt or fixed-lag. See the module docstring for the graph, the modes and the
    outputs; the star and motion factors are in :mod:`rollingstar.estimators.attitude.gtsam_graph`."""

    name = "gtsam"
    provides = frozenset({"attitude", "rate"})
    Params = GtsamParams
    defers_output = True

    def setup(self, context) -> None:
        super().setup(context)
        p = self.params
        self._sigma_px = default_sigma_px(p.sigma_px, context)
        self._merge_ns = int(round(p.merge_us * 1e3))
        self._gyro = GyroIntegrator(keep_s=1e9)  # keep every sample (batch needs the whole log)
        self._mode: str | None = None
        self._noise = None
        self._pending: deque[_Block] = deque()  # not yet in the graph (batch: all; fixed-lag: gyro not there yet)
        self._in_graph: deque[_Block] = deque()  # fixed-lag: in the graph, not released
        self._released: list[FrameData] = []
        self._n_states = 0
        self._n_segments = 0
        self._last: tuple[int, int, int, int] | None = None  # (state, t_ns, segment, segment t_ns)
        self._t_origin: int | None = None
        self._guess_rate = np.zeros(3)
        self._guess_last: tuple[Rotation, int] | None = None
        self._prev_quest: tuple[Rotation, int] | None = None
        self._smoother = None
        self._failed = ""
        self._ref_info = np.zeros((3, 3))  # sum (I - r r^T) of the catalogue directions in the graph

    # ------------------------------------------------------------------ streaming interface
    def process(self, frame: FrameData) -> FrameData:
        if frame.gyro.t_ns.size:
            self._gyro.add(frame.gyro)
        p = self.params
        camera = frame_camera(frame, self.context)
        frame = apply_robust(frame, camera, p, self._sigma_px, p.use_star_sigma, p.star_covariance)
        obs, dropped = star_observations(frame.stars, camera, self._sigma_px, p.use_star_sigma, self._merge_ns,
                                         p.star_covariance)
        reason = ""
        if obs.n == 0:
            reason = "no identified stars" + (f" ({dropped} with non-finite position or reference)" if dropped else "")
        elif self._mode is None:
            self._mode = resolve_mode(self.params, not self._gyro.empty)
            self._noise = motion_noise(self.params, self._mode)
            self._t_origin = int(obs.t_ns[0])
        self._pending.append(_Block(frame, obs, reason))
        if self.params.mode == "fixed-lag":
            self._advance(final=False)
        return self._provisional(frame, obs, reason)

    def release(self) -> list[FrameData]:
        out, self._released = self._released, []
        return out

    def finish(self) -> list[FrameData]:
        if self.params.mode == "fixed-lag":
            self._advance(final=True)
            return self.release()
        blocks = list(self._pending)
        self._pending.clear()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for b in blocks:
            self._ingest(b, graph, values, None)
        result, marginals = None, None
        if values.size() and self._unobservable():
            self._failed = self._unobservable()
        elif values.size():
            try:
                result = gtsam.LevenbergMarquardtOptimizer(graph, values, self._lm_params()).optimize()
            except RuntimeError as exc:  # GTSAM's IndeterminantLinearSystemException et al.
                self._failed = f"attitude unobservable from the stars and motion model ({type(exc).__name__}: {exc})"
            if result is not None:
                # LM gives up silently (returning its start) when it cannot solve the damped system:
                # a normalised chi-square far above 1 means no solution, never a valid estimate.
                dof = sum(graph.at(i).dim() for i in range(graph.size()))
                chi2_dof = 2.0 * graph.error(result) / max(dof, 1)
                if chi2_dof > self.params.max_chi2_dof:
                    self._failed = (f"Levenberg-Marquardt did not converge (chi2/dof {chi2_dof:.3g} > {self.params.max_chi2_dof}); "
                                    "the motion noise may be too small for the star noise")
                    result = None
            if result is not None and self.params.covariance:
                marginals = self._marginals(graph, result)
        return [self._output(b, result, marginals) for b in blocks]

    @staticmethod
    def _marginals(graph, result):
        """GTSAM marginals (``marginalCovariance(key)``): ``Marginals`` (Cholesky), else, when that
        declares the system indeterminate (stiff motion factors, see ``_lm_params``), an ISAM2 Bayes
        tree built with QR at ``result``; None when both fail (the frames are then flagged)."""
        try:
            return gtsam.Marginals(graph, result)
        except RuntimeError:
            pass
        try:
            params = gtsam.ISAM2Params()
            params.setFactorization("QR")
            isam = gtsam.ISAM2(params)
            isam.update(graph, result)
            return isam
        except RuntimeError:
            return None

    # ------------------------------------------------------------------ fixed-lag
    def _new_smoother(self):
        lag = self.params.lag_s + 3.0 * self.context.timing.frame_period_ns * S_PER_NS  # margin: read before marginalising
        if self.params.fixed_lag_backend == "isam2":
            isam = gtsam.ISAM2Params()
            # GTSAM's default relinearisation threshold (0.1 rad) never relinearises arcsecond-level
            # corrections: relinearise every variable that moved by more than 1e-9 rad, at every update.
            isam.setRelinearizeThreshold(1e-9)
            isam.relinearizeSkip = 1
            isam.setFactorization("QR")  # see _lm_params
            return gtsam.IncrementalFixedLagSmoother(lag, isam)
        return gtsam.BatchFixedLagSmoother(lag, self._lm_params())

    def _lm_params(self) -> gtsam.LevenbergMarquardtParams:
        """LM stopping rules tightened from GTSAM's defaults (relative decrease 1e-5 of a cost of
        thousands of star residuals stops a fraction of a sigma early)."""
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(self.params.max_iterations)
        lm.setRelativeErrorTol(1e-12)
        lm.setAbsoluteErrorTol(1e-9)
        # QR on the whitened Jacobian, not Cholesky on the normal equations: motion factors between
        # stars microseconds apart are ~1e7 times stiffer than a star, which squares to a condition
        # number (~1e14) GTSAM's Cholesky declares indeterminate.
        lm.setLinearSolverType("MULTIFRONTAL_QR")
        return lm

    def _advance(self, final: bool) -> None:
        """Move ready blocks into the fixed-lag graph, update, and release the frames now final."""
        if self._smoother is None:
            self._smoother = self._new_smoother()
        graph, values, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
        newest_sample = None if self._gyro.empty else self._gyro.origin_ns + round(self._gyro.tau[-1] / S_PER_NS)
        ready = []
        while self._pending:
            b = self._pending[0]
            if (not final and self._mode == "gyro" and b.m
                    and (newest_sample is None or newest_sample < int(b.obs.state_t_ns[-1]))):
                break  # its gyro samples arrive with the next frame
            ready.append(self._pending.popleft())
        newest = max((int(b.obs.state_t_ns[-1]) for b in ready if b.m), default=None)
        if newest is not None:
            # A long gap would marginalise a frame inside this update before it is released:
            # release such frames first, with the estimate so far.
            horizon = newest - int(self._smoother.smootherLag() / S_PER_NS)
            while self._in_graph and (not self._in_graph[0].m or int(self._in_graph[0].obs.state_t_ns[0]) < horizon):
                self._released.append(self._output_fixed_lag(self._in_graph.popleft()))
        for b in ready:
            self._ingest(b, graph, values, stamps)
            self._in_graph.append(b)
        if values.size() and not self._failed and not self._unobservable():
            try:
                self._smoother.update(graph, values, stamps)
            except RuntimeError as exc:
                self._failed = f"attitude unobservable from the stars and motion model ({type(exc).__name__}: {exc})"
        t_now = self._last[1] if self._last is not None else None
        lag_ns = int(self.params.lag_s / S_PER_NS)
        while self._in_graph:
            b = self._in_graph[0]
            done = final or not b.m or (t_now is not None and int(b.obs.state_t_ns[-1]) <= t_now - lag_ns)
            if not done:
                break
            self._in_graph.popleft()
            self._released.append(self._output_fixed_lag(b))
        if final:
            while self._pending:  # only blocks with no stars can remain here
                self._released.append(self._output(self._pending.popleft(), None, None))

    def _output_fixed_lag(self, b: _Block) -> FrameData:
        est = self._smoother.calculateEstimate() if b.m and not self._failed else None
        if est is None or self._unobservable() or not est.exists(rot_key(b.first)):
            if b.m and not self._failed:
                b.reason = self._unobservable() or "no solution (state already marginalised)"
            return self._output(b, None, None)
        marg = None
        if self.params.covariance:
            if self.params.fixed_lag_backend == "isam2":
                marg = self._smoother
            else:
                marg = self._marginals(self._smoother.getFactors(), est)
        return self._output(b, est, marg)

    def _unobservable(self) -> str:
        """Reason the attitude is unobservable from the stars so far (all along one direction), or ''."""
        ev = np.linalg.eigvalsh(self._ref_info)
        if ev[0] > 1e-12 * max(ev.sum(), np.finfo(float).tiny):
            return ""
        return "attitude unobservable from the stars and motion model: every identified star so far has the same direction"

    # ------------------------------------------------------------------ graph construction
    def _ingest(self, b: _Block, graph, values, stamps) -> None:
        """Add block ``b``'s states, star factors and motion factors (linking to the previous block)."""
        if not b.m:
            return
        obs, n = b.obs, self._noise
        self._ref_info += obs.n * np.eye(3) - obs.ref.T @ obs.ref
        b.first = self._n_states
        self._n_states += b.m
        b.segment = self._n_segments
        self._n_segments += 1
        b.init = self._initial_rotations(obs)
        t_seg = int(obs.state_t_ns[0])
        kb = bias_key(b.segment)
        values.insert(kb, np.zeros(3) if self._mode == "gyro" else -self._guess_rate)
        if self._last is None:
            graph.add(bias_prior_factor(kb, n.beta_sigma))
        else:
            graph.add(bias_walk_factor(bias_key(self._last[2]), kb, (t_seg - self._last[3]) * S_PER_NS, n.sigma_u))
        params = rotation_params(n.sigma_v)
        slices = obs.state_slices()
        for j in range(b.m):
            key = rot_key(b.first + j)
            values.insert(key, to_rot3(b.init[j]))
            for f in self._star_factors(key, obs, slices[j], b.init[j]):
                graph.add(f)
            t_j = int(obs.state_t_ns[j])
            if j > 0:
                prev, t_prev, seg = b.first + j - 1, int(obs.state_t_ns[j - 1]), b.segment
            elif self._last is not None:
                prev, t_prev, seg = self._last[0], self._last[1], self._last[2]
            else:
                prev = None
            if prev is not None:
                dt = (t_j - t_prev) * S_PER_NS
                graph.add(ahrs_factor(rot_key(prev), key, bias_key(seg), self._mean_rate(t_prev, t_j), dt, params))
            if stamps is not None:
                stamps[key] = (t_j - self._t_origin) * S_PER_NS
        if stamps is not None:
            stamps[kb] = (int(obs.state_t_ns[-1]) - self._t_origin) * S_PER_NS
        self._last = (b.first + b.m - 1, int(obs.state_t_ns[-1]), b.segment, t_seg)

    def _star_factors(self, key: int, obs: StarObservations, sl: slice, R_init: Rotation) -> list:
        """The star factors of one state (isotropic, or with the stars' 2 x 2 covariances)."""
        d = obs.direction
        if d is None:
            return star_factors(key, obs.body[sl], obs.ref[sl], obs.sigma_rad[sl], self.params.huber_k)
        return star_factors(key, obs.body[sl], obs.ref[sl], obs.sigma_rad[sl], self.params.huber_k,
                            d.cov[sl], d.basis[sl], R_init)

    def _mean_rate(self, t_a: int, t_b: int) -> np.ndarray:
        if self._mode != "gyro":
            return np.zeros(3)
        return self._gyro.increment(np.int64(t_a), np.int64(t_b)) / ((t_b - t_a) * S_PER_NS)

    def _initial_rotations(self, obs: StarObservations) -> list[Rotation]:
        """Initial values: the frame's QUEST attitude at its weighted-mean time moved to each state
        with the guessed rate (gyro, or QUEST-to-QUEST differences); without a QUEST solution the
        last initial value propagated the same way."""
        a = 1.0 / obs.sigma_rad**2
        res = quest(obs.ref[None], obs.body[None], a[None]) if obs.n >= 2 else None
        if res is not None and res.valid[0]:
            base = int(obs.t_ns[0])
            t_q = base + int(np.rint(np.sum(a * (obs.t_ns - base)) / np.sum(a)))
            R_q = Rotation.from_quat(res.q_xyzw[0])
            if self._mode != "gyro" and self._prev_quest is not None and t_q > self._prev_quest[1]:
                R0, t0 = self._prev_quest
                self._guess_rate = (R0.inv() * R_q).as_rotvec() / ((t_q - t0) * S_PER_NS)
            self._prev_quest = (R_q, t_q)
            anchor = (R_q, t_q)
        elif self._guess_last is not None:
            anchor = self._guess_last
        else:
            anchor = (Rotation.identity(), int(obs.state_t_ns[0]))
        out = [anchor[0] * Rotation.from_rotvec(self._guess_increment(anchor[1], int(t))) for t in obs.state_t_ns]
        self._guess_last = (out[-1], int(obs.state_t_ns[-1]))
        return out

    def _guess_increment(self, t_a: int, t_b: int) -> np.ndarray:
        if self._mode == "gyro":
            return self._gyro.increment(np.int64(t_a), np.int64(t_b))
        return self._guess_rate * ((t_b - t_a) * S_PER_NS)

    # ------------------------------------------------------------------ outputs
    def _provisional(self, frame: FrameData, obs: StarObservations, reason: str) -> FrameData:
        """The causal single-frame estimate :meth:`process` returns (QUEST at the stars' weighted-mean
        time, Shuster's covariance): the smoothed frames come from :meth:`release` / :meth:`finish`;
        the runner writes those and feeds this one to the identifier's prior."""
        t_ref = self.context.timing.frame_reference_ns(frame.t0_ns)
        est = AttitudeEstimate.invalid(t_ref, obs.n, reason or "provisional: fewer than 2 identified stars or collinear")
        if obs.n >= 2:
            a = 1.0 / obs.sigma_rad**2
            res = quest(obs.ref[None], obs.body[None], a[None])
            if res.valid[0]:
                base = int(obs.t_ns[0])
                t_q = base + int(np.rint(np.sum(a * (obs.t_ns - base)) / np.sum(a)))
                est = AttitudeEstimate(t_ns=t_q, q_xyzw=res.q_xyzw[0], n_stars=obs.n,
                                       covariance_rad2=quest_covariance(obs.body[None], a[None])[0])
        return frame.evolve(attitudes=frame.attitudes + (est,))

    def _output(self, b: _Block, result, marginals) -> FrameData:
        frame, obs = b.frame, b.obs
        counts = np.bincount(obs.state_of, minlength=obs.n_states) if obs.n else np.zeros(0, dtype=int)
        if not b.m or result is None:
            reason = b.reason or self._failed or "no solution"
            times = obs.state_t_ns if b.m else [self.context.timing.frame_reference_ns(frame.t0_ns)]
            cnts = counts if b.m else [0]
            ests = tuple(AttitudeEstimate.invalid(int(t), int(c), reason) for t, c in zip(times, cnts))
            return frame.evolve(attitudes=frame.attitudes + ests, flags=frame.flags + ("attitude_invalid",))
        kb = bias_key(b.segment)
        beta = np.asarray(result.atVector(kb), dtype=float)
        bias = beta.copy() if self._mode == "gyro" else None
        ests = []
        for j in range(b.m):
            key = rot_key(b.first + j)
            q = rotation_of(result.atRot3(key)).as_quat(canonical=True)
            cov = None
            if marginals is not None:
                P = np.asarray(marginals.marginalCovariance(key), dtype=float)
                cov = 0.5 * (P + P.T)
            ests.append(AttitudeEstimate(t_ns=int(obs.state_t_ns[j]), q_xyzw=q, n_stars=int(counts[j]),
                                         covariance_rad2=cov, gyro_bias_rad_s=bias))
        out = frame.evolve(attitudes=frame.attitudes + tuple(ests))
        if marginals is None and self.params.covariance:
            out = out.flagged("covariance_unavailable")
        if out.rate is None:
            t_last = int(obs.state_t_ns[-1])
            u = self._gyro.rate_at(np.int64(t_last)) if self._mode == "gyro" else np.zeros(3)
            cov = None
            if marginals is not None:
                P = np.asarray(marginals.marginalCovariance(kb), dtype=float)
                cov = 0.5 * (P + P.T)
            out = out.evolve(rate=RateEstimate(t_ns=t_last, omega_rad_s=u - beta, covariance=cov))
        return out
