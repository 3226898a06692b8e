"""The solver digest that stores and benchmark caches record follows the code an answer depends on."""
from __future__ import annotations

import shutil
from pathlib import Path

import solver
from solver.version import answer_modules, solver_digest

PACKAGE = Path(solver.__file__).parent


def _copy(tmp_path: Path) -> Path:
    copy = tmp_path / "solver"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    return copy


def test_the_digest_covers_the_unloading_and_what_it_imports_but_not_the_verification_problems():
    names = {p.name for p in answer_modules()}
    assert {"lv.py", "assembly.py", "material.py", "fibres.py", "adaptive.py", "meshing.py"} <= names
    assert "land_problems.py" not in names


def test_a_change_to_the_assembly_changes_the_digest_and_one_to_the_verification_problems_does_not(tmp_path):
    copy = _copy(tmp_path)
    before = solver_digest(copy)
    assert before == solver_digest()
    with open(copy / "land_problems.py", "a") as f:
        f.write("\n# a comment\n")
    assert solver_digest(copy) == before
    with open(copy / "assembly.py", "a") as f:
        f.write("\n# a comment\n")
    assert solver_digest(copy) != before
