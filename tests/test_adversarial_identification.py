"""No false identification reported valid: every shipped identifier configuration on frames built
to fool it (studies/adversarial.py): a prior from an unrelated part of the sky, a prior a few gates
off, shuffled and mirrored star fields, random points, true stars plus false spots."""
from __future__ import annotations

import pytest

from rollingstar.studies.adversarial import CASES, run_adversarial

pytestmark = pytest.mark.long_study  # 950 adversarial frames through every identifier: `make test-long`


@pytest.fixture(scope="module")
def result():
    return run_adversarial(frames_per_case=14, seed=7)  # 58 configuration x case runs: 812 frames


def test_no_valid_attitude_is_wrong(result):
    assert result["frames"] >= 14 * 7 * result["configurations"]  # every case (7 or more) on every configuration
    assert result["configurations"] >= 5  # every identifier stage shipped in configs/ and diagnose
    wrong = [r for r in result["rows"] if r["wrong"]]
    assert result["wrong_valid"] == 0, wrong


def test_every_case_ran_on_every_configuration(result):
    seen = {(r["config"], r["case"].split(" ")[0]) for r in result["rows"]}
    configs = {r["config"] for r in result["rows"]}
    assert seen == {(c, case) for c in configs for case in CASES}


def test_the_identifiers_still_identify(result):
    """The check does not buy its zero by rejecting everything: the true field is identified."""
    for r in result["rows"]:
        if r["case"] in ("control", "stars_plus_false_spots"):
            assert r["valid"] >= 0.9 * r["frames"], r


def test_a_wrong_prior_is_refused_by_trackers_and_recovered_by_lost_in_space(result):
    for r in result["rows"]:
        if r["case"] in ("unrelated_prior", "prior_few_gates_off"):
            if r["identifier"] == "tracking":
                assert r["valid"] == 0, r
            else:
                assert r["valid"] >= 0.9 * r["frames"], r


def test_rejections_are_named(result):
    assert result["flags"].get("identification_rejected:false_match_probability", 0) > 0
    assert result["flags"].get("lost_in_space_rejected:mirrored_image", 0) > 0
