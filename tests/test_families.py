"""The family registry: every family loads under its own name and fits the contract (the import rules between the
core and the families are import-linter contracts, tests/test_architecture.py)."""

from __future__ import annotations

import typing

import numpy as np
import pytest

from adaptdiffuser.config import Params, params_from_dict
from adaptdiffuser.config.family_settings import family_names, settings_model
from adaptdiffuser.config.tasks import GENERIC_SECTIONS, build_task
from adaptdiffuser.contract import Family, Simulator
from adaptdiffuser.data.normalizer import fit_normalizer
from adaptdiffuser.diffusion.conditions import CONDITIONINGS
from adaptdiffuser.families.maze2d.simulator import Maze2D
from adaptdiffuser.family_registry import FAMILIES, get_family, task_params_model

#: a task name of each family
TASK_OF = {"maze2d": "maze2d-umaze", "locomotion": "hopper-medium", "kuka": "kuka-stacking"}


def test_every_registered_family_loads_under_its_own_name() -> None:
    for name in FAMILIES:
        family = get_family(name)
        assert isinstance(family, Family) and family.name == name


def test_unknown_family_names_the_registered_ones() -> None:
    assert set(FAMILIES) == {"maze2d", "locomotion", "kuka"}
    with pytest.raises(KeyError, match=r"registered families: \['kuka', 'locomotion', 'maze2d'\]"):
        get_family("quadcopter")
    with pytest.raises(KeyError, match=r"registered families: \['kuka', 'locomotion', 'maze2d'\]"):
        task_params_model("quadcopter")


def test_the_registry_hands_config_each_family_settings_model() -> None:
    """Config imports no family: it knows the families only as the registry registered them."""
    assert family_names() == sorted(FAMILIES)
    for name in FAMILIES:
        assert settings_model(name) is task_params_model(name)
    with pytest.raises(KeyError, match=r"registered families: \['kuka', 'locomotion', 'maze2d'\]"):
        settings_model("quadcopter")


def test_each_family_is_typed_by_its_own_settings_model() -> None:
    """``Family[<its TASK_PARAMS>]``, so ``task.settings`` in a family's code has the family's own type."""
    for name in FAMILIES:
        bases = [b for b in type(get_family(name)).__orig_bases__ if typing.get_origin(b) is Family]
        assert [typing.get_args(b) for b in bases] == [(task_params_model(name),)], name
        task = build_task(TASK_OF[name], {"family": name}, {key: getattr(Params(), key) for key in GENERIC_SECTIONS})
        assert type(task.settings) is task_params_model(name)


def test_locomotion_family_builds_the_simulator_of_a_task_name() -> None:
    family = get_family("locomotion")
    sim = family.make_simulator("walker2d-medium-replay")
    assert isinstance(sim, Simulator) and (sim.obs_dim, sim.act_dim) == (17, 6)
    obs = sim.reset(np.random.default_rng(0))
    assert obs.shape == (17,) and sim.get_state().shape == (sim.state_dim,)
    assert sim.episode_steps == 1000
    task = params_from_dict(
        {
            "tasks": ["walker2d-medium-replay"],
            "unseen_tasks": [],
            "evolve": None,
            "task": {"walker2d-medium-replay": {"family": "locomotion", "episode_steps": 200}},
        }
    ).resolve("walker2d-medium-replay")
    assert family.describe(task) == {"env_id": "Walker2d-v5", "dataset": "medium-replay", "episode_steps": 200}
    assert family.make_simulator(task).episode_steps == 200  # the task's protocol length
    assert family.conditioning == "start" and family.normalizer_kind == "gaussian"
    assert family.uses_value_function is True
    with pytest.raises(ValueError, match="unknown locomotion task"):
        family.make_simulator("hopper-expertish")


def test_maze2d_family_builds_the_simulator_of_a_task() -> None:
    family = get_family("maze2d")
    assert family.conditioning == "start_goal" and family.normalizer_kind == "minmax"
    assert family.uses_value_function is False
    task = Params().resolve("maze2d-umaze")
    sim = family.make_simulator(task)
    assert isinstance(sim, Maze2D) and isinstance(sim, Simulator)
    assert (sim.obs_dim, sim.act_dim, sim.state_dim) == (4, 2, 4) and sim.episode_steps == 300
    assert sim.name == "umaze" and family.describe(task) == {"maze": "umaze", "episode_steps": 300}
    assert family.make_simulator(task) is not sim  # a fresh one each time


def test_every_family_declares_its_class_attributes() -> None:
    for name in FAMILIES:
        family = get_family(name)
        assert family.conditioning in CONDITIONINGS
        assert family.normalizer_kind in ("minmax", "gaussian")
        fit_normalizer(family.normalizer_kind, np.arange(12.0).reshape(6, 2))  # a kind the pipeline can fit
        assert isinstance(family.uses_value_function, bool)
        # the task model of its params entries declares it as its family
        assert task_params_model(name)().family == name
