"""The documentation site's generated reference pages (``make docs``): every registered plugin with
its parameters (from its ``Params`` model, :mod:`rollingstar.pipelines.plugin_docs`) and every
shipped config with the comment it opens with. Generated at build time, so they cannot drift from
the code."""
from __future__ import annotations

from pathlib import Path

from rollingstar.config import CONFIGS


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def plugins_page() -> str:
    from rollingstar.pipelines.plugin_docs import parameters, summary
    from rollingstar.pipelines.registry import available_kinds, plugins_by_role

    kinds = {target: kind for kind, target in available_kinds().items()}
    lines = ["# Plugins", "", "Every registered plugin by role, with its parameters as a pipeline config sets them "
             "(`stages: - {kind: <kind>, params: {...}}`). The same tables print with `rollingstar plugins`; "
             "writing your own: [Writing a plugin](../plugins.md).", ""]
    for role, classes in plugins_by_role().items():
        lines += [f"## Role: {role}", ""]
        for cls in classes:
            kind = kinds.get(f"{cls.__module__}:{cls.__name__}", cls.name)
            lines += [f"### `{kind}`", "", summary(cls), "", f"Class: `{cls.__module__}.{cls.__name__}`", ""]
            params = parameters(cls)
            if not params:
                lines += ["No parameters.", ""]
                continue
            lines += ["| parameter | type | default | unit | meaning |", "| --- | --- | --- | --- | --- |"]
            lines += [f"| `{p.name}` | {_cell(p.type)} | `{_cell(p.default)}` | {p.unit} | {_cell(p.description)} |"
                      for p in params]
            lines.append("")
    return "\n".join(lines)


def _opening_comment(path: Path) -> str:
    """The comment lines a config file opens with, as one paragraph."""
    text = []
    for line in path.read_text().splitlines():
        if not line.startswith("#"):
            break
        text.append(line.lstrip("#").strip())
    return " ".join(t for t in text if t)


def configs_page() -> str:
    lines = ["# Shipped configs", "", "Every config in `configs/`, used by name on the command line "
             "(`rollingstar run baseline ...`) or by path. The description is the comment the file opens with.", ""]
    for folder, what in (("scenarios", "Scenarios (`rollingstar simulate`)"),
                         ("pipelines", "Pipelines (`rollingstar run`)"),
                         ("compare", "Comparisons (`rollingstar compare`)"),
                         ("cameras", "Cameras (`rollingstar import images --camera`)")):
        files = sorted((CONFIGS / folder).glob("*.yaml"))
        if not files:
            continue
        lines += [f"## {what}", "", "| name | description |", "| --- | --- |"]
        lines += [f"| `{f.stem}` | {_cell(_opening_comment(f)) or '-'} |" for f in files]
        lines.append("")
    return "\n".join(lines)


def write_reference_pages(folder: Path) -> list[Path]:
    """Write ``plugins.md`` and ``configs.md`` into ``folder`` (replaced when their text changed)."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in (("plugins.md", plugins_page()), ("configs.md", configs_page())):
        path = folder / name
        if not path.exists() or path.read_text() != text:  # unchanged pages keep Sphinx's cache valid
            path.write_text(text)
        written.append(path)
    return written
