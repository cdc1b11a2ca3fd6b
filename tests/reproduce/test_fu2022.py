"""fu2022 quick reproduction: the paper's bounds where our simulation meets them, our own spread elsewhere.

Margins come from our Monte Carlo (full run, 500 trials per condition, docs/reproductions/fu2022.md):
the quick run has 30 trials per condition, so quantiles are bounded at roughly 2-3x the full-run value.
Where the paper's bound is not met (heavy tails of three-star geometry with a 20 us line delay, see
the doc), the test pins our behaviour instead of the paper's number.
"""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.studies.reproduce import run_reproduction

pytestmark = [pytest.mark.slow, pytest.mark.long_study]  # a whole reproduction: `make test-long` runs it


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
    assert get(rows, "run_time").trials == (28 + 3 * 4) * 30  # ~15 s CPU (timing not asserted)


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


def _sweep(rows, stat_cond):
    """{line delay us: ours} of one line-delay sweep (condition prefix up to the line delay)."""
    out = {}
    for r in rows:
        if r.condition.startswith(stat_cond + ", line delay "):
            out[float(r.condition.split("line delay ")[1].split(" us")[0])] = r.ours
    assert len(out) == 3, (stat_cond, out)
    return out


def test_line_delay_sweep_error_falls_as_one_over_line_delay(rows):
    """The rate is seen only through the row-time differences: the noise-limited error falls as
    1 / line delay (15.6x from 20 to 312.5 us). Quick run: Fig 12 Q3 at 0.01 px 0.077 -> 0.0070
    (11x), at 0.05 px 0.26 -> 0.016 (16x); with 30 trials the quantiles scatter by ~30 %, so we ask
    for > 6x and a monotonic fall."""
    for cond in ("wx = 3 deg/s, sigma 0.01 px, q3 error", "wx = 3 deg/s, sigma 0.05 px, q3 error",
                 "wx = wy = 1 deg/s, sigma 0.02 px, median error"):
        s = _sweep(rows, cond)
        e = [s[k] for k in sorted(s)]
        assert e[0] > e[1] > e[2], (cond, s)
        assert e[0] / e[2] > 6.0, (cond, s)


def test_fig12_bound_reached_with_a_long_readout(rows):
    # paper: Fig 12 Q3 < 0.01 deg/s at 3 deg/s for sigma < 0.05 px. Reached at 0.01 px once the 1280
    # rows take 400 ms (312.5 us per row): quick 0.0070, full run 0.0074 deg/s (implied: 172 us per row)
    s = _sweep(rows, "wx = 3 deg/s, sigma 0.01 px, q3 error")
    assert s[312.5] < 0.01
    implied = [r for r in rows if r.quantity == "implied_line_delay" and "sigma 0.01 px" in r.condition][0].ours
    assert 78.125 < implied < 312.5  # longer than a readout spanning the whole 100 ms exposure


@pytest.mark.xfail(strict=True, reason="Fig 12 Q3 < 0.01 deg/s with our assumed 20 us line delay: measured 0.088 "
                   "(0.01 px) to 0.37 deg/s (0.05 px), full run 500 trials")
def test_fig12_bound_at_the_assumed_line_delay(rows):
    q3 = {r.condition: r.ours for r in get(rows, "fig12_q3_error") if "line delay" not in r.condition}
    assert all(v < 0.01 for c, v in q3.items() if "selection" not in c and "n_stars" not in c), q3


@pytest.mark.xfail(strict=True, reason="Fig 11 max |error| < 0.1 deg/s: ours 16 (x) / 10 deg/s (y) at 20 us, and "
                   "still > 0.1 deg/s at 625 us (ill-conditioned adjacent triples, full run 500 trials per rate)")
def test_fig11_max_bound(rows):
    assert get(rows, "fig11_max_error_x", "0.5-5 deg/s").ours < 0.1 and get(rows, "fig11_max_error_y", "0.5-5 deg/s").ours < 0.1
