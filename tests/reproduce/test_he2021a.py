"""Quick he2021a reproduction (``rollingstar reproduce he2021a --quick``) against the paper's bounds.

Bounds we do not reproduce are strict xfails with the reason (docs/reproductions/he2021a.md):
they turn into failures (XPASS) as soon as they are met, so they cannot silently stay loose.
"""
from __future__ import annotations

import pytest

from pipelines.reproduce import paper_values, run_reproduction


@pytest.fixture(scope="module")
def rows():
    return run_reproduction("he2021a", quick=True, seed=1)


def _get(rows, quantity, condition_start):
    hits = [r for r in rows if r.quantity == quantity and r.condition.startswith(condition_start)]
    assert len(hits) == 1, (quantity, condition_start, [r.condition for r in rows if r.quantity == quantity])
    assert hits[0].ours is not None, (quantity, condition_start)
    return hits[0].ours


def test_rows_are_complete(rows):
    paper = paper_values("he2021a")
    assert {r.source for r in rows if r.paper is not None} <= {v["source"] for v in paper.values()}
    assert all(r.trials and r.seed == 1 for r in rows if r.quantity != "run time")
    assert _get(rows, "run time", "quick") < 30


@pytest.mark.parametrize("axis", ["x", "y"])
def test_correction_removes_most_rolling_shutter_pair_error(rows, axis):
    before = _get(rows, "pair distance error before, systematic (RMS)", f"3 deg/s about {axis}")
    after = _get(rows, "pair distance error after, systematic (RMS)", f"3 deg/s about {axis}")
    assert before > 1.0  # the rolling-shutter distortion is there (Fig 12: linear in rate)
    assert after < before / 3  # quick run: 4.6 -> 0.65 (x), 2.4 -> 0.62 (y)


def test_static_pair_distance_below_paper_bound(rows):
    # 0 deg/s, R = 0.05: systematic 0.048 px in the quick run (per frame 0.095)
    assert _get(rows, "pair distance error after, systematic (RMS)", "0 deg/s about x") < 0.1


def test_static_attitude_cross_boresight_within_10_arcsec(rows):
    for ax in "xy":
        assert _get(rows, f"attitude error {ax} after (RMS, 5 stars)", "0 deg/s about x") < 10.0


def test_smear_error_before_exceeds_0p1_at_3deg_s(rows):
    assert _get(rows, "smear centroid error before (RMS radial)", "3 deg/s about x") > 0.1


@pytest.mark.xfail(strict=True, reason="real-sky stars cross the 10 deg FOV in <= 37 frames at 3 deg/s and the "
                   "pinhole image acceleration is not in the CV model with Q=1e-4 (docs/reproductions/he2021a.md)")
@pytest.mark.parametrize("axis", ["x", "y"])
def test_paper_pair_distance_after_below_0p1_at_3deg_s(rows, axis):
    assert _get(rows, "pair distance error after, systematic (RMS)", f"3 deg/s about {axis}") < 0.1


@pytest.mark.xfail(strict=True, reason="image acceleration (~0.3 px/s^2 at 1 deg/s) vs Q = 1e-4 px^2/s^4: lag bias "
                   "(docs/reproductions/he2021a.md)")
def test_paper_filter_bounds_after_50_frames(rows):
    for ax in "xy":
        assert _get(rows, f"filtered position error {ax} (RMS)", "1 deg/s about x") < 0.1
        assert _get(rows, f"filtered velocity deviation v{ax} (RMS)", "1 deg/s about x") < 0.02


@pytest.mark.xfail(strict=True, reason="short tracks and filter lag at 3 deg/s (docs/reproductions/he2021a.md)")
def test_paper_smear_after_below_0p06(rows):
    assert _get(rows, "smear centroid error after eqs 12-16 (RMS radial)", "3 deg/s about x") < 0.06


@pytest.mark.xfail(strict=True, reason="5-star roll (z) error is noise-limited above 10 arcsec with R = 0.05 px^2; "
                   "x about 11 arcsec at 3 deg/s about x (docs/reproductions/he2021a.md)")
def test_paper_attitude_within_10_arcsec_at_3deg_s(rows):
    for axis in "xy":
        for ax in "xyz":
            assert _get(rows, f"attitude error {ax} after (RMS, 5 stars)", f"3 deg/s about {axis}") < 10.0
