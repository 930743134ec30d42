"""The family registry and the dependency rule: the core reaches families only through base and registry."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from adaptdiffuser.families.base import Family, Simulator
from adaptdiffuser.families.registry import FAMILIES, get_family

SRC = Path(__file__).resolve().parents[1] / "src" / "adaptdiffuser"
ALLOWED = {"adaptdiffuser.families", "adaptdiffuser.families.base", "adaptdiffuser.families.registry"}


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


def test_core_modules_never_import_a_family_directly() -> None:
    offenders = []
    for path in SRC.rglob("*.py"):
        if "families" in path.relative_to(SRC).parts:
            continue
        for name in _imports(path):
            if name.startswith("adaptdiffuser.families") and name not in ALLOWED:
                offenders.append(f"{path.relative_to(SRC)} imports {name}")
    assert not offenders, offenders


def test_every_registered_family_loads_under_its_own_name() -> None:
    for name in FAMILIES:
        family = get_family(name)
        assert isinstance(family, Family) and family.name == name


def test_unknown_family_names_the_registered_ones() -> None:
    with pytest.raises(KeyError, match="registered families: .*locomotion"):
        get_family("quadcopter")


def test_locomotion_family_builds_the_simulator_of_a_task_name() -> None:
    family = get_family("locomotion")
    sim = family.make_simulator("walker2d-medium-replay")
    assert isinstance(sim, Simulator) and (sim.obs_dim, sim.act_dim) == (17, 6)
    obs = sim.reset(np.random.default_rng(0))
    assert obs.shape == (17,) and sim.get_state().shape == (sim.state_dim,)
    assert family.describe("walker2d-medium-replay") == {"env_id": "Walker2d-v5", "dataset": "medium-replay"}
    assert family.conditioning == "start" and family.normalizer_kind() == "gaussian"
    with pytest.raises(ValueError, match="unknown locomotion task"):
        family.make_simulator("hopper-expertish")
