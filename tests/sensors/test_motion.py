"""Attitude motion: exact kinematics, rate consistency, segment chaining, right Jacobian."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from rollingstar.sensors.motion import (
    JitterMotion,
    PiecewiseMotion,
    Segment,
    compose_rotations,
    constant_acceleration,
    constant_rate,
    inertial_hold,
    so3_right_jacobian,
)

NS = 1_000_000_000
vec3 = st.tuples(*[st.floats(-1.0, 1.0)] * 3).map(np.array)
quat = st.tuples(*[st.floats(-1.0, 1.0)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1).map(Rotation.from_quat)


def _fd_rate(motion, t_ns, h_ns):
    """Central difference Log(R(t - h/2)^T R(t + h/2)) / h: O(h^2) estimate of the body rate."""
    t = np.asarray(t_ns, dtype=np.int64)
    a, b = motion.attitude(t - h_ns // 2), motion.attitude(t + h_ns // 2)
    return (a.inv() * b).as_rotvec() / (h_ns / NS)


def _assert_rate_consistent(motion, t_ns, rtol=1e-9, atol=5e-11):
    """omega(t) against a Richardson-extrapolated (O(h^4)) finite difference of the attitude."""
    w = motion.angular_velocity(t_ns)
    fd = (4 * _fd_rate(motion, t_ns, 20_000) - _fd_rate(motion, t_ns, 40_000)) / 3
    err = np.linalg.norm(fd - w, axis=-1)
    assert np.all(err <= rtol * np.linalg.norm(w, axis=-1) + atol), (err, w)


def test_constant_rate_one_degree_about_x():
    r0 = Rotation.from_euler("zyx", [10, -20, 30], degrees=True)
    m = constant_rate(r0, np.radians([1.0, 0, 0]), start_ns=5 * NS)
    step = r0.inv() * m.attitude(6 * NS)
    np.testing.assert_allclose(step.as_rotvec(), np.radians([1.0, 0, 0]), atol=1e-16)
    np.testing.assert_allclose(m.angular_velocity(6 * NS), np.radians([1.0, 0, 0]), atol=1e-18)
    # body frame: the camera x axis is fixed in ICRS, y rotates about it
    np.testing.assert_allclose(m.attitude(6 * NS).apply([1, 0, 0]), r0.apply([1, 0, 0]), atol=1e-15)
    # before start_ns the law extends backwards
    back = r0.inv() * m.attitude(4 * NS)
    np.testing.assert_allclose(back.as_rotvec(), np.radians([-1.0, 0, 0]), atol=1e-16)


def test_inertial_hold():
    r0 = Rotation.from_rotvec([0.1, 0.2, 0.3])
    m = inertial_hold(r0, start_ns=10)
    t = np.array([-10**15, 0, 10, 10**15])
    np.testing.assert_allclose(m.attitude(t).as_quat(), np.tile(r0.as_quat(), (4, 1)), atol=0)
    np.testing.assert_array_equal(m.angular_velocity(t), np.zeros((4, 3)))


def test_parallel_acceleration_is_uniformly_accelerated_rotation():
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    m = constant_acceleration(Rotation.identity(), 0.3 * axis, -0.1 * axis)
    t = np.array([0, NS, 7 * NS], dtype=np.int64)
    s = t / NS
    np.testing.assert_allclose(m.angular_velocity(t), (0.3 - 0.1 * s)[:, None] * axis, atol=1e-15)
    np.testing.assert_allclose(m.attitude(t).as_rotvec(), (0.3 * s - 0.05 * s**2)[:, None] * axis, atol=1e-14)


def test_large_time_precision():
    # integer-ns differences: at t ~ 1.7e18 ns (Unix epoch now) 1 ns still resolves
    start = 1_700_000_000 * NS
    m = constant_rate(Rotation.identity(), [0.0, 0.0, 1.0], start_ns=start)
    np.testing.assert_allclose(m.attitude(start + 1).as_rotvec(), [0, 0, 1e-9], rtol=1e-12)


@settings(max_examples=40, deadline=None)
@given(r0=quat, w=vec3, a=vec3, t=st.integers(-5 * NS, 20 * NS))
def test_acceleration_rate_matches_attitude(r0, w, a, t):
    _assert_rate_consistent(constant_acceleration(r0, w, a), [t])


@settings(max_examples=30, deadline=None)
@given(
    r0=quat,
    ws=st.lists(st.tuples(vec3, vec3, st.integers(1, 3 * NS)), min_size=1, max_size=4),
    start=st.integers(-NS, NS),
    frac=st.lists(st.floats(-0.2, 1.2), min_size=5, max_size=5),
)
def test_piecewise_rate_matches_attitude(r0, ws, start, frac):
    segs = [Segment(d, w, a) for w, a, d in ws]
    m = PiecewiseMotion(r0, segs, start_ns=start)
    total = sum(d for _, _, d in ws)
    t = start + (np.array(frac) * total).astype(np.int64)
    # stay away from the (rate-discontinuous) segment boundaries by more than h
    bounds = np.asarray(m.segment_starts_ns)
    near = np.min(np.abs(t[:, None] - bounds[None, 1:]), axis=1, initial=10**18) < 40_000
    _assert_rate_consistent(m, t[~near])


@settings(max_examples=40, deadline=None)
@given(
    r0=quat,
    w=vec3,
    a=vec3,
    amp=st.lists(st.floats(0.0, 1e-3), min_size=6, max_size=6),
    freq=st.lists(st.floats(0.0, 50.0), min_size=2, max_size=2),
    phase=st.lists(st.floats(-np.pi, np.pi), min_size=6, max_size=6),
    t=st.integers(0, 10 * NS),
)
def test_jitter_rate_matches_attitude(r0, w, a, amp, freq, phase, t):
    base = constant_acceleration(r0, w, 0.1 * a)
    m = JitterMotion(base, np.reshape(amp, (2, 3)), freq, np.reshape(phase, (2, 3)))
    _assert_rate_consistent(m, [t])


def test_jitter_known_answer():
    # single-axis jitter on an inertial hold: R = Exp(A sin(2 pi f t) x), omega = A 2 pi f cos(...) x
    m = JitterMotion(inertial_hold(Rotation.identity()), [[1e-4, 0, 0]], [10.0], [[0.0, 0, 0]])
    t = np.array([0, 25_000_000, 12_345_678], dtype=np.int64)
    s = t / NS
    np.testing.assert_allclose(m.attitude(t).as_rotvec()[:, 0], 1e-4 * np.sin(2 * np.pi * 10 * s), atol=1e-18)
    np.testing.assert_allclose(m.angular_velocity(t)[:, 0], 1e-4 * 2 * np.pi * 10 * np.cos(2 * np.pi * 10 * s), atol=1e-15)
    np.testing.assert_allclose(m.angular_velocity(t)[:, 1:], 0.0, atol=0)


def test_segment_boundaries_chain_exactly():
    r0 = Rotation.from_rotvec([0.3, -0.2, 0.1])
    s1 = Segment(2 * NS + 7, [0.1, -0.4, 0.2], [0.05, 0.02, -0.3])
    s2 = Segment(NS, [-0.3, 0.1, 0.0], [0.0, 0.2, 0.1])
    s3 = Segment(NS // 2, [0.0, 0.0, 0.5])
    m = PiecewiseMotion(r0, [s1, s2, s3], start_ns=100)
    b1, b2 = 100 + s1.duration_ns, 100 + s1.duration_ns + s2.duration_ns
    # segment 1's law extended to b1 equals segment 2's start
    only1 = PiecewiseMotion(r0, [s1], start_ns=100)
    assert (only1.attitude(b1).inv() * m.attitude(b1)).magnitude() < 1e-15
    # continuity: 1 ns either side moves by at most |omega| * 1 ns
    for b in (b1, b2):
        before, at, after = m.attitude(np.array([b - 1, b, b + 1]))
        assert (before.inv() * at).magnitude() < 2e-9 and (at.inv() * after).magnitude() < 2e-9
    # rate at a boundary is the new segment's start rate; after the end the last law continues
    np.testing.assert_allclose(m.angular_velocity(b1), s2.omega_rad_s, atol=1e-16)
    tail = constant_rate(m.attitude(b2 + s3.duration_ns), s3.omega_rad_s, start_ns=b2 + s3.duration_ns)
    far = b2 + 10 * NS
    assert (tail.attitude(far).inv() * m.attitude(far)).magnitude() < 1e-14


def test_scalar_and_vector_evaluation_identical():
    m = JitterMotion(constant_acceleration(Rotation.from_rotvec([1, 2, 3]), [0.1, 0.2, 0.3], [0.0, -0.1, 0.05]),
                     [[1e-4, 2e-4, 0.0]], [3.0], [[0.1, 0.2, 0.3]])
    t = np.array([-NS, 0, 123_456_789, 5 * NS], dtype=np.int64)
    vec_q, vec_w = m.attitude(t).as_quat(), m.angular_velocity(t)
    for i, ti in enumerate(t):
        single = m.attitude(int(ti))
        assert single.single
        np.testing.assert_array_equal(single.as_quat(), vec_q[i])
        assert m.angular_velocity(int(ti)).shape == (3,)
        np.testing.assert_array_equal(m.angular_velocity(ti), vec_w[i])
    assert len(m.attitude(t[:1])) == 1 and m.angular_velocity(t[:1]).shape == (1, 3)


@settings(max_examples=50, deadline=None)
@given(direction=vec3.filter(lambda v: np.linalg.norm(v) > 1e-3), norm=st.sampled_from([0.0, 1e-9, 1e-5, 0.05, 0.0999, 0.1001, 0.7, 2.0, 3.1]))
def test_right_jacobian_matches_numerical(direction, norm):
    theta = direction / np.linalg.norm(direction) * norm
    jr = so3_right_jacobian(theta)
    h = 1e-6
    num = np.empty((3, 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        plus = (Rotation.from_rotvec(theta).inv() * Rotation.from_rotvec(theta + e)).as_rotvec()
        minus = (Rotation.from_rotvec(theta).inv() * Rotation.from_rotvec(theta - e)).as_rotvec()
        num[:, i] = (plus - minus) / (2 * h)
    np.testing.assert_allclose(jr, num, atol=1e-8)


def test_right_jacobian_identities():
    rng = np.random.default_rng(0)
    theta = rng.normal(size=(200, 3)) * rng.uniform(0, 3, size=(200, 1))
    theta[:5] *= 1e-8
    jr = so3_right_jacobian(theta)
    # J_r(theta) theta = theta; J_r(-theta) = J_r(theta)^T; det J_r = 2 (1 - cos x) / x^2
    np.testing.assert_allclose(np.einsum("nij,nj->ni", jr, theta), theta, atol=1e-15)
    np.testing.assert_allclose(so3_right_jacobian(-theta), np.swapaxes(jr, -1, -2), atol=1e-15)
    x = np.linalg.norm(theta, axis=1)
    np.testing.assert_allclose(np.linalg.det(jr), np.sinc(x / (2 * np.pi)) ** 2, rtol=1e-12)
    # series/closed-form switch is continuous
    a, b = so3_right_jacobian(np.array([[0.1 - 1e-12, 0, 0.0], [0.1 + 1e-12, 0, 0.0]] ) * [1, 1, 1])
    np.testing.assert_allclose(a, b, atol=1e-12)
    np.testing.assert_array_equal(so3_right_jacobian(np.zeros(3)), np.eye(3))


def test_validation():
    with pytest.raises(ValueError, match="duration_ns"):
        Segment(0, np.zeros(3))
    with pytest.raises(ValueError, match="omega_rad_s"):
        Segment(10, [1.0, 2.0])
    with pytest.raises(ValueError, match="segments"):
        PiecewiseMotion(Rotation.identity(), [])
    with pytest.raises(ValueError, match="initial"):
        PiecewiseMotion(Rotation.identity(2), [Segment(1, np.zeros(3))])
    with pytest.raises(ValueError, match="frequency_hz"):
        JitterMotion(inertial_hold(Rotation.identity()), [[1e-4, 0, 0]], [1.0, 2.0], [[0, 0, 0]])
    with pytest.raises(ValueError, match="t_ns"):
        inertial_hold(Rotation.identity()).attitude(0.5)


def test_compose_rotations_matches_scipy():
    a, b = Rotation.random(500, random_state=1), Rotation.random(500, random_state=2)
    got = compose_rotations(a, b)
    assert np.max((got.inv() * (a * b)).magnitude()) < 1e-15
    v = np.array([0.3, -0.4, 0.5])
    np.testing.assert_allclose(got.apply(v), a.apply(b.apply(v)), atol=1e-15)
