"""Locomotion data from outside (D4RL's files, Minari's MuJoCo datasets) as a task's dataset.

Observations and actions must have the task's environment's dimensions (gymnasium ``-v5``). The full state of each
row is ``infos/qpos`` and ``infos/qvel`` where the source has them; otherwise it is rebuilt from the observation,
which holds qpos without the root x and then qvel (the root x does not change the dynamics, so it is set to 0).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from adaptdiffuser.data.d4rl import ExternalData
from adaptdiffuser.data.schema import Trajectories
from adaptdiffuser.families.locomotion.simulator import LocomotionSimulator


def locomotion_trajectories(task: Any, sim: LocomotionSimulator, raw: ExternalData) -> Trajectories:
    """External data as the task's dataset, refused with a one-line error when a dimension does not match."""
    raw.check_dim("observations", raw.observations, sim.obs_dim, task.name)
    raw.check_dim("actions", raw.actions, sim.act_dim, task.name)
    n = len(raw)
    if raw.qpos is not None and raw.qvel is not None:
        raw.check_dim("infos/qpos", raw.qpos.reshape(n, -1), sim.nq, task.name)
        raw.check_dim("infos/qvel", raw.qvel.reshape(n, -1), sim.nv, task.name)
        state = np.concatenate([raw.qpos.reshape(n, -1), raw.qvel.reshape(n, -1)], axis=1)
        how = "infos/qpos and infos/qvel of the source"
    elif sim.obs_dim == sim.state_dim - 1:
        state = np.concatenate([np.zeros((n, 1)), raw.observations], axis=1)
        how = "rebuilt from the observations (root x = 0)"
    else:
        raise raw.fail("infos/qpos", f"is missing and task {task.name}'s observations do not hold the full state")
    return raw.trajectories(task.name, raw.observations, raw.actions, {"sim_state": how}, sim_state=state)


def locomotion_export_spec(sim: LocomotionSimulator) -> tuple[Any, Any, Any]:
    """The gymnasium env spec of the task's robot and its spaces (observations as the env gives them)."""
    import gymnasium as gym

    spec = gym.spec(sim.name)
    obs_space = gym.spaces.Box(-np.inf, np.inf, (sim.obs_dim,), np.float32)
    act_space = gym.spaces.Box(sim.action_low.astype(np.float32), sim.action_high.astype(np.float32))
    return spec, obs_space, act_space
