"""kf-cv: he2021a eqs (5)-(11) -- batched numpy == filterpy, tracking a constant velocity, Riccati."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rollingstar.estimators.data import FrameData, StarTable
from rollingstar.estimators.filters.kf_cv import (
    KfCvFilter,
    cv_process_noise,
    kf_cv_batch,
    kf_cv_predict,
    kf_cv_update,
    steady_state_covariance,
)
from rollingstar.sensors.timing import DetectorTiming

TIMING = DetectorTiming(mode="rolling", exposure_ns=44_900_000, line_delay_ns=43_900, rows=1024)
CONTEXT = SimpleNamespace(timing=TIMING)


def _frames(seed: int, n_ids: int, n_frames: int, p_present: float, noise: float):
    """Random tracks: stars with random constant velocities, appearing and disappearing at random."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(0, 1000, (n_ids, 2))
    v = rng.normal(0, 80, (n_ids, 2))
    frames = []
    for k in range(n_frames):
        t0 = int(TIMING.frame_start_ns(k))
        present = rng.random(n_ids) < p_present
        idx = rng.permutation(np.flatnonzero(present))  # arbitrary row order
        t_s = k * TIMING.frame_period_ns * 1e-9
        pos = x0[idx] + v[idx] * t_s + rng.normal(0, noise, (idx.size, 2))
        t_ns = TIMING.row_mid_exposure_ns(t0, pos[:, 1])
        stars = StarTable.build(pos[:, 0], pos[:, 1], t_ns, catalog_id=idx + 100, sigma_px=np.full(idx.size, noise))
        frames.append(FrameData(index=k, t0_ns=t0, stars=stars))
    return frames


def _run(frames, **params):
    f = KfCvFilter(**params)
    f.setup(CONTEXT)
    return [f.process(fr) for fr in frames]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), n_ids=st.integers(1, 12), n_frames=st.integers(1, 15),
       p_present=st.floats(0.3, 1.0), q=st.sampled_from([0.0, 1e-4, 1e-2, 10.0]),
       r=st.floats(1e-3, 1.0), dt_source=st.sampled_from(["star_time", "frame_start"]))
def test_batched_equals_filterpy(seed, n_ids, n_frames, p_present, q, r, dt_source):
    frames = _frames(seed, n_ids, n_frames, p_present, np.sqrt(r))
    a = _run(frames, backend="batched", q=q, r=r, dt_source=dt_source)
    b = _run(frames, backend="filterpy", q=q, r=r, dt_source=dt_source)
    for fa, fb in zip(a, b):
        for col in ("x", "y", "vx", "vy", "sigma_px"):
            np.testing.assert_allclose(getattr(fa.stars, col), getattr(fb.stars, col), rtol=0, atol=1e-9, equal_nan=True)
        assert fa.flags == fb.flags


def test_lifecycle_and_eq6_initialisation():
    frames = _frames(3, 4, 3, 1.0, 0.0)
    out = _run(frames)
    assert np.all(np.isnan(out[0].stars.vx))  # first sighting: no velocity
    # second sighting: eq (6), position = measurement, velocity = difference / star-time difference
    s0, s1 = frames[0].stars, frames[1].stars
    o0 = np.argsort(s0.catalog_id)
    o1 = np.argsort(s1.catalog_id)
    dt = (s1.t_ns[o1] - s0.t_ns[o0]) * 1e-9
    np.testing.assert_allclose(out[1].stars.vx[o1], (s1.x[o1] - s0.x[o0]) / dt, rtol=1e-12)
    np.testing.assert_array_equal(out[1].stars.x, s1.x)
    # a star that disappears is retired; when it comes back it starts again
    f = KfCvFilter()
    f.setup(CONTEXT)
    f.process(frames[0])
    f.process(frames[1].evolve(stars=frames[1].stars.take(frames[1].stars.catalog_id != 100)))
    back = f.process(frames[2])
    assert np.isnan(back.stars.vx[back.stars.catalog_id == 100]).all()
    assert np.isfinite(back.stars.vx[back.stars.catalog_id != 100]).all()
    # inputs untouched, unidentified stars pass through
    unid = frames[2].stars.with_columns(catalog_id=np.full(frames[2].stars.n, -1))
    res = f.process(frames[2].evolve(stars=unid))
    np.testing.assert_array_equal(res.stars.x, unid.x)
    assert np.isnan(res.stars.vx).all()


def test_tracks_constant_velocity_truth():
    """200 stars, 100 frames, R = 0.05 px^2: errors shrink like a CV least-squares fit."""
    rng = np.random.default_rng(7)
    T, n, dt, r = 100, 200, 0.08985, 0.05
    v = rng.normal(0, 76.0, (n, 2))
    truth = rng.uniform(0, 1000, (n, 2))[None] + v[None] * (np.arange(T) * dt)[:, None, None]
    z = truth + rng.normal(0, np.sqrt(r), truth.shape)
    X, P = kf_cv_batch(z, dt, q=1e-4, r=r)
    pos_err = np.hypot(X[-1, :, 0] - truth[-1, :, 0], X[-1, :, 2] - truth[-1, :, 1])
    vel_err = np.hypot(X[-1, :, 1] - v[:, 0], X[-1, :, 3] - v[:, 1])
    # least-squares line over N points: endpoint sigma = sigma sqrt(2(2N-1)/(N(N+1))), slope sigma*sqrt(12/(N(N^2-1)))/dt
    sig_end = np.sqrt(r) * np.sqrt(2 * (2 * T - 1) / (T * (T + 1)))
    sig_v = np.sqrt(r) * np.sqrt(12 / (T * (T**2 - 1))) / dt
    assert np.sqrt(np.mean(pos_err**2) / 2) < 1.25 * sig_end
    assert np.sqrt(np.mean(vel_err**2) / 2) < 1.25 * sig_v
    # the filter's own covariance is consistent with its errors
    assert 0.7 < np.sqrt(np.mean(pos_err**2) / 2) / np.sqrt(np.mean(P[-1, :, 0, 0])) < 1.3


@pytest.mark.parametrize("q, r", [(1e-4, 0.05), (1.0, 0.1), (100.0, 0.05)])
def test_steady_state_matches_riccati(q, r):
    dt = 0.08985
    _, P = kf_cv_batch(np.zeros((4000, 1, 2)), dt, q=q, r=r)
    prior, post = steady_state_covariance(dt, q, r)
    np.testing.assert_allclose(P[-1, 0], post, rtol=1e-6, atol=1e-14)
    # and the prior is a fixed point of predict + update
    Xp, Pp = kf_cv_predict(np.zeros((1, 4)), post[None], [dt], q)
    np.testing.assert_allclose(Pp[0], prior, rtol=1e-6, atol=1e-14)
    _, Pu = kf_cv_update(Xp, Pp, np.zeros((1, 2)), r)
    np.testing.assert_allclose(Pu[0], post, rtol=1e-6, atol=1e-14)


def test_process_noise_eq8_corrected():
    dt, q = 0.09, 2.0
    Q = cv_process_noise([dt], q)[0]
    blk = q * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
    np.testing.assert_allclose(Q[:2, :2], blk)
    np.testing.assert_allclose(Q[2:, 2:], blk)
    assert np.all(Q[:2, 2:] == 0)
