"""Importing D4RL and Minari data, and exporting ours to Minari, on inputs made here with the real tools: D4RL-layout
HDF5 files written with h5py from rollouts of our environments, Minari datasets recorded with ``minari.DataCollector``
on real gymnasium environments (never a download)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
import yaml
from deps_trace import check_stage, dvc_stages, load_traces, traced_env
from typer.testing import CliRunner

from adaptdiffuser.cli import app
from adaptdiffuser.config import ConfigError, Params, apply_profile, params_from_dict
from adaptdiffuser.data.d4rl import DataImportError, read_d4rl, write_d4rl
from adaptdiffuser.data.minari_io import read_minari
from adaptdiffuser.data.schema import make_metadata, read_trajectories, write_trajectories
from adaptdiffuser.families.locomotion.simulator import LocomotionSimulator
from adaptdiffuser.families.maze2d.external import (
    d4rl_position_to_xy,
    d4rl_vector_to_xy,
    our_observation_to_d4rl,
    xy_to_d4rl_position,
    xy_vector_to_d4rl,
)
from adaptdiffuser.families.maze2d.layouts import MAZES, parse_layout
from adaptdiffuser.families.maze2d.simulator import Maze2D
from adaptdiffuser.layout import collect_dir, dataset_path
from adaptdiffuser.stages.import_data import run_import
from adaptdiffuser.stages.pretrain import run_pretrain

minari = pytest.importorskip("minari")

REPO = Path(__file__).resolve().parents[1]
MAZE, HOPPER = "maze2d-umaze", "hopper-medium"


@pytest.fixture(autouse=True)
def _isolated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))


def smoke_params(tmp_path: Path, imports: dict[str, dict]) -> Params:
    """The smoke profile with ``imports`` (its tasks taken off ``collect_tasks``)."""
    raw = yaml.safe_load(apply_profile("smoke", REPO / "profiles", tmp_path / "params.yaml").read_text())
    raw["imports"] = imports
    raw["collect_tasks"] = [t for t in raw["tasks"] if t not in imports]
    return params_from_dict(raw)


# -- inputs made here -----------------------------------------------------------------------------------------------


def maze_rollout(steps: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Our U-Maze expert as D4RL records it: one stream, a new random goal cell whenever one is reached, in OUR
    coordinates (obs, actions, goal per step)."""
    env = Maze2D(parse_layout(MAZES["umaze"]), name="umaze")
    rng = np.random.default_rng(seed)
    free = env.layout.free_cells
    obs = env.reset(rng)
    env.set_goal(free[rng.integers(len(free))])
    rows: dict[str, list] = {"obs": [], "act": [], "goal": []}
    for _ in range(steps):
        if np.linalg.norm(obs[:2] - env.goal_xy) <= env.goal_radius:
            env.set_goal(free[rng.integers(len(free))])
        action = env.expert_action(obs)
        rows["obs"].append(obs)
        rows["act"].append(action)
        rows["goal"].append(env.goal_xy.copy())
        obs = env.step(action).observation
    return {key: np.asarray(values) for key, values in rows.items()}


def maze_d4rl_file(path: Path, steps: int = 600) -> tuple[Path, dict[str, np.ndarray]]:
    """A D4RL Maze2D file (D4RL's coordinates, infos/goal, qpos, qvel) of our expert's stream."""
    ours = maze_rollout(steps)
    layout = parse_layout(MAZES["umaze"])
    obs = our_observation_to_d4rl(layout, ours["obs"])
    n = len(obs)
    write_d4rl(
        path,
        {
            "observations": obs.astype(np.float32),
            "actions": xy_vector_to_d4rl(ours["act"]).astype(np.float32),
            "rewards": np.zeros(n, dtype=np.float32),
            "terminals": np.zeros(n, dtype=bool),
            "timeouts": np.zeros(n, dtype=bool),
            "qpos": obs[:, :2],
            "qvel": obs[:, 2:],
            "goal": xy_to_d4rl_position(layout, ours["goal"]),
        },
    )
    return path, ours


def hopper_d4rl_file(path: Path, steps: int = 300) -> tuple[Path, dict[str, np.ndarray]]:
    """A D4RL locomotion file of Hopper-v5 under random actions (terminals at falls, timeouts every 100 steps)."""
    sim = LocomotionSimulator("Hopper-v5")
    rng = np.random.default_rng(0)
    rows: dict[str, list] = {k: [] for k in ("observations", "actions", "rewards", "terminals", "timeouts", "state")}
    obs, t = sim.reset(rng), 0
    for _ in range(steps):
        action = rng.uniform(-1, 1, sim.act_dim)
        state = sim.get_state()
        step = sim.step(action)
        t += 1
        timeout = t == 100 and not step.terminated
        for key, value in zip(rows, (obs, action, step.reward, step.terminated, timeout, state), strict=True):
            rows[key].append(value)
        obs = step.observation
        if step.terminated or timeout:
            obs, t = sim.reset(rng), 0
    arrays = {key: np.asarray(values) for key, values in rows.items()}
    state = arrays.pop("state")
    write_d4rl(path, {**arrays, "qpos": state[:, : sim.nq], "qvel": state[:, sim.nq :]})
    return path, {**arrays, "state": state}


def collect_minari(dataset_id: str, env_id: str, steps: int, seed: int = 0) -> Path:
    """A Minari dataset recorded with ``minari.DataCollector`` on the real env ``env_id`` under random actions."""
    import gymnasium_robotics  # noqa: F401  (registers PointMaze)

    env = minari.DataCollector(gym.make(env_id, max_episode_steps=100))
    env.reset(seed=seed)
    env.action_space.seed(seed)
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
    env.create_dataset(dataset_id=dataset_id, algorithm_name="random", description="test data")
    env.close()
    return Path(minari.load_dataset(dataset_id).spec.data_path).parent


# -- the maze conversion --------------------------------------------------------------------------------------------


def test_d4rl_maze_coordinates_match_our_cells() -> None:
    layout = parse_layout(MAZES["umaze"])
    env = Maze2D(layout, name="umaze")
    # U-Maze: D4RL's (1, 1) (x = row, y = column) is our (-1, 1)
    assert np.allclose(d4rl_position_to_xy(layout, np.array([1.0, 1.0])), [-1.0, 1.0])
    for cell in layout.free_cells:  # every cell centre, by our env's own geometry
        assert np.allclose(d4rl_position_to_xy(layout, np.array(cell, dtype=float)), env.cell_to_xy(cell))
        assert np.allclose(xy_to_d4rl_position(layout, env.cell_to_xy(cell)), cell)
    large = parse_layout(MAZES["large"])  # not square: width 12, height 9
    big = Maze2D(large, name="large")
    assert np.allclose(d4rl_position_to_xy(large, np.array([7.0, 9.0])), big.cell_to_xy((7, 9)))
    # moving along a row (D4RL +y) is our +x; down the rows (D4RL +x) is our -y
    assert np.allclose(d4rl_vector_to_xy(np.array([0.0, 1.0])), [1.0, 0.0])
    assert np.allclose(d4rl_vector_to_xy(np.array([1.0, 0.0])), [0.0, -1.0])
    v = np.random.default_rng(0).normal(size=(5, 2))
    assert np.allclose(xy_vector_to_d4rl(d4rl_vector_to_xy(v)), v)


def test_d4rl_maze_file_imports_in_our_coordinates_and_replays(tmp_path: Path) -> None:
    path, ours = maze_d4rl_file(tmp_path / "maze2d-umaze-v1.hdf5")
    raw = read_d4rl(path)
    changes = int(np.any(ours["goal"][1:] != ours["goal"][:-1], axis=1).sum())
    assert raw.episode_end.sum() == changes + 1  # one stream, cut where the goal changes
    params = smoke_params(tmp_path, {MAZE: {"format": "d4rl", "path": str(path)}})
    out = run_import(params, MAZE, tmp_path, progress=False)
    traj = read_trajectories(out, env=MAZE)
    assert np.allclose(traj.observation, ours["obs"], atol=1e-5)
    assert np.allclose(traj.action, ours["act"], atol=1e-6)
    assert len(traj.episodes()) == changes + 1 and traj.timeout.sum() == changes + 1
    # the converted actions drive our simulator from each converted state to the next one
    env = Maze2D(parse_layout(MAZES["umaze"]), name="umaze")
    for t in (0, 50, 200):
        env.set_state(traj.observation[t].astype(np.float64))
        nxt = env.step(traj.action[t].astype(np.float64)).observation
        assert np.allclose(nxt, traj.observation[t + 1], atol=1e-4)
    summary = json.loads((tmp_path / collect_dir(MAZE) / "import.json").read_text())
    assert summary["imported"] and summary["format"] == "d4rl" and summary["steps"] == len(traj)
    assert traj.metadata["generator"]["source_sha256"] == summary["source_sha256"]

    # a smoke pretrain on the imported data
    models = run_pretrain(params, MAZE, tmp_path, torch.device("cpu"), progress=False)
    assert any(Path(models).rglob("*.pt"))


def test_import_refuses_data_that_does_not_fit_the_task(tmp_path: Path) -> None:
    hopper, _ = hopper_d4rl_file(tmp_path / "hopper.hdf5", steps=50)
    params = smoke_params(tmp_path, {MAZE: {"format": "d4rl", "path": str(hopper)}})
    with pytest.raises(DataImportError) as err:
        run_import(params, MAZE, tmp_path, progress=False)
    message = str(err.value)
    assert len(message.splitlines()) == 1 and str(hopper) in message
    assert "'observations' has dimension 11, expected 4" in message
    # maze data given to the hopper task
    maze, _ = maze_d4rl_file(tmp_path / "maze.hdf5", steps=50)
    params = smoke_params(tmp_path, {HOPPER: {"format": "d4rl", "path": str(maze)}})
    with pytest.raises(DataImportError, match="'observations' has dimension 4, expected 11"):
        run_import(params, HOPPER, tmp_path, progress=False)
    # a missing field is named
    write_d4rl(tmp_path / "bad.hdf5", {"observations": np.zeros((3, 4)), "actions": np.zeros((3, 2))})
    with pytest.raises(DataImportError, match="field 'rewards' is missing"):
        read_d4rl(tmp_path / "bad.hdf5")


def test_d4rl_hopper_file_keeps_the_full_state(tmp_path: Path) -> None:
    path, data = hopper_d4rl_file(tmp_path / "hopper-medium-v2.hdf5")
    params = smoke_params(tmp_path, {HOPPER: {"format": "d4rl", "path": str(path)}})
    traj = read_trajectories(run_import(params, HOPPER, tmp_path, progress=False), env=HOPPER)
    assert np.array_equal(traj.sim_state, data["state"])
    assert np.allclose(traj.observation, data["observations"], atol=1e-5)
    ends = data["terminals"] | data["timeouts"]
    ends[-1] = True
    assert len(traj.episodes()) == int(ends.sum()) and traj.terminal.sum() == data["terminals"].sum()


# -- Minari ---------------------------------------------------------------------------------------------------------


def test_minari_pointmaze_imports_by_path_and_by_id(tmp_path: Path) -> None:
    folder = collect_minari("test/pointmaze-umaze-v0", "PointMaze_UMaze-v3", steps=250)
    expected = minari.load_dataset("test/pointmaze-umaze-v0")
    obs = np.concatenate([ep.observations["observation"][:-1] for ep in expected.iterate_episodes()])
    act = np.concatenate([ep.actions for ep in expected.iterate_episodes()])
    for source in (str(folder), "test/pointmaze-umaze-v0"):
        raw = read_minari(source)
        assert {"achieved_goal", "desired_goal"} <= set(raw.parts)
        params = smoke_params(tmp_path, {MAZE: {"format": "minari", "path": source}})
        traj = read_trajectories(run_import(params, MAZE, tmp_path, progress=False), env=MAZE)
        assert np.allclose(traj.observation, obs, atol=1e-6) and np.allclose(traj.action, act, atol=1e-6)
        assert len(traj.episodes()) == expected.total_episodes


def test_minari_hopper_rebuilds_states_from_observations(tmp_path: Path) -> None:
    collect_minari("test/hopper-random-v0", "Hopper-v5", steps=200)
    params = smoke_params(tmp_path, {HOPPER: {"format": "minari", "path": "test/hopper-random-v0"}})
    traj = read_trajectories(run_import(params, HOPPER, tmp_path, progress=False), env=HOPPER)
    sim = LocomotionSimulator("Hopper-v5")
    for t in (0, 37, 150):  # the rebuilt state gives back the observation
        assert np.allclose(sim.set_state(traj.sim_state[t]), traj.observation[t], atol=1e-5)


# -- export ---------------------------------------------------------------------------------------------------------


def test_export_to_minari_round_trips_expert_and_selected_data(tmp_path: Path, monkeypatch) -> None:
    path, _ = maze_d4rl_file(tmp_path / "maze.hdf5", steps=300)
    params = smoke_params(tmp_path, {MAZE: {"format": "d4rl", "path": str(path)}})
    expert = run_import(params, MAZE, tmp_path, progress=False)
    traj = read_trajectories(expert)
    # a synthetic "selected" file of phase 1 (the discriminator's output path)
    selected = tmp_path / "data" / MAZE / "phase1" / "selected" / "seed0.parquet"
    traj.metadata = make_metadata(MAZE, 4, 2, "synthetic", {"phase": 1, "recipe": "plans"})
    write_trajectories(selected, traj)

    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    store = tmp_path / "store"
    for data, dataset_id in ((expert, "adaptdiffuser/umaze-expert-v0"), (selected, "adaptdiffuser/umaze-phase1-v0")):
        args = ["export-minari", str(data), "--task", MAZE, "--dataset-id", dataset_id, "--path", str(store)]
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
        again = runner.invoke(app, args)  # an existing id is refused without --force
        assert again.exit_code == 2 and "--force" in again.output
        assert runner.invoke(app, [*args, "--force"]).exit_code == 0

        monkeypatch.setenv("MINARI_DATASETS_PATH", str(store))
        loaded = minari.load_dataset(dataset_id)
        source = read_trajectories(data)
        episodes = [rows for rows in source.episodes() if rows.stop - rows.start > 1]
        assert loaded.total_episodes == len(episodes)
        for rows, ep in zip(episodes, loaded.iterate_episodes(), strict=True):
            assert np.allclose(ep.observations, source.observation[rows])
            assert np.allclose(ep.actions, source.action[rows][:-1])
        description = loaded.storage.metadata["description"]
        assert (
            loaded.spec.env_spec.id == "PointMaze_UMaze-v3"
            and MAZE in description
            and source.metadata["source"] in description
        )
        assert loaded.observation_space.shape == (4,)
        # and it reads back: each episode's observations the actions were taken at
        raw = read_minari(str(store / dataset_id))
        kept = np.concatenate([source.observation[rows][:-1] for rows in episodes])
        assert np.allclose(raw.observations, kept) and raw.metadata["dataset_id"] == dataset_id


# -- params ---------------------------------------------------------------------------------------------------------


def test_imports_and_collect_tasks_are_checked(tmp_path: Path) -> None:
    raw = yaml.safe_load((REPO / "params.yaml").read_text())
    ok = params_from_dict(raw | {"collect_tasks": [], "imports": {MAZE: {"format": "minari", "path": "/x"}}})
    assert ok.collect_tasks == () and ok.imports[MAZE].format == "minari"
    cases = [
        ({"imports": {MAZE: {"format": "csv", "path": "/x"}}, "collect_tasks": []}, "imports.maze2d-umaze.format"),
        ({"imports": {MAZE: {"format": "d4rl", "path": 3}}, "collect_tasks": []}, "imports.maze2d-umaze.path"),
        ({"imports": {MAZE: {"format": "d4rl", "path": "/x"}}}, "collect_tasks: 'maze2d-umaze' is imported"),
        ({"collect_tasks": []}, "collect_tasks: 'maze2d-umaze' of tasks has no data source"),
        ({"collect_tasks": [MAZE, HOPPER]}, "collect_tasks: 'hopper-medium' is not one of tasks"),
    ]
    for overlay, start in cases:
        with pytest.raises(ConfigError) as err:
            params_from_dict(raw | overlay)
        assert str(err.value).startswith(start) and len(str(err.value).splitlines()) == 1, str(err.value)


def test_set_writes_an_import_in_one_command(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text((REPO / "params.yaml").read_text())
    result = CliRunner().invoke(
        app,
        ["set", "collect_tasks=[]", "imports={maze2d-umaze: {format: d4rl, path: /data/maze2d-umaze-v1.hdf5}}",
         "--params", str(params)],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    loaded = params_from_dict(yaml.safe_load(params.read_text()))
    assert loaded.imports[MAZE].path == "/data/maze2d-umaze-v1.hdf5" and loaded.collect_tasks == ()


# -- DVC ------------------------------------------------------------------------------------------------------------


@pytest.mark.e2e
def test_dvc_import_stage_depends_on_the_external_file(tmp_path: Path) -> None:
    from smoke_project import make_smoke_project

    traces = tmp_path / "traces"

    def run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess:
        out = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=os.environ | traced_env(traces))
        assert out.returncode == 0, f"{cmd}: {out.stdout}\n{out.stderr}"
        return out

    data, _ = maze_d4rl_file(tmp_path / "external" / "maze2d-umaze-v1.hdf5", steps=300)

    def edit(params_path: Path) -> None:
        raw = yaml.safe_load(params_path.read_text())
        raw["imports"] = {MAZE: {"format": "d4rl", "path": str(data)}}
        raw["collect_tasks"] = [t for t in raw["tasks"] if t != MAZE]
        params_path.write_text(yaml.safe_dump(raw, sort_keys=False))

    (tmp_path / "project").mkdir()
    root = make_smoke_project(tmp_path / "project", run, edit)
    stages = run(["dvc", "stage", "list", "--name-only"], root).stdout.split()
    assert f"import-data@{MAZE}" in stages and f"collect@{MAZE}" not in stages and f"collect@{HOPPER}" in stages
    run(["dvc", "repro", f"import-data@{MAZE}"], root)  # and the task's code fingerprint before it
    name = f"import-data@{MAZE}"  # dvc.yaml lists every module and file the stage used
    assert not check_stage(dvc_stages(root)[name], load_traces(traces)[name], root).missing
    assert read_trajectories(root / dataset_path(MAZE), env=MAZE).metadata["generator"]["format"] == "d4rl"
    assert "up to date" in run(["dvc", "status", f"import-data@{MAZE}"], root).stdout
    maze_d4rl_file(data, steps=310)  # the external file changes
    status = run(["dvc", "status", f"import-data@{MAZE}"], root).stdout
    assert "changed deps" in status and str(data) in status
