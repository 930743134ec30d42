"""Shared fixtures: a tiny model configuration, a real expert dataset collected in U-Maze, and the smoke project
after one `dvc repro` (built once per test session: its tests share one pytest-xdist worker)."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch
from deps_trace import traced_env
from smoke_project import make_smoke_project, run_tool, traces_dir

from adaptdiffuser.config import DiffusionParams, ModelParams, Params
from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.data.schema import Trajectories, make_metadata
from adaptdiffuser.data.windows import WindowDataset, joint_array
from adaptdiffuser.families.maze2d.expert import collect_expert_stream
from adaptdiffuser.families.maze2d.simulator import Maze2D
from adaptdiffuser.family_registry import get_family


def maze_sim(params: Params | None = None, task: str = "maze2d-umaze") -> Maze2D:
    """A fresh Maze2D simulator of ``task`` in ``params`` (default params: U-Maze), as the stages build it."""
    params = Params() if params is None else params
    resolved = params.resolve(task)
    return get_family(resolved.family).make_simulator(resolved)


@pytest.fixture(autouse=True)
def no_mlflow_run_left_active() -> Iterator[None]:
    """A test that leaves an MLflow run active in this process (MLflow starts one implicitly when something logs
    outside a run) fails at teardown, and the run is ended so the tests after it are not hit instead."""
    yield
    leaked = mlflow.active_run()
    if leaked is not None:
        mlflow.end_run()
        pytest.fail(f"the test left MLflow run {leaked.info.run_id} active (something logged outside a stage run)")


#: the quick tier (``-m "not slow"``) leaves out these modules and tests besides the e2e ones: what took longest in
#: the full run of 2026-12-06 (its junit durations on the 2-core AVX2-only EPYC: a module over about 20 s in all, a
#: test over about 4 s, fixture set-up included), so that the tier runs in minutes; rewrite from a new run's figures
#: when the suite changes
SLOW_MODULES: tuple[str, ...] = (
    "tests/test_compiled.py",
    "tests/test_pool.py",
    "tests/test_locomotion_pipeline.py",
    "tests/test_batch_independence.py",
    "tests/test_import_model.py",
    "tests/test_band.py",
    "tests/test_evolution_stages.py",
    "tests/test_training_seeds.py",
    "tests/test_sweep.py",
    "tests/test_sweep_load.py",
    "tests/test_mlflow_server.py",
    "tests/test_long_run.py",
)
SLOW_TESTS: tuple[str, ...] = (
    "tests/test_value.py::test_training_learns_a_value_of_the_first_state",
    "tests/test_import_export.py::test_dvc_import_stage_depends_on_the_external_file",
    "tests/test_repository.py::test_a_kept_model_scores_what_it_supports_on_its_evaluation_episodes",
    "tests/test_repository.py::test_kept_models_of_several_seeds_play_their_own_start_states_and_give_an_interval",
    "tests/test_checkpoint.py::test_a_training_process_stopped_by_sigterm_ends_by_it_with_its_resume_state_written",
)

#: session fixtures built once and shared by tests of several modules (the others are cheap to build twice)
SHARED_SESSION_FIXTURES = ("smoke_repo",)


def shared_fixture_group(item: pytest.Item) -> str | None:
    """The costly shared fixture an item uses, as an xdist group name: the smoke project (:func:`smoke_repo`), or the
    item's module when it uses a module-scoped fixture of its own. None for an item that uses neither."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return None
    for name in SHARED_SESSION_FIXTURES:
        if name in info.name2fixturedefs:
            return name
    for definitions in info.name2fixturedefs.values():
        definition = definitions[-1]
        if definition.scope == "module" and definition.baseid and "conftest" not in definition.baseid:
            return definition.baseid
    return None


@pytest.hookimpl(tryfirst=True)  # before ``-m`` selects: the quick tier's ``-m "not slow"`` sees the added marks
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """End-to-end tests are slow tests. Tests that share a costly fixture run in one pytest-xdist worker
    (``--dist loadgroup`` in scripts/test.sh), so it is built once per session rather than once in each worker; the
    smoke project's tests go first, so that the longest group does not start last, then the other slow tests, so
    that the quick ones fill the workers' last minutes instead of a long test running alone at the end."""
    groups: dict[str, str | None] = {}
    for item in items:
        module = item.nodeid.split("::", 1)[0]
        if (
            item.get_closest_marker("e2e") is not None
            or module in SLOW_MODULES
            or item.nodeid.split("[", 1)[0] in SLOW_TESTS
        ):
            item.add_marker(pytest.mark.slow)  # left out of the quick tier (-m "not slow")
        groups[item.nodeid] = group = shared_fixture_group(item)
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
    items.sort(  # stable: the collection order is kept within each part
        key=lambda item: (groups[item.nodeid] != SHARED_SESSION_FIXTURES[0], item.get_closest_marker("slow") is None)
    )


def _group_suffix(item: pytest.Item) -> str:
    """The suffix pytest-xdist gives the id of an item marked ``xdist_group`` (its groups' names, sorted, joined by
    ``_``); empty for an item with no group."""
    names = sorted({mark.args[0] if mark.args else mark.kwargs.get("name", "default") for mark in
                    item.iter_markers("xdist_group")})  # fmt: skip
    return f"@{'_'.join(names)}" if names else ""


class GroupCheck:
    """Fails the run when ``--dist loadgroup`` would not keep a group in one worker. pytest-xdist passes a test's
    group to its scheduler as an ``@group`` suffix of the test's id; pytest 9.2 ignores the way xdist 3.8 sets it
    (pytest-xdist#1386), so the groups were silently spread over the workers and each built the smoke project
    (requirements-dev.lock pins pytest below 9.2 for this). A plugin of its own, as a conftest holds one hook
    function of each name."""

    @pytest.hookimpl(trylast=True)  # after pytest-xdist's own hook, which adds the suffix
    def pytest_collection_modifyitems(self, config: pytest.Config, items: list[pytest.Item]) -> None:
        if not getattr(config.option, "loadgroup", False):  # set in the xdist workers of a loadgroup run only
            return
        lost = [item.nodeid for item in items if (group := _group_suffix(item)) and not item.nodeid.endswith(group)]
        if lost:
            message = (
                f"--dist loadgroup does not group here ({lost[0]} has no @group suffix): this pytest and pytest-xdist "
                "spread grouped tests over workers (pytest-xdist#1386); install the pytest requirements-dev.lock pins"
            )
            print(f"error: {message}", file=sys.__stderr__)  # xdist reports the worker's error without its text
            raise pytest.UsageError(message)


def pytest_configure(config: pytest.Config) -> None:
    config.pluginmanager.register(GroupCheck(), "group-check")
    # Tiny networks run fastest on one thread; extra intra-op threads only contend with other work on the machine:
    # the tests run in one pytest-xdist worker per core (scripts/test.sh), and the stages, `dvc` and sweep workers
    # they start inherit one thread too.
    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")


@pytest.fixture
def umaze() -> Maze2D:
    """A fresh U-Maze simulator with the default params."""
    return maze_sim()


@pytest.fixture(scope="session")
def tiny_model_params() -> ModelParams:
    return ModelParams(dim=8, dim_mults=[1, 2], kernel_size=5)


@pytest.fixture(scope="session")
def tiny_diffusion_params() -> DiffusionParams:
    return DiffusionParams(horizon=16, n_steps=8)


@pytest.fixture(scope="session")
def expert_traj() -> Trajectories:
    """About 3000 steps of the real waypoint expert in U-Maze, cut into episodes as the collect stage does."""
    env = maze_sim()
    traj = collect_expert_stream(env, steps=3000, seed=0, progress=False)
    traj.metadata = make_metadata("maze2d-umaze", env.obs_dim, env.act_dim, "expert", {"steps": 3000})
    return traj


@pytest.fixture(scope="session")
def normalizer(expert_traj: Trajectories) -> MinMaxNormalizer:
    """The min/max normalizer of :func:`expert_traj`."""
    return MinMaxNormalizer.fit(joint_array(expert_traj))


@pytest.fixture(scope="session")
def dataset(expert_traj: Trajectories, normalizer: MinMaxNormalizer) -> WindowDataset:
    """Training windows of 16 steps over :func:`expert_traj`."""
    return WindowDataset(expert_traj, 16, normalizer)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def smoke_repo(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A temporary git + DVC repository holding the project on the smoke profile, after one traced `dvc repro`
    (its stage traces in :func:`smoke_project.traces_dir`). Tests that change it restore it, or work on a copy."""
    root = make_smoke_project(tmp_path_factory.mktemp("project"), run_tool)
    run_tool(["dvc", "repro"], root, **traced_env(traces_dir(root)))
    return root
