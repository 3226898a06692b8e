"""The code's structure keeps the rules of docs/architecture.md (scripts/architecture.py measures them)."""
import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("architecture", ROOT / "scripts" / "architecture.py")
architecture = importlib.util.module_from_spec(spec)
sys.modules["architecture"] = architecture  # (its dataclasses look their module up)
spec.loader.exec_module(architecture)


def test_no_import_circles_and_no_import_up_a_layer():
    report = architecture.measure(ROOT)
    assert report.circles == [] and report.upward == []


def test_modules_functions_and_commands_stay_short():
    report = architecture.measure(ROOT)
    assert report.long_modules == [] and report.long_functions == [] and report.long_commands == []


def test_only_the_command_line_names_its_flags():
    assert architecture.measure(ROOT).flag_text == []


def test_the_measure_sees_a_circle_and_a_flag(tmp_path):
    """The checker itself: two modules importing each other are a circle; a `--flag` in a lower layer's
    string is found, one in cli.py is not."""
    (tmp_path / "solver").mkdir()
    (tmp_path / "solver" / "__init__.py").write_text("")
    (tmp_path / "solver" / "a.py").write_text("from . import b\nX = 'use --nodes 5'\n")
    (tmp_path / "solver" / "b.py").write_text("def f():\n    from .a import X\n")
    (tmp_path / "cli.py").write_text("from solver import a\nHELP = '--nodes'\n")
    report = architecture.measure(tmp_path)
    assert report.circles == [["solver.a", "solver.b"]]
    assert [f.split()[-1] for f in report.flag_text] == ["--nodes"] and "cli.py" not in report.flag_text[0]
