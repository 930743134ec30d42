"""One place per default: the config classes state every default, the quick profile (the base of every profile)
states only where it differs from them, ``adaptdiffuser check`` names the family keys a task entry leaves to the
defaults, and the config package has no import cycle (type-only imports included)."""

from __future__ import annotations

import ast
from pathlib import Path

import yaml
from typer.testing import CliRunner

from adaptdiffuser.cli import app
from adaptdiffuser.config import load_params
from adaptdiffuser.config.defaults import class_defaults, complete, family_defaults, unwritten

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "src" / "adaptdiffuser" / "config"


def leaves(tree: dict, prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for key, value in tree.items():
        if isinstance(value, dict) and value:
            out |= leaves(value, f"{prefix}{key}.")
        else:
            out[f"{prefix}{key}"] = value
    return out


def test_the_quick_profile_states_only_what_differs_from_the_class_defaults() -> None:
    quick = yaml.safe_load((REPO / "profiles" / "quick.yaml").read_text())
    defaults = leaves(complete({}))
    restated = [key for key, value in leaves(quick).items() if key in defaults and defaults[key] == value]
    assert restated == []
    # what it does change: its training recipe, planner, guidance, compiling, evolution sizes, phases and sweep
    assert {key for key in leaves(quick) if key in defaults} == {
        "task.maze2d-umaze.gold_coin.cases_per_kind",
        *(f"pretrain.{k}" for k in ("steps", "lr", "lr_schedule", "lr_warmup", "ema_decay", "checkpoint_every")),
        "planner.sampler_steps",
        "alpha",
        "compile.training",
        "evolution.generate.batch_size",
        "evolution.discriminate.top_k",
        "evolution.finetune.steps_fraction",
    }


def test_the_written_params_hold_every_default() -> None:
    """params.yaml writes every key the classes default, and every family key of its task entry."""
    raw = yaml.safe_load((REPO / "params.yaml").read_text())
    written = leaves(raw)
    open_mappings = {"phases", "sweep.space"}  # empty by default, written with their entries
    assert set(leaves(class_defaults())) - open_mappings <= set(written)
    assert unwritten(raw) == []
    assert leaves(family_defaults("maze2d")).keys() == leaves(raw["task"]["maze2d-umaze"]).keys()


def test_check_names_the_family_keys_a_task_entry_leaves_to_the_defaults(tmp_path: Path) -> None:
    raw = yaml.safe_load((REPO / "params.yaml").read_text())
    del raw["task"]["maze2d-umaze"]["env"]["goal_radius"], raw["task"]["maze2d-umaze"]["expert"]["p_gain"]
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    assert load_params(path) == load_params(REPO / "params.yaml")  # the same values: the family's defaults
    result = CliRunner().invoke(app, ["check", "--params", str(path)])
    assert result.exit_code == 0, result.output
    lines = [line for line in result.output.splitlines() if "defaults" in line]
    assert lines == [
        f"{path}: 2 task keys not written, taken from their family's defaults: "
        "task.maze2d-umaze.env.goal_radius=0.5, task.maze2d-umaze.expert.p_gain=10.0"
    ]
    complete_run = CliRunner().invoke(app, ["check", "--params", str(REPO / "params.yaml")])
    assert complete_run.exit_code == 0 and "not written" not in complete_run.output


def test_a_whole_section_left_out_is_named_key_by_key(tmp_path: Path) -> None:
    raw = {"task": {"hopper-medium": {"family": "locomotion", "guide": {"scale": 0.01}}}}
    missing = unwritten(raw)
    assert "task.hopper-medium.guide.n_samples=64" in missing and "task.hopper-medium.value.steps=200000" in missing
    assert not any(key.startswith("task.hopper-medium.guide.scale=") for key in missing)


def config_imports(path: Path) -> set[str]:
    """The modules of the config package that ``path`` imports anywhere (type-only and function-level included)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        else:
            continue
        found |= {n.split(".")[2] for n in names if n.startswith("adaptdiffuser.config.") and n.count(".") >= 2}
    return found & {p.stem for p in CONFIG.glob("*.py")}


def test_the_config_package_has_no_import_cycle() -> None:
    graph = {path.stem: config_imports(path) - {path.stem} for path in CONFIG.glob("*.py") if path.stem != "__init__"}
    assert "params" not in graph["tasks"]  # the cycle params <-> tasks is gone
    done: set[str] = set()

    def visit(module: str, chain: tuple[str, ...]) -> None:
        assert module not in chain, f"import cycle: {' -> '.join((*chain, module))}"
        if module in done:
            return
        for imported in sorted(graph.get(module, ())):
            visit(imported, (*chain, module))
        done.add(module)

    for module in sorted(graph):
        visit(module, ())
