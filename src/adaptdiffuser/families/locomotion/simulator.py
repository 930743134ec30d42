"""One gymnasium MuJoCo locomotion env (Hopper, Walker2d, HalfCheetah ``-v5``) behind the family's
:class:`~adaptdiffuser.contract.Simulator` interface.

The env is used unwrapped (no ``TimeLimit``): the episode length (``episode_steps``) is the caller's business. The
full state is ``qpos`` then ``qvel`` (float64), from which the reward and the termination can be recomputed exactly
(:meth:`LocomotionSimulator.reward`, :meth:`LocomotionSimulator.terminated`).

MuJoCo warm-starts its constraint solver from the previous step's accelerations, which qpos and qvel do not hold,
so a restored state would replay only to ~1e-12. With ``exact_state`` (the default) the warm start is off: the full
state is then Markov and restoring it replays bit-exactly; the dynamics differ from stock v5 only at the solver's
tolerance.
"""

from __future__ import annotations

import sys
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from adaptdiffuser.contract import Simulator, Step
from adaptdiffuser.families.locomotion.params import DATASET_KINDS, ENV_IDS, parse_task_name

__all__ = ["DATASET_KINDS", "ENV_IDS", "LocomotionSimulator", "env_id_of", "parse_task_name"]

#: envs with a healthy check (healthy reward and termination when unhealthy)
_HEALTHY_ENVS = ("Hopper-v5", "Walker2d-v5")


#: MuJoCo's warning about an attribute of gymnasium's HalfCheetah model, printed each time the model is compiled
_SETTOTALMASS = "compiler attribute 'settotalmass' is deprecated"


def silence_settotalmass_warning() -> None:
    """Drop MuJoCo's deprecation warning about ``settotalmass`` in gymnasium's HalfCheetah-v5 model (its file is not
    ours to change), printed for every env made, so that a long run's log shows its progress. MuJoCo's other warnings
    still go where they went (to the handler installed before, else printed to stderr)."""
    previous = mujoco.get_mju_user_warning()
    if getattr(previous, "drops_settotalmass", False):
        return

    def warn(message: str) -> None:
        if _SETTOTALMASS in message:
            return
        if previous is not None:
            previous(message)
        else:
            print(f"WARNING: {message}", file=sys.stderr, flush=True)

    warn.drops_settotalmass = True  # type: ignore[attr-defined]
    mujoco.set_mju_user_warning(warn)


def env_id_of(name: str) -> str:
    """The gymnasium env id of a task name (``hopper-medium``) or of an env id itself (``Hopper-v5``)."""
    if name in ENV_IDS.values():
        return name
    return parse_task_name(name)[0]


class LocomotionSimulator(Simulator):
    """A gymnasium MuJoCo locomotion env, unwrapped, with the full state (qpos, qvel) exposed."""

    def __init__(self, env_id: str, episode_steps: int = 1000, exact_state: bool = True, **env_kwargs: Any) -> None:
        if env_id not in ENV_IDS.values():
            raise ValueError(f"unknown locomotion env {env_id!r}; known: {sorted(ENV_IDS.values())}")
        if episode_steps <= 0:
            raise ValueError(f"episode_steps must be positive, got {episode_steps}")
        self._init_args = (env_id, episode_steps, exact_state, dict(env_kwargs))
        silence_settotalmass_warning()
        self.env = gym.make(env_id, **env_kwargs).unwrapped
        if exact_state:
            self.env.model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_WARMSTART)
        self.name = env_id
        self.episode_steps = int(episode_steps)
        self.nq = int(self.env.model.nq)
        self.nv = int(self.env.model.nv)
        self.state_dim = self.nq + self.nv
        self.obs_dim = int(self.env.observation_space.shape[0])
        self.act_dim = int(self.env.action_space.shape[0])
        self.action_low = self.env.action_space.low.astype(np.float64)
        self.action_high = self.env.action_space.high.astype(np.float64)
        self.dt = float(self.env.dt)
        self.has_healthy_check = env_id in _HEALTHY_ENVS
        self.forward_reward_weight = float(self.env._forward_reward_weight)
        self.ctrl_cost_weight = float(self.env._ctrl_cost_weight)
        self.healthy_reward = float(getattr(self.env, "_healthy_reward", 0.0))

    def __getstate__(self) -> dict[str, Any]:
        """Pickled as its constructor's arguments and the current full state: gymnasium pickles a MuJoCo env by
        building it anew, which would lose the state of an episode under way."""
        return {"init_args": self._init_args, "state": self.get_state()}

    def __setstate__(self, saved: dict[str, Any]) -> None:
        env_id, episode_steps, exact_state, env_kwargs = saved["init_args"]
        self.__init__(env_id, episode_steps, exact_state, **env_kwargs)
        self.set_state(saved["state"])

    # -- episode --------------------------------------------------------------------------------------------------

    def reset(self, rng: np.random.Generator) -> np.ndarray:
        """The env's standard reset noise, seeded from ``rng``: the same generator state gives the same start."""
        obs, _ = self.env.reset(seed=int(rng.integers(0, 2**31 - 1)))
        return np.asarray(obs, dtype=np.float64)

    def get_state(self) -> np.ndarray:
        return np.concatenate([self.env.data.qpos, self.env.data.qvel]).astype(np.float64)

    def set_state(self, state: np.ndarray) -> np.ndarray:
        state = np.asarray(state, dtype=np.float64)
        if state.shape != (self.state_dim,):
            raise ValueError(f"{self.name} state must have shape ({self.state_dim},), got {state.shape}")
        self.env.set_state(state[: self.nq], state[self.nq :])
        return self.observation()

    def observation(self) -> np.ndarray:
        """The observation at the current state."""
        return np.asarray(self.env._get_obs(), dtype=np.float64)

    def clip_action(self, action: np.ndarray) -> np.ndarray:
        """``action`` as float64, clipped to the action space."""
        return np.clip(np.asarray(action, dtype=np.float64).reshape(self.act_dim), self.action_low, self.action_high)

    def step(self, action: np.ndarray) -> Step:
        """Apply the clipped action: the next observation, the env's reward and its termination."""
        obs, reward, terminated, _, _ = self.env.step(self.clip_action(action))
        return Step(observation=np.asarray(obs, dtype=np.float64), reward=float(reward), terminated=bool(terminated))

    # -- reward and termination from full states ------------------------------------------------------------------

    def is_healthy(self, state: np.ndarray) -> bool:
        """gymnasium v5's healthy check (always true for HalfCheetah)."""
        if not self.has_healthy_check:
            return True
        state = np.asarray(state, dtype=np.float64)
        z, angle = state[1], state[2]
        min_z, max_z = self.env._healthy_z_range
        min_angle, max_angle = self.env._healthy_angle_range
        healthy = min_z < z < max_z and min_angle < angle < max_angle
        if self.name == "Hopper-v5":
            min_s, max_s = self.env._healthy_state_range
            healthy = healthy and bool(np.all((min_s < state[2:]) & (state[2:] < max_s)))
        return bool(healthy)

    def terminated(self, state: np.ndarray) -> bool:
        """Whether an episode ends at ``state`` (unhealthy Hopper/Walker2d; HalfCheetah never terminates)."""
        return self.has_healthy_check and bool(self.env._terminate_when_unhealthy) and not self.is_healthy(state)

    def reward(self, state: np.ndarray, action: np.ndarray, next_state: np.ndarray) -> float:
        """The env's reward of ``state --action--> next_state``: forward velocity of the root x, healthy reward
        (Hopper/Walker2d, when ``next_state`` is healthy) minus the control cost of the clipped action."""
        x_velocity = (float(next_state[0]) - float(state[0])) / self.dt
        healthy = self.healthy_reward * float(self.is_healthy(next_state)) if self.has_healthy_check else 0.0
        ctrl_cost = self.ctrl_cost_weight * float(np.sum(np.square(self.clip_action(action))))
        return self.forward_reward_weight * x_velocity + healthy - ctrl_cost

    # -- picture --------------------------------------------------------------------------------------------------

    def draw(self, ax: Any, states: np.ndarray, plan_states: np.ndarray | None = None, title: str = "") -> None:
        """The torso's path in the (x, height) plane from full states, with a plan's path overlaid if given."""
        states = np.asarray(states, dtype=np.float64)
        ax.plot(states[:, 0], states[:, 1], color="tab:blue", lw=1.5, label="episode")
        ax.scatter(states[:1, 0], states[:1, 1], color="tab:green", s=20, zorder=3, label="start")
        ax.scatter(states[-1:, 0], states[-1:, 1], color="tab:red", s=20, zorder=3, label="end")
        if plan_states is not None:
            plan_states = np.asarray(plan_states, dtype=np.float64)
            ax.plot(plan_states[:, 0], plan_states[:, 1], color="tab:orange", ls="--", lw=1.2, label="plan")
        if self.has_healthy_check:
            ax.axhline(self.env._healthy_z_range[0], color="gray", ls=":", lw=0.8, label="min healthy height")
        ax.set_xlabel("torso x position")
        ax.set_ylabel("torso height (qpos[1])")
        ax.set_title(title or f"{self.name}: {len(states)} steps, x = {states[-1, 0]:.2f}")
        ax.legend(loc="best", fontsize="small")

    def close(self) -> None:
        self.env.close()
