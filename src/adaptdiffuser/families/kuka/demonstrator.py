"""The scripted stacking demonstrator (the expert data of the seen task): for each block of a stacking order after the
first (blocks 1, 2, 3 on block 0, or a random order per demonstration), move the cup above the block, descend, attach,
lift, move over the tower, descend, release and lift; every way point reached by inverse kinematics, in straight
cup-space segments at a fixed speed."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np

from adaptdiffuser.contract import Controller
from adaptdiffuser.families.kuka.scene import BLOCK_HALF, N_BLOCKS, N_JOINTS, KukaScene
from adaptdiffuser.families.kuka.tasks import block_positions


def _cylindrical(p: np.ndarray) -> np.ndarray:
    return np.array([np.hypot(p[0], p[1]), np.arctan2(p[1], p[0]), p[2]])


def _segment(start: np.ndarray, end: np.ndarray, step: float) -> Iterator[np.ndarray]:
    """Points every ``step`` metres (about) from ``start`` to ``end``, moving in cylindrical coordinates around the
    base (radius, angle, height), so a move across the workspace swings around the arm instead of through it."""
    a, b = _cylindrical(start), _cylindrical(end)
    length = np.sqrt((b[0] - a[0]) ** 2 + ((b[1] - a[1]) * max(a[0], b[0])) ** 2 + (b[2] - a[2]) ** 2)
    n = max(1, int(np.ceil(length / step)))
    for k in range(1, n + 1):
        r, angle, z = a + (b - a) * k / n
        yield np.array([r * np.cos(angle), r * np.sin(angle), z])


def stacking_order(rng: np.random.Generator | None) -> np.ndarray:
    """The blocks bottom to top: a permutation drawn from ``rng`` (``demonstrator.order: shuffled``), or blocks
    0, 1, 2, 3 without one (``in_turn``)."""
    return np.arange(N_BLOCKS) if rng is None else rng.permutation(N_BLOCKS)


def stacking_commands(
    scene: KukaScene,
    obs: np.ndarray,
    speed: float,
    safe_height: float,
    dwell: int,
    order: Sequence[int] = tuple(range(N_BLOCKS)),
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Cup way points and suction flags ``(cup_xyz, flags[4])`` of one stacking demonstration from ``obs`` that
    builds the tower ``order`` (bottom to top); the caller turns each into joint targets and steps the scene (the
    tower's top is read from the live scene)."""
    cup, _ = scene.cup()
    flags = np.zeros(N_BLOCKS)
    for below, block in zip(order[:-1], order[1:], strict=True):
        pos = block_positions(scene.observation())
        top = pos[block] + np.array([0.0, 0.0, BLOCK_HALF[2] + 0.005])
        tower = pos[below] + np.array([0.0, 0.0, BLOCK_HALF[2] + 2 * BLOCK_HALF[2] + 0.01])
        height = max(safe_height, tower[2] + 0.15)
        for goal, flag in ((top, 1.0), (tower, 0.0)):  # fetch the block, then put it on the tower
            for target in (np.array([cup[0], cup[1], height]), np.array([goal[0], goal[1], height]), goal):
                for point in _segment(cup, target, speed):
                    yield point, flags.copy()
                cup = target
            flags[block] = flag
            for _ in range(dwell):
                yield cup, flags.copy()


def demonstrate(
    scene: KukaScene,
    obs: np.ndarray,
    substeps: int,
    speed: float,
    safe_height: float,
    dwell: int,
    order: Sequence[int] = tuple(range(N_BLOCKS)),
) -> np.ndarray:
    """Run one stacking demonstration of the tower ``order`` from the scene's current state (``obs``); return the
    observations ``[T + 1, 39]``."""
    observations = [obs]
    joints = obs[:N_JOINTS]
    for cup, flags in stacking_commands(scene, obs, speed, safe_height, dwell, order):
        joints = scene.inverse_kinematics(cup, joints)
        observations.append(scene.command(joints, flags, substeps))
    return np.asarray(observations)


def record_demonstration(simulator, rng: np.random.Generator, settings) -> np.ndarray:
    """One demonstration from a protocol start drawn with ``rng`` (then its stacking order, when
    ``demonstrator.order`` is ``shuffled``): the observations ``[T, 39]`` from the start to ``rest_steps`` steps
    after the last release (the arm holding still)."""
    d, c = settings.demonstrator, settings.control
    obs = simulator.reset(rng)
    order = stacking_order(rng if d.order == "shuffled" else None)
    observations = demonstrate(simulator.scene, obs, c.substeps, d.speed, d.safe_height, d.dwell, order)
    hold = observations[-1][:N_JOINTS]
    rest = [simulator.scene.command(hold, np.zeros(N_BLOCKS), c.substeps) for _ in range(max(1, d.rest_steps))]
    return np.concatenate([observations, rest])


def collect_demonstrations(simulator, settings, env: str, progress: bool):
    """The stacking dataset: ``collect.episodes`` demonstrations (episode ``i`` from the start drawn with
    ``(collect.seed, i)``), state only (``act_dim`` 0); the reward of a step is the change in stacked blocks.
    Returns the trajectories and the demonstrator's stacking figures."""
    from tqdm import tqdm

    from adaptdiffuser.families.kuka.dataset import state_episodes
    from adaptdiffuser.families.kuka.tasks import stacked_count

    episodes, rewards, counts = [], [], []
    n = settings.collect.episodes
    for i in tqdm(range(n), desc="stacking demonstrations", disable=not progress):
        obs = record_demonstration(simulator, np.random.default_rng([settings.collect.seed, i]), settings)
        count = np.array([stacked_count(o) for o in obs], dtype=np.float32)
        episodes.append(obs)
        rewards.append(np.append(np.diff(count), np.float32(0.0)))
        counts.append(int(count[-1]))
    lengths = [len(o) for o in episodes]
    figures = {
        "episodes": n,
        "stacked_mean": float(np.mean(counts)),
        "success_rate": float(np.mean(np.asarray(counts) == N_BLOCKS - 1)),
        "length_mean": float(np.mean(lengths)),
        "length_max": int(max(lengths)),
    }
    generator = {"kind": "scripted stacking demonstrator", **settings.demonstrator.model_dump(), **figures}
    return state_episodes(episodes, env, "expert", generator, rewards=rewards), figures


class DemonstratorController(Controller):
    """The scripted stacking demonstrator on each environment (the expert reference); it holds still when done.
    With ``order_seed``, episode ``e`` stacks in the order drawn with ``(order_seed, e)``; without, blocks in turn."""

    def __init__(self, speed: float, safe_height: float, dwell: int, order_seed: int | None = None) -> None:
        self.speed, self.safe_height, self.dwell = speed, safe_height, dwell
        self.order_seed = order_seed

    def begin(self, envs, obs, episodes):
        seed = self.order_seed
        orders = [stacking_order(None if seed is None else np.random.default_rng([seed, e])) for e in episodes]
        self.scripts = [
            stacking_commands(env.scene, o, self.speed, self.safe_height, self.dwell, order)
            for env, o, order in zip(envs, obs, orders, strict=True)
        ]
        self.last = [(o[:N_JOINTS].copy(), np.zeros(N_BLOCKS)) for o in obs]

    def act(self, envs, obs, t):
        actions = []
        for i, (env, script) in enumerate(zip(envs, self.scripts, strict=True)):
            joints, flags = self.last[i]
            waypoint = next(script, None)
            if waypoint is not None:
                cup, flags = waypoint
                joints = env.scene.inverse_kinematics(cup, joints)
            self.last[i] = (joints, flags)
            actions.append(np.concatenate([joints, flags]))
        return np.asarray(actions)
