"""The quick discrepancy benchmark on a fixed seed: naming above 3x the detection limit, nulls, out-of-library."""
from __future__ import annotations

import pytest

from rollingstar.studies.bench.discrepancy import NULL_FRACTION, run_benchmark

pytestmark = pytest.mark.slow  # whole reproductions, benchmarks or killed processes: `-m 'not slow'` skips them


@pytest.fixture(scope="module")
def bench():
    return run_benchmark(quick=True, seed=1, show_progress=False)


def test_case_mix(bench):
    s = bench["summary"]
    assert s["null_fraction"] >= 0.30 and s["null_fraction"] >= NULL_FRACTION - 0.05
    assert s["out_of_library_cases"] >= 1
    assert s["cases_above_3x"] >= 2  # the seed must exercise naming above 3x, or the test below is empty


def test_no_false_discovery_on_nulls(bench):
    nulls = [c for c in bench["cases"] if c["kind"] == "null"]
    assert nulls and all(c["outcome"] == "correct" and not c["mismatch"] for c in nulls), nulls


def test_named_correctly_above_3x(bench):
    above = [c for c in bench["cases"] if c["kind"] in ("library", "two") and (c.get("multiple") or 0) >= 3.0
             and c["outcome"] != "invisible_in_design"]
    bad = [c for c in above if c["outcome"] != "correct"]
    assert not bad, bad
    for c in above:  # parameters of correctly named effects: no gross error (a fit stuck at its start,
        # a wrong sign): within 4 reported sigma (P = 6e-5 per parameter for a correct sigma) and 25 %
        # of the injected offset (coverage itself is measured on the full benchmark)
        for e in c["param_errors"]:
            assert abs(e["pull"]) < 4.0 and e["rel_error"] < 0.25, c


def test_out_of_library_is_not_named_confidently(bench):
    for c in bench["cases"]:
        if c["kind"] == "out_of_library":
            assert c["outcome"] != "confident_wrong_name", c
            if (c.get("multiple") or 0) >= 3.0:
                assert c["outcome"] == "unexplained", c
