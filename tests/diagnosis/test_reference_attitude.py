"""A reference attitude the recording carries (``/truth/attitude``), used as a prior of stated
accuracy on every frame's attitude, makes testable the effects the attitude absorbs.

Recordings: the discrepancy benchmark's base sensor (he2021b optics, 1024 x 1024, 0.05 px) turning
about one axis, with a boresight roll (a rotation of the whole field, which the stars alone cannot
see) and a clock offset (a constant-rate rotation, the same). The reference is the simulation's
truth; where its stated accuracy must be real, it is perturbed by that much.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import yaml
from scipy import stats
from scipy.spatial.transform import Rotation

from rollingstar.config import validate
from rollingstar.estimators.diagnosis.report import write_report
from rollingstar.pipelines import diagnose as P
from rollingstar.pipelines.diagnose import DiagnoseOptions, diagnose_recording
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.conventions import ARCSEC_TO_RAD
from rollingstar.sensors.scenario import ScenarioConfig
from rollingstar.studies.bench import discrepancy as D

OPTIONS = DiagnoseOptions(n_boot=10, stability=False, resimulate=False, seed=1)


def _recording(tmp_path, seed: int, effects: list[dict]) -> tuple[ScenarioConfig, ScenarioConfig, str]:
    """The base scenario, the one the recording was made with (``effects`` added) and the recording."""
    cfg = D.design_scenario(D.base_scenario(20), "single_axis", 20.0, np.random.default_rng(seed), 20, seed)
    truth = validate(ScenarioConfig, {**cfg.model_dump(mode="json"), "effects": effects}, "<t>")
    rec = tmp_path / f"{seed}-{len(effects)}.mcap"
    simulate_to_log(truth, rec, show_progress=False)
    return cfg, truth, rec


def _noisy_reference(monkeypatch, rng: np.random.Generator, sigma_arcsec: float) -> None:
    """Read the reference with a random rotation of ``sigma_arcsec`` per axis on every frame."""
    read = P.read_reference

    def noisy(recording, obs, *checks):
        attitude, covered = read(recording, obs, *checks)
        return Rotation.from_rotvec(rng.normal(0.0, sigma_arcsec * ARCSEC_TO_RAD, (len(attitude), 3))) * attitude, covered

    monkeypatch.setattr(P, "read_reference", noisy)


ROLL = [{"kind": "boresight_rotation", "params": {"roll_arcsec": 60.0}}]


def test_a_reference_attitude_makes_an_absorbed_roll_testable(tmp_path):
    """A 60 arcsec boresight roll: the stars alone cannot see it (listed as absorbed, not named).
    With the recording's truth attitude as a 0.5 arcsec reference it is tested and measured; on a
    recording without the roll nothing is seen."""
    cfg, _, rec = _recording(tmp_path, 5, ROLL)
    _, _, null = _recording(tmp_path, 5, [])
    plain, _ = diagnose_recording(rec, cfg, None, OPTIONS)
    assert "boresight_rotation" in [a["name"] for a in plain["absorbed_by_attitude"]] and plain["effects"] == []
    with_ref = replace(OPTIONS, reference_sigma_arcsec=0.5)
    result, _ = diagnose_recording(rec, cfg, None, with_ref)
    row = next(c for c in result["attitude_reference"]["candidates"] if c["name"] == "boresight_rotation")
    roll = row["params"]["roll_arcsec"]
    print("roll against the reference:", roll)  # pytest -s: the figure in docs/diagnosis.md
    assert row["tested"] and abs(roll["value"] - 60.0) < 4 * roll["sigma"], row
    assert result["mismatch"] and "seen against the reference attitude" in result["summary"]
    clean, _ = diagnose_recording(null, cfg, None, with_ref)
    assert not any(c["tested"] for c in clean["attitude_reference"]["candidates"]), clean["attitude_reference"]
    assert clean["attitude_reference"]["model"] == []


@pytest.mark.parametrize("given_roll", [0.0, 25.0])
def test_the_effect_seen_against_the_reference_goes_to_the_updated_scenario_and_closes_the_fit(tmp_path, given_roll):
    """The roll measured against the reference is written to the updated scenario (on top of the
    roll the scenario already has, if any), at the value the report gives; diagnosed again against
    that scenario, the attitude differences are consistent with the reference's accuracy."""
    cfg, _, rec = _recording(tmp_path, 7, ROLL)
    if given_roll:
        cfg = validate(ScenarioConfig, {**cfg.model_dump(mode="json"), "effects": [
            {"kind": "boresight_rotation", "params": {"roll_arcsec": given_roll}}]}, "<t>")
    with_ref = replace(OPTIONS, reference_sigma_arcsec=0.5)
    first, d = diagnose_recording(rec, cfg, None, with_ref)
    (model,) = first["attitude_reference"]["model"]
    roll = model["params"]["roll_arcsec"]
    assert model["name"] == "boresight_rotation" and abs(roll["value"] - 60.0) < 4 * roll["sigma"], roll
    assert f"roll_arcsec = {roll['value']:.4g}" in first["summary"]
    updated = d.updated_scenario()
    (effect,) = [e for e in updated.effects if e.kind == "boresight_rotation"]
    assert effect.params["roll_arcsec"] == pytest.approx(roll["value"])
    again, _ = diagnose_recording(rec, updated, None, with_ref)
    ref = again["attitude_reference"]
    assert ref["model"] == [] and not any(c["tested"] for c in ref["candidates"]), ref
    assert stats.chi2.sf(ref["chi2"], ref["dof"]) > 1e-3, ref
    assert ref["chi2"] < 0.2 * first["attitude_reference"]["chi2"]


@pytest.mark.parametrize("offset_ms", [20.0, 5.0])
def test_two_absorbed_effects_are_fitted_together_and_a_collinear_pair_is_reported(tmp_path, offset_ms):
    """A roll and a clock offset at once. Fitted together, both come out right. At a constant rate
    an exposure smear's shift of the reference time is the same rotation as the clock offset: at
    5 ms (a smear fraction of about 0.25) the report says the reference cannot tell them apart, with
    the experiment that would; at 20 ms the smear would need a fraction of about 1, beyond its
    bound of 0.5, so the clock offset is the only explanation. The updated scenario holds what was
    chosen either way."""
    effects = [*ROLL, {"kind": "time_offset", "params": {"offset_ms": offset_ms}}]
    cfg, _, rec = _recording(tmp_path, 3, effects)
    result, d = diagnose_recording(rec, cfg, None, replace(OPTIONS, reference_sigma_arcsec=1.0))
    ref = result["attitude_reference"]
    model = {m["name"]: m["params"] for m in ref["model"]}
    pairs = [sorted(a["candidates"]) for a in ref["ambiguous"]]
    roll = model["boresight_rotation"]["roll_arcsec"]
    assert abs(roll["value"] - 60.0) < 4 * roll["sigma"], roll
    if offset_ms == 20.0:
        assert set(model) == {"boresight_rotation", "time_offset"}, ref
        # at a constant rate both are constant rotations, as a misaligned reference would show; the
        # clock offset is not paired with the smear
        assert sorted(pairs) == [["a misaligned reference", "boresight_rotation"],
                                 ["a misaligned reference", "time_offset"]], ref["ambiguous"]
        offset = model["time_offset"]["offset_ms"]
        assert abs(offset["value"] - offset_ms) < 0.05 * offset_ms, offset
    else:
        assert set(model) in ({"boresight_rotation", "time_offset"}, {"boresight_rotation", "exposure_smear"}), ref
        assert ["exposure_smear", "time_offset"] in pairs, ref["ambiguous"]
        assert "cannot tell" in result["summary"] and "two exposure times" in result["summary"]
    assert {e.kind for e in d.updated_scenario().effects} == set(model)
    assert stats.chi2.sf(ref["chi2_after"], ref["dof_after"]) > 1e-4, ref
    page = write_report(result, d, tmp_path / "report").read_text()
    assert "Against the reference attitude" in page and "value in the joint model" in page


def _misaligned_reference(monkeypatch, rotvec_arcsec) -> None:
    """Read the reference as a second tracker misaligned by ``rotvec_arcsec`` (camera axes) would give it."""
    read = P.read_reference

    def misaligned(recording, obs, *checks):
        attitude, covered = read(recording, obs, *checks)
        return attitude * Rotation.from_rotvec(np.asarray(rotvec_arcsec) * ARCSEC_TO_RAD), covered

    monkeypatch.setattr(P, "read_reference", misaligned)


def test_a_misaligned_reference_is_fitted_as_such_not_named_as_physics(tmp_path, monkeypatch):
    """A recording with no effect, against a reference misaligned by (20, -15, 10) arcsec. Taken as
    aligned, whatever the reference shows is a constant rotation, and every effect it names is
    reported as not told apart from a misaligned reference. With ``reference_mount_free`` the
    misalignment is fitted (within 4 sigma per axis) and nothing is named."""
    m = np.array([20.0, -15.0, 10.0])
    cfg, _, rec = _recording(tmp_path, 6, [])
    _misaligned_reference(monkeypatch, m)
    aligned = diagnose_recording(rec, cfg, None, replace(OPTIONS, reference_sigma_arcsec=0.5))[0]["attitude_reference"]
    print("taken as aligned:", [m["name"] for m in aligned["model"]], aligned["ambiguous"])
    assert aligned["model"], aligned  # the misalignment shows as effects: each must carry the caveat
    for effect in aligned["model"]:
        assert [effect["name"], "a misaligned reference"] in [a["candidates"] for a in aligned["ambiguous"]], aligned
    free_opts = replace(OPTIONS, reference_sigma_arcsec=0.5, reference_mount_free=True)
    result = diagnose_recording(rec, cfg, None, free_opts)[0]
    free = result["attitude_reference"]
    assert free["model"] == [] and not any(c["tested"] for c in free["candidates"]), free
    fitted, sigma = np.array(free["mount"]["rotation_arcsec"]), np.array(free["mount"]["sigma_arcsec"])
    assert np.all(np.abs(fitted - m) < 4 * sigma), (fitted, sigma)
    assert stats.chi2.sf(free["chi2"], free["dof"]) > 1e-3, free
    assert "misalignment, fitted" in result["summary"]


def test_a_free_mount_leaves_a_roll_untested_and_says_why(tmp_path):
    """A boresight roll is a constant rotation: with the reference's misalignment free it cannot be
    told from it, and is not tested (nothing determined), where an aligned reference measures it."""
    cfg, _, rec = _recording(tmp_path, 5, ROLL)
    result = diagnose_recording(rec, cfg, None, replace(OPTIONS, reference_sigma_arcsec=0.5, reference_mount_free=True))[0]
    ref, summary = result["attitude_reference"], result["summary"]
    row = next(c for c in ref["candidates"] if c["name"] == "boresight_rotation")
    assert not row["determined"] and not row["tested"] and ref["model"] == [], row
    assert abs(ref["mount"]["rotation_arcsec"][2] + 60.0) < 4 * ref["mount"]["sigma_arcsec"][2], ref["mount"]
    assert "boresight_rotation (a constant rotation, which the reference's fitted misalignment takes up" in summary


def _raw_copy(src, dst, edit) -> None:
    """Copy a recording with the plain ``mcap`` package, ``edit`` changing every /truth/attitude
    message's JSON as a hostile writer could (our writer refuses such records)."""
    import json

    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f, open(dst, "wb") as g:
        reader, writer = make_reader(f), Writer(g)
        writer.start(profile="", library="a hostile writer")
        for md in reader.iter_metadata():
            writer.add_metadata(md.name, md.metadata)
        schemas, channels = {}, {}
        for schema, channel, msg in reader.iter_messages():
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas[schema.id], channel.metadata)
            data = msg.data
            if channel.topic == "/truth/attitude":
                record = json.loads(data)
                edit(record)
                data = json.dumps(record).encode()
            writer.add_message(channels[channel.id], msg.log_time, data, msg.publish_time, msg.sequence)
        writer.finish()


@pytest.mark.parametrize("edit, needle", [
    (lambda r: r["qx"].__setitem__(len(r["qx"]) // 2, None), "Input should be a valid number"),
    (lambda r: r["t_ns"].__setitem__(len(r["t_ns"]) // 2, r["t_ns"][0]), "t_ns must be non-decreasing"),
])
def test_a_damaged_reference_is_refused_with_the_message_and_field(tmp_path, edit, needle):
    """A reference attitude with a null quaternion component or times running back, written with
    the plain mcap package: the diagnosis with --reference-attitude-arcsec exits 2 and names the
    topic and the field; no traceback, no reference quietly ignored."""
    from tests.reliability.helpers import cli

    cfg, _, rec = _recording(tmp_path, 5, ROLL)
    (tmp_path / "sim.yaml").write_text(yaml.safe_dump(cfg.model_dump(mode="json")))
    _raw_copy(rec, tmp_path / "damaged.mcap", edit)
    code, out, err = cli("diagnose", "--sim", tmp_path / "sim.yaml", "--recording", tmp_path / "damaged.mcap",
                         "--reference-attitude-arcsec", "0.5", "--json", "-q")
    assert code == 2 and "/truth/attitude" in err and needle in err, (code, err[-500:])
    assert "Traceback" not in out + err


@pytest.mark.long_study
def test_the_reference_measurements_scatter_as_their_stated_sigma(tmp_path, monkeypatch):
    """Monte Carlo over recordings and reference noise: a 30 arcsec roll measured against a
    reference perturbed by its stated 3 arcsec per axis. The pulls (estimate - truth) / sigma have
    mean 0 and spread 1; the joint model's chi-square sums to its degrees of freedom; on the same
    recordings without the roll, the reference sees an effect in no more than a few."""
    n, sigma_ref = 30, 3.0
    rng = np.random.default_rng(11)
    _noisy_reference(monkeypatch, rng, sigma_ref)
    opts = replace(OPTIONS, reference_sigma_arcsec=sigma_ref)
    pulls, chi2, dof, false = [], 0.0, 0, 0
    for seed in range(n):
        cfg, _, rec = _recording(tmp_path, seed, [{"kind": "boresight_rotation", "params": {"roll_arcsec": 30.0}}])
        ref = diagnose_recording(rec, cfg, None, opts)[0]["attitude_reference"]
        roll = {m["name"]: m["params"] for m in ref["model"]}["boresight_rotation"]["roll_arcsec"]
        pulls.append((roll["value"] - 30.0) / roll["sigma"])
        chi2, dof = chi2 + ref["chi2_after"], dof + ref["dof_after"]
        _, _, null = _recording(tmp_path, seed, [])
        false += bool(diagnose_recording(null, cfg, None, opts)[0]["attitude_reference"]["model"])
    pulls = np.array(pulls)
    print(f"pulls: mean {pulls.mean():.3f} std {pulls.std(ddof=1):.3f}; chi2 {chi2:.1f} over {dof}; "
          f"false {false} of {n}")
    assert abs(pulls.mean()) < 3.0 / np.sqrt(n), pulls
    assert 0.7 < pulls.std(ddof=1) < 1.35, pulls
    assert abs(chi2 - dof) < 4.0 * np.sqrt(2.0 * dof), (chi2, dof)
    assert false <= 2, false


def test_the_reference_test_is_the_joint_fit_with_the_reference_as_a_prior():
    """The identity behind :mod:`.reference`: for an effect the stars see only through the
    attitude (image columns ``J = A_k a_k``), the joint least squares of the stars and a prior
    ``u_k ~ N(m_k, sigma^2 I)`` on every frame's attitude gives the same effect estimate and
    covariance as the weighted fit of ``a_k theta`` to ``e_k = s_k - m_k`` (``s_k``: the stars'
    own attitude fit, covariance ``C_k``) with covariance ``C_k + sigma^2 I``."""
    from rollingstar.estimators.diagnosis.gyro_channel import absorbed_rotations, attitude_covariances
    from rollingstar.estimators.diagnosis.reference import weighted_fit

    rng = np.random.default_rng(4)
    n_frames, p, sigma = 6, 2, 0.3
    frame = np.repeat(np.arange(n_frames), rng.integers(3, 9, n_frames))
    att = rng.normal(size=(frame.size, 2, 3))
    a_true = rng.normal(size=(n_frames, 3, p))
    cols = np.einsum("nij,njp->nip", att, a_true[frame])
    u, theta = rng.normal(size=(n_frames, 3)), np.array([0.7, -1.3])
    y = np.einsum("nij,nj->ni", att, u[frame]) + cols @ theta + rng.normal(size=(frame.size, 2))
    m = u + sigma * rng.normal(size=(n_frames, 3))

    # the joint least squares over (u_1 .. u_F, theta): star rows, then the prior's rows
    x = np.zeros((2 * frame.size + 3 * n_frames, 3 * n_frames + p))
    for i, k in enumerate(frame):
        x[2 * i:2 * i + 2, 3 * k:3 * k + 3] = att[i]
        x[2 * i:2 * i + 2, 3 * n_frames:] = cols[i]
    x[2 * frame.size:, :3 * n_frames] = np.eye(3 * n_frames) / sigma
    rhs = np.concatenate([y.ravel(), m.ravel() / sigma])
    joint = np.linalg.lstsq(x, rhs, rcond=None)[0][3 * n_frames:]
    joint_cov = np.linalg.inv(x.T @ x)[3 * n_frames:, 3 * n_frames:]

    c = attitude_covariances(frame, n_frames, att, np.ones(frame.size), np.ones(frame.size, bool))
    s = np.stack([np.linalg.lstsq(att[frame == k].reshape(-1, 3), y[frame == k].ravel(), rcond=None)[0]
                  for k in range(n_frames)])
    a = absorbed_rotations(frame, n_frames, att, cols)
    np.testing.assert_allclose(a, a_true, atol=1e-10)
    w = np.linalg.inv(c + sigma**2 * np.eye(3))
    estimate, cov, _, rank = weighted_fit(a, w, s - m)
    assert rank == p
    np.testing.assert_allclose(estimate, joint, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cov, joint_cov, rtol=1e-9, atol=1e-12)


def test_the_mount_is_the_joint_fit_with_a_constant_rotation():
    """The reference's misalignment and its sigma are those of the dense joint fit of a constant
    rotation and the chosen effect (here one partly collinear with a constant rotation), and the
    effect's estimate and covariance from the projected problem are the joint fit's too."""
    from rollingstar.estimators.diagnosis.reference import _mount, _without_mount, weighted_fit

    rng = np.random.default_rng(8)
    n_frames = 12
    w = np.stack([(lambda q: q @ q.T + 0.1 * np.eye(3))(rng.normal(size=(3, 3))) for _ in range(n_frames)])
    a = rng.normal(size=(n_frames, 3, 1)) + np.array([2.0, 0.0, 0.0])[None, :, None]  # partly a constant rotation
    m = np.array([20.0, -15.0, 10.0]) * ARCSEC_TO_RAD
    e = -m + (a @ np.array([3e-5]))[..., None].reshape(n_frames, 3) + 1e-6 * rng.normal(size=(n_frames, 3))
    design = np.concatenate([np.broadcast_to(np.eye(3), (n_frames, 3, 3)), a], axis=2)
    joint, joint_cov, _, _ = weighted_fit(design, w, e)
    mount = _mount(e, {"x": a}, w, ["x"])
    np.testing.assert_allclose(np.array(mount["rotation_arcsec"]) * ARCSEC_TO_RAD, -joint[:3], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(np.array(mount["sigma_arcsec"]) * ARCSEC_TO_RAD, np.sqrt(np.diag(joint_cov)[:3]), rtol=1e-9)
    projected, projected_cov, _, _ = weighted_fit(_without_mount(a, w), w, _without_mount(e, w))
    np.testing.assert_allclose(projected, joint[3:], rtol=1e-9)
    np.testing.assert_allclose(projected_cov, joint_cov[3:, 3:], rtol=1e-9)
    # the marginal sigma is not the one of the constant rotation alone: about x, the axis the effect shares
    alone = np.sqrt(np.diag(np.linalg.inv(w.sum(axis=0))))
    assert alone[0] < 0.8 * np.sqrt(joint_cov[0, 0]), (alone, np.sqrt(np.diag(joint_cov)))
