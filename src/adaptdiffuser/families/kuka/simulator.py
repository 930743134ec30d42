"""The KUKA simulator behind the family interface: an action is a planned configuration (7 joint targets and 4
suction flags) reached by position control over a fixed number of physics steps; the reward of a step is the change
of the task's count (blocks stacked, or blocks placed), so an episode's return is what it achieved."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from adaptdiffuser.contract import Simulator, Step
from adaptdiffuser.families.kuka.scene import (
    FLAG_COLUMNS,
    HOME_JOINTS,
    N_BLOCKS,
    N_JOINTS,
    OBS_DIM,
    KukaScene,
    block_position_columns,
)
from adaptdiffuser.families.kuka.tasks import (
    placed_count,
    scattered_blocks,
    stacked_count,
    tower_blocks,
)

#: what an episode is scored on
KINDS = ("stacking", "pick_place")
#: where the blocks start: ``scattered`` on the floor, or one ``tower`` (pick-and-place setups 1 and 2)
LAYOUTS = ("scattered", "tower")

if TYPE_CHECKING:
    from adaptdiffuser.families.kuka.params import KukaTaskParams


class KukaSimulator(Simulator):
    """One KUKA episode: ``kind`` says what is counted, ``layout`` how the blocks start; ``settings`` is the task's
    :class:`~adaptdiffuser.families.kuka.params.KukaTaskParams`."""

    obs_dim = OBS_DIM
    act_dim = N_JOINTS + N_BLOCKS
    state_dim = 0

    def __init__(
        self, settings: KukaTaskParams, kind: str = "stacking", layout: str = "scattered", episode_steps: int = 381
    ):
        if kind not in KINDS:
            raise ValueError(f"unknown KUKA task kind {kind!r}; choose one of {KINDS}")
        if layout not in LAYOUTS:
            raise ValueError(f"unknown KUKA block layout {layout!r}; choose one of {LAYOUTS}")
        self.name = f"kuka-{kind}"
        self.settings = settings
        self.kind = kind
        self.layout = layout
        self.episode_steps = episode_steps
        c = settings.control
        self.scene = KukaScene(c.joint_force, c.position_gain, c.suction_reach, c.free_top_only, c.max_joint_step)
        self.count = placed_count if kind == "pick_place" else stacked_count
        self.obs: np.ndarray | None = None

    def sample_scene(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """A start of the protocol: the arm near its home configuration and the blocks placed per ``layout``
        (pick-and-place keeps them on the far side from the targets)."""
        s = self.settings.scene
        joints = HOME_JOINTS + rng.uniform(-s.home_noise, s.home_noise, size=N_JOINTS)
        max_x = s.pick_place_max_x if self.kind == "pick_place" else None
        if self.layout == "tower":
            blocks = tower_blocks(rng, tuple(s.radius), max_x)
        else:
            blocks = scattered_blocks(rng, tuple(s.radius), s.min_gap, max_x)
        return joints, blocks

    def reset(self, rng: np.random.Generator) -> np.ndarray:
        joints, blocks = self.sample_scene(rng)
        return self.start(joints, blocks)

    def start(self, joints: np.ndarray, blocks: np.ndarray) -> np.ndarray:
        """Start an episode from this arm configuration and block poses ``[4, 7]``."""
        self.obs = self.scene.build(joints, blocks)
        return self.obs.copy()

    def get_state(self) -> np.ndarray:
        """The observation (scenes are restored at rest: velocities are not part of the state)."""
        return self.scene.observation()

    def set_state(self, state: np.ndarray) -> np.ndarray:
        """Rebuild the world at an observation (arm and blocks at rest; blocks whose flag is on re-attached when the
        cup reaches them)."""
        state = np.asarray(state, dtype=np.float64)
        starts = [block_position_columns(i).start for i in range(N_BLOCKS)]
        self.scene.build(state[:N_JOINTS], np.stack([state[k : k + 7] for k in starts]))  # xyz + quaternion
        self.scene.set_suction(state[list(FLAG_COLUMNS)])
        self.obs = self.scene.observation()
        return self.obs.copy()

    def step(self, action: np.ndarray) -> Step:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (self.act_dim,):
            raise ValueError(
                f"a KUKA action is 7 joint targets + 4 suction flags, shape ({self.act_dim},); got {action.shape}"
            )
        before = self.count(self.obs)
        self.obs = self.scene.command(action[:N_JOINTS], action[N_JOINTS:], self.settings.control.substeps)
        return Step(self.obs.copy(), float(self.count(self.obs) - before), False)

    def render(self, width: int = 320, height: int = 240) -> np.ndarray:
        return self.scene.render(width, height)

    def close(self) -> None:
        self.scene.close()
