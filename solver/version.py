"""A digest of the solver code that an LV answer depends on: stores and cached benchmark results record
it, so results of other solver code are recognised."""
from __future__ import annotations

import ast
import hashlib
from pathlib import Path

# the modules whose answers stores and benchmark caches hold: unloading (fixed-size and adaptive) and the
# built-in shapes and their meshes; the digest follows their imports within the package
ANSWER_MODULES = ("lv", "adaptive", "meshing", "shape_model")


def _package_imports(path: Path) -> set[str]:
    """Names of the sibling modules that a solver module imports (relative or `solver.x`), at any depth."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level == 1:
                names.update([node.module] if node.module else [a.name for a in node.names])
            elif node.level == 0 and node.module and node.module.startswith("solver."):
                names.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            names.update(a.name.split(".")[1] for a in node.names if a.name.startswith("solver."))
    return {n.split(".")[0] for n in names}


def answer_modules(package: Path | None = None) -> list[Path]:
    """The solver's source files an answer depends on: ANSWER_MODULES and everything they import within
    the package, sorted by name."""
    package = package or Path(__file__).parent
    seen, todo = set(), list(ANSWER_MODULES)
    while todo:
        name = todo.pop()
        path = package / f"{name}.py"
        if name in seen or not path.exists():
            continue
        seen.add(name)
        todo.extend(_package_imports(path) - seen)
    return sorted(package / f"{n}.py" for n in seen)


def solver_digest(package: Path | None = None) -> str:
    """First 12 hex digits of the SHA-256 over `answer_modules` (names and bytes): code the answers do not
    depend on (the verification problems, reports) leaves it unchanged."""
    h = hashlib.sha256()
    for p in answer_modules(package):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:12]
