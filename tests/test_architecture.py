"""The package's shape: one import name, layers that only import downwards, short functions.

(Lint and import order: ``ruff check``, run by ``make test`` before the tests.)

Layers, lowest first (a module may import its own sub-package and any lower layer, nothing else):

0. ``rollingstar.errors``, ``.progress``, ``.config``, ``.outputs``, ``._version``, ``.configs``: what every layer
   may use (error types, progress bars, reading YAML configs, writing outputs safely, the shipped configs);
1. ``rollingstar.sensors``: camera, timing, sky, motion, gyro, simulator, physics effects, scenario;
2. ``rollingstar.logs`` (the recording format) and ``rollingstar.estimators`` (the plugin roles and
   the diagnosis algorithm), side by side: neither imports the other;
3. ``rollingstar.pipelines``: configs, registry, runner, evaluation, comparison, diagnose command;
4. ``rollingstar.studies``: reproductions, figures, benchmarks, studies of real data;
5. ``rollingstar.api``, ``rollingstar.cli``, ``rollingstar.__main__`` and the package's own
   ``__init__`` (whose lazy attribute access loads the API).
"""
from __future__ import annotations

import ast
import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"rollingstar": "rollingstar", "sensors": "rollingstar.sensors", "estimators": "rollingstar.estimators",
           "logs": "rollingstar.logs", "pipelines": "rollingstar.pipelines", "studies": "rollingstar.studies",
           "configs": "rollingstar.configs"}
BARE = {"sensors", "estimators", "logs", "pipelines", "studies"}
LAYERS = {
    "rollingstar.errors": 0, "rollingstar.progress": 0, "rollingstar.config": 0, "rollingstar._version": 0,
    "rollingstar.outputs": 0,
    "rollingstar.configs": 0,
    "rollingstar.sensors": 1,
    "rollingstar.logs": 2, "rollingstar.estimators": 2,
    "rollingstar.pipelines": 3,
    "rollingstar.studies": 4,
    "rollingstar.api": 5, "rollingstar.cli": 5, "rollingstar.__main__": 5, "rollingstar": 5,
}
# The package's own modules (not its sub-packages) may import each other within their layer.
OWN_MODULES = {"rollingstar", "rollingstar.errors", "rollingstar.progress", "rollingstar.config", "rollingstar._version",
               "rollingstar.outputs",
               "rollingstar.api", "rollingstar.cli", "rollingstar.__main__"}
MAX_FUNCTION_LINES = 80
# Compiled kernels, kept whole on purpose: numba compiles one function, and splitting the loop
# nest would put a call (and its argument marshalling) inside the per-pixel loop.
LONG_FUNCTION_EXCEPTIONS = {"estimators/centroiders/window_kernel.py:centroid_windows_kernel"}


def _modules():
    """(dotted module name, path) of every Python module the package installs."""
    for folder, package in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            parts = parts[:-1] if parts[-1] == "__init__" else parts
            yield ".".join((package, *parts)), path


def _group(module: str) -> str:
    """The layer entry a module belongs to (its longest prefix in LAYERS)."""
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in LAYERS:
            return ".".join(parts[:n])
    raise AssertionError(f"{module} is in no layer: add it to LAYERS")


def _imports(module: str, path: Path):
    """Every project module ``path`` imports (also inside functions), absolute names."""
    is_package = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = module.split(".")[: len(module.split(".")) - node.level + (1 if is_package else 0)]
                base = ".".join([*anchor, *([base] if base else [])])
            for alias in node.names:
                yield f"{base}.{alias.name}" if _is_module(f"{base}.{alias.name}") else base


def _is_module(name: str) -> bool:
    return name in _MODULE_NAMES


_MODULES = list(_modules())
_MODULE_NAMES = {module for module, _ in _MODULES}


def test_no_module_imports_a_bare_top_level_folder():
    bad = [f"{path.relative_to(ROOT)}: import {name}" for module, path in _MODULES
           for name in _imports(module, path) if name.split(".")[0] in BARE]
    for path in sorted((ROOT / "tests").rglob("*.py")) + sorted((ROOT / "benchmarks").rglob("*.py")):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        bad += [f"{path.relative_to(ROOT)}: import {name}" for name in _imports(module, path)
                if name.split(".")[0] in BARE]
    assert not bad, "import through the rollingstar namespace:\n" + "\n".join(bad)


def test_layers_only_import_downwards():
    bad = []
    for module, path in _MODULES:
        own = _group(module)
        for name in _imports(module, path):
            if not name.startswith("rollingstar"):
                continue
            target = _group(name)
            same_room = target == own or {target, own} <= OWN_MODULES
            if not same_room and LAYERS[target] >= LAYERS[own]:
                bad.append(f"{module} (layer {LAYERS[own]}) imports {name} (layer {LAYERS[target]})")
    assert not bad, "\n".join(bad)


def test_pyproject_installs_every_package_folder():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(cfg["packages"])
    on_disk = {module for module, path in _MODULES if path.name == "__init__.py"}
    assert on_disk <= listed, f"packages missing from pyproject.toml: {sorted(on_disk - listed)}"
    mapping = cfg["package-dir"]
    assert {mapping[p] for p in FOLDERS.values()} == set(FOLDERS)


def test_functions_are_short():
    long = []
    for module, path in _MODULES:
        rel = path.relative_to(ROOT)
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
                length = node.end_lineno - first + 1
                if length > MAX_FUNCTION_LINES and f"{rel}:{node.name}" not in LONG_FUNCTION_EXCEPTIONS:
                    long.append(f"{rel}:{node.lineno} {node.name}: {length} lines")
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(long)


def test_no_development_history_in_code_or_user_docs():
    pattern = re.compile(r"\bissues? \d+\b|\bissue\d+\b", re.IGNORECASE)
    files = [p for p in ROOT.rglob("*") if p.suffix in (".py", ".md", ".yaml", ".toml")
             and not {".venv", ".git", "build"} & set(p.relative_to(ROOT).parts)]
    bad = [f"{p.relative_to(ROOT)}:{i}: {line.strip()[:100]}" for p in files
           for i, line in enumerate(p.read_text(errors="replace").splitlines(), 1) if pattern.search(line)]
    assert not bad, "explain the code, not its history:\n" + "\n".join(bad[:40])
