"""The rolling-shutter bundle adjustment (``rs-bundle``): attitude and rate of one frame fitted together.

Centroid-level frames from the project's simulator (he2021b sensor, 15 stars, rolling shutter)
at rates where an attitude solver that ignores the row times is biased; the estimates must be
unbiased and their errors must match the covariance the stage states (Monte Carlo NEES).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from rollingstar.estimators.attitude.frame_fit import velocity_rate
from rollingstar.estimators.attitude.rs_bundle import RsBundleSolver
from rollingstar.estimators.data import FrameData, SensorContext, StarTable
from rollingstar.pipelines.simulate import build_simulator
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.scenario import load_scenario
from rollingstar.sensors.so3 import skew
from tests.estimators.attitude_scenes import errors_rad, nees, run_plugin, sim_frames


@pytest.mark.parametrize("rate_deg_s", [(0.0, 0.0, 0.0), (1.0, -0.5, 2.0)])
def test_attitude_and_rate_errors_match_the_stated_covariance(rate_deg_s):
    frames, motion, ctx, _ = sim_frames(40, seed=3, sigma_px=0.05, rate_deg_s=rate_deg_s)
    outs = run_plugin(RsBundleSolver(pixels=False), frames, ctx)
    att = [a for o in outs for a in o.attitudes]
    assert all(a.valid for a in att)
    # attitude at the stated time: chi-square with 3 degrees of freedom per frame
    e = nees(att, motion)
    lo, hi = chi2.ppf([0.001, 0.999], 3 * len(e)) / len(e)
    assert lo < e.mean() < hi, e.mean()
    # no bias beyond 4 standard errors on any axis
    d = errors_rad(att, motion)
    sd = np.sqrt(np.mean([np.diag(a.covariance_rad2) for a in att], axis=0) / len(d))
    assert np.all(np.abs(d.mean(axis=0)) < 4 * sd)
    # rate: the same test against the rate block
    rates = [o.rate for o in outs]
    t = np.array([r.t_ns for r in rates])
    err = np.array([r.omega_rad_s for r in rates]) - motion.angular_velocity(t)
    q = np.einsum("ni,ni->n", err, np.linalg.solve(np.array([r.covariance for r in rates]), err[..., None])[..., 0])
    assert lo < q.mean() < hi, q.mean()


def test_velocity_rate_recovers_a_rigid_rotation_from_image_velocities():
    cam = PinholeCamera(focal_length_m=24.09e-3, pixel_size_m=5.5e-6, width=1024, height=1024)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 1023, 30), rng.uniform(0, 1023, 30)
    omega = np.radians([10.0, -4.0, 7.0])
    w = cam.unproject(x, y)
    v = np.einsum("nij,nj->ni", cam.projection_jacobian(w) @ skew(w), np.broadcast_to(omega, (30, 3)))
    stars = StarTable.build(x, y, np.zeros(30, dtype=np.int64), vx=v[:, 0], vy=v[:, 1])
    assert np.allclose(velocity_rate(cam, stars), omega, rtol=1e-9, atol=1e-12)
    # mirror test: the same velocities on a field turned by 180 deg about the boresight
    mirrored = StarTable.build(1023 - x, 1023 - y, np.zeros(30, dtype=np.int64), vx=-v[:, 0], vy=-v[:, 1])
    turned = Rotation.from_euler("z", 180, degrees=True).apply(omega)
    assert np.allclose(velocity_rate(cam, mirrored), turned, rtol=1e-9, atol=1e-12)


def _image_frames(n_frames: int, rate_deg_s, seed: int, psf_sigma_px: float = 1.0):
    """he2021a frames rendered by the project's image simulator (exact sampled smear, Poisson, read
    noise, 12-bit ADC), each with its true stars identified and their positions 0.3 px off (a rough
    centroider: the pixel step must not depend on it)."""
    cfg = load_scenario("configs/scenarios/he2021a.yaml")
    cfg = cfg.model_copy(update={"frames": n_frames, "seed": seed,
                                 "motion": cfg.motion.model_copy(update={"rate_deg_s": tuple(rate_deg_s)}),
                                 "image": cfg.image.model_copy(update={"psf_sigma_px": psf_sigma_px})})
    sim = build_simulator(cfg)
    rng = np.random.default_rng(seed)
    frames = []
    for f in sim.frames(n_frames):
        tr = f.truth
        x, y = tr.x + rng.normal(0, 0.3, len(tr)), tr.y + rng.normal(0, 0.3, len(tr))
        stars = StarTable.build(x, y, tr.t_ns, tr.row_time_ns, catalog_id=tr.catalog_id, ref_icrs=tr.unit_icrs,
                                sigma_px=np.full(len(tr), 0.3))
        frames.append(FrameData(index=f.index, t0_ns=f.t0_ns, image=f.image, stars=stars))
    return frames, sim.motion, SensorContext.from_scenario(cfg)


@pytest.mark.parametrize("rate_deg_s", [(0.0, 0.0, 0.0), (6.0, 0.0, 0.0)])
def test_pixel_step_errors_match_the_pixel_information(rate_deg_s):
    """On rendered frames the pixel step's attitude and rate errors are unbiased and scatter as the
    Fisher information of the pixels it states (NEES within its chi-square band)."""
    frames, motion, ctx = _image_frames(16, rate_deg_s, seed=5)
    outs = run_plugin(RsBundleSolver(), frames, ctx)
    att = [a for o in outs for a in o.attitudes]
    assert all(a.valid for a in att)
    e = nees(att, motion)
    lo, hi = chi2.ppf([0.0005, 0.9995], 3 * len(e)) / len(e)
    assert lo < e.mean() < hi, e.mean()
    rates = [o.rate for o in outs]
    t = np.array([r.t_ns for r in rates])
    err = np.array([r.omega_rad_s for r in rates]) - motion.angular_velocity(t)
    q = np.einsum("ni,ni->n", err, np.linalg.solve(np.array([r.covariance for r in rates]), err[..., None])[..., 0])
    assert lo < q.mean() < hi, q.mean()


@pytest.mark.parametrize("psf_sigma_px, tolerance", [(0.8, 0.07), (2.0, 0.02)])
def test_the_pixel_step_measures_the_camera_psf_and_reaches_its_information(psf_sigma_px, tolerance):
    """A camera whose PSF is not the simulator's default: the pixel step measures the width from
    the first frame's stars and then scatters as the information it states. The model draws the
    pixel-integrated PSF as a Gaussian of sigma ``sqrt(s^2 + 1/12)``, right in its second moment
    but not in its shape: under ~1 px the width that fits best runs a few per cent wide (0.84 px
    for 0.8), which is the width the model needs."""
    frames, motion, ctx = _image_frames(12, (3.0, 0.0, 0.0), seed=8, psf_sigma_px=psf_sigma_px)
    solver = RsBundleSolver()
    outs = run_plugin(solver, frames, ctx)
    print(f"\nPSF {psf_sigma_px} px measured as {solver.psf_sigma_px:.3f} px")  # pytest -s
    assert abs(solver.psf_sigma_px / psf_sigma_px - 1) < tolerance, solver.psf_sigma_px
    assert all(o.psf_sigma_px == solver.psf_sigma_px for o in outs)
    att = [a for o in outs for a in o.attitudes]
    assert all(a.valid for a in att)
    assert not any(f.startswith("pixel_step_skipped") for o in outs for f in o.flags)
    e = nees(att, motion)
    lo, hi = chi2.ppf([0.0005, 0.9995], 3 * len(e)) / len(e)
    assert lo < e.mean() < hi, e.mean()


def test_a_pixel_model_that_explains_no_star_falls_back_to_the_positions_and_says_so():
    """The PSF stated far off the camera's (1 px against 2.5 px stars): no star passes the pixel
    step's screen, so the frame keeps the position solution, valid, flagged with the reason."""
    frames, motion, ctx = _image_frames(3, (0.0, 0.0, 0.0), seed=9, psf_sigma_px=2.5)
    outs = run_plugin(RsBundleSolver(psf_sigma_px=1.0), frames, ctx)
    for o in outs:
        assert o.attitudes[0].valid
        assert any(f.startswith("pixel_step_skipped:model_misfit") for f in o.flags), o.flags
    positions = run_plugin(RsBundleSolver(pixels=False), frames, ctx)
    for o, p in zip(outs, positions):
        np.testing.assert_allclose(o.attitudes[0].q_xyzw, p.attitudes[0].q_xyzw, atol=1e-12)


def _reference_position_fit(R, omega, ref, dt, d, iterations, k, huber_k):
    """The position step written with numpy and scipy rotations, straight from the normal equations
    of ``frame_fit.fit_positions``'s docstring (a test oracle for the compiled fit)."""
    Et = np.swapaxes(d.basis, -1, -2)

    def normal(R, omega, huber):
        w = np.stack([Rotation.from_rotvec(omega * t).inv().apply(R.inv().apply(r)) for r, t in zip(ref, dt)])
        S = Et @ skew(w)
        H = np.concatenate([S, S * dt[:, None, None]], axis=2)[:, :, :k]
        e = np.einsum("nki,ni->nk", Et, d.body - w)
        info = d.info
        if huber is not None:
            m = np.sqrt(np.einsum("ni,nij,nj->n", e, info, e))
            info = info * np.minimum(1.0, huber / m)[:, None, None]
        HtW = np.swapaxes(H, -1, -2) @ info
        return np.sum(HtW @ H, axis=0), np.einsum("nik,nk->i", HtW, e)

    for it in range(iterations):
        step = np.linalg.solve(*normal(R, omega, huber_k if it else None))
        R, omega = R * Rotation.from_rotvec(step[:3]), omega + (step[3:] if k == 6 else 0.0)
    return R, omega, normal(R, omega, None)[0]


@pytest.mark.parametrize("fit_rate, huber_k", [(True, 3.0), (True, None), (False, 3.0)])
def test_the_compiled_position_fit_equals_its_normal_equations_written_out(fit_rate, huber_k):
    from rollingstar.estimators.attitude.frame_fit import fit_positions
    from rollingstar.estimators.attitude.star_covariance import direction_covariance

    rng = np.random.default_rng(7)
    cam = PinholeCamera(focal_length_m=0.025, pixel_size_m=5.5e-6, width=1024, height=1024, k1=-0.05)
    n = 25
    x, y = rng.uniform(0, 1023, n), rng.uniform(0, 1023, n)
    cov = np.einsum("nij,nkj->nik", a := rng.normal(0, 0.08, (n, 2, 2)), a) + 1e-4 * np.eye(2)
    d = direction_covariance(cam, x, y, cov)
    truth, omega = Rotation.from_rotvec([0.4, -1.1, 2.0]), np.radians([2.0, -1.0, 4.0])
    dt = rng.uniform(-0.025, 0.025, n)
    ref = np.stack([truth.apply(Rotation.from_rotvec(omega * t).apply(b)) for b, t in zip(d.body, dt)])
    ref[5] = Rotation.from_rotvec([0.0, 2e-3, 0.0]).apply(ref[5])  # a wrong identification the Huber weight bounds
    start = truth * Rotation.from_rotvec([2e-3, -1e-3, 3e-3])
    omega0 = np.zeros(3) if fit_rate else omega
    R, w, info = fit_positions(start, omega0, ref, dt, d, 4, fit_rate, huber_k)
    R_ref, w_ref, info_ref = _reference_position_fit(start, omega0, ref, dt, d, 4, 6 if fit_rate else 3, huber_k)
    assert (R_ref.inv() * R).magnitude() < 1e-12
    np.testing.assert_allclose(w, w_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(info, 0.5 * (info_ref + info_ref.T), rtol=1e-9)
    assert info.shape == ((6, 6) if fit_rate else (3, 3))


@pytest.mark.parametrize("rate_deg_s", [(0.0, 0.0, 0.0), (3.0, 0.0, 0.0), (10.0, 0.0, 0.0)])
def test_the_pixel_step_stops_where_iterating_on_would_move_it_by_hundredths_of_a_sigma(rate_deg_s, monkeypatch):
    """The pixel step ends once Gauss-Newton's next step is predicted below PREDICTED_SIGMAS
    (pixel_bundle's docstring). Iterating until a step itself is under CONVERGED_SIGMAS, from a
    rough start (positions 0.3 px off), moves no attitude or rate component by 0.1 of its sigma."""
    from rollingstar.estimators.attitude import pixel_bundle

    frames, _, ctx = _image_frames(6, rate_deg_s, seed=11)
    early = run_plugin(RsBundleSolver(), frames, ctx)
    monkeypatch.setattr(pixel_bundle, "PREDICTED_SIGMAS", -1.0)  # no prediction: the step rule alone
    full = run_plugin(RsBundleSolver(), frames, ctx)
    for a, b in zip(early, full):
        att_a, att_b = a.attitudes[-1], b.attitudes[-1]
        assert att_a.valid and att_b.valid
        moved = (Rotation.from_quat(att_b.q_xyzw).inv() * Rotation.from_quat(att_a.q_xyzw)).as_rotvec()
        assert np.all(np.abs(moved) < 0.1 * np.sqrt(np.diag(att_b.covariance_rad2))), moved
        rate_moved = a.rate.omega_rad_s - b.rate.omega_rad_s
        assert np.all(np.abs(rate_moved) < 0.1 * np.sqrt(np.diag(b.rate.covariance))), rate_moved
