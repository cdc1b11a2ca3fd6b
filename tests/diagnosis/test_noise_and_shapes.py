"""What the library cannot name: a recording whose noise is not the stated one gets a measured
noise factor (never a physical effect), and a systematic outside the library gets a described
shape (where, which axis, how big) written to the updated scenario as an empirical correction
that closes the fit.

Recordings: the discrepancy benchmark's base sensor (he2021b optics, 1024 x 1024, 0.05 px), its
nuisance rewrites (centroids rebuilt from the noise-free truth with another noise) and its
out-of-library perturbations (a stitched detector, a column ripple), which the library does not hold.
"""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.config import validate
from rollingstar.estimators.diagnosis.library import library, separating_experiment
from rollingstar.pipelines.diagnose import DiagnoseOptions, diagnose_recording
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.scenario import ScenarioConfig
from rollingstar.studies.bench import discrepancy as D

OPTIONS = DiagnoseOptions(n_boot=10, stability=False, resimulate=False, seed=1)
OOL_NAMES = [c.name for c in D.OUT_OF_LIBRARY]


def _design(design: str, seed: int, frames: int = 20) -> ScenarioConfig:
    return D.design_scenario(D.base_scenario(frames), design, 20.0, np.random.default_rng(seed), frames, seed)


def _nuisance(tmp_path, nuisance: str, design: str = "single_axis", seed: int = 5):
    cfg = _design(design, seed, frames=30)
    rec = tmp_path / f"{nuisance}-{design}-{seed}.mcap"
    D.nuisance_recording(cfg, nuisance, rec, np.random.default_rng(seed))
    return diagnose_recording(rec, cfg, None, OPTIONS)


def _with_effect(tmp_path, design: str, kind: str, params: dict, seed: int = 5):
    cfg = _design(design, seed)
    rec = tmp_path / f"{kind}-{design}-{seed}.mcap"
    # the benchmark-only effects are registered while the recording is made and run (its metadata
    # names them); the diagnosis excludes them and is given the base scenario only
    with D.registered(D.OUT_OF_LIBRARY):
        truth = validate(ScenarioConfig, {**cfg.model_dump(mode="json"), "effects": [{"kind": kind, "params": params}]}, "<t>")
        simulate_to_log(truth, rec, show_progress=False)
        return cfg, rec, diagnose_recording(rec, cfg, None, OPTIONS, exclude_effects=OOL_NAMES)


# ------------------------------------------------------------------------------------ noise
@pytest.mark.parametrize("nuisance,factor", [("noise_1.5x", 1.5), ("noise_0.67x", 1 / 1.5)])
def test_a_wrong_noise_level_is_a_measured_factor_not_physics(tmp_path, nuisance, factor):
    result, d = _nuisance(tmp_path, nuisance)
    check = result["noise_check"]
    assert result["effects"] == [], result["summary"]
    assert check["applied"] and abs(check["factor"] - factor) < 4 * check["factor_sigma"], check
    assert not result["unexplained_systematic"]["present"], result["summary"]
    assert "centroid noise is" in result["summary"]
    updated = d.updated_scenario().noise.centroid_sigma_px
    assert updated == pytest.approx(0.05 * check["factor"])


@pytest.mark.parametrize("design,seed", [("inertial_hold", 3), ("single_axis", 4), ("multi_axis", 6), ("rate_reversal", 7)])
def test_the_stated_noise_is_kept_when_it_is_right(tmp_path, design, seed):
    cfg = _design(design, seed)
    rec = tmp_path / "null.mcap"
    simulate_to_log(cfg, rec, show_progress=False)
    result, _ = diagnose_recording(rec, cfg, None, OPTIONS)
    check = result["noise_check"]
    assert not check["applied"] and abs(np.log(check["factor"])) < 4 * check["factor_sigma"] / check["factor"], check
    assert not result["mismatch"], result["summary"]


def test_smooth_physics_does_not_look_like_noise(tmp_path):
    """A strong rolling-shutter error moves each star alike in consecutive frames: the factor
    (measured on the named model's residuals) stays 1 and the effect is named."""
    _, _, (result, _) = _with_effect(tmp_path, "single_axis", "rolling_shutter", {"line_delay_error_us": 8.0})
    assert [e["name"] for e in result["effects"]] == ["rolling_shutter"], result["summary"]
    assert not result["noise_check"]["applied"], result["noise_check"]


# --------------------------------------------------------------------------- out of the library
def test_a_stitched_detector_is_described_as_a_step_and_corrected(tmp_path):
    cfg, rec, (result, d) = _with_effect(tmp_path, "single_axis", "bench_stitch_step", {"dy": 0.3})
    desc = result["unexplained_systematic"]["description"]
    assert desc is not None, result["summary"]
    print("described:", desc["text"])  # pytest -s: the example in docs/diagnosis.md
    assert (desc["shape"], desc["axis"], desc["coordinate"]) == ("step", "y", "column"), desc["text"]
    lo, hi = desc["between_px"]
    assert lo <= 511.5 <= hi  # the dies meet at the principal point's column
    assert abs(desc["coefficients_px"][0] - 0.3) < 4 * desc["sigmas_px"][0], desc
    assert desc["heldout_chi2_after"] < desc["heldout_chi2_before"]
    assert "steps by" in result["summary"]
    # with the correction in the model no library effect is needed (none was injected)
    assert result["effects"] == [], result["summary"]
    assert result["heldout_rms_after_px"] < result["heldout_rms_before_px"]
    updated = d.updated_scenario()
    assert "empirical_step" in [e.kind for e in updated.effects]
    # the user's simulation, updated, explains the recording: no systematic left
    with D.registered(D.OUT_OF_LIBRARY):
        again, _ = diagnose_recording(rec, updated, None, OPTIONS, exclude_effects=OOL_NAMES)
    assert not again["unexplained_systematic"]["present"], again["summary"]


def test_a_large_step_is_sized_through_the_correction_rounds(tmp_path):
    """A 1.4 px stitch in a rate-reversal design: the first linear estimate of the step is biased by
    the rates the attitudes imply; the correction rounds add what the corrected model still leaves,
    and the physics named again is none."""
    _, _, (result, _) = _with_effect(tmp_path, "rate_reversal", "bench_stitch_step", {"dy": 1.4})
    desc = result["unexplained_systematic"]["description"]
    assert (desc["shape"], desc["axis"], desc["coordinate"]) == ("step", "y", "column"), desc["text"]
    assert abs(desc["correction"]["params"]["size_px"] - 1.4) < 0.03, desc["correction"]
    assert result["effects"] == [], result["summary"]


def test_a_column_ripple_is_described_with_its_period_and_axis(tmp_path):
    _, _, (result, d) = _with_effect(tmp_path, "multi_axis", "bench_column_ripple", {"amplitude": 0.1})
    desc = result["unexplained_systematic"]["description"]
    assert desc is not None, result["summary"]
    print("described:", desc["text"])  # pytest -s: the example in docs/diagnosis.md
    assert (desc["shape"], desc["axis"], desc["coordinate"]) == ("ripple", "x", "row"), desc["text"]
    assert desc["period_px"] == pytest.approx(150.0, rel=0.1)
    amplitude = float(np.hypot(*desc["coefficients_px"]))
    assert amplitude == pytest.approx(0.1, rel=0.25)
    assert "ripple of period" in result["summary"]
    assert "empirical_ripple" in [e.kind for e in d.updated_scenario().effects]


def test_empirical_shapes_are_never_candidates():
    names = set(library())
    assert "empirical_step" not in names and "empirical_ripple" not in names


# ------------------------------------------------------------------------------------ verdict
def test_the_summary_leads_with_what_differs_how_big_and_held_out(tmp_path):
    _, _, (result, _) = _with_effect(tmp_path, "single_axis", "radial_distortion", {"k1": 0.02})
    text = result["summary"]
    assert text.startswith("What differs: radial_distortion (k1 = "), text
    assert "held-out stars" in text and "->" in text


def test_separating_experiments_are_specific_to_the_pair():
    lib = library()
    text = separating_experiment(lib["stellar_aberration"], lib["magnitude_bias"])
    assert lib["stellar_aberration"].follows in text and lib["magnitude_bias"].follows in text
    generic = separating_experiment(lib["catalog_epoch"], lib["refraction"])
    assert "vary the motion" not in generic
    for c in lib.values():  # every physical effect states what its displacement follows
        assert c.follows and c.shown_by, c.name


def test_too_few_stars_to_train_on_is_said_as_such(tmp_path):
    """A single frame of ten stars leaves too few training stars after the held-out split: the
    message says so (not that the sensor model is far off)."""
    from rollingstar.errors import UserError

    cfg = _design("inertial_hold", 3, frames=1)
    rec = tmp_path / "one.mcap"
    simulate_to_log(cfg, rec, show_progress=False)
    with pytest.raises(UserError, match="left for training"):
        diagnose_recording(rec, cfg, None, OPTIONS)


@pytest.mark.parametrize("with_cov", [False, True])
def test_the_period_search_projects_single_axis_columns_as_the_general_projection(with_cov):
    """The period search's sparse projection (``describe._SingleAxisRows``) gives the rows of the
    general one (``_Projector.rows`` of the whitened single-axis columns): several frames, one of
    them with a single star (no attitude fit), 2 x 2 star covariances, named effects free."""
    from dataclasses import replace

    from rollingstar.estimators.diagnosis import describe as S
    from rollingstar.estimators.diagnosis.observations import predict
    from tests.diagnosis.synthetic import synthetic

    obs, truth, camera, timing = synthetic(frames=5, stars=12, seed=3)
    keep = ~((obs.frame == 2) & (np.arange(obs.n) % 12 > 0))  # frame 2 keeps one star
    obs = replace(obs, **{k: getattr(obs, k)[keep] for k in ("frame", "x", "y", "sigma", "t_ns", "u_icrs", "magnitude",
                                                             "catalog_id", "flux")})
    rng = np.random.default_rng(8)
    if with_cov:
        a = rng.normal(0, 0.05, (obs.n, 2, 2))
        obs = replace(obs, cov=a @ a.transpose(0, 2, 1) + 0.01 * np.eye(2))
    pred = predict(obs, truth, camera, timing)
    train = rng.uniform(size=obs.n) < 0.7
    named = rng.normal(size=(2 * int(train.sum()), 2))
    proj = S._Projector(obs, pred, named)
    values = S._wave(obs.y, np.array([37.0, 150.0, 600.0]))
    for axis in (0, 1):
        general = proj.rows(S.whiten(obs, S._single_axis(values, axis)), train)
        fast = S._SingleAxisRows(proj, axis, train).rows(values)
        np.testing.assert_allclose(fast, general, rtol=0, atol=1e-12 * np.abs(general).max())
        assert np.abs(general).max() > 0.1  # the columns are not projected away
