"""Every tutorial of the documentation site runs as written: its files (``{code-block}`` blocks with a
``:caption:`` file name) are written and its ``console`` commands run in order, in a scratch folder."""
import os
import re
import shlex
from pathlib import Path

import pytest
from typer.testing import CliRunner

from rollingstar import cli as cli_module

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = ROOT / "docs" / "tutorials"
BLOCK = re.compile(r"^```(\{code-block\} \w+|console)\n(.*?)^```", re.S | re.M)


def steps(page: Path) -> list[tuple[str, str]]:
    """``("file", name, text)`` and ``("run", command)`` steps of a tutorial, in page order."""
    out = []
    for kind, body in BLOCK.findall(page.read_text()):
        if kind == "console":
            out += [("run", line.strip()) for line in body.splitlines() if line.strip()]
        else:
            caption = re.match(r":caption: (\S+)\n\n?", body)
            if caption:
                out.append(("file", caption.group(1), body[caption.end():]))
    return out


def test_the_tutorial_pages_are_the_ones_the_index_lists():
    index = (TUTORIALS / "index.md").read_text()
    pages = {p.stem for p in TUTORIALS.glob("*.md")} - {"index"}
    assert pages <= set(re.findall(r"^([a-z-]+)$", index, re.M))
    assert all(steps(TUTORIALS / f"{p}.md") for p in pages)


@pytest.mark.parametrize("page", sorted(p.stem for p in TUTORIALS.glob("*.md") if p.stem != "index"))
def test_tutorial_runs(page, tmp_path, monkeypatch):
    text = (TUTORIALS / f"{page}.md").read_text()
    env = dict(os.environ)
    if "$ROLLINGSTAR_REAL_DATA" in text:
        real = Path(os.environ.get("ROLLINGSTAR_REAL_DATA", ROOT.parent / "shared" / "data" / "real"))
        if not real.is_dir():
            pytest.skip(f"real data not found at {real} (set ROLLINGSTAR_REAL_DATA to the shared/data/real folder)")
        env["ROLLINGSTAR_REAL_DATA"] = str(real.resolve())
    printed = ""
    monkeypatch.chdir(tmp_path)  # the commands run in the command line's own process (no interpreter start-up each)
    monkeypatch.setitem(cli_module._state, "debug", False)
    for name, value in env.items():
        if name == "ROLLINGSTAR_REAL_DATA":
            monkeypatch.setenv(name, value)
    for step in steps(TUTORIALS / f"{page}.md"):
        if step[0] == "file":
            (tmp_path / step[1]).write_text(step[2])
            continue
        args = shlex.split(step[1].replace("$ROLLINGSTAR_REAL_DATA", env.get("ROLLINGSTAR_REAL_DATA", "")))
        assert args[0] == "rollingstar", step[1]
        res = CliRunner().invoke(cli_module.app, [*args[1:], "-q"] if _takes_quiet(args) else args[1:])
        assert res.exit_code == 0, (step[1], res.output[-3000:])
        printed += res.output
    if page == "simulate-and-evaluate":
        assert {p.name for p in (tmp_path / "plots").iterdir()} >= {"attitude_error.png", "rate_error.png"}
    if page == "diagnose-a-mismatch":
        assert (tmp_path / "report" / "index.html").is_file() and (tmp_path / "report" / "scenario_updated.yaml").is_file()
        assert "named: radial_distortion, rolling_shutter" in printed  # the two effects the page conceals


def _takes_quiet(args: list[str]) -> bool:
    """Commands with progress bars: quiet in the test (the page shows them as a user types them)."""
    return args[1] in ("simulate", "run", "compare", "diagnose") or args[1:3] == ["import", "images"]
