"""benchmarks/ holds a few maintained benchmarks on the library's public contract (docs/studies.md keeps the
one-question studies that used to live there): at most 12 scripts, none importing a family's internals."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
MAX_SCRIPTS = 12
FORBIDDEN = "adaptdiffuser.families"


def scripts() -> list[Path]:
    """The Python scripts of benchmarks/ (the recipes folder holds YAML only)."""
    return sorted(BENCHMARKS.glob("*.py"))


def imported_modules(source: str) -> list[str]:
    """Every module a source imports, at any depth of the file (``from a import b`` gives ``a`` and ``a.b``, since
    ``b`` may be a submodule)."""
    modules = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            modules += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            modules.append(node.module)
            modules += [f"{node.module}.{alias.name}" for alias in node.names]
    return modules


def reaches_families(module: str) -> bool:
    return module == FORBIDDEN or module.startswith(FORBIDDEN + ".")


def test_at_most_twelve_scripts() -> None:
    names = [path.name for path in scripts()]
    assert names, "benchmarks/ holds no scripts"
    assert len(names) <= MAX_SCRIPTS, f"{len(names)} scripts in benchmarks/ (at most {MAX_SCRIPTS}): {names}"


@pytest.mark.parametrize("path", scripts(), ids=lambda path: path.name)
def test_no_family_internals(path: Path) -> None:
    bad = [m for m in imported_modules(path.read_text()) if reaches_families(m)]
    assert not bad, f"{path.name} imports {bad}: use adaptdiffuser.family_registry and the Family contract"


def test_the_check_sees_every_form_of_import() -> None:
    source = (
        "import adaptdiffuser.families.maze2d.simulator\n"
        "from adaptdiffuser import families\n"
        "def f():\n"
        "    from adaptdiffuser.families.kuka import params\n"
        "from adaptdiffuser.family_registry import get_family\n"
        "from .families import x\n"
    )
    found = [m for m in imported_modules(source) if reaches_families(m)]
    assert found == [
        "adaptdiffuser.families.maze2d.simulator",
        "adaptdiffuser.families",
        "adaptdiffuser.families.kuka",
        "adaptdiffuser.families.kuka.params",
    ]
