"""The command line on good input: the documented outputs and keys."""
import hashlib
import json
import subprocess
import sys
from pathlib import Path

from rollingstar.logs.reader import LogReader

ROOT = Path(__file__).resolve().parents[2]


def cli(*args):
    return subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, timeout=300)


def test_evaluate_json_has_the_documented_keys(small_output):
    proc = cli("evaluate", small_output, "--json")
    assert proc.returncode == 0, proc.stderr
    m = json.loads(proc.stdout)
    for key in ("frames", "attitude_updates", "update_rate_hz"):
        assert isinstance(m[key], (int, float))
    assert set(m["attitude_error_arcsec"]) >= {"x_rmse", "y_rmse", "z_rmse", "x_max", "y_max", "z_max"}
    for key in ("centroid_error_px", "star_pair_distance_error_px", "rate_error_deg_s"):
        assert set(m[key]) >= {"rmse", "max"}
    assert m["rate_error_deg_s"]["rmse"] is None  # no rate estimator in the baseline: null, not invented
    assert m["frames"] == 20 and m["attitude_updates"] == 20
    assert 9.9 < m["update_rate_hz"] < 10.0  # one update per 100.176 ms frame


def test_info_lists_topics_counts_and_metadata(small_recording):
    proc = cli("info", small_recording)
    assert proc.returncode == 0, proc.stderr
    for needle in ("/camera/centroids", "/truth/attitude", "/truth/stars", "rollingstar.Stars", "metadata scenario",
                   "format_version", "he2021b"):
        assert needle in proc.stdout, needle


def test_plugins_lists_every_role_and_parameters():
    proc = cli("plugins")
    assert proc.returncode == 0, proc.stderr
    for needle in ("role: centroider", "role: attitude", "cog", "tracking", "quest", "gate_px", "threshold_sigma"):
        assert needle in proc.stdout, needle


def test_simulate_is_deterministic_apart_from_wall_clock_metadata(tmp_path):
    scenario = ROOT / "configs" / "scenarios" / "he2021b.yaml"
    digests = []
    for name in ("a.mcap", "b.mcap"):
        proc = cli("simulate", scenario, "-o", tmp_path / name, "--frames", "5", "--seed", "7", "-q")
        assert proc.returncode == 0, proc.stderr
        h = hashlib.sha256()
        for m in LogReader(tmp_path / name).messages():
            h.update(m.topic.encode() + str(m.log_time_ns).encode() + json.dumps(m.data, sort_keys=True).encode())
        digests.append(h.hexdigest())
    assert digests[0] == digests[1]
