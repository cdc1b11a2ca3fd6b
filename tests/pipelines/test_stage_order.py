"""A pipeline's stages are checked against each other when built, and against the recording before
the first frame: every stage gets what it declares it needs (``Plugin.needs``) from a stage before
it or from the recording."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from rollingstar.config import parse_yaml, validate
from rollingstar.errors import ConfigError, PipelineError
from rollingstar.estimators.plugin import FRAME_CONTENTS, Plugin
from rollingstar.pipelines import registry
from rollingstar.pipelines import runner as runner_module
from rollingstar.pipelines.config import PipelineConfig, load_pipeline
from rollingstar.pipelines.demo import DEMO_PIPELINE_YAML
from rollingstar.pipelines.diagnose import default_pipeline
from rollingstar.pipelines.runner import build_stages, run_pipeline
from rollingstar.pipelines.source import open_recording

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = sorted((ROOT / "configs" / "pipelines").glob("*.yaml"))


def _config(*stages) -> PipelineConfig:
    return PipelineConfig(stages=[s if isinstance(s, dict) else {"kind": s} for s in stages])


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, timeout=300)


@pytest.fixture(scope="module")
def image_recording(tmp_path_factory) -> Path:
    """Two frames of the he2021a scenario at image level."""
    from rollingstar.pipelines.simulate import simulate_to_log
    from rollingstar.sensors.scenario import load_scenario

    out = tmp_path_factory.mktemp("img") / "he2021a_2.mcap"
    simulate_to_log(load_scenario(ROOT / "configs" / "scenarios" / "he2021a.yaml"), out, frames=2, show_progress=False)
    return out


def test_out_of_order_pipeline_is_exit_2_naming_the_stage_and_what_it_misses(tmp_path, small_recording):
    pipe = tmp_path / "misordered.yaml"
    pipe.write_text("stages:\n  - {kind: cog}\n  - {kind: quest}\n  - {kind: tracking}\n")
    proc = _cli("run", pipe, small_recording, "-o", tmp_path / "out.mcap")
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr
    message = " ".join(proc.stderr.split())  # the console wraps long lines
    for needle in (str(pipe), "stages[1] ('quest', attitude solver)", "'identified'", "stages[2] ('tracking', identifier)",
                   "centroider -> identifier -> [star-motion filter] -> [rolling-shutter correction] -> attitude solver"):
        assert needle in message, (needle, message)
    assert not list(tmp_path.glob("out.mcap*"))


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_every_shipped_pipeline_is_in_a_valid_order(path):
    registry.check_stage_order(build_stages(load_pipeline(path), str(path)), str(path))


@pytest.mark.parametrize("config", [
    validate(PipelineConfig, parse_yaml(DEMO_PIPELINE_YAML, "demo"), "demo"), default_pipeline(),
], ids=["demo", "diagnose"])
def test_pipelines_built_in_code_are_in_a_valid_order(config):
    build_stages(config, config.name)


@pytest.mark.parametrize("stages, stage, missing, hint", [
    (("tracking", "cog", "quest"), "stages[0] ('tracking', identifier)", "'spots'", "only the later stages[1] ('cog'"),
    (("cog", "tracking", "time-domain", "quest"), "stages[2] ('time-domain'", "'velocities'", "add a star-motion filter"),
    (("cog", "tracking", "rate-correction", "quest"), "stages[2] ('rate-correction'", "'rate'", "add a rate estimator"),
    (("cog", "tracking", {"kind": "request", "params": {"rate_source": "estimate"}}, "pso-rate"),
     "stages[2] ('request'", "'rate'", "only the later stages[3] ('pso-rate'"),
    (("cog", "kf-cv", "tracking", "quest"), "stages[1] ('kf-cv', star-motion filter)", "'identified'",
     "only the later stages[2] ('tracking'"),
])
def test_a_stage_without_its_input_is_a_config_error(stages, stage, missing, hint):
    with pytest.raises(ConfigError) as exc:
        build_stages(_config(*stages), "p.yaml")
    message = str(exc.value)
    assert message.startswith("p.yaml: ") and stage in message and f"needs {missing}" in message and hint in message
    assert registry.VALID_ORDER in message


@pytest.mark.parametrize("stages", [
    ("quest",),  # a recording of identified stars (imported astrometry.net tables)
    ("tracking", "quest"),  # a centroid recording
    ("pso-correction", "quest"),  # the correction estimates its rate itself
    ("cog", "tracking", "pso-rate", {"kind": "request", "params": {"rate_source": "estimate"}}),
    ("cog", "tracking", {"kind": "request", "params": {"rate_source": "gyro"}}),
    ("cog", "tracking", "mekf", "rate-correction", "quest"),  # mekf sets frame.rate
    ("cog", "tracking", "quest", "ls-rate"),  # a rate estimator after the solver: nothing needs it earlier
])
def test_valid_orders_build(stages):
    build_stages(_config(*stages), "p.yaml")


def test_declarations_of_parameter_dependent_plugins():
    def stage(kind, **params):
        return registry.get_plugin_class(kind)(**registry.stage_params(kind, params))

    quest, request_est, request_gyro = stage("quest"), stage("request", rate_source="estimate"), stage("request", rate_source="gyro")
    corr, pso_corr, none, td = stage("rate-correction"), stage("pso-correction"), stage("none"), stage("time-domain")
    assert quest.needs == request_gyro.needs == {"identified"} and request_est.needs == {"identified", "rate"}
    assert corr.needs == {"rate"} and corr.provides == {"common_time"}
    assert pso_corr.needs == {"identified"} and pso_corr.provides == {"common_time", "rate"}
    assert none.provides == frozenset() and td.needs == {"velocities"}
    words = set(FRAME_CONTENTS)
    for classes in registry.plugins_by_role().values():
        for cls in classes:
            plugin = cls()  # declarations may depend on the parameters: read them on an instance
            assert set(plugin.needs) <= words and set(plugin.provides) <= words, plugin


class Undeclared(Plugin):
    """A third-party stage that declares neither needs nor provides (a pass-through)."""

    role = "filter"
    name = "undeclared"

    def process(self, frame):
        return frame.evolve()


@pytest.fixture
def undeclared(monkeypatch):
    real = runner_module.get_plugin_class
    monkeypatch.setattr(runner_module, "get_plugin_class", lambda kind: Undeclared if kind == "undeclared" else real(kind))


def test_a_plugin_without_declarations_is_accepted_anywhere(undeclared, tmp_path, small_recording):
    assert Undeclared.needs == Undeclared.provides == frozenset()
    for position in range(4):
        kinds = ["cog", "tracking", "quest"]
        kinds.insert(position, "undeclared")
        build_stages(_config(*kinds), "p.yaml")
    summary = run_pipeline(small_recording, _config("undeclared", "tracking", "quest"), tmp_path / "o.mcap",
                           show_progress=False)
    assert summary.frames == 20 and summary.valid_estimates > 0


def test_what_a_recording_provides(small_recording, image_recording):
    assert open_recording(small_recording).provides == {"spots"}  # simulated centroids are not identified
    assert open_recording(image_recording).provides == {"image"}


def test_an_image_recording_without_a_centroider_is_refused_before_the_first_frame(tmp_path, image_recording):
    pipe = tmp_path / "no_centroider.yaml"
    pipe.write_text("stages:\n  - {kind: tracking}\n  - {kind: quest}\n")
    proc = _cli("run", pipe, image_recording, "-o", tmp_path / "out.mcap")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    message = " ".join(proc.stderr.split())
    for needle in (str(pipe), "stages[0] ('tracking', identifier) needs 'spots'", str(image_recording),
                   "it holds 'image'", "add a centroider before it"):
        assert needle in message, (needle, message)
    assert not list(tmp_path.glob("out.mcap*"))


def test_a_centroid_recording_checks_against_what_it_holds(tmp_path, small_recording):
    """Unidentified centroids and no identifier: refused; the centroider of a centroid recording is
    skipped by the run and by the check."""
    with pytest.raises(PipelineError, match=r"stages\[0\] \('quest', attitude solver\) needs 'identified'"):
        run_pipeline(small_recording, _config("quest"), tmp_path / "o.mcap", show_progress=False)
    assert not list(tmp_path.glob("o.mcap*"))
    stages = build_stages(_config("cog", "tracking", "quest"))
    registry.check_stages_on_recording(stages, frozenset({"spots"}), "rec.mcap")
    with pytest.raises(PipelineError, match="'identified'"):
        registry.check_stages_on_recording(stages[:1] + stages[2:], frozenset({"spots"}), "rec.mcap")
    registry.check_stages_on_recording(stages[:1] + stages[2:], frozenset({"spots", "identified"}), "rec.mcap")
