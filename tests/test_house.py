"""House rules a newcomer relies on: modules and classes a reader can hold, a README whose
Layout names every package and folder, a BENCHMARKS.md that opens with today's figures, and a
test suite that runs the same examples every time in CI."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FOLDERS = ("core", "cli", "device", "drivers", "sim", "calibration", "hostlink", "bench")
MAX_MODULE_LINES = 800
MAX_CLASS_LINES = 500


def _sources() -> list[Path]:
    return sorted(p for f in FOLDERS for p in (ROOT / f).rglob("*.py"))


def _kernel_share(tree: ast.Module, n_lines: int) -> float:
    """The share of a module's lines inside numba-compiled functions (``@njit``, ``@numba.njit``,
    ``@jit``, ``@vectorize``, with or without arguments)."""
    inside = 0
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            for d in node.decorator_list:
                name = ast.unparse(d.func if isinstance(d, ast.Call) else d)
                if name.split(".")[-1] in ("njit", "jit", "vectorize", "guvectorize"):
                    first = min([node.lineno] + [x.lineno for x in node.decorator_list])
                    inside += node.end_lineno - first + 1  # type: ignore[operator]
                    break
    return inside / max(n_lines, 1)


def test_no_module_over_800_lines_but_numba_kernels_and_no_class_over_500() -> None:
    long_modules, long_classes = [], []
    for p in _sources():
        text = p.read_text(encoding="utf-8")
        n = len(text.splitlines())
        tree = ast.parse(text)
        if n > MAX_MODULE_LINES and _kernel_share(tree, n) < 0.8:
            long_modules.append(f"{p.relative_to(ROOT)}: {n} lines")
        long_classes += [f"{p.relative_to(ROOT)}:{c.lineno} {c.name}: {c.end_lineno - c.lineno + 1} lines"
                         for c in ast.walk(tree) if isinstance(c, ast.ClassDef)
                         and c.end_lineno - c.lineno + 1 > MAX_CLASS_LINES]  # type: ignore[operator]
    assert long_modules == []
    assert long_classes == []
    # the measure sees what it polices: a file of kernels counts as one, a plain one does not
    kernels = ast.parse("import numba\n@numba.njit(cache=True)\ndef f(x):\n    return x\n")
    assert _kernel_share(kernels, 4) == 0.75
    assert _kernel_share(ast.parse("def f(x):\n    return x\n"), 2) == 0.0


def _layout_section() -> str:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    m = re.search(r"^## Layout\n(.*?)^## ", readme, re.S | re.M)
    assert m, "README.md has no Layout section"
    return m.group(1)


def test_the_readme_layout_names_every_package_and_folder() -> None:
    layout = _layout_section()
    named = set(re.findall(r"`([\w/]+/)`", layout))
    tops = {f"{p.name}/" for p in ROOT.iterdir() if p.is_dir() and not p.name.startswith(".")
            and p.name not in ("build", "dist", "state", "test-artifacts") and not p.name.endswith(".egg-info")}
    packages = {f"{p.parent.relative_to(ROOT).as_posix()}/" for f in FOLDERS for p in (ROOT / f).rglob("__init__.py")}
    missing = set()
    for folder in sorted(tops | packages):
        # a subpackage may be named by its path (device/formats/) or, within its parent's row, by its name (cuts/)
        if folder not in named and folder.split("/")[-2] + "/" not in named:
            missing.add(folder)
    assert missing == set()


def test_benchmarks_open_with_todays_figures() -> None:
    text = (ROOT / "BENCHMARKS.md").read_text(encoding="utf-8")
    first = text.split("\n## ", 2)[1]
    assert first.startswith("Today's figures")
    rows = [r for r in first.splitlines() if r.startswith("| ") and not r.startswith("| stage") and "---" not in r]
    assert len(rows) >= 20
    for r in rows:
        cells = [c.strip() for c in r.strip("|").split("|")]
        assert len(cells) == 6, r
        _stage, target, figure, met, when, command = cells
        assert target, r
        assert figure, r
        assert met, r
        assert re.match(r"20\d\d-\d\d-\d\d", when), r  # a date
        assert "`" in command, r  # the command (or test) that measures it


def test_hypothesis_runs_the_same_examples_every_time_in_ci() -> None:
    code = ("import conftest, hypothesis; s = hypothesis.settings.default; "
            "print(s.derandomize, s.deadline)")
    env = {**os.environ, "CI": "true"}
    env.pop("HYPOTHESIS_PROFILE", None)
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT / "tests", env=env, capture_output=True, text=True,
                       timeout=120, check=True)
    assert r.stdout.split() == ["True", "None"]
