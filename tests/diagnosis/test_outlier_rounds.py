"""Model-aware outliers: the stars the model as given misses by more than the gate come back once
the diagnosis has named the physics that moved them, and real misidentifications stay out."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.scenario import load_scenario
from tests.diagnosis.test_diagnose import BASE  # he2021b's optics, 12 frames at 0.5 deg/s, 0.05 px noise

K1 = 0.3  # moves corner stars by ~6 px: far beyond the 30-sigma gate of the model as given


@pytest.fixture(scope="module")
def strong_distortion(tmp_path_factory):
    from rollingstar.pipelines.diagnose import build_observations, identify_stars
    from rollingstar.sensors import build

    d = tmp_path_factory.mktemp("outliers")
    base, truth, rec = d / "base.yaml", d / "truth.yaml", d / "truth.mcap"
    base.write_text(BASE)
    truth.write_text(BASE + f"effects: [{{kind: radial_distortion, params: {{k1: {K1}}}}}]\n")
    simulate_to_log(load_scenario(truth), rec, show_progress=False)
    scenario = load_scenario(base)
    _, stars, att = identify_stars(rec, None, "<test>", False)
    obs, att0 = build_observations(stars, att, scenario, build.build_catalog(scenario, build.build_camera(scenario)))
    return scenario, obs, att0


def _diagnose(scenario, obs, att0):
    from rollingstar.estimators.diagnosis.algorithm import diagnose
    from rollingstar.pipelines.diagnose import DiagnoseOptions

    return diagnose(obs, att0, scenario, None, DiagnoseOptions(n_boot=5, stability=False, resimulate=False))


def test_stars_the_named_distortion_explains_come_back(strong_distortion):
    from rollingstar.estimators.diagnosis.inputs import sensor_model
    from rollingstar.estimators.diagnosis.locating import gross_outliers

    scenario, obs, att0 = strong_distortion
    as_given = gross_outliers(obs, att0, sensor_model(scenario), np.ones(obs.n, dtype=bool)).mean()
    d = _diagnose(*strong_distortion)
    rounds = d.outlier_rounds
    print(f"beyond the gate of the model as given: {as_given:.3f}; outlier rounds:",
          [(r["gate"], r["rejected"], round(r["fraction"], 3)) for r in rounds])  # pytest -s
    assert as_given > 0.1  # the model as given would drop the outer stars, which carry the signature
    assert rounds[0]["gate"] == ["lens fit"] and rounds[0]["rejected"] == 0  # so the lens is fitted first
    assert d.projection is not None and not d.projection.searched and not d.projection.restated
    assert rounds[-1]["rejected"] == 0
    assert [c.name for c in d.verification.named] == ["radial_distortion"]
    k1, sigma = d.model.thetas[0][0], d.model.fit["sigmas"][0][0]
    assert abs(k1 - K1) < 4 * sigma, (k1, sigma)
    assert d.verification.quality.heldout_rms_px.after < 1.2 * 0.05
    assert d.noise is not None and not d.noise.applied, d.noise  # the modelled distortion is not taken for noise


def test_misidentified_stars_stay_out(strong_distortion):
    """Three stars given another star's catalogue direction (a wrong identification, degrees off):
    no model explains them, so every round keeps them out and the distortion is still recovered."""
    from dataclasses import replace

    scenario, obs, att0 = strong_distortion
    rng = np.random.default_rng(0)
    wrong = rng.choice(obs.n, 3, replace=False)
    u = obs.u_icrs.copy()
    for i in wrong:  # the direction of another catalogue star at least 0.5 deg away
        far = np.flatnonzero(obs.u_icrs @ obs.u_icrs[i] < np.cos(np.radians(0.5)))
        u[i] = obs.u_icrs[rng.choice(far)]
    d = _diagnose(scenario, replace(obs, u_icrs=u), att0)
    assert d.outlier_rounds[-1]["rejected"] == 3
    assert [c.name for c in d.verification.named] == ["radial_distortion"]
    k1, sigma = d.model.thetas[0][0], d.model.fit["sigmas"][0][0]
    assert abs(k1 - K1) < 4 * sigma, (k1, sigma)


def test_a_round_naming_its_gates_effects_in_another_order_is_the_fixed_point(monkeypatch):
    """The rounds stop when a round names the effects its gate held, whatever order the naming
    lists them in (a set of effects, not a sequence)."""
    from types import SimpleNamespace

    from rollingstar.estimators.diagnosis import algorithm

    namings = iter([["a", "b"], ["b", "a"], ["c"]])  # the third would run only if the order counted
    stars = iter(range(10))

    def locate(observations, attitudes, sensor, cands, gyro, options, gate):
        k = next(stars)  # every round keeps other stars, so only the names can end the rounds
        return SimpleNamespace(data=SimpleNamespace(n_rejected=1, obs=SimpleNamespace(n=5, x=np.full(5, k), y=np.zeros(5),
                                                                                       heldout=np.zeros(5, bool))))

    def verify(location, naming, model, sensor, cands, options):
        return SimpleNamespace(named=[SimpleNamespace(name=n) for n in naming], thetas=[])

    monkeypatch.setattr(algorithm, "locate", locate)
    monkeypatch.setattr(algorithm, "name_effects", lambda location, sensor, cands, options: next(namings))
    monkeypatch.setattr(algorithm, "model_effects", lambda data, naming, sensor, options: None)
    monkeypatch.setattr(algorithm, "verify", verify)
    monkeypatch.setattr(algorithm, "updated_scenario", lambda scenario, named, thetas: scenario)
    monkeypatch.setattr(algorithm, "sensor_model", lambda scenario, moving: SimpleNamespace(scenario=scenario, moving=moving))
    sensor = SimpleNamespace(scenario=None, moving=False, camera=None)
    *_, verification, rounds = algorithm._outlier_rounds(SimpleNamespace(n=5), None, sensor, {}, None, None)
    assert [c.name for c in verification.named] == ["b", "a"]
    assert [r["gate"] for r in rounds] == [[], ["a", "b"]]


def test_the_reported_model_carries_its_stability_rows(strong_distortion):
    """The stability refits run once, for the model reported: its rows are those of the final
    model's own subsets, and every named effect's ``stable`` flag is read from them."""
    from dataclasses import replace

    from rollingstar.estimators.diagnosis.algorithm import diagnose
    from rollingstar.estimators.diagnosis.modelling import with_stability
    from rollingstar.pipelines.diagnose import DiagnoseOptions

    scenario, obs, att0 = strong_distortion
    d = diagnose(obs, att0, scenario, None, DiagnoseOptions(n_boot=5, stability=True, resimulate=False))
    rows = d.model.stability
    assert rows and {r["effect"] for r in rows} == {c.name for c in d.model.chosen}
    again = with_stability(d.location.data, replace(d.model, stability=[]), d.sensor).stability
    assert again == rows
    for e in d.verification.effects:
        assert e["stable"] == all(r["stable"] is not False for r in rows if r["effect"] == e["name"])
