"""The Maze2D simulator: gymnasium-robotics PointMaze with Diffuser's evaluation protocol, D4RL's waypoint expert
and the plan follower's tracking action, behind :class:`PlanningEnv` (what the maze's plan following, evolution
and gold-coin code ask of a simulator beyond :class:`~adaptdiffuser.contract.Simulator`).

Coordinates are gymnasium-robotics' (centred, y up): cell (row, col) has its centre at
x = col + 0.5 - width / 2, y = height / 2 - (row + 0.5). Observations are (x, y, vx, vy); actions are forces
in [-1, 1]^2. The protocol's reward is 1 at every step within ``goal_radius`` (0.5) of the goal.
"""

from __future__ import annotations

from abc import abstractmethod
from collections import deque

import numpy as np

from adaptdiffuser.contract import Simulator, Step
from adaptdiffuser.families.maze2d.layouts import EPISODE_STEPS, MAZES, Layout, parse_layout
from adaptdiffuser.families.maze2d.point_mass import make_point_mass

Cell = tuple[int, int]


def silence_adroit_notice() -> None:
    """Drop gymnasium-robotics' notice about its Adroit environments' rewards (this project never uses them) before
    it is first imported.

    gymnasium_robotics prints, with ``print(..., file=sys.stderr)`` on import (not through ``warnings`` or
    ``logging``, so no filter catches it), the message ``farama_notifications`` holds for its installed version.
    This removes exactly that message (the one naming ``AdroitHand``) from the table; any other notice still
    prints."""
    try:
        from farama_notifications import notifications
    except ImportError:
        return
    robotics = notifications.get("gymnasium_robotics", {})
    for version, message in list(robotics.items()):
        if "AdroitHand" in str(message):
            del robotics[version]


def resolve_layout(maze: str, layout: list[str] | None = None) -> Layout:
    """The built-in maze named ``maze``, or a custom ``layout`` (list of strings) when one is given."""
    if layout is not None:
        return parse_layout(list(layout))
    if maze not in MAZES:
        raise ValueError(f"unknown maze {maze!r}; choose one of {sorted(MAZES)} or give a layout")
    return parse_layout(MAZES[maze])


def bfs_distances(layout: Layout, goal: Cell) -> dict[Cell, int]:
    """Shortest path length (in cells, 4-connected) from every reachable free cell to ``goal``."""
    dist = {goal: 0}
    queue = deque([goal])
    while queue:
        r, c = queue.popleft()
        for nr, nc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
            if layout.is_free(nr, nc) and (nr, nc) not in dist:
                dist[(nr, nc)] = dist[(r, c)] + 1
                queue.append((nr, nc))
    return dist


def shortest_path(layout: Layout, start: Cell, goal: Cell) -> list[Cell]:
    """Cells from ``start`` to ``goal`` inclusive along a shortest 4-connected path."""
    dist = bfs_distances(layout, goal)
    if start not in dist:
        raise ValueError(f"cell {start} cannot reach {goal}")
    path = [start]
    while path[-1] != goal:
        r, c = path[-1]
        neighbours = [(r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)]
        path.append(min((n for n in neighbours if n in dist), key=lambda n: dist[n]))
    return path


class PlanningEnv(Simulator):
    """A simulator with a goal task: reset, step, the protocol's reward, an expert, a tracking controller, a picture.

    Observations and actions are flat float vectors. One instance simulates one episode at a time; batch work
    (evaluation, tracking) holds one instance per parallel episode.
    """

    name: str
    obs_dim: int
    act_dim: int
    episode_steps: int

    @abstractmethod
    def reward(self, obs: np.ndarray) -> float:
        """The evaluation protocol's reward for being at ``obs``."""

    @abstractmethod
    def goal_state(self) -> np.ndarray:
        """The state the planner is conditioned to end in for the current task."""

    @abstractmethod
    def set_goal_state(self, goal: np.ndarray) -> None:
        """Make ``goal`` (a state, as :meth:`goal_state` returns) the current task's goal."""

    def tracking_error(self, executed: np.ndarray, planned: np.ndarray) -> float:
        """How far an executed state is from the planned one (full-state L2 unless an env says otherwise)."""
        return float(np.linalg.norm(np.asarray(executed) - np.asarray(planned)))

    @abstractmethod
    def seed_expert(self, seed: int) -> None:
        """Seed the expert's own randomness (for reproducible reference returns and data)."""

    @abstractmethod
    def expert_action(self, obs: np.ndarray) -> np.ndarray:
        """The scripted expert's action towards the current goal."""

    @abstractmethod
    def tracking_action(self, obs: np.ndarray, target: np.ndarray) -> np.ndarray:
        """The action that moves from ``obs`` towards the planned next state ``target``."""

    @abstractmethod
    def draw(
        self,
        ax,
        plan: np.ndarray | None = None,
        executed: np.ndarray | None = None,
        goal: np.ndarray | None = None,
    ) -> None:
        """Draw the task (optionally a planned and an executed state sequence, and the episode's goal state
        if it differs from the current one) on a matplotlib axis."""


class Maze2D(PlanningEnv):
    """One PointMaze simulator with a goal, the protocol's reset and reward, an expert and a tracker."""

    obs_dim = 4
    act_dim = 2
    state_dim = 4

    def __init__(
        self,
        layout: Layout,
        name: str = "maze2d",
        episode_steps: int | None = None,
        goal_radius: float = 0.5,
        reset_pos_noise: float = 0.1,
        reset_vel_noise: float = 0.1,
        random_goal: bool = False,
        expert_p_gain: float = 10.0,
        expert_d_gain: float = 1.0,
        expert_jitter: float = 0.2,
        expert_waypoint_radius: float = 0.3,
        tracking_p_gain: float = 1.0,
        tracking_d_gain: float = 1.0,
    ) -> None:
        silence_adroit_notice()

        self.layout = layout
        self.name = name
        self.episode_steps = episode_steps or EPISODE_STEPS.get(name, 300)
        self.goal_radius = goal_radius
        self.reset_pos_noise = reset_pos_noise
        self.reset_vel_noise = reset_vel_noise
        self.random_goal = random_goal
        self.expert_p_gain = expert_p_gain
        self.expert_d_gain = expert_d_gain
        self.expert_jitter = expert_jitter
        self.expert_waypoint_radius = expert_waypoint_radius
        self.tracking_p_gain = tracking_p_gain
        self.tracking_d_gain = tracking_d_gain
        self._point = make_point_mass(layout.wall_map())
        self._expert_rng = np.random.default_rng(0)
        self._waypoints: list[np.ndarray] = []
        self._waypoint_index = 0
        self._obs = np.zeros(4)
        self.goal_cell: Cell = layout.goal_cell or layout.free_cells[-1]
        self.goal_xy = self.cell_to_xy(self.goal_cell)

    # -- geometry -------------------------------------------------------------------------------------------
    def cell_to_xy(self, cell: Cell) -> np.ndarray:
        r, c = cell
        return np.array([c + 0.5 - self.layout.width / 2, self.layout.height / 2 - (r + 0.5)])

    def xy_to_cell(self, xy: np.ndarray) -> Cell:
        col = int(np.floor(xy[0] + self.layout.width / 2))
        row = int(np.floor(self.layout.height / 2 - xy[1]))
        return row, col

    def in_wall(self, xy: np.ndarray) -> bool:
        """Whether the point ``xy`` lies inside a wall block (or outside the maze)."""
        return not self.layout.is_free(*self.xy_to_cell(xy))

    # -- task -------------------------------------------------------------------------------------------------
    def set_goal(self, cell: Cell) -> None:
        """Make ``cell`` the goal (its centre); the expert re-plans towards it."""
        if not self.layout.is_free(*cell):
            raise ValueError(f"goal cell {cell} is not a free cell of the maze")
        self.goal_cell = tuple(cell)
        self.goal_xy = self.cell_to_xy(self.goal_cell)
        self._waypoints = []

    def set_goal_state(self, goal: np.ndarray) -> None:
        """Make the position of ``goal`` the goal (need not be a cell centre); the expert re-plans towards it."""
        xy = np.asarray(goal, dtype=np.float64)[:2]
        cell = self.xy_to_cell(xy)
        if not self.layout.is_free(*cell):
            raise ValueError(f"goal position {xy.tolist()} lies in a wall (cell {cell})")
        self.goal_cell = cell
        self.goal_xy = xy.copy()
        self._waypoints = []

    def tracking_error(self, executed: np.ndarray, planned: np.ndarray) -> float:
        """Position distance: planned velocities are noisy, positions are what the task is about."""
        return float(np.linalg.norm(np.asarray(executed)[:2] - np.asarray(planned)[:2]))

    def goal_state(self) -> np.ndarray:
        """The planner's goal condition: goal position with zero velocity."""
        return np.array([*self.goal_xy, 0.0, 0.0])

    def reset(self, rng: np.random.Generator, cell: Cell | None = None) -> np.ndarray:
        """Protocol start in ``cell`` (random if None); with ``random_goal`` also a new goal cell elsewhere."""
        free = self.layout.free_cells
        if cell is None:
            cell = free[rng.integers(len(free))]
        if self.random_goal:
            others = [c for c in free if c != tuple(cell)]
            self.set_goal(others[rng.integers(len(others))])
        pos = self.cell_to_xy(cell) + rng.uniform(-self.reset_pos_noise, self.reset_pos_noise, size=2)
        vel = rng.normal(0.0, self.reset_vel_noise, size=2)
        self._waypoints = []
        return self.set_state(np.concatenate([pos, vel]))

    def set_state(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        self._point.set_state(obs[:2].copy(), obs[2:4].copy())
        self._obs = np.concatenate([self._point.data.qpos, self._point.data.qvel]).copy()
        return self._obs.copy()

    def get_state(self) -> np.ndarray:
        """The full state is the observation (qpos = position, qvel = velocity)."""
        return self._obs.copy()

    def step(self, action: np.ndarray) -> Step:
        """One step of the point mass; the reward is the protocol's for the state reached, never terminal."""
        obs, *_ = self._point.step(np.asarray(action, dtype=np.float64))
        self._obs = obs.copy()
        return Step(obs, self.reward(obs), False)

    def reward(self, obs: np.ndarray) -> float:
        return float(np.linalg.norm(np.asarray(obs)[:2] - self.goal_xy) <= self.goal_radius)

    # -- controllers ------------------------------------------------------------------------------------------
    def _plan_waypoints(self, xy: np.ndarray) -> None:
        cells = shortest_path(self.layout, self.xy_to_cell(xy), self.goal_cell)[1:]
        self._waypoints = [
            self.cell_to_xy(cell) - self._expert_rng.uniform(0.0, self.expert_jitter, size=2) for cell in cells[:-1]
        ] + [self.goal_xy.copy()]
        self._waypoint_index = 0

    def seed_expert(self, seed: int) -> None:
        """Seed the expert's waypoint jitter."""
        self._expert_rng = np.random.default_rng(seed)

    def expert_action(self, obs: np.ndarray) -> np.ndarray:
        """D4RL's waypoint controller: PD control towards the next cell centre of a shortest path."""
        xy, vel = obs[:2], obs[2:4]
        if not self._waypoints:
            self._plan_waypoints(xy)
        last = len(self._waypoints) - 1
        while (
            self._waypoint_index < last
            and np.linalg.norm(self._waypoints[self._waypoint_index] - xy) < self.expert_waypoint_radius
        ):
            self._waypoint_index += 1
        target = self._waypoints[self._waypoint_index]
        action = self.expert_p_gain * (target - xy) - self.expert_d_gain * vel
        return np.clip(action, -1.0, 1.0)

    def tracking_action(self, obs: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Diffuser's plan follower: position error plus velocity error towards the planned next state."""
        action = self.tracking_p_gain * (target[:2] - obs[:2]) + self.tracking_d_gain * (target[2:4] - obs[2:4])
        return np.clip(action, -1.0, 1.0)

    # -- picture ----------------------------------------------------------------------------------------------
    def draw(
        self,
        ax,
        plan: np.ndarray | None = None,
        executed: np.ndarray | None = None,
        goal: np.ndarray | None = None,
    ) -> None:
        from matplotlib.patches import Circle, Rectangle

        for r in range(self.layout.height):
            for c in range(self.layout.width):
                if not self.layout.is_free(r, c):
                    x, y = self.cell_to_xy((r, c))
                    ax.add_patch(Rectangle((x - 0.5, y - 0.5), 1, 1, color="0.35"))
        if plan is not None:
            ax.plot(plan[:, 0], plan[:, 1], "-", color="tab:blue", lw=1.5, label="plan")
            ax.scatter(plan[:, 0], plan[:, 1], c=np.linspace(0, 1, len(plan)), cmap="winter", s=6, zorder=3)
        if executed is not None:
            ax.plot(executed[:, 0], executed[:, 1], "-", color="tab:orange", lw=1.5, label="executed")
            ax.plot(*executed[0, :2], "o", color="tab:green", ms=8, label="start")
        goal_xy = self.goal_xy if goal is None else np.asarray(goal)[:2]
        ax.add_patch(Circle(tuple(goal_xy), self.goal_radius, color="tab:red", alpha=0.3, label="goal"))
        ax.set_xlim(-self.layout.width / 2, self.layout.width / 2)
        ax.set_ylim(-self.layout.height / 2, self.layout.height / 2)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
