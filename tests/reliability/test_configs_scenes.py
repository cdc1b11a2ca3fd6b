"""Configs with wrong units, a plugin that raises, and hostile scenes through the runner (docs/reliability.md)."""
from __future__ import annotations

import numpy as np
import pytest

from estimators.attitude.base import AttitudeSolver
from logs.reader import LogReader
from pipelines import runner as runner_module
from pipelines.config import PipelineConfig
from pipelines.errors import PipelineError
from pipelines.runner import run_pipeline

from .helpers import SCENARIO, assert_exit_2, rewrite


def test_wrong_units_name_the_key_with_the_unit(tmp_path):
    p = tmp_path / "s.yaml"
    p.write_text(SCENARIO.read_text().replace("exposure_ms: 50.0", "exposure_s: 0.05"))
    print(assert_exit_2(("simulate", p, "-o", tmp_path / "r.mcap"), "shutter.exposure_s: unknown key",
                        "did you mean 'exposure_ms'", "shutter.exposure_ms: Field required"))


class Exploding(AttitudeSolver):
    """A plugin that raises on frame 4."""

    name = "exploding"

    def process(self, frame):
        if frame.index == 4:
            raise ZeroDivisionError("division by zero")
        return frame


def test_a_plugin_that_raises_names_stage_and_frame_and_keeps_earlier_frames(tmp_path, small_recording, monkeypatch):
    real = runner_module.get_plugin_class
    monkeypatch.setattr(runner_module, "get_plugin_class", lambda kind: Exploding if kind == "exploding" else real(kind))
    out = tmp_path / "o.mcap"
    with pytest.raises(PipelineError, match=r"stage 'exploding' \(attitude\) failed on frame 4 \(t0 = \d+ ns\): "
                                            r"ZeroDivisionError: division by zero"):
        run_pipeline(small_recording, PipelineConfig(stages=[{"kind": "tracking"}, {"kind": "exploding"}]), out,
                     show_progress=False)
    assert [m.data["frame"] for m in LogReader(out).messages("/estimate/frame")] == [0, 1, 2, 3]


def _keep(n_by_frame):
    def edit(ms):
        out = []
        for m in ms:
            if m.topic == "/camera/centroids" and m.data["frame"] in n_by_frame:
                n = n_by_frame[m.data["frame"]]
                m = type(m)(m.topic, m.log_time_ns, m.schema_name,
                            {k: (v[:n] if isinstance(v, list) else v) for k, v in m.data.items()})
            out.append(m)
        return out
    return edit


def test_no_stars_and_one_star_frames_are_flagged_and_tracking_recovers(tmp_path, small_recording):
    rec = rewrite(small_recording, tmp_path / "sparse.mcap", _keep({5: 0, 6: 0, 7: 1}))
    out = tmp_path / "o.mcap"
    s = run_pipeline(rec, PipelineConfig(stages=[{"kind": "tracking"}, {"kind": "quest"}]), out, show_progress=False)
    est = {m.data["frame"]: m.data for m in LogReader(out).messages("/estimate/attitude")}
    flags = {m.data["frame"]: m.data["flags"] for m in LogReader(out).messages("/estimate/frame")}
    assert s.frames == 20 and s.valid_estimates == 17
    for f in (5, 6, 7):
        assert not est[f]["valid"] and est[f]["q"] is None and est[f]["reason"]
        assert "too_few_stars" in flags[f] and "attitude_invalid" in flags[f]
    print({f: est[f]["reason"] for f in (5, 6, 7)})
    assert est[5]["reason"] == est[6]["reason"] == "no stars"
    assert est[7]["reason"].startswith("fewer than 2 identified stars")
    assert all(est[f]["valid"] and not flags[f] for f in range(8, 20))  # tracking picks the stars up again


def test_a_planet_among_the_stars_is_rejected_by_the_gate(tmp_path, small_recording):
    """A bright non-catalogue spot the identifier matched (planted: a spot with a wrong catalogue
    direction, i.e. a centroid recording already identified, as `import corr` writes)."""
    from pipelines.outlier_bench import clean_scene, plant_false_matches, rms_error_arcsec, run_solver

    from .helpers import ROOT

    scene = clean_scene(4, seed=9, root=ROOT)
    frames = plant_false_matches(scene, 1, seed=2)
    gated = run_solver("quest", {"robust": "ransac"}, frames, scene.context)
    clean = run_solver("quest", {}, scene.frames, scene.context)
    assert np.isclose(rms_error_arcsec(gated, scene.motion)[0], rms_error_arcsec(clean, scene.motion)[0], rtol=1e-9)
