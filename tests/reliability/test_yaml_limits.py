"""YAML configs and recording metadata are read within bounds: size, alias expansion, depth, keys."""
from __future__ import annotations

import os

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rollingstar.config import MAX_YAML_BYTES, excerpt, parse_yaml, read_yaml
from rollingstar.errors import ConfigError
from rollingstar.sensors.scenario import scenario_from_yaml


def _alias_bomb(levels: int = 9) -> str:
    """Under 1 kB that expands to 9**levels scalars when every alias is followed."""
    names = [f"l{i}" for i in range(levels + 1)]
    lines = [f"{names[0]}: &{names[0]} [x, x, x, x, x, x, x, x, x]"]
    lines += [f"{b}: &{b} [{', '.join(['*' + a] * 9)}]" for a, b in zip(names, names[1:])]
    return "\n".join(lines) + "\n"


def test_alias_bomb_is_refused_before_expansion():
    text = _alias_bomb()
    assert len(text) < 1024
    with pytest.raises(ConfigError, match="expands to more than"):
        parse_yaml(text, "bomb.yaml")


def test_alias_bomb_in_a_recordings_metadata_is_refused():
    with pytest.raises(ConfigError, match="expands to more than"):
        scenario_from_yaml(_alias_bomb(), "rec.mcap (metadata 'scenario')")


def test_small_shared_aliases_are_fine():
    data = parse_yaml("base: &b {rate: 1.0}\nfirst: *b\nsecond: {<<: *b, rate: 2.0}\n", "ok.yaml")
    assert data["first"] == {"rate": 1.0} and data["second"] == {"rate": 2.0}


def test_duplicate_key_names_the_key_and_both_lines():
    with pytest.raises(ConfigError, match=r"line 3: duplicate key 'frames' \(first at line 1\)"):
        parse_yaml("frames: 10\nseed: 1\nframes: 20\n", "dup.yaml")


def test_nested_duplicate_key_is_refused():
    with pytest.raises(ConfigError, match="duplicate key 'x'"):
        parse_yaml("motion:\n  x: 1\n  x: 2\n", "dup.yaml")


@pytest.mark.parametrize("text", ["a: " + "[" * 3000 + "]" * 3000, "a: " + "{b: " * 3000 + "1" + "}" * 3000,
                                  "a: " + "[" * 80 + "]" * 80])
def test_deep_nesting_is_an_error_not_a_recursion_error(text):
    with pytest.raises(ConfigError, match="deeper than"):
        parse_yaml(text, "deep.yaml")


def test_recursive_alias_is_refused():
    with pytest.raises(ConfigError, match="recursive"):
        parse_yaml("a: &x [1, *x]\n", "loop.yaml")


def test_oversized_file_is_refused_without_reading_it(tmp_path):
    path = tmp_path / "big.yaml"
    with open(path, "wb") as fh:
        fh.truncate(MAX_YAML_BYTES + 1)
    with pytest.raises(ConfigError, match="at most"):
        read_yaml(path)


def test_fifo_is_refused_without_blocking(tmp_path):
    path = tmp_path / "pipe.yaml"
    os.mkfifo(path)
    with pytest.raises(ConfigError, match="not a regular file"):
        read_yaml(path)


def test_binary_file_is_a_config_error(tmp_path):
    path = tmp_path / "bin.yaml"
    path.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ConfigError, match="not UTF-8"):
        read_yaml(path)


def test_error_messages_show_a_short_excerpt_of_a_huge_value():
    assert len(excerpt("x" * 10**6)) <= 80
    with pytest.raises(ConfigError) as info:
        scenario_from_yaml("name: " + "y" * 100000 + "\nframes: [" + ", ".join(["1"] * 5000) + "]\n", "big.yaml")
    assert len(str(info.value)) < 2000


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=300))
def test_any_text_gives_a_mapping_or_a_config_error(text):
    try:
        assert isinstance(parse_yaml(text, "fuzz.yaml"), dict)
    except ConfigError:
        pass
