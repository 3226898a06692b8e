"""Measure the code's structure against the rules in docs/architecture.md.

Prints import circles between modules (imports inside functions included), imports from a lower layer
up to a higher one, modules over 600 lines, functions over 80 lines, CLI commands over 40 lines, and
`--flag` text below cli.py. Exit status 1 when any rule is broken.

    .venv/bin/python scripts/architecture.py
"""

from __future__ import annotations

import ast
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("solver", "storage", "orchestrator", "trainer", "bench", "app")
LAYER = {"solver": 0, "storage": 1, "orchestrator": 2, "trainer": 2, "app": 3, "bench": 4, "cli": 5}
CLI_LAYER = ("cli", "app.terminal")  # the only code that names command-line flags


def layer(module: str) -> int:
    """A module's floor: its package's, except the command line's own modules (CLI_LAYER), at the top."""
    if module.startswith(CLI_LAYER):
        return LAYER["cli"]
    return LAYER[module.split(".")[0]]
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80
MAX_COMMAND_LINES = 40
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]+")


@dataclass
class Report:
    circles: list[list[str]] = field(default_factory=list)
    upward: list[str] = field(default_factory=list)
    long_modules: list[str] = field(default_factory=list)
    long_functions: list[str] = field(default_factory=list)
    long_commands: list[str] = field(default_factory=list)
    flag_text: list[str] = field(default_factory=list)

    def broken(self) -> bool:
        return any(getattr(self, name) for name in self.__dataclass_fields__)


def module_files(root: Path = ROOT) -> dict[str, Path]:
    """Module name → file, for every production module (tests and scripts excluded)."""
    files = {"cli": root / "cli.py"}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            files[name] = path
    return {name: path for name, path in files.items() if path.exists()}


def _imported(node: ast.AST, module: str, is_package: bool) -> list[str]:
    """Absolute names a single import statement refers to."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if not isinstance(node, ast.ImportFrom):
        return []
    if node.level:
        base = module.split(".")
        base = base if is_package else base[:-1]
        base = base[: len(base) - (node.level - 1)]
        prefix = ".".join(base + ([node.module] if node.module else []))
    else:
        prefix = node.module or ""
    return [prefix] + [f"{prefix}.{alias.name}" for alias in node.names]


def import_graph(files: dict[str, Path]) -> dict[str, set[str]]:
    """Module → the project modules it imports, at module level or inside functions."""
    graph: dict[str, set[str]] = {}
    for module, path in files.items():
        tree = ast.parse(path.read_text(), str(path))
        targets = set()
        for node in ast.walk(tree):
            for name in _imported(node, module, path.name == "__init__.py"):
                if name in files and name != module:
                    targets.add(name)
        graph[module] = targets
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    sys.setrecursionlimit(10_000)
    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """Imports from a lower layer to a higher one, or between the two layer-2 packages."""
    found = []
    for module, targets in graph.items():
        top = module.split(".")[0]
        for target in targets:
            target_top = target.split(".")[0]
            if layer(target) > layer(module) or (target_top != top and layer(module) == layer(target) == 2):
                found.append(f"{module} → {target}")
    return sorted(found)


def _function_lengths(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node, node.end_lineno - node.lineno + 1


def _is_command(node: ast.AST) -> bool:
    for decorator in getattr(node, "decorator_list", ()):
        call = decorator.func if isinstance(decorator, ast.Call) else decorator
        if isinstance(call, ast.Attribute) and call.attr == "command":
            return True
    return False


def _docstring_lines(tree: ast.AST) -> set[int]:
    """Line numbers inside module, class and function docstrings."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = getattr(node, "body", [])
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                if isinstance(body[0].value.value, str):
                    lines.update(range(body[0].lineno, body[0].end_lineno + 1))
    return lines


def flag_text(module: str, path: Path, tree: ast.AST, root: Path = ROOT) -> list[str]:
    """String constants below cli.py that name a command-line flag (docstrings and comments excluded)."""
    if module.startswith(CLI_LAYER):
        return []
    skip = _docstring_lines(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.lineno not in skip:
            match = FLAG.search(node.value)
            if match:
                found.append(f"{path.relative_to(root)}:{node.lineno} {match.group(0)}")
    return found


def measure(root: Path = ROOT) -> Report:
    files = module_files(root)
    graph = import_graph(files)
    report = Report(circles=circles(graph), upward=upward_imports(graph))
    for module, path in files.items():
        text = path.read_text()
        tree = ast.parse(text, str(path))
        where = path.relative_to(root)
        if text.count("\n") > MAX_MODULE_LINES:
            report.long_modules.append(f"{where}: {text.count(chr(10))} lines")
        for node, length in _function_lengths(tree):
            if length > MAX_FUNCTION_LINES:
                report.long_functions.append(f"{where}:{node.lineno} {node.name}: {length} lines")
            if module == "cli" and _is_command(node) and length > MAX_COMMAND_LINES:
                report.long_commands.append(f"{where}:{node.lineno} {node.name}: {length} lines")
        report.flag_text.extend(flag_text(module, path, tree, root))
    return report


def main() -> int:
    report = measure()
    for name in report.__dataclass_fields__:
        items = getattr(report, name)
        print(f"{name.replace('_', ' ')}: {len(items)}")
        for item in items:
            print(f"    {' ⇄ '.join(item) if isinstance(item, list) else item}")
    return 1 if report.broken() else 0


if __name__ == "__main__":
    sys.exit(main())
