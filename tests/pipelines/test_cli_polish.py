"""The command line as a reader meets it: every option explained, no markup or internals leaking."""
import re
import subprocess
import sys
from pathlib import Path

import pytest
import typer

from rollingstar.cli import app
from rollingstar.pipelines.plugin_docs import first_sentence, parameters, plain, type_name, unit_of
from rollingstar.pipelines.registry import plugins_by_role

ROOT = Path(__file__).resolve().parents[2]


def _commands(cmd=None, path=()):
    cmd = cmd or typer.main.get_command(app)
    if hasattr(cmd, "commands"):
        for name, sub in cmd.commands.items():
            yield from _commands(sub, (*path, name))
    else:
        yield " ".join(path), cmd


COMMANDS = dict(_commands())


def cli(*args, columns=200):
    return subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, timeout=300, env={"COLUMNS": str(columns), "PATH": "/usr/bin:/bin"})


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_and_option_says_what_it_does(name):
    cmd = COMMANDS[name]
    assert cmd.help and cmd.help.strip(), name
    for p in cmd.params:
        assert getattr(p, "help", None), f"{name} {p.opts}: no help text"
        assert not re.search(r"\bissue \d", p.help, re.I), f"{name} {p.opts}: development history in the help"


@pytest.mark.parametrize("name", ["run", "evaluate", "demo", "diagnose", "compare seeds", "figures"])
def test_help_shows_no_value_type_for_flags(name):
    proc = cli(*name.split(), "--help")
    assert proc.returncode == 0, proc.stderr
    assert "<bool>" not in proc.stdout
    assert "--help" in proc.stdout


def test_plugins_table_has_types_rounded_defaults_units_and_no_markup():
    proc = cli("plugins")
    assert proc.returncode == 0, proc.stderr
    text = proc.stdout
    for leak in ("PydanticUndefined", ":func:", ":class:", ":mod:", "``", "0.2886751345948129", "docstring"):
        assert leak not in text, leak
    for role in {role for role in plugins_by_role()}:
        assert f"role: {role}" in text
    assert re.search(r"gate_px\s*│\s*float\s*│\s*10\s*│\s*px", text)
    assert "0.2887" in text  # noise_floor_adu rounded
    assert cli("plugins", "no-such-plugin").returncode == 2


def test_every_plugin_parameter_reads_as_plain_words():
    for classes in plugins_by_role().values():
        for cls in classes:
            for p in parameters(cls):
                assert p.description and "`" not in p.description and "PydanticUndefined" not in p.default, (cls, p)


def test_plugin_text_helpers_on_known_inputs():
    assert unit_of("rate_sigma_deg_s", "") == "deg/s" and unit_of("accel_sigma_deg_s2", "") == "deg/s²"
    assert unit_of("tile_px", "") == "px" and unit_of("map_filter_tiles", "Median-filter width (tiles) of") == "tiles"
    assert unit_of("threshold_sigma", "in noise sigmas.") == ""
    assert unit_of("angular_accel_noise_deg_s_sqrt_s", "") == "deg/s/√s" and unit_of("gyro_arw_deg_sqrt_h", "") == "deg/√h"
    assert unit_of("use_star_velocity", "Use each star's image velocity (px/s)", bool) == ""
    assert plain("see :func:`~rollingstar.sensors.so3.skew` and ``x``") == "see skew and x"
    assert first_sentence("Fit it (e.g. twice. Really). Then more.") == "Fit it (e.g. twice. Really)."
    assert first_sentence("'median': one; 'tiles': two. Else.") == "'median': one; 'tiles': two."
    assert first_sentence("Use i.e. this one. Not that.") == "Use i.e. this one."
    from typing import Literal

    assert type_name(float | None) == "float or None" and type_name(Literal["a", "b"]) == "'a' | 'b'"
    assert type_name(tuple[float, ...]) == "tuple of float" and type_name(tuple[float, float, float]) == "tuple of 3 float"


def test_info_indents_metadata_documents(small_output):
    proc = cli("info", small_output)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    start = lines.index("  yaml: |", next(i for i, line in enumerate(lines) if line.startswith("metadata scenario")))
    body = lines[start + 1: start + 6]
    assert all(line.startswith("    ") for line in body), body
    assert proc.stdout.endswith("\n")


def test_a_seed_out_of_range_is_refused_in_words():
    proc = cli("simulate", "he2021b", "-o", "/tmp/never.mcap", "--seed", "-1")
    assert proc.returncode == 2 and "0 to 2^63 - 1" in proc.stdout + proc.stderr
