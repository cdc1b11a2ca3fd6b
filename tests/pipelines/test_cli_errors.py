"""Bad input at the command line: exit code 2, a one-paragraph message, no traceback."""
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "configs" / "scenarios" / "he2021b.yaml"
BASELINE = ROOT / "configs" / "pipelines" / "baseline.yaml"


def cli(*args, cwd=None):
    proc = subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd or ROOT, timeout=300)
    return proc


def assert_clean_error(proc, *needles):
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr and "Traceback" not in proc.stdout, proc.stderr
    for needle in needles:
        assert needle in proc.stderr, (needle, proc.stderr)


def test_unknown_plugin_kind(tmp_path, small_recording):
    p = tmp_path / "p.yaml"
    p.write_text("stages:\n  - {kind: qest}\n")
    assert_clean_error(cli("run", p, small_recording, "-o", tmp_path / "o.mcap"), "qest", "valid kinds", "quest")


def test_unknown_config_key(tmp_path):
    p = tmp_path / "s.yaml"
    p.write_text(SCENARIO.read_text().replace("frames: 300", "frames: 300\nframse: 3"))
    assert_clean_error(cli("simulate", p, "-o", tmp_path / "r.mcap"), str(p), "framse", "unknown key")


def test_yaml_syntax_error(tmp_path, small_recording):
    p = tmp_path / "p.yaml"
    p.write_text("stages:\n  - {kind: quest\n")
    assert_clean_error(cli("run", p, small_recording, "-o", tmp_path / "o.mcap"), "line", "YAML syntax error")


def test_missing_recording(tmp_path):
    assert_clean_error(cli("run", BASELINE, tmp_path / "none.mcap", "-o", tmp_path / "o.mcap"), "none.mcap")


def test_not_an_mcap(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"this is not an mcap file at all" * 10)
    assert_clean_error(cli("info", bad), "bad.mcap")


def test_recording_missing_required_topic(tmp_path, small_output):
    # an output log has no /camera/* topic: running a pipeline over it must name the missing topic
    assert_clean_error(cli("run", BASELINE, small_output, "-o", tmp_path / "o.mcap"), "/camera/centroids")


def test_unwritable_output(tmp_path, small_recording):
    assert_clean_error(cli("run", BASELINE, small_recording, "-o", tmp_path / "no_such_dir" / "o.mcap"), "no_such_dir")


def test_configs_are_found_by_name_from_any_directory(tmp_path):
    proc = cli("simulate", "he2021b", "-o", tmp_path / "rec.mcap", "--frames", "3", "-q", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert_clean_error(cli("simulate", "he2021", "-o", tmp_path / "x.mcap", cwd=tmp_path),
                       "he2021", "not the name of a shipped scenario config", "he2021b")


def _in_process(monkeypatch, *args):
    """Run the CLI's app in this process (so a test can make a command fail in a chosen way)."""
    from typer.testing import CliRunner

    from rollingstar import cli as cli_module

    monkeypatch.setitem(cli_module._state, "debug", False)
    return CliRunner().invoke(cli_module.app, [str(a) for a in args])


@pytest.mark.parametrize("exc, needle", [
    (RuntimeError("boom"), "unexpected RuntimeError: 'boom'"),
    (OverflowError("int too large to convert"), "a number in the input is too large"),
    (RecursionError("maximum recursion depth"), "nested too deeply"),
    (MemoryError(), "ran out of memory"),
    (OSError(28, "No space left on device", "out.mcap"), "out.mcap: No space left on device (the disk is full"),
    (OSError(30, "Read-only file system", "out.mcap"), "read-only file system: write the output somewhere else"),
])
def test_every_exception_becomes_exit_2_with_a_message(monkeypatch, tmp_path, exc, needle):
    import rollingstar.pipelines.evaluate as evaluate

    def fail(path, **options):
        raise exc

    monkeypatch.setattr(evaluate, "evaluate_log", fail)
    res = _in_process(monkeypatch, "evaluate", tmp_path / "out.mcap")
    assert res.exit_code == 2, res.output
    assert needle in res.output and "Traceback" not in res.output


def test_debug_shows_the_traceback(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "rollingstar", "--debug", "info", tmp_path / "missing.mcap"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert proc.returncode != 0 and "Traceback" in proc.stderr


def test_version(tmp_path):
    import rollingstar

    proc = subprocess.run([sys.executable, "-m", "rollingstar", "--version"], capture_output=True, text=True,
                          cwd=tmp_path, timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip() == f"rollingstar {rollingstar.__version__}"


def test_an_unparsable_source_date_epoch_is_named(tmp_path):
    env = dict(__import__("os").environ, SOURCE_DATE_EPOCH="yesterday")
    proc = subprocess.run([sys.executable, "-m", "rollingstar", "simulate", "he2021b", "-o", tmp_path / "r.mcap",
                           "--frames", "2", "-q"], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert_clean_error(proc, "SOURCE_DATE_EPOCH must be a whole number of seconds", "'yesterday'")
    assert not (tmp_path / "r.mcap").exists()


def test_arguments_in_the_wrong_order_are_named(tmp_path, small_recording):
    assert_clean_error(cli("run", small_recording, BASELINE, "-o", tmp_path / "o.mcap"),
                       "an MCAP recording where a YAML config was expected; are the arguments in order")
