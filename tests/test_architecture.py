"""The architecture as the import linter and DVC see it: the import contracts of pyproject.toml hold, fail on a
violating import, and name every module of the package; the code stage of dvc.yaml fingerprints the core and the
task's family and nothing else."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib
import yaml
from dvc.repo import Repo

from adaptdiffuser.config import apply_profile
from adaptdiffuser.tooling.code_fingerprint import PACKAGE_DIR, code_paths, core_paths, fingerprint

REPO = Path(__file__).resolve().parents[1]
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"
#: an import for type checking alone, of the module named by ``format``
TYPE_ONLY = "import typing\nif typing.TYPE_CHECKING:\n    import adaptdiffuser.{}"


def _lint(package_parent: Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``lint-imports`` with the project's contracts on the package found under ``package_parent``."""
    env = dict(os.environ, PYTHONPATH=str(package_parent))
    config = REPO / "pyproject.toml"
    cmd = [str(LINT_IMPORTS), "--config", str(config), "--no-cache"]
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)


def rel(path: str, root: Path) -> str:
    return Path(os.path.relpath(path, root)).as_posix()


def _contracts() -> list[dict]:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]


def test_the_import_contracts_hold() -> None:
    out = _lint(REPO / "src", REPO)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "0 broken" in out.stdout


@pytest.mark.parametrize(
    ("module", "line", "contract"),
    [
        ("contract.py", "import adaptdiffuser.evaluation", "The contract imports only what its types name"),
        ("config/tasks.py", "import adaptdiffuser.family_registry", "Config imports neither the family registry"),
        ("config/defaults.py", TYPE_ONLY.format("contract"), "the bottom layer"),
        ("config/sections.py", "import adaptdiffuser.families.maze2d.params", "Config imports neither"),
        ("evaluation.py", "import adaptdiffuser.stages.common", "never import the stages"),
        ("stages/summarize.py", "import adaptdiffuser.families.kuka.scene", "imported only inside its own folder"),
        ("families/kuka/tasks.py", "import adaptdiffuser.families.maze2d.layouts", "independent of each other"),
        ("io.py", "import adaptdiffuser.plots", "No import cycles"),
        ("planning.py", TYPE_ONLY.format("contract"), "No import cycles"),
    ],
)
def test_a_violating_import_breaks_its_contract(tmp_path: Path, module: str, line: str, contract: str) -> None:
    """The linter reads the package it is given: a copy with one bad import fails, naming the contract; imports for
    type checking alone count too."""
    shutil.copytree(PACKAGE_DIR, tmp_path / "adaptdiffuser", ignore=shutil.ignore_patterns("__pycache__"))
    target = tmp_path / "adaptdiffuser" / module
    target.write_text(target.read_text() + f"\n{line}  # a deliberate violation\n")
    out = _lint(tmp_path, tmp_path)
    assert out.returncode == 1, out.stdout + out.stderr
    broken = out.stdout.split("Broken contracts")[-1]
    assert contract in broken, out.stdout


def test_the_contracts_name_every_top_level_module() -> None:
    """A new top-level module must be placed in the architecture: the forbidden contracts list each one."""
    top = {
        f"adaptdiffuser.{p.stem}"
        for p in PACKAGE_DIR.iterdir()
        if (p.suffix == ".py" and p.stem != "__init__") or (p.is_dir() and (p / "__init__.py").exists())
    }
    contracts = {c["name"]: c for c in _contracts()}
    bottom = [c for name, c in contracts.items() if name.startswith("Config, the file layout and the file helpers")][0]
    assert set(bottom["source_modules"]) | set(bottom["forbidden_modules"]) == top
    contract = [c for name, c in contracts.items() if name.startswith("The contract imports only")][0]
    below_contract = {"config", "data", "planning", "layout", "checkpoint", "diffusion", "models", "io"}
    allowed = {f"adaptdiffuser.{name}" for name in below_contract}
    assert set(contract["forbidden_modules"]) == top - allowed - {"adaptdiffuser.contract"}
    core = [c for name, c in contracts.items() if name.startswith("The core and the families never import")][0]
    assert set(core["source_modules"]) | set(core["forbidden_modules"]) == top
    internals = contracts["A family's internals are imported only inside its own folder"]
    assert set(internals["source_modules"]) == top - {"adaptdiffuser.families"}
    families = {f"adaptdiffuser.families.{p.name}" for p in (PACKAGE_DIR / "families").iterdir() if p.is_dir()}
    families.discard("adaptdiffuser.families.__pycache__")
    assert set(internals["forbidden_modules"]) == families
    assert set(contracts["The families are independent of each other"]["modules"]) == families


def test_the_code_stage_depends_on_the_core_and_the_task_family_only(tmp_path: Path) -> None:
    """On the smoke profile (a task of every family), as DVC resolves dvc.yaml: code@<task> lists the core and its
    family's folder; every other stage of the task lists no project code but its stage script and fingerprint."""
    for name in ["dvc.yaml", "profiles"]:
        src = REPO / name
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, tmp_path / name)
    apply_profile("smoke", tmp_path / "profiles", tmp_path / "params.yaml")
    families = {
        name: entry["family"] for name, entry in yaml.safe_load((tmp_path / "params.yaml").read_text())["task"].items()
    }
    assert sorted(set(families.values())) == ["kuka", "locomotion", "maze2d"]
    with Repo.init(str(tmp_path), no_scm=True) as repo:
        stages = {stage.name: stage for stage in repo.index.stages}
        deps = {
            name: [
                Path(os.path.relpath(d.fs_path, tmp_path)).as_posix()
                for d in s.deps
                if hasattr(d, "hash_info") and not d.__class__.__name__.startswith("Params")
            ]
            for name, s in stages.items()
        }
    for task, family in families.items():
        assert deps[f"code@{task}"] == ["pipeline/code.py", *code_paths(family)]
    for name, paths in deps.items():
        if name.startswith("code@") or name in ("summarize", "report"):
            continue
        code = [p for p in paths if p.startswith("src/")]
        assert code == [], f"{name} lists code beside its fingerprint: {code}"
        assert sum(p.startswith("code/") for p in paths) == 1, name
    assert core_paths() == code_paths("maze2d")[:-1]


def test_the_fingerprint_changes_with_the_family_code_only(tmp_path: Path) -> None:
    shutil.copytree(PACKAGE_DIR, tmp_path / "src/adaptdiffuser", ignore=shutil.ignore_patterns("__pycache__"))
    before = {family: fingerprint(tmp_path, family) for family in ("maze2d", "locomotion", "kuka")}
    scene = tmp_path / "src/adaptdiffuser/families/kuka/scene.py"
    scene.write_text(scene.read_text() + "# edited\n")
    after = {family: fingerprint(tmp_path, family) for family in ("maze2d", "locomotion", "kuka")}
    assert after["maze2d"] == before["maze2d"] and after["locomotion"] == before["locomotion"]
    assert after["kuka"] != before["kuka"]
    core = tmp_path / "src/adaptdiffuser/io.py"
    core.write_text(core.read_text() + "# edited\n")
    again = {family: fingerprint(tmp_path, family) for family in ("maze2d", "locomotion", "kuka")}
    assert all(again[family] != after[family] for family in again)
