"""The shape of the code: the longest functions and the project imports made inside functions.

    python benchmarks/code_shape.py [--top 10] [ROOT]

Lengths count every line of a ``def`` from its first decorator to its last line, as a reader sees it.
"""
from __future__ import annotations

import argparse
import ast
from pathlib import Path

CODE_DIRS = ("rollingstar", "sensors", "estimators", "logs", "pipelines", "studies")
PROJECT = ("rollingstar", "sensors", "estimators", "logs", "pipelines", "studies")


def python_files(root: Path):
    for folder in CODE_DIRS:
        yield from sorted((root / folder).rglob("*.py"))


def function_lengths(root: Path) -> list[tuple[int, str]]:
    """(length in lines, ``path:line name``) of every function and method under the code folders."""
    rows = []
    for path in python_files(root):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
                rows.append((node.end_lineno - first + 1, f"{path.relative_to(root)}:{node.lineno} {node.name}"))
    return sorted(rows, reverse=True)


def imports_inside_functions(root: Path) -> int:
    """How many ``import`` statements of project modules stand inside a function body."""
    count = 0
    for path in python_files(root):
        for fn in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(fn):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                         else [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else [])
                count += any(n.split(".")[0] in PROJECT for n in names)
    return count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", nargs="?", default=Path(__file__).resolve().parents[1], type=Path)
    parser.add_argument("--top", type=int, default=10)
    args = parser.parse_args()
    print(f"{args.top} longest functions:")
    for length, where in function_lengths(args.root)[: args.top]:
        print(f"  {length:4d}  {where}")
    print(f"project imports inside functions: {imports_inside_functions(args.root)}")


if __name__ == "__main__":
    main()
