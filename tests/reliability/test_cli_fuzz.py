"""Every command on random bytes, random YAML and mutated recordings: exit 0 or 2, no traceback,
inputs untouched.

Each example writes hostile files, runs one command in-process (the CLI's own error boundary, as a
user meets it) and checks the exit code, the absence of a traceback, and that every input file is
byte-for-byte what it was. ``ROLLINGSTAR_FUZZ_EXAMPLES`` raises the number of examples.
"""
from __future__ import annotations

import hashlib
import os
import warnings
from pathlib import Path

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.reliability.helpers import PIPELINE, SCENARIO, cli
from tests.reliability.test_fuzz import _log_bytes, _mutate, mutation

EXAMPLES = int(os.environ.get("ROLLINGSTAR_FUZZ_EXAMPLES", 12))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize="ROLLINGSTAR_FUZZ_EXAMPLES" not in os.environ,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

# YAML that parses: scalars, lists and mappings nested a little, keys from the real configs
_keys = st.sampled_from(["sensor", "shutter", "motion", "frames", "seed", "stages", "kind", "params", "width_px",
                         "exposure_ms", "name", "level", "noise", "scenarios", "pipelines", "camera", "x"])
_leaf = st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20), st.floats(allow_nan=False),
                  st.text(max_size=8))
_value = st.recursive(_leaf, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                     st.dictionaries(_keys, inner, max_size=4)), max_leaves=12)
random_yaml = st.one_of(
    st.dictionaries(_keys, _value, max_size=6).map(lambda d: yaml.safe_dump(d)),
    st.text(max_size=200),
    st.sampled_from([SCENARIO.read_text(), PIPELINE.read_text()]).flatmap(
        lambda text: st.integers(0, len(text)).map(lambda cut: text[:cut])),
)
random_bytes = st.binary(max_size=512)


def _digests(paths) -> dict:
    out = {}
    for p in paths:
        p = Path(p)
        if p.is_file():
            out[p] = hashlib.sha256(p.read_bytes()).hexdigest()
        elif p.is_dir():
            out.update(_digests(sorted(p.iterdir())))
    return out


def _check(args, inputs):
    before = _digests(inputs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code, out, err = cli(*args)
    assert code in (0, 2), (args, code, out[-2000:], err[-2000:])
    assert "Traceback" not in out + err, (args, err[-3000:])
    assert _digests(inputs) == before, f"{args}: an input changed"


def _recording(tmp_path, mutations) -> Path:
    path = tmp_path / "rec.mcap"
    path.write_bytes(_mutate(_log_bytes(tmp_path), mutations) if mutations else _log_bytes(tmp_path))
    return path


@FUZZ
@given(text=random_yaml)
def test_config_commands_on_random_yaml(tmp_path, text):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    rec = _recording(tmp_path, [])
    _check(["simulate", cfg, "-o", tmp_path / "o.mcap", "--frames", "2", "-q"], [cfg])
    _check(["run", cfg, rec, "-o", tmp_path / "o2.mcap", "-q"], [cfg, rec])
    _check(["compare", cfg, "-o", tmp_path / "cmp", "-q"], [cfg])
    _check(["import", "centroids", tmp_path / "c.csv", "-o", tmp_path / "o3.mcap", "--camera", cfg], [cfg])


@FUZZ
@given(data=random_bytes)
def test_every_file_argument_on_random_bytes(tmp_path, data):
    junk = tmp_path / "junk.bin"
    junk.write_bytes(data)
    _check(["info", junk], [junk])
    _check(["evaluate", junk], [junk])
    _check(["run", PIPELINE, junk, "-o", tmp_path / "o.mcap", "-q"], [junk])
    _check(["simulate", junk, "-o", tmp_path / "o.mcap", "-q"], [junk])
    _check(["import", "centroids", junk, "-o", tmp_path / "o.mcap", "--camera", junk], [junk])
    _check(["diagnose", "--recording", junk, "-q"], [junk])


@FUZZ
@given(mutations=st.lists(mutation, min_size=1, max_size=3))
def test_recording_commands_on_mutated_recordings(tmp_path, mutations):
    rec = _recording(tmp_path, mutations)
    _check(["info", rec], [rec])
    _check(["evaluate", rec], [rec])
    _check(["run", PIPELINE, rec, "-o", tmp_path / "o.mcap", "-q"], [rec])


def test_outputs_that_are_inputs_are_refused_for_every_writing_command(tmp_path):
    rec = _recording(tmp_path, [])
    scenario = tmp_path / "s.yaml"
    scenario.write_text(SCENARIO.read_text())
    for args, inputs in (
        (["simulate", scenario, "-o", scenario, "-q"], [scenario]),
        (["run", PIPELINE, rec, "-o", rec, "-q"], [rec]),
        (["compare", scenario, "-o", scenario, "-q"], [scenario]),
    ):
        _check(args, inputs)
        assert cli(*args)[0] == 2
