"""Maze2D on the real MuJoCo PointMaze: geometry, the protocol, the expert, the tracker and custom layouts."""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np
import pytest
from conftest import maze_sim
from matplotlib.figure import Figure

from adaptdiffuser.config import Params, params_from_dict
from adaptdiffuser.families.maze2d.execution import PlanFollower
from adaptdiffuser.families.maze2d.layouts import EPISODE_STEPS, MAZES, parse_layout
from adaptdiffuser.families.maze2d.params import EnvParams, Maze2DTaskParams
from adaptdiffuser.families.maze2d.simulator import Maze2D, bfs_distances, resolve_layout, shortest_path
from adaptdiffuser.family_registry import get_family

CUSTOM = [
    "######",
    "#..#G#",
    "#....#",
    "#.##.#",
    "######",
]


def env_for(maze: str | None = None, layout: list[str] | None = None) -> Maze2D:
    task = Params().resolve("maze2d-umaze")
    env_params = dataclasses.replace(task.settings.env, maze=maze or task.settings.env.maze, layout=layout)
    task = dataclasses.replace(task, settings=dataclasses.replace(task.settings, env=env_params))
    return get_family("maze2d").make_simulator(task)


def reaches_goal(env: Maze2D, cell: tuple[int, int], seed: int) -> int | None:
    """Run the expert from ``cell`` for one protocol episode; the first step with reward 1, or None."""
    env.seed_expert(seed)
    obs = env.reset(np.random.default_rng(seed), cell=cell)
    for t in range(env.episode_steps):
        obs = env.step(env.expert_action(obs)).observation
        if env.reward(obs) == 1.0:
            return t
    return None


@pytest.mark.parametrize("maze", sorted(MAZES))
def test_cell_xy_round_trip_for_every_cell(maze: str) -> None:
    env = env_for(maze)
    rng = np.random.default_rng(0)
    for r in range(env.layout.height):
        for c in range(env.layout.width):
            xy = env.cell_to_xy((r, c))
            assert env.xy_to_cell(xy) == (r, c)
            # any point strictly inside the cell maps back to it
            assert env.xy_to_cell(xy + rng.uniform(-0.49, 0.49, size=2)) == (r, c)
    # cell centres are one unit apart, y grows upwards (row index grows downwards)
    np.testing.assert_allclose(env.cell_to_xy((1, 2)) - env.cell_to_xy((1, 1)), [1.0, 0.0])
    np.testing.assert_allclose(env.cell_to_xy((2, 1)) - env.cell_to_xy((1, 1)), [0.0, -1.0])


def test_umaze_geometry_and_protocol(umaze: Maze2D) -> None:
    np.testing.assert_allclose(umaze.cell_to_xy((1, 1)), [-1.0, 1.0])
    assert umaze.goal_cell == (1, 1)
    np.testing.assert_allclose(umaze.goal_xy, [-1.0, 1.0])
    np.testing.assert_allclose(umaze.goal_state(), [-1.0, 1.0, 0.0, 0.0])
    assert umaze.episode_steps == 300
    assert (umaze.obs_dim, umaze.act_dim) == (4, 2)
    assert len(umaze.layout.free_cells) == 7


@pytest.mark.parametrize(("maze", "goal", "steps"), [("medium", (6, 6), 600), ("large", (7, 9), 800)])
def test_builtin_goals_and_episode_lengths(maze: str, goal: tuple[int, int], steps: int) -> None:
    env = env_for(maze)
    assert env.goal_cell == goal and env.episode_steps == steps == EPISODE_STEPS[maze]


@pytest.mark.parametrize("maze", ["umaze", "medium"])
def test_expert_reaches_goal_from_every_free_cell(maze: str) -> None:
    env = env_for(maze)
    assert env.episode_steps == {"umaze": 300, "medium": 600}[maze]
    for cell in env.layout.free_cells:
        for seed in (0, 1):
            assert reaches_goal(env, cell, seed) is not None, f"expert never reached the goal from {cell}"


def test_expert_actions_are_bounded_and_stay_out_of_walls(umaze: Maze2D) -> None:
    umaze.seed_expert(0)
    obs = umaze.reset(np.random.default_rng(3), cell=(3, 1))
    for _ in range(200):
        action = umaze.expert_action(obs)
        assert action.shape == (2,) and np.all(np.abs(action) <= 1.0)
        obs = umaze.step(action).observation
        assert not umaze.in_wall(obs[:2])


def test_reward_is_one_within_goal_radius_only(umaze: Maze2D) -> None:
    g = umaze.goal_xy
    for offset, expected in [
        ((0.0, 0.0), 1.0),
        ((0.49, 0.0), 1.0),
        ((0.3, -0.3), 1.0),
        ((0.0, -0.51), 0.0),
        ((0.36, 0.36), 0.0),
        ((2.0, 0.0), 0.0),
    ]:
        for vel in ((0.0, 0.0), (3.0, -2.0)):
            assert umaze.reward(np.array([*(g + offset), *vel])) == expected, offset


def test_reset_near_free_cell_centre_and_reproducible(umaze: Maze2D) -> None:
    starts = []
    for seed in range(40):
        obs = umaze.reset(np.random.default_rng(seed))
        cell = umaze.xy_to_cell(obs[:2])
        assert cell in umaze.layout.free_cells
        assert np.max(np.abs(obs[:2] - umaze.cell_to_xy(cell))) <= 0.1 + 1e-9
        assert np.all(np.abs(obs[2:]) < 1.0)
        starts.append(cell)
    assert len(set(starts)) == len(umaze.layout.free_cells)  # 40 draws visit all 7 cells

    a = umaze.reset(np.random.default_rng(7))
    umaze.step(np.array([1.0, 1.0]))
    b = umaze.reset(np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, umaze.reset(np.random.default_rng(8)))

    fixed = umaze.reset(np.random.default_rng(0), cell=(3, 3))
    assert umaze.xy_to_cell(fixed[:2]) == (3, 3)


def test_set_state_reads_back_and_is_markov(umaze: Maze2D) -> None:
    state = np.array([0.3, -0.2, 0.5, -0.4])
    np.testing.assert_allclose(umaze.set_state(state), state, atol=1e-12)
    action = np.array([0.7, -0.3])
    first = umaze.step(action).observation
    assert not np.allclose(first, state)
    assert first[0] > state[0] and first[1] < state[1]  # it moves along its velocity
    umaze.set_state(np.array([-1.0, 1.0, 0.0, 0.0]))
    umaze.step(np.array([-1.0, 1.0]))
    umaze.set_state(state)
    np.testing.assert_allclose(umaze.step(action).observation, first, atol=1e-10)


def test_in_wall(umaze: Maze2D) -> None:
    for r in range(umaze.layout.height):
        for c in range(umaze.layout.width):
            assert umaze.in_wall(umaze.cell_to_xy((r, c))) == (umaze.layout.rows[r][c] == "#")
    assert umaze.in_wall(np.array([10.0, 0.0]))  # outside the maze
    assert umaze.in_wall(umaze.cell_to_xy((2, 1)))


def test_set_goal(umaze: Maze2D) -> None:
    umaze.set_goal((3, 1))
    np.testing.assert_allclose(umaze.goal_xy, umaze.cell_to_xy((3, 1)))
    assert umaze.reward(np.array([*umaze.cell_to_xy((3, 1)), 0, 0])) == 1.0
    assert umaze.reward(np.array([-1.0, 1.0, 0, 0])) == 0.0
    assert reaches_goal(umaze, (1, 1), seed=0) is not None
    with pytest.raises(ValueError, match="not a free cell"):
        umaze.set_goal((2, 1))


def test_shortest_path_in_umaze() -> None:
    layout = resolve_layout("umaze")
    assert shortest_path(layout, (3, 1), (1, 1)) == [(3, 1), (3, 2), (3, 3), (2, 3), (1, 3), (1, 2), (1, 1)]
    dist = bfs_distances(layout, (1, 1))
    assert set(dist) == set(layout.free_cells) and dist[(3, 1)] == 6


def test_custom_layout_works_without_new_code() -> None:
    layout = resolve_layout("umaze", CUSTOM)  # the layout wins over the maze name
    assert (layout.height, layout.width) == (5, 6)
    assert layout.goal_cell == (1, 4)
    assert len(layout.free_cells) == 9

    env = env_for(layout=CUSTOM)
    assert env.name == "custom" and env.episode_steps == 300
    np.testing.assert_allclose(env.goal_xy, [1.5, 1.0])
    custom = Maze2DTaskParams(env=EnvParams(layout=CUSTOM))
    assert custom.maze_name == "custom" and custom.episode_steps == 300
    for cell in layout.free_cells:
        assert reaches_goal(env, cell, seed=0) is not None, cell


def test_layout_without_goal_uses_last_free_cell() -> None:
    env = Maze2D(parse_layout(["#####", "#...#", "#####"]))
    assert env.goal_cell == (1, 3)


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        (["#####", "#G.#", "#####"], "same length"),
        (["#####", "#G.x#", "#####"], "unknown characters.*'x'"),
        (["#####", "#G...", "#####"], r"enclosed by walls; cell \(1, 4\)"),
        (["#####", "#G.G#", "#####"], "2 'G' cells"),
        (["###", "#G#", "###"], "at least two free cells"),
        ([], "non-empty"),
    ],
    ids=["ragged", "unknown-char", "open-border", "two-goals", "too-small", "empty"],
)
def test_bad_layouts_raise_helpful_errors(rows: list[str], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_layout(rows)
    with pytest.raises(ValueError, match=message):
        resolve_layout("umaze", rows)


def test_unknown_builtin_maze() -> None:
    with pytest.raises(ValueError, match="unknown maze 'huge'"):
        resolve_layout("huge")


@pytest.mark.parametrize(("p_gain", "d_gain"), [(1.0, 1.0), (2.0, 0.5)], ids=["diffuser", "default"])
def test_tracking_action_moves_towards_target(p_gain: float, d_gain: float) -> None:
    env = maze_sim(_with_follower(p_gain, d_gain))
    start = env.set_state(np.array([*env.cell_to_xy((3, 3)), 0.0, 0.0]))
    target = np.array([*env.cell_to_xy((3, 1)), 0.0, 0.0])
    obs = start
    distances = [np.linalg.norm(obs[:2] - target[:2])]
    for _ in range(300):
        action = env.tracking_action(obs, target)
        assert np.all(np.abs(action) <= 1.0)
        obs = env.step(action).observation
        distances.append(np.linalg.norm(obs[:2] - target[:2]))
    assert distances[10] < distances[0]
    assert distances[-1] < 0.1 * distances[0]  # it settles at the target within an episode
    # the first action points straight at the target
    first = env.tracking_action(start, target)
    assert first[0] < 0 and first[1] == pytest.approx(0.0, abs=1e-9)


def _with_follower(p_gain: float, d_gain: float) -> Params:
    """Default params whose U-Maze task follows plans with these gains."""
    entry = {"family": "maze2d", "follower": {"p_gain": p_gain, "d_gain": d_gain}}
    return params_from_dict({"task": {"maze2d-umaze": entry}})


def test_tracking_gains_come_from_the_task_follower() -> None:
    env = maze_sim(_with_follower(3.0, 0.25))
    assert (env.tracking_p_gain, env.tracking_d_gain) == (3.0, 0.25)
    obs = np.array([0.0, 0.0, 0.4, -0.2])
    target = np.array([0.1, -0.05, 0.0, 0.6])
    np.testing.assert_allclose(env.tracking_action(obs, target), [3 * 0.1 - 0.25 * 0.4, 3 * -0.05 + 0.25 * 0.8])
    np.testing.assert_array_equal(env.tracking_action(obs, np.array([5.0, -5.0, 0.0, 0.0])), [1.0, -1.0])


def test_plan_follower(umaze: Maze2D) -> None:
    plan = np.array([[0.0, 0.0, 0.1, 0.1], [0.1, 0.0, 0.2, 0.0], [0.2, 0.1, 0.3, 0.4], [0.5, 0.5, 0.6, -0.7]])
    original = plan.copy()
    follower = PlanFollower(umaze, plan)
    for t in range(3):
        np.testing.assert_array_equal(follower.waypoint(t), plan[t + 1])
    for t in (3, 4, 50):
        np.testing.assert_array_equal(follower.waypoint(t), [0.5, 0.5, 0.0, 0.0])
    np.testing.assert_array_equal(plan, original)  # the plan itself is not modified
    obs = np.array([0.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(follower.act(obs, 1), umaze.tracking_action(obs, plan[2]))
    np.testing.assert_array_equal(follower.act(obs, 9), umaze.tracking_action(obs, [0.5, 0.5, 0.0, 0.0]))


def test_draw_puts_walls_plan_and_goal_on_axis(umaze: Maze2D) -> None:
    ax = Figure().add_subplot()
    plan = np.array([[1.0, -1.0, 0, 0], [0.0, -1.0, 0, 0], [-1.0, -1.0, 0, 0]])
    umaze.draw(ax, plan=plan, executed=plan)
    n_walls = sum(row.count("#") for row in umaze.layout.rows)
    assert len(ax.patches) == n_walls + 1  # wall blocks and the goal disc
    labels = {line.get_label() for line in ax.get_lines()}
    assert {"plan", "executed", "start"} <= labels
    assert ax.get_xlim() == (-2.5, 2.5)


def test_random_goal_variant_draws_reproducible_goals_away_from_the_start() -> None:
    env = Maze2D(resolve_layout("medium"), name="medium", random_goal=True)
    goals = []
    for seed in range(8):
        obs = env.reset(np.random.default_rng(seed))
        assert env.xy_to_cell(obs[:2]) != env.goal_cell
        goals.append(env.goal_cell)
        env.reset(np.random.default_rng(seed))
        assert env.goal_cell == goals[-1]
    assert len(set(goals)) > 1


def test_draw_uses_the_episode_goal_when_given(umaze: Maze2D) -> None:
    ax = Figure().add_subplot()
    umaze.draw(ax, goal=np.array([1.0, -1.0, 0.0, 0.0]))
    goal_disc = ax.patches[-1]
    assert tuple(goal_disc.center) == (1.0, -1.0)


def test_set_goal_state_accepts_free_positions_and_rejects_walls(umaze: Maze2D) -> None:
    umaze.set_goal_state(np.array([0.8, -1.2, 0.0, 0.0]))
    assert umaze.goal_cell == (3, 3) and umaze.reward(np.array([0.8, -1.2, 0, 0])) == 1.0
    with pytest.raises(ValueError, match="wall"):
        umaze.set_goal_state(np.array([-1.0, 0.0, 0.0, 0.0]))


def test_point_mass_steps_exactly_as_pointmaze_and_compiles_its_maze_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The simulator's point mass (its maze compiled once per process) follows the same states, bit for bit, as a
    freshly built gymnasium-robotics ``PointMazeEnv`` through wall contacts, beside other simulators of the same maze;
    making six of them writes and compiles the maze's MJCF once and leaves no file behind."""
    from gymnasium_robotics.envs.maze.maze_v4 import Maze
    from gymnasium_robotics.envs.maze.point_maze import PointMazeEnv

    from adaptdiffuser.families.maze2d import point_mass

    wall_map = parse_layout(MAZES["medium"]).wall_map()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # PointMaze writes its MJCF files into the temp folder
    reference = PointMazeEnv(maze_map=wall_map, continuing_task=True).point_env
    left_by_pointmaze = set(tmp_path.glob("*.xml"))
    assert len(left_by_pointmaze) == 1
    monkeypatch.setattr(point_mass, "_compiled", {})  # as in a new process
    made = []
    make_maze = Maze.make_maze.__func__
    monkeypatch.setattr(Maze, "make_maze", classmethod(lambda cls, *args: made.append(args) or make_maze(cls, *args)))
    ours = [point_mass.make_point_mass(wall_map) for _ in range(6)]
    assert len(made) == 1 and set(tmp_path.glob("*.xml")) == left_by_pointmaze
    rng = np.random.default_rng(0)
    start = (np.array([-1.5, 1.5]), np.array([0.3, -0.2]))
    for env in [reference, *ours]:
        env.set_state(*start)
    contacts = 0
    for _ in range(400):
        action = rng.uniform(-1.0, 1.0, size=2)
        expected, *_ = reference.step(action)
        contacts += reference.data.ncon > 0
        for env in ours:
            observed, *_ = env.step(action)
            np.testing.assert_array_equal(observed, expected)
    assert contacts > 0  # the walk hit walls, where the solver's state matters
