"""Quick he2021a reproduction (``rollingstar reproduce he2021a --quick``, seed 1) against the paper's bounds.

Two motion modes (docs/reproductions/he2021a.md): ``drift`` is the paper's own eq (19) assumption
(uniform image velocity), ``sky`` a rigid rotation over the real sky. Bounds met are asserted; the
ones we do not reproduce are strict xfails whose reason gives the measured number, so they fail
loudly (XPASS) once met. Numbers in comments are the quick run's; margins are from the full run's
per-trial spread (the doc's table, "per trial" notes).
"""
from __future__ import annotations

import pytest

from rollingstar.studies.reproduce import paper_values, run_reproduction

pytestmark = pytest.mark.slow  # whole reproductions, benchmarks or killed processes: `-m 'not slow'` skips them


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
    for mode in ("drift", "sky"):  # every experiment in both modes
        assert any(r.condition.startswith(f"{mode}: ") and r.quantity.startswith("filtered") for r in rows)
        assert any(r.condition.startswith(f"{mode}: ") and r.quantity.startswith("smear") for r in rows)
        assert any(r.condition.startswith(f"{mode}: ") and r.quantity.startswith("pair") for r in rows)
        assert any(r.condition.startswith(f"{mode}: ") and r.quantity.startswith("attitude") for r in rows)


# ------------------------------------------------------------------ paper assumption (eq 19): bounds reached
def test_drift_filter_bounds_after_50_frames(rows):
    # Figs 6-7: quick 0.053 / 0.052 px and 0.018 / 0.016 px/s. For q -> 0 the filter is the
    # least-squares line fit, whose end-point errors for 50-99 frames of 0.224 px noise are
    # 0.062-0.044 px and 0.024-0.009 px/s: the paper's bounds are this floor.
    for ax in "xy":
        assert _get(rows, f"filtered position error {ax} (RMS)", "drift: 1 deg/s about x") < 0.1
        assert _get(rows, f"filtered velocity deviation v{ax} (RMS)", "drift: 1 deg/s about x") < 0.02


def test_drift_smear_after_below_0p06(rows):
    # Fig 10: quick 0.041 px at 3 deg/s (full run 0.04-0.05 at 0-3 deg/s)
    assert _get(rows, "smear centroid error after eqs 12-16 (RMS radial)", "drift: 3 deg/s about x") < 0.06


def test_drift_attitude_cross_boresight_within_10_arcsec(rows):
    # Figs 14-15: quick 1.6-2.1 arcsec at 3 deg/s about x and y
    for axis in "xy":
        for ax in "xy":
            assert _get(rows, f"attitude error {ax} after (RMS, 5 stars)", f"drift: 3 deg/s about {axis}") < 10.0


# Full run, drift, 3 deg/s, R = 0.05: 0.100 (x) / 0.103 (y) px, per-trial ranges 0.096-0.105 and 0.093-0.110
# over 4 trials, i.e. a per-trial standard deviation of about 0.007 px (range / 2.06): the paper's bound
# is met within our Monte Carlo spread, no better. The quick run is one trial per axis.
PAIR_TRIAL_SIGMA = 0.007


@pytest.mark.parametrize("axis", ["x", "y"])
def test_drift_pair_distance_after_at_the_0p1_bound_at_3deg_s(rows, axis):
    after = _get(rows, "pair distance error after, systematic (RMS)", f"drift: 3 deg/s about {axis}")
    assert after < 0.1 + 2 * PAIR_TRIAL_SIGMA  # quick 0.100 (x), 0.098 (y)


@pytest.mark.parametrize("mode", ["drift", "sky"])
@pytest.mark.parametrize("axis", ["x", "y"])
def test_correction_removes_the_rolling_shutter_pair_error(rows, mode, axis):
    before = _get(rows, "pair distance error before, systematic (RMS)", f"{mode}: 3 deg/s about {axis}")
    after = _get(rows, "pair distance error after, systematic (RMS)", f"{mode}: 3 deg/s about {axis}")
    assert before > 2.0  # Fig 12: the distortion is there, linear in rate (quick 4.6 about x, 2.4 about y)
    # drift: removed down to the noise floor (quick 4.6 -> 0.10, 2.4 -> 0.098); sky: the filter's lag
    # on the accelerating stars remains (4.6 -> 0.65, 2.4 -> 0.61)
    assert after < before / (20 if mode == "drift" else 3)


def test_static_pair_distance_and_attitude(rows):
    # 0 deg/s, R = 0.05: pair 0.046 px (systematic); cross-boresight 1.2 / 0.9 arcsec (quick)
    assert _get(rows, "pair distance error after, systematic (RMS)", "sky: 0 deg/s about x") < 0.1
    for ax in "xy":
        assert _get(rows, f"attitude error {ax} after (RMS, 5 stars)", "sky: 0 deg/s about x") < 10.0


# ------------------------------------------------------------------ not reproduced (strict xfail, measured number)
@pytest.mark.xfail(strict=True, reason="real sky: pinhole image acceleration is outside the CV model; quick "
                   "0.29/0.34 px and 0.25/0.32 px/s with q=1e-4, and no q in 1e-4..10 px^2/s^4 gets the velocity "
                   "below 0.1 px/s (Q sweep, docs/reproductions/he2021a.md)")
def test_sky_filter_bounds_after_50_frames(rows):
    for ax in "xy":
        assert _get(rows, f"filtered position error {ax} (RMS)", "sky: 1 deg/s about x") < 0.1
        assert _get(rows, f"filtered velocity deviation v{ax} (RMS)", "sky: 1 deg/s about x") < 0.02


@pytest.mark.xfail(strict=True, reason="real sky: filter lag on accelerating stars, quick 0.65 (x) / 0.61 (y) px "
                   "at 3 deg/s (docs/reproductions/he2021a.md)")
@pytest.mark.parametrize("axis", ["x", "y"])
def test_sky_pair_distance_after_below_0p1_at_3deg_s(rows, axis):
    assert _get(rows, "pair distance error after, systematic (RMS)", f"sky: 3 deg/s about {axis}") < 0.1


@pytest.mark.xfail(strict=True, reason="real sky: filter lag, quick 0.19 px at 3 deg/s (docs/reproductions/he2021a.md)")
def test_sky_smear_after_below_0p06(rows):
    assert _get(rows, "smear centroid error after eqs 12-16 (RMS radial)", "sky: 3 deg/s about x") < 0.06


@pytest.mark.xfail(strict=True, reason="our CoG of a smeared rolling-shutter spot is unbiased about the time it claims: "
                   "quick 0.052 (drift) / 0.053 (sky) px at 3 deg/s, noise only; the paper's reference for 'before' "
                   "is not stated (docs/reproductions/he2021a.md)")
@pytest.mark.parametrize("mode", ["drift", "sky"])
def test_smear_before_exceeds_0p1_at_3deg_s(rows, mode):
    assert _get(rows, "smear centroid error before (RMS radial)", f"{mode}: 3 deg/s about x") > 0.1


@pytest.mark.xfail(strict=True, reason="roll (z) with five stars is noise-limited at R = 0.05 px^2: quick 13.7/20.7 "
                   "arcsec (drift) and 28/53 (sky) at 3 deg/s, 9.1 at rest (docs/reproductions/he2021a.md)")
@pytest.mark.parametrize("mode", ["drift", "sky"])
def test_roll_within_10_arcsec_at_3deg_s(rows, mode):
    for axis in "xy":
        assert _get(rows, "attitude error z after (RMS, 5 stars)", f"{mode}: 3 deg/s about {axis}") < 10.0
