"""The quick he2021b reproduction (``rollingstar reproduce he2021b --quick``) and its bounds.

Margins: the quick run pools 3 trials x 60 frames (seed 1); the relative standard error of a
pooled per-axis RMSE is about 1/sqrt(2 * 180) = 5 %, so the +-25 % CRB bands are ~5 sigma. The
orderings compare configurations run on the same noise realisations (paired), whose differences
are far larger than their trial-to-trial spread (see the rows' notes).
"""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.studies.reproduce import he2021b

pytestmark = [pytest.mark.slow, pytest.mark.long_study]  # a whole reproduction: `make test-long` runs it


@pytest.fixture(scope="module")
def quick():
    rows = he2021b.run(quick=True, plots_dir=None, seed=1)
    return {(r.quantity, r.condition): r for r in rows}, None


def _get(rows, quantity, cond_contains=""):
    found = [r for (q, c), r in rows.items() if q == quantity and cond_contains in c]
    assert len(found) == 1, (quantity, cond_contains, found)
    return found[0]


def _fig11(rows, axis, rate, source, explained=False):
    """A per-5 Fig 11 row: the forgetting-1 sweep (exact condition) or the explained-reading sweep."""
    found = [r for (q, c), r in rows.items() if q == f"fig11_rmse_{axis}_per5" and c.startswith(f"{rate} deg/s, {source}")
             and ("explained" in c) == explained]
    assert len(found) == 1, (axis, rate, source, explained, found)
    return found[0].ours


def test_run_time_row_is_measured(quick):
    # The row reports the CPU time the reproduction took (its size is judged by `rollingstar
    # reproduce`, never asserted here: the machine is shared).
    row = _get(quick[0], "run time")
    assert row.ours > 0 and row.unit == "s (CPU)"


def test_updates_per_frame_and_rate(quick):
    rows, _ = quick
    for g, n in ((1, 15), (3, 5), (5, 3)):
        r = _get(rows, f"updates_per_frame_per{g}")
        # per-1: the first update of each run (one star) is invalid, nothing else
        assert r.ours == pytest.approx(n - (1 / 60 if g == 1 else 0), abs=1e-9)
        assert r.trials == 3 and r.seed == 1
        hz = _get(rows, f"update_rate_per{g}").ours
        assert hz == pytest.approx(r.ours / 0.100176, rel=1e-6)
    for g, n in ((4, 2), (2, 4), (1, 8)):
        r = _get(rows, f"star1000_updates_per_frame_per{g}")
        assert r.ours == pytest.approx(n - (1 / 30 if g == 1 else 0), abs=1e-9)
        assert _get(rows, f"star1000_update_rate_per{g}").ours == pytest.approx(r.ours / 0.2000448, rel=1e-4)


@pytest.mark.parametrize("forgetting", ["forgetting 1 (eqs 30-31)", "forgetting 0.5"])
def test_rmse_ordering_more_stars_per_update_is_better(quick, forgetting):
    rows, _ = quick
    for ax in "xyz":
        r1, r3, r5 = (_get(rows, f"rmse_{ax}_per{g}", forgetting).ours for g in (1, 3, 5))
        if forgetting == "forgetting 0.5":
            assert r1 > 1.3 * r3 and r3 > 1.1 * r5, (ax, r1, r3, r5)  # full run: 1.7x and 1.3x
        else:
            # no forgetting: every past star is fused, per-3 and per-5 converge to the same accuracy
            # (full run: Z per-3 1.40 < per-5 1.43); only per-1 is clearly worse
            assert r1 > r3 and r1 > r5, (ax, r1, r3, r5)
    # Z (roll about the boresight) is the weak axis, as in the paper
    for g in (1, 3, 5):
        assert _get(rows, f"rmse_z_per{g}", forgetting).ours > 5 * _get(rows, f"rmse_x_per{g}", forgetting).ours


def test_global_quest_at_crb_and_fusion_beats_single_frame(quick):
    rows, _ = quick
    for ax in "xyz":
        crb = _get(rows, f"crb_{ax}").ours
        glob = _get(rows, f"global_rmse_{ax}").ours
        assert 0.8 < glob / crb < 1.25, (ax, glob, crb)
        # the paper's eqs 30-31 (no forgetting) with the true rate fuse every past star
        assert _get(rows, f"rmse_{ax}_per5", "forgetting 1 (eqs 30-31)").ours < 0.5 * crb
        # fading memory 0.5 per 5 stars keeps ~15 stars: close to the single-frame bound
        assert 0.7 < _get(rows, f"rmse_{ax}_per5", "forgetting 0.5").ours / crb < 1.5


def test_rate_dependence(quick):
    rows, _ = quick
    z0 = _fig11(rows, "z", "0.0", "true rate")
    z2 = _fig11(rows, "z", "0.2", "true rate")
    assert z2 == pytest.approx(z0, rel=0.1)  # with the true rate, correction + propagation remove the motion
    n0 = _fig11(rows, "z", "0.0", "zero rate")
    n2 = _fig11(rows, "z", "0.2", "zero rate")
    assert n0 == pytest.approx(z0, rel=1e-6) and n2 > 5 * n0  # without a rate the error grows with it


def test_fig11_xy_bound_with_the_true_rate(quick):
    # paper Fig 11: at 0.2 deg/s the X and Y RMSE is within 10 arcsec for updates every 1, 3 and 5 stars
    assert _get(quick[0], "rmse_xy_max_over_groups", "true rate").ours < 10.0  # quick: 0.30, full: 0.15


def test_rate_source_cost(quick):
    """An imperfect rate costs accuracy at every rate; with unlimited memory (forgetting 1) the cost
    is the rate error integrated over the whole run, with fading memory it is much smaller.
    Quick run: truth X 0.17, gyro 39.6, pso estimate 18.5 arcsec at every rate (independent of it:
    neither the gyro's nor the PSO's error grows with the rate)."""
    rows, _ = quick
    for rate in ("0.0", "0.1", "0.2"):
        truth = _fig11(rows, "x", rate, "true rate")
        gyro = _fig11(rows, "x", rate, "gyro")
        est = _fig11(rows, "x", rate, "pso-rate estimate")
        assert gyro > 20 * truth and est > 20 * truth, (rate, truth, gyro, est)
        e_truth = _fig11(rows, "x", rate, "true rate", explained=True)
        e_gyro = _fig11(rows, "x", rate, "gyro", explained=True)
        assert 1.5 < e_gyro / e_truth < 0.2 * gyro / truth, (rate, e_truth, e_gyro)
    # the rate sources' own errors (the gyro's ARW at 200 Hz: 0.0025 deg/sqrt(s) * sqrt(200) * sqrt(2) = 0.050)
    g = _get(rows, "fig11_rate_error_rms", "0.1 deg/s, gyro").ours
    assert g == pytest.approx(0.15 / 60 * np.sqrt(200) * np.sqrt(2), rel=0.05)


@pytest.mark.xfail(strict=True, reason="paper Fig 11: per-1 Z RMSE > 80 arcsec at 0.2 deg/s; ours with the true rate "
                   "is 3.0 (quick) / 1.9 arcsec (full run): our error does not grow with the rate (see the doc)")
def test_fig11_z_per1_exceeds_80_arcsec(quick):
    assert _get(quick[0], "rmse_z_per1", "true rate").ours > 80.0


@pytest.mark.xfail(strict=True, reason="literal reading (0.05 px, forgetting 1) is 20-40x below Table 3: full run "
                   "per-5 X/Y/Z 0.107/0.116/1.43 vs 2.05/2.28/23.2 arcsec")
def test_table3_literal_reading_matches_paper(quick):
    for g in (1, 3, 5):
        for ax in "xyz":
            r = _get(quick[0], f"rmse_{ax}_per{g}", "forgetting 1 (eqs 30-31)")
            assert 0.5 < r.ours / r.paper < 2.0, (g, ax, r.ours, r.paper)


def test_table3_explained_reading(quick):
    """The fitted (noise, forgetting) reading: the measured RMSE at the fitted noise equals the
    linear prediction (RMSE proportional to the centroid noise), so all nine Table 3 cells come out
    within the shape mismatch of the fit (log-spread 0.12: factors within exp(3 * 0.12) = 1.43)."""
    rows, _ = quick
    fits = {c: r for (q, c), r in rows.items() if q == "table3_sigma_fit"}
    best = [r for r in fits.values() if "best" in r.note]
    assert len(best) == 1
    rho = best[0].condition.split()[-1]
    assert rho != "1.0"  # unlimited memory does not give the paper's shape (spread 0.22 vs 0.12)
    assert 0.1 < best[0].ours < 0.4  # px: a plausible centroid noise, 2-8x our 0.05 px
    ratios = []
    for g in (1, 3, 5):
        for ax in "xyz":
            r = _get(rows, f"rmse_{ax}_per{g}", "explained reading")
            ratios.append(r.ours / r.paper)
    ratios = np.array(ratios)
    assert np.all((ratios > 1 / 1.43) & (ratios < 1.43)), ratios
    assert abs(np.mean(np.log(ratios))) < 0.1  # geometric mean ~1: RMSE is linear in the noise (quick: 3 x 60 frames)
