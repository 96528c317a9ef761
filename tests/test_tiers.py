"""The quick tier (`pytest -m "not slow"`) reaches every module of hte_jax and experiments: some test file
that has a test not marked `slow` imports the module or a name it defines (at the file's top, in a
fixture or helper, or in such a test), or names it for a process it starts (`python -m experiments.x`);
tests/ helper modules such a file imports count as part of it. Read from the source, not by running."""

import ast
import importlib
import re
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hte_jax", "experiments")
MODULE = re.compile(r"(?:hte_jax|experiments|tests)(?:\.\w+)*")


def _modules() -> set[str]:
    found = set()
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            found.add(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return found


def _is_slow(marks) -> bool:
    """Whether `pytest.mark.slow` is among the marks (a parametrized case's own marks do not count)."""
    return any(ast.unparse(mark) == "pytest.mark.slow" for mark in marks)


def _module_slow(tree) -> bool:
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "pytestmark" for t in node.targets):
            return _is_slow(node.value.elts if isinstance(node.value, ast.List) else [node.value])
    return False


def _quick_parts(tree) -> list[ast.AST] | None:
    """The nodes of a test file that its quick tests may run: all but its slow tests; None if it has no quick test."""
    tests = [n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef)) and n.name.lower().startswith("test")]
    slow = set() if not _module_slow(tree) else set(tests)
    slow |= {n for n in tests if _is_slow(n.decorator_list)}
    if not set(tests) - slow:
        return None
    return [n for n in tree.body if n not in slow]


def _code(text: str) -> list[ast.AST]:
    """The statements of a string that is Python (a script a test runs), else none."""
    try:
        return ast.parse(textwrap.dedent(text)).body
    except (SyntaxError, ValueError):
        return []


def _uses(nodes) -> set[str]:
    """Modules the nodes import (a name imported from a module counts for the module that defines it), name as
    a string (`-m experiments.render`), or import in a string of Python (a script a test runs)."""
    used = set()
    for node in (n for top in nodes for n in ast.walk(top)):
        if isinstance(node, ast.Import):
            used |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            used.add(node.module)
            for alias in node.names:
                candidate = f"{node.module}.{alias.name}"
                try:
                    importlib.import_module(candidate)
                    used.add(candidate)
                except ImportError:
                    if node.module.split(".")[0] in PACKAGES:
                        value = getattr(importlib.import_module(node.module), alias.name, None)
                        used.add(getattr(value, "__module__", None) or node.module)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if MODULE.fullmatch(node.value):
                used.add(node.value)
            elif "import" in node.value:
                used |= _uses(_code(node.value))
    return used


def _quick_uses() -> set[str]:
    used, helpers, seen = set(), [], set()
    for path in sorted((ROOT / "tests").glob("test_*.py")):
        parts = _quick_parts(ast.parse(path.read_text()))
        if parts is not None:
            found = _uses(parts)
            used |= found
            helpers += [m for m in found if m.startswith("tests.")]
    while helpers:  # tests/ helpers (golden runs, scripts a test starts) reached from quick files
        name = helpers.pop()
        path = ROOT / (name.replace(".", "/") + ".py")
        if name in seen or not path.is_file():
            continue
        seen.add(name)
        found = _uses(ast.parse(path.read_text()).body)
        used |= found
        helpers += [m for m in found if m.startswith("tests.")]
    return used


def test_the_quick_tier_reaches_every_module():
    missing = sorted(_modules() - _quick_uses())
    assert not missing, f"no quick test file imports {missing}: add a test not marked slow, or remove the mark"
