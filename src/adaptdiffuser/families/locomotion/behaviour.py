"""D4RL's locomotion dataset recipe, regenerated: train a behaviour policy with stable-baselines3, stop it at a
"medium" score (about a third of expert), and record datasets from it.

* ``medium``: ``dataset_steps`` steps of the medium policy, its deterministic action plus Gaussian noise
  (``rollout_noise`` times the action half-range, clipped), in episodes of at most ``episode_steps`` steps.
* ``medium-replay``: every transition the learner saw up to the medium point, in its episodes as they happened.
* ``medium-expert``: the ``medium`` rollouts followed by as many rollouts of a policy trained on to ``expert_score``.

Every row records the full simulator state (qpos, qvel) before the step. Everything is seeded from
:class:`BehaviourSettings`: the same settings give the same dataset.
"""

from __future__ import annotations

import io
import json
import math
import pickle
import random
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import numpy as np
from tqdm.auto import tqdm

from adaptdiffuser.data.schema import Trajectories, make_metadata
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.evaluation import standard_error
from adaptdiffuser.families.locomotion.band import Band, BandNotReachedError, SearchState, search_band
from adaptdiffuser.families.locomotion.params import BehaviourSettings
from adaptdiffuser.families.locomotion.reference import normalized_score
from adaptdiffuser.families.locomotion.simulator import LocomotionSimulator, env_id_of, parse_task_name
from adaptdiffuser.io import atomic_path, write_json

Policy = Callable[[np.ndarray], np.ndarray]

#: the evaluation curve and the policies' summary, beside the ``.zip`` files
SUMMARY_FILE = "behaviour.json"

#: how often (wall-clock seconds, at an evaluation) the band search writes its resume state: any state resumes
#: exactly, so this trades only disk writes (a replay of a million steps is some hundred megabytes) against work lost
CHECKPOINT_EVERY_S = 600.0


# -- evaluation -----------------------------------------------------------------------------------------------


def sb3_policy(model: Any, deterministic: bool = True) -> Policy:
    """An SB3 model as an ``observation -> action`` function."""

    def act(obs: np.ndarray) -> np.ndarray:
        action, _ = model.predict(obs, deterministic=deterministic)
        return np.asarray(action, dtype=np.float64)

    return act


def random_policy(sim: LocomotionSimulator, seed: int) -> Policy:
    """A uniformly random policy over ``sim``'s action space (the score reference's "random")."""
    rng = np.random.default_rng(seed)
    return lambda obs: rng.uniform(sim.action_low, sim.action_high)


def evaluate_policy_returns(
    policy: Policy | Any,
    task: str | LocomotionSimulator,
    episodes: int,
    seed: int,
    episode_steps: int | None = None,
    noise: float = 0.0,
) -> np.ndarray:
    """Undiscounted returns of ``policy`` (a function or an SB3 model, deterministic) over ``episodes`` episodes;
    episode ``i`` starts from ``np.random.default_rng([seed, i])``, so the same seed gives the same starts. With
    ``noise``, actions get Gaussian noise of ``noise`` times the action half-range, as datasets are recorded."""
    sim = task if isinstance(task, LocomotionSimulator) else LocomotionSimulator(env_id_of(task))
    act = sb3_policy(policy) if hasattr(policy, "predict") else policy
    horizon = episode_steps or sim.episode_steps
    half_range = (sim.action_high - sim.action_low) / 2
    returns = np.zeros(episodes)
    for i in range(episodes):
        obs = sim.reset(np.random.default_rng([seed, i]))
        noise_rng = np.random.default_rng([seed, i, 1])
        for _ in range(horizon):
            action = np.asarray(act(obs), dtype=np.float64)
            if noise > 0:
                action = sim.clip_action(action + noise * half_range * noise_rng.standard_normal(sim.act_dim))
            out = sim.step(action)
            returns[i] += out.reward
            obs = out.observation
            if out.terminated:
                break
    return returns


# -- recording ------------------------------------------------------------------------------------------------


@dataclass
class _Recorder:
    """Rows of steps as they happen: observation, action, reward, terminal, timeout and state before the step."""

    observation: list[np.ndarray] = field(default_factory=list)
    action: list[np.ndarray] = field(default_factory=list)
    reward: list[float] = field(default_factory=list)
    terminal: list[bool] = field(default_factory=list)
    timeout: list[bool] = field(default_factory=list)
    state: list[np.ndarray] = field(default_factory=list)
    episode: list[int] = field(default_factory=list)

    def add(self, episode: int, obs: np.ndarray, state: np.ndarray, action: np.ndarray, reward: float,
            terminal: bool, timeout: bool) -> None:  # fmt: skip
        self.episode.append(episode)
        self.observation.append(obs)
        self.state.append(state)
        self.action.append(action)
        self.reward.append(reward)
        self.terminal.append(terminal)
        self.timeout.append(timeout)

    def __len__(self) -> int:
        return len(self.episode)

    def __getstate__(self) -> dict[str, np.ndarray]:
        """Pickled as one array per column: a million rows of small arrays would pickle slowly and large."""
        return {name: np.asarray(rows) for name, rows in vars(self).items()}

    def __setstate__(self, saved: dict[str, np.ndarray]) -> None:
        for name, column in saved.items():
            setattr(self, name, list(column))

    def truncate(self, rows: int) -> None:
        """Keep the first ``rows`` rows (training went back to that point); an episode cut there ends with a
        timeout."""
        for column in (self.observation, self.action, self.reward, self.terminal, self.timeout, self.state,
                       self.episode):  # fmt: skip
            del column[rows:]
        if rows and not (self.terminal[-1] or self.timeout[-1]):
            self.timeout[-1] = True

    def columns(self, rows: int | None = None) -> dict[str, np.ndarray]:
        """The first ``rows`` rows as arrays; an episode cut by the end of the rows ends with a timeout."""
        n = len(self) if rows is None else rows
        cols = {
            "episode": np.asarray(self.episode[:n], dtype=np.int64),
            "observation": np.asarray(self.observation[:n], dtype=np.float64).reshape(n, -1),
            "action": np.asarray(self.action[:n], dtype=np.float64).reshape(n, -1),
            "reward": np.asarray(self.reward[:n], dtype=np.float64),
            "terminal": np.asarray(self.terminal[:n], dtype=bool),
            "timeout": np.asarray(self.timeout[:n], dtype=bool),
            "state": np.asarray(self.state[:n], dtype=np.float64).reshape(n, -1),
        }
        if n and not (cols["terminal"][-1] or cols["timeout"][-1]):
            cols["timeout"][-1] = True
        return cols


class _SimEnv(gym.Env):
    """A gymnasium env over a :class:`LocomotionSimulator` with our episode limit, recording every step."""

    def __init__(self, sim: LocomotionSimulator, recorder: _Recorder | None = None) -> None:
        self.sim = sim
        self.recorder = recorder
        self.observation_space = sim.env.observation_space
        self.action_space = sim.env.action_space
        self._obs = np.zeros(sim.obs_dim)
        self._t = 0
        self._episode = -1

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self._obs = self.sim.reset(self.np_random)
        self._t = 0
        self._episode += 1
        return self._obs, {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        state = self.sim.get_state()
        action = self.sim.clip_action(action)
        out = self.sim.step(action)
        self._t += 1
        truncated = self._t >= self.sim.episode_steps and not out.terminated
        if self.recorder is not None:
            self.recorder.add(self._episode, self._obs, state, action, out.reward, out.terminated, truncated)
        self._obs = out.observation
        return out.observation, out.reward, out.terminated, truncated, {}


def record_rollouts(
    sim: LocomotionSimulator,
    policy: Policy,
    steps: int,
    rng: np.random.Generator,
    noise: float = 0.0,
    progress: bool = False,
    desc: str = "rollouts",
) -> dict[str, np.ndarray]:
    """``steps`` steps of ``policy`` plus Gaussian action noise (``noise`` times the action half-range), in
    episodes ending on termination or after ``sim.episode_steps`` steps; the last one is cut at ``steps``."""
    recorder = _Recorder()
    half_range = (sim.action_high - sim.action_low) / 2
    episode, t, obs = 0, 0, sim.reset(rng)
    for _ in tqdm(range(steps), desc=desc, disable=not progress, mininterval=1.0):
        state = sim.get_state()
        action = np.asarray(policy(obs), dtype=np.float64)
        if noise > 0:
            action = action + noise * half_range * rng.standard_normal(sim.act_dim)
        action = sim.clip_action(action)
        out = sim.step(action)
        t += 1
        truncated = t >= sim.episode_steps and not out.terminated
        recorder.add(episode, obs, state, action, out.reward, out.terminated, truncated)
        obs = out.observation
        if out.terminated or truncated:
            episode, t, obs = episode + 1, 0, sim.reset(rng)
    return recorder.columns()


def record_medium_rollouts(
    policy: Any, sim: LocomotionSimulator, settings: BehaviourSettings, progress: bool = False
) -> dict[str, np.ndarray]:
    """The ``medium`` dataset's rollouts of ``policy`` (an SB3 model): ``dataset_steps`` steps with
    ``rollout_noise``, from the settings' seed, so the same policy and settings give the same rows."""
    rng = np.random.default_rng([settings.seed, 1])
    return record_rollouts(sim, sb3_policy(policy), settings.dataset_steps, rng, settings.rollout_noise, progress,
                           "medium rollouts")  # fmt: skip


def rollout_scores(columns: dict[str, np.ndarray], env_id: str) -> np.ndarray:
    """The normalized score of every episode of recorded rollouts (the last one cut where the recording ends), from
    rewards rounded to the dataset's float32 as the reference stage scores the stored dataset."""
    _, index = np.unique(columns["episode"], return_inverse=True)
    returns = np.bincount(index, weights=columns["reward"].astype(np.float32).astype(np.float64))
    return np.asarray(normalized_score(returns, env_id))


# -- training -------------------------------------------------------------------------------------------------


@contextmanager
def _torch_threads(n: int) -> Iterator[None]:
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _algorithm_class(name: str) -> type:
    from stable_baselines3 import PPO, SAC, TD3

    return {"sac": SAC, "td3": TD3, "ppo": PPO}[name]


def _learn(learner: Any, steps: int, callback: Any) -> None:
    """``learner.learn`` for ``steps`` more steps with a logger that writes nowhere: SB3's default one would leave an
    empty ``SB3-<time>`` folder in the temporary directory on every call (hundreds per collection)."""
    from stable_baselines3.common.logger import Logger

    learner.set_logger(Logger(folder=None, output_formats=[]))
    learner.learn(steps, reset_num_timesteps=False, callback=callback)


def make_learner(env: gym.Env, settings: BehaviourSettings) -> Any:
    """A fresh SB3 learner on ``env`` with the settings' algorithm, networks and seed (CPU)."""
    cls = _algorithm_class(settings.algorithm)
    common = {"seed": settings.seed, "device": "cpu", "verbose": 0, "learning_rate": settings.learning_rate}
    if settings.algorithm == "ppo":
        arch = {"pi": list(settings.net_arch), "vf": list(settings.net_arch)}
        return cls("MlpPolicy", env, n_steps=settings.ppo_n_steps, batch_size=min(settings.batch_size,
                   settings.ppo_n_steps), policy_kwargs={"net_arch": arch}, **common)  # fmt: skip
    kwargs: dict[str, Any] = {
        "buffer_size": settings.max_expert_steps,
        "learning_starts": settings.learning_starts,
        "batch_size": settings.batch_size,
        "policy_kwargs": {"net_arch": list(settings.net_arch)},
    }
    if settings.algorithm == "td3":
        from stable_baselines3.common.noise import NormalActionNoise

        act_dim = env.action_space.shape[0]
        kwargs["action_noise"] = NormalActionNoise(np.zeros(act_dim), 0.1 * np.ones(act_dim))
    return cls("MlpPolicy", env, **kwargs, **common)


@dataclass
class TrainingResult:
    """What :func:`train_behaviour` did: the learner at the end, the evaluation curve and the saved policies."""

    learner: Any
    curve: list[dict[str, float]]
    replay: dict[str, np.ndarray]
    medium: dict[str, Any]
    #: the ``medium`` dataset's rollouts, recorded when the band search chose the policy (``None`` without a band)
    medium_rollouts: dict[str, np.ndarray] | None = None
    expert: dict[str, Any] | None = None
    medium_policy: Any = None
    expert_policy: Any = None


def train_behaviour(
    env_id: str,
    out_dir: Path,
    settings: BehaviourSettings,
    expert: bool = False,
    progress: bool = False,
    setting: str = "behaviour",
    resume_path: Path | None = None,
    checkpoint_every_s: float = CHECKPOINT_EVERY_S,
    resume_tag: str | None = None,
) -> TrainingResult:
    """Train until the medium score's band (see :mod:`~adaptdiffuser.families.locomotion.band`; without a band,
    the first evaluation at the medium score or the step budget's end), save ``medium.zip``; with ``expert``, go on
    to the expert score (or its budget) and save ``expert.zip``. ``behaviour.json`` in ``out_dir`` holds the
    evaluation curve. ``setting`` is the params key that errors name (``task.<name>.behaviour``). With
    ``resume_path``, the band search writes its whole state there at an evaluation every ``checkpoint_every_s``
    seconds, and a search killed midway continues from it exactly (the same policy and data as an uninterrupted
    search); the file is removed when the search is refused or training ends (a kill after the choice, in the expert
    phase say, resumes near the choice). A state is taken up only under the same env, settings, ``resume_tag`` (the
    pipeline's: the task's code digest) and library versions."""
    from stable_baselines3.common.callbacks import BaseCallback

    out_dir = Path(out_dir)
    cls = _algorithm_class(settings.algorithm)
    recorder = _Recorder()
    sim = LocomotionSimulator(env_id, episode_steps=settings.episode_steps)
    eval_sim = LocomotionSimulator(env_id, episode_steps=settings.episode_steps)
    curve: list[dict[str, float]] = []
    summary: dict[str, Any] = {"env_id": env_id, "settings": settings.model_dump(), "curve": curve}
    budget = settings.max_expert_steps if expert else settings.max_train_steps
    bar = tqdm(total=budget, desc=f"{settings.algorithm} {env_id}", disable=not progress, unit="step")

    class _Bar(BaseCallback):
        def _on_step(self) -> bool:
            bar.update(self.model.num_timesteps - bar.n)
            return True

    def save(learner: Any, name: str) -> Any:
        with atomic_path(out_dir / f"{name}.zip") as tmp:
            learner.save(tmp)
        return cls.load(out_dir / f"{name}.zip", device="cpu")

    def phase(learner: Any, target: float, limit: int, name: str, start: float) -> tuple[dict[str, Any], Any]:
        best = -math.inf
        while learner.num_timesteps < limit:
            _learn(learner, min(settings.eval_every, limit - learner.num_timesteps), _Bar())
            returns = evaluate_policy_returns(learner, eval_sim, settings.eval_episodes, settings.eval_seed)
            score = float(normalized_score(returns.mean(), env_id))
            best = max(best, score)
            curve.append({"steps": int(learner.num_timesteps), "mean_return": float(returns.mean()),
                          "normalized_score": score, "wall_s": time.perf_counter() - start})  # fmt: skip
            bar.set_postfix(score=f"{score:.1f}")
            write_json(out_dir / SUMMARY_FILE, summary)
            if score >= target:
                break
        last = curve[-1] if curve else {"steps": 0, "mean_return": math.nan, "normalized_score": math.nan}
        info = {"file": f"{name}.zip", "target": target, "reached": bool(last["normalized_score"] >= target),
                "steps": last["steps"], "mean_return": last["mean_return"],
                "normalized_score": last["normalized_score"], "best_score": best,
                "wall_s": time.perf_counter() - start}  # fmt: skip
        return info, save(learner, name)

    def medium_in_band(learner: Any) -> tuple[_Learner, dict[str, Any], Any]:
        nonlocal start
        band = Band(settings.medium_score, settings.medium_band)
        trainee = _Learner(learner, train_env, recorder, eval_sim, settings, _Bar, progress)
        key = {"env_id": env_id, "settings": settings.model_dump(), "tag": resume_tag, "versions": _versions()}
        saved = _load_search(resume_path, key)
        state = None
        if saved is not None:
            header, trainee_bytes = saved
            state = header["search"]
            trainee = _Learner.from_exact_state(trainee_bytes, eval_sim, settings, _Bar, progress)
            curve.extend(header["curve"])
            start -= header["wall_s"]  # the times go on from the interrupted search's
            bar.update(trainee.steps())
        last_write = time.monotonic()

        def on_eval(record: dict[str, Any]) -> None:
            score = record.get("confirm_score", record.get("band_score", record["quick_score"]))
            curve.append({**record, "normalized_score": score, "wall_s": time.perf_counter() - start})
            bar.set_postfix(score=f"{score:.1f}")
            write_json(out_dir / SUMMARY_FILE, summary)
            if not progress:  # a line per evaluation, so that a run without bars still shows how far it got
                tqdm.write(f"{env_id} {settings.algorithm}: {record['steps']} steps, score {score:.1f}, "
                           f"{record['action']}")  # fmt: skip

        def on_state(search: SearchState) -> None:
            nonlocal last_write
            if resume_path is None or not curve or time.monotonic() - last_write < checkpoint_every_s:
                return
            header = {**key, "search": search, "curve": list(curve), "wall_s": time.perf_counter() - start}
            _save_search(resume_path, header, trainee.exact_state())
            last_write = time.monotonic()

        try:
            choice = search_band(trainee, band, settings.eval_every, settings.min_eval_every,
                                 settings.max_train_steps, on_eval, setting=setting, state=state,
                                 on_state=on_state)  # fmt: skip
        except BandNotReachedError:
            if resume_path is not None:  # refused: the same settings would be refused again
                resume_path.unlink(missing_ok=True)
            raise
        info = {"file": "medium.zip", "target": settings.medium_score, "band": [band.low, band.high],
                "reached": True, "steps": choice.steps, "normalized_score": choice.score,
                "score_stderr": choice.stderr, "score_of": "dataset",
                "score_episodes": len(np.unique(trainee.recorded["episode"])),
                "score_noise": settings.rollout_noise,
                "spent_steps": choice.spent, "rewinds": choice.rewinds,
                "wall_s": time.perf_counter() - start}  # fmt: skip
        return trainee, info, save(trainee.learner, "medium")

    with _torch_threads(settings.torch_threads):
        train_env = _SimEnv(sim, recorder)
        learner = make_learner(train_env, settings)
        start = time.perf_counter()
        rollouts = None
        if settings.medium_band is None:
            medium, medium_policy = phase(learner, settings.medium_score, settings.max_train_steps, "medium", start)
        else:
            trainee, medium, medium_policy = medium_in_band(learner)
            learner, rollouts = trainee.learner, trainee.recorded
            train_env, recorder = trainee.env, trainee.recorder  # a resumed search brought its own
        summary["medium"] = medium
        replay = recorder.columns(len(recorder))
        result = TrainingResult(learner, curve, replay, medium, rollouts, medium_policy=medium_policy)
        if expert:
            train_env.recorder = None  # the replay after the medium point is not kept
            result.expert, result.expert_policy = phase(
                learner, settings.expert_score, settings.max_expert_steps, "expert", start
            )
            summary["expert"] = result.expert
        summary["train_steps_per_s"] = learner.num_timesteps / max(time.perf_counter() - start, 1e-9)
    if resume_path is not None:  # kept until here: a stage killed after the choice resumes the search near its end
        resume_path.unlink(missing_ok=True)
    bar.close()
    write_json(out_dir / SUMMARY_FILE, summary)
    return result


def _mean_and_stderr(scores: np.ndarray) -> tuple[float, float]:
    return float(scores.mean()), standard_error(scores)


class _Learner:
    """An SB3 learner as the band search's :class:`~adaptdiffuser.families.locomotion.band.Trainee`: snapshots are
    the saved learner (policy, optimizer, step count) with the replay recorder's length; going back reloads it,
    cuts the recorder there and reseeds (an off-policy learner restarts its replay buffer). Its confirmation records
    the ``medium`` dataset, kept in :attr:`recorded`: the chosen policy's recording is the dataset."""

    def __init__(self, learner: Any, env: _SimEnv, recorder: _Recorder, eval_sim: LocomotionSimulator,
                 settings: BehaviourSettings, callback: type, progress: bool = False) -> None:  # fmt: skip
        self.learner, self.env, self.recorder = learner, env, recorder
        self.eval_sim, self.settings, self.callback, self.progress = eval_sim, settings, callback, progress
        self.recorded: dict[str, np.ndarray] = {}

    def train(self, steps: int) -> int:
        before = self.learner.num_timesteps
        _learn(self.learner, steps, self.callback())
        return int(self.learner.num_timesteps - before)

    def steps(self) -> int:
        return int(self.learner.num_timesteps)

    def _scores(self, episodes: int, seed: int) -> np.ndarray:
        """Normalized scores per episode as the data will be recorded: deterministic action plus rollout noise."""
        noise = self.settings.rollout_noise
        returns = evaluate_policy_returns(self.learner, self.eval_sim, episodes, seed, noise=noise)
        return np.asarray(normalized_score(returns, self.eval_sim.name))

    def quick_score(self) -> float:
        return float(self._scores(self.settings.eval_episodes, self.settings.eval_seed).mean())

    def band_score(self) -> tuple[float, float]:
        return _mean_and_stderr(self._scores(self.settings.band_episodes, self.settings.eval_seed + 1))

    def confirm_score(self) -> tuple[float, float]:
        self.recorded = record_medium_rollouts(self.learner, self.eval_sim, self.settings, self.progress)
        return _mean_and_stderr(rollout_scores(self.recorded, self.eval_sim.name))

    def snapshot(self) -> tuple[bytes, int]:
        buffer = io.BytesIO()
        self.learner.save(buffer)
        return buffer.getvalue(), len(self.recorder)

    def restore(self, snapshot: tuple[bytes, int], attempt: int) -> None:
        saved, rows = snapshot
        self.learner = _algorithm_class(self.settings.algorithm).load(io.BytesIO(saved), env=self.env, device="cpu")
        self.learner.set_random_seed(derive_seed(self.settings.seed, attempt))
        self.recorder.truncate(rows)

    def exact_state(self) -> bytes:
        """Everything the training path depends on, pickled: the learner with its env (mid-episode) and buffers,
        the replay recorder and the global random streams SB3 draws from; :meth:`from_exact_state` goes on from it
        as this learner would."""
        rng = {"numpy": np.random.get_state(), "torch": _torch_rng_state(), "python": random.getstate()}
        with _compact_replay_buffer(self.learner):
            return pickle.dumps({"learner": self.learner, "env": self.env, "recorder": self.recorder, "rng": rng},
                                protocol=pickle.HIGHEST_PROTOCOL)  # fmt: skip

    @classmethod
    def from_exact_state(cls, saved: bytes, eval_sim: LocomotionSimulator, settings: BehaviourSettings,
                         callback: type, progress: bool = False) -> _Learner:  # fmt: skip
        import torch

        state = pickle.loads(saved)
        _expand_replay_buffer(state["learner"])
        np.random.set_state(state["rng"]["numpy"])
        torch.set_rng_state(state["rng"]["torch"])
        random.setstate(state["rng"]["python"])
        return cls(state["learner"], state["env"], state["recorder"], eval_sim, settings, callback, progress)


def _torch_rng_state() -> Any:
    import torch

    return torch.get_rng_state()


#: an off-policy replay buffer's arrays (SB3 ``ReplayBuffer``), allocated whole and filled from the start
_REPLAY_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


@contextmanager
def _compact_replay_buffer(learner: Any) -> Iterator[None]:
    """While pickling: an off-policy learner's replay buffer cut to its filled rows (the rest are zeros)."""
    buffer = getattr(learner, "replay_buffer", None)
    if buffer is None or buffer.full or buffer.optimize_memory_usage:  # the latter keeps a row at ``pos``
        yield
        return
    whole = {name: getattr(buffer, name) for name in _REPLAY_ARRAYS if getattr(buffer, name, None) is not None}
    try:
        for name, array in whole.items():
            setattr(buffer, name, array[: buffer.pos])
        yield
    finally:
        for name, array in whole.items():
            setattr(buffer, name, array)


def _expand_replay_buffer(learner: Any) -> None:
    """Undo :func:`_compact_replay_buffer` on an unpickled learner: zeros after the filled rows, as allocated."""
    buffer = getattr(learner, "replay_buffer", None)
    if buffer is None or buffer.full:
        return
    for name in _REPLAY_ARRAYS:
        array = getattr(buffer, name, None)
        if array is not None and len(array) < buffer.buffer_size:
            whole = np.zeros((buffer.buffer_size, *array.shape[1:]), dtype=array.dtype)
            whole[: len(array)] = array
            setattr(buffer, name, whole)


def _versions() -> dict[str, str]:
    """The versions of the libraries a saved learner is pickled with (another version may not load it alike)."""
    from importlib.metadata import version

    return {name: version(name) for name in ("stable-baselines3", "torch", "gymnasium", "mujoco", "numpy")}


def _save_search(path: Path, header: dict[str, Any], trainee: bytes) -> None:
    """Write a search's state atomically: ``header`` (key, search state, curve) pickled, then the trainee's bytes."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        pickle.dump(header, f, protocol=pickle.HIGHEST_PROTOCOL)
        f.write(trainee)


def _load_search(path: Path | None, key: dict[str, Any]) -> tuple[dict[str, Any], bytes] | None:
    """The header and trainee bytes of the band search saved at ``path`` when it was written under the same ``key``
    (env, settings, code, library versions; saying so), else ``None`` (saying why, when a state is ignored)."""
    if path is None or not path.exists():
        return None
    try:
        with open(path, "rb") as f:
            header = pickle.load(f)
            trainee = f.read()
    except Exception as err:  # a state that cannot be read is of no use: start over (and overwrite it)
        tqdm.write(f"ignoring behaviour search state {path}: unreadable ({type(err).__name__}: {err})")
        return None
    if not isinstance(header, dict) or {name: header.get(name) for name in key} != key:
        tqdm.write(f"ignoring behaviour search state {path}: it belongs to other settings, code or libraries")
        return None
    tqdm.write(f"resuming the behaviour search after {len(header['curve'])} evaluations ({path})")
    return header, trainee


# -- datasets -------------------------------------------------------------------------------------------------


def to_trajectories(parts: list[dict[str, np.ndarray]], task_name: str, sim: LocomotionSimulator,
                    generator: dict[str, Any]) -> Trajectories:  # fmt: skip
    """Recorded parts, one after the other, as :class:`Trajectories` with consecutive episode ids from 0."""
    episode_ids, offset = [], 0
    for part in parts:
        _, ids = np.unique(part["episode"], return_inverse=True)
        episode_ids.append(ids + offset)
        offset += int(ids.max()) + 1 if len(ids) else 0
    episode_id = np.concatenate(episode_ids).astype(np.int64)
    step = np.zeros(len(episode_id), dtype=np.int32)
    if len(episode_id):
        starts = np.flatnonzero(np.r_[True, np.diff(episode_id) != 0])
        counts = np.diff(np.r_[starts, len(episode_id)])
        step = (np.arange(len(episode_id)) - np.repeat(starts, counts)).astype(np.int32)
    cat = {key: np.concatenate([p[key] for p in parts]) for key in ("observation", "action", "reward", "terminal",
                                                                      "timeout", "state")}  # fmt: skip
    return Trajectories(
        episode_id=episode_id,
        step=step,
        observation=cat["observation"].astype(np.float32),
        action=cat["action"].astype(np.float32),
        reward=cat["reward"].astype(np.float32),
        terminal=cat["terminal"],
        timeout=cat["timeout"],
        metadata=make_metadata(task_name, sim.obs_dim, sim.act_dim, "expert", generator, state_dim=sim.state_dim),
        sim_state=cat["state"],
    )


def collect_locomotion_dataset(
    task_name: str,
    out_dir: Path,
    settings: BehaviourSettings,
    progress: bool = False,
    resume_path: Path | None = None,
    checkpoint_every_s: float = CHECKPOINT_EVERY_S,
    resume_tag: str | None = None,
) -> Trajectories:
    """Train the behaviour policies of ``task_name`` (saved in ``out_dir``) and record its D4RL-style dataset;
    ``resume_path``, ``checkpoint_every_s`` and ``resume_tag`` as :func:`train_behaviour`'s."""
    env_id, kind = parse_task_name(task_name)
    sim = LocomotionSimulator(env_id, episode_steps=settings.episode_steps)
    result = train_behaviour(env_id, out_dir, settings, expert=kind == "medium-expert", progress=progress,
                             setting=f"task.{task_name}.behaviour", resume_path=resume_path,
                             checkpoint_every_s=checkpoint_every_s, resume_tag=resume_tag)  # fmt: skip
    generator: dict[str, Any] = {
        "recipe": "d4rl-regenerated",
        "env_id": env_id,
        "dataset": kind,
        "settings": settings.model_dump(),
        "medium": _without_times(result.medium),
        "expert": _without_times(result.expert),
    }
    if kind == "medium-replay":
        parts = [result.replay]
    else:
        with _torch_threads(settings.torch_threads):
            medium = result.medium_rollouts  # recorded by the band search when it chose the policy
            if medium is None:
                medium = record_medium_rollouts(result.medium_policy, sim, settings, progress)
            parts = [medium]
            if kind == "medium-expert":
                rng = np.random.default_rng([settings.seed, 2])
                parts.append(record_rollouts(sim, sb3_policy(result.expert_policy), settings.dataset_steps, rng,
                                             settings.rollout_noise, progress, "expert rollouts"))  # fmt: skip
    return to_trajectories(parts, task_name, sim, generator)


def _without_times(info: dict[str, Any] | None) -> dict[str, Any] | None:
    """A policy's record as the dataset stores it: without wall-clock times, so that the same seed writes the same
    dataset bytes on every run (``behaviour.json`` keeps the times)."""
    return None if info is None else {key: value for key, value in info.items() if key != "wall_s"}


def load_behaviour_policy(out_dir: Path, which: Literal["medium", "expert"] = "medium") -> Any:
    """A saved behaviour policy (SB3 model) from ``out_dir``, its algorithm read from ``behaviour.json``."""
    summary = json.loads((Path(out_dir) / SUMMARY_FILE).read_text())
    return _algorithm_class(summary["settings"]["algorithm"]).load(Path(out_dir) / f"{which}.zip", device="cpu")
