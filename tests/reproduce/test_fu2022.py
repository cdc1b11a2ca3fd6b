"""fu2022 quick reproduction: the paper's bounds where our simulation meets them, our own spread elsewhere.

Margins come from our Monte Carlo (full run, 500 trials per condition, docs/reproductions/fu2022.md):
the quick run has 30 trials per condition, so quantiles are bounded at roughly 2-3x the full-run value.
Where the paper's bound is not met (heavy tails of three-star geometry with a 20 us line delay, see
the doc), the test pins our behaviour instead of the paper's number.
"""
from __future__ import annotations

import numpy as np
import pytest

from pipelines.reproduce import run_reproduction


@pytest.fixture(scope="module")
def rows():
    return run_reproduction("fu2022", quick=True, seed=1)


def get(rows, quantity, condition_part=""):
    hits = [r for r in rows if r.quantity == quantity and condition_part in r.condition]
    assert hits, (quantity, condition_part)
    return hits[0] if len(hits) == 1 else hits


def test_every_row_has_counts_and_seed(rows):
    for r in rows:
        assert r.seed == 1
        if r.quantity not in ("fig7_max_velocity_wz1",):
            assert r.trials and r.trials >= 30
    assert get(rows, "run_time").trials == 28 * 30  # ~15 s on an idle 2-core machine (timing not asserted)


def test_fig9_noise_free_median_within_paper_bound(rows):
    # paper: error <= 0.002 deg/s at wx = wy = 1 deg/s; ours meets it for the typical (median) trial
    assert get(rows, "fig9_rate_error_max").note  # median is in the note; p95 row below
    clean = get(rows, "fig9_rate_error_p95").ours
    assert clean < 0.5  # heavy tail from ill-conditioned adjacent triples (full run: see doc)
    median = float(get(rows, "fig9_rate_error_max").note.split("median ")[1].split(",")[0])
    assert median < 0.002


def test_fig9_linear_model_as_printed_is_biased(rows):
    lin = get(rows, "fig9_rate_error_median_linear").ours
    median = float(get(rows, "fig9_rate_error_max").note.split("median ")[1].split(",")[0])
    assert lin > 5 * median


def test_fig10_iterations_within_50(rows):
    assert get(rows, "fig10_iterations_max").ours <= 50


def test_fig11_fig12_fig14_our_spread(rows):
    for axis in ("x", "y"):
        assert get(rows, f"fig11_q3_error_{axis}").ours < 1.0
    q3 = {r.condition: r.ours for r in get(rows, "fig12_q3_error")}
    assert all(v < 0.8 for v in q3.values())
    adj = q3["wx = 3 deg/s, sigma 0.05 px"]
    assert q3["wx = 3 deg/s, sigma 0.05 px, n_stars=all"] < adj  # more stars, better conditioning
    for kind in ("x", "y", "xy"):
        assert get(rows, f"fig14_rmse_{kind}").ours < 5.0


def test_fig7_velocity_is_radius_times_wz(rows):
    # exact for a rotation about the boresight: |v| = r * wz; the Table 1 detector's half diagonal is 1204 px
    v = get(rows, "fig7_max_velocity_wz1").ours
    assert 19.0 < v < np.hypot(1024, 640) * np.pi / 180
