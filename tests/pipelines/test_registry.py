"""Plugin registry: built-ins, third-party entry points validated exactly like built-ins."""
import sys
import textwrap

import pytest

from rollingstar.errors import ConfigError
from rollingstar.pipelines import registry
from rollingstar.pipelines.config import PipelineConfig
from rollingstar.pipelines.runner import build_stages


def test_builtins_have_their_declared_role_and_name():
    for kind, target in registry.BUILTIN.items():
        cls = registry.get_plugin_class(kind)
        assert cls.role in registry.ROLES
        assert cls.name == kind, f"{target} declares name {cls.name!r}"


@pytest.fixture
def third_party_plugin(tmp_path, monkeypatch):
    """A real installed distribution (dist-info on sys.path) exposing a plugin entry point."""
    (tmp_path / "acme_plugin.py").write_text(textwrap.dedent("""
        from pydantic import BaseModel, ConfigDict
        from rollingstar.estimators.corrections.base import Correction

        class Shift(Correction):
            '''Adds a constant shift to every star (a test plugin).'''
            name = "acme-shift"

            class Params(BaseModel):
                model_config = ConfigDict(extra="forbid")
                dx_px: float = 0.0

            def process(self, frame):
                return frame
    """))
    dist = tmp_path / "acme_plugin-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-plugin\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[rollingstar.plugins]\nacme-shift = acme_plugin:Shift\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    registry._third_party.cache_clear()
    yield
    registry._third_party.cache_clear()
    sys.modules.pop("acme_plugin", None)


def test_third_party_plugin_is_found_and_validated_like_builtins(third_party_plugin):
    assert "acme-shift" in registry.available_kinds()
    stages = build_stages(PipelineConfig(stages=[{"kind": "acme-shift", "params": {"dx_px": 0.5}}]))
    assert stages[0].params.dx_px == 0.5 and stages[0].role == "correction"
    with pytest.raises(ConfigError, match=r"stages\[0\]\.params\.dy_px: unknown key"):
        build_stages(PipelineConfig(stages=[{"kind": "acme-shift", "params": {"dy_px": 1}}]))
    assert any(c.name == "acme-shift" for c in registry.plugins_by_role()["correction"])


def test_aliases_build_the_plugin_they_stand_for_with_its_parameters():
    """pso-correction and ls-correction are rate-correction with a rate estimator of its own; the
    estimator's parameters given beside the correction's (their configs' form) become estimator_params."""
    rate_correction = registry.get_plugin_class("rate-correction")
    for alias in registry.ALIASES:
        assert registry.get_plugin_class(alias) is rate_correction
        assert alias not in registry.available_kinds()  # one entry per class in listings
    stages = build_stages(PipelineConfig(stages=[
        {"kind": "pso-correction", "params": {"particles": 40, "model": "linear", "reuse_rate": True}},
        {"kind": "ls-correction", "params": {"estimate_z": False, "reference": "frame_start"}},
    ]))
    pso, ls = (s.params for s in stages)
    assert (pso.estimator, pso.model, pso.reuse_rate, pso.rotation_form) == ("pso-rate", "linear", True, "rotation-vector")
    assert pso.estimator_params == {"particles": 40}
    assert (ls.estimator, ls.reference, ls.reuse_rate, ls.estimator_params) == ("ls-rate", "frame_start", False,
                                                                                 {"estimate_z": False})
    with pytest.raises(ConfigError, match="particels"):
        build_stages(PipelineConfig(stages=[{"kind": "pso-correction", "params": {"particels": 40}}]))
    with pytest.raises(ConfigError, match="pso-correction"):  # the error lists the aliases among the kinds
        build_stages(PipelineConfig(stages=[{"kind": "pso-corection"}]))
