"""External offline data as plain arrays, and D4RL's HDF5 layout read into them.

:class:`ExternalData` is what every importer yields and what a family turns into its task's
:class:`~adaptdiffuser.data.schema.Trajectories` (:meth:`~adaptdiffuser.contract.Family.from_external`): one
row per step, episodes one after the other, in the source's own coordinates and with its own field names kept where
a family needs them (``parts``: the entries of a dict observation, such as Minari's ``desired_goal``).

A D4RL file (``h5py``) holds ``observations``, ``actions``, ``rewards``, ``terminals`` and ``timeouts`` (one row
per step), and where present ``infos/qpos``, ``infos/qvel`` and ``infos/goal``. Episodes end where ``terminals`` or
``timeouts`` is set; D4RL's Maze2D files are one stream whose episodes end where the goal (``infos/goal``) changes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from adaptdiffuser.data.schema import SchemaError, Trajectories, make_metadata

#: the per-step fields every D4RL file has
D4RL_FIELDS = ("observations", "actions", "rewards", "terminals", "timeouts")
#: the optional ones, under ``infos/``
D4RL_INFOS = ("qpos", "qvel", "goal")


class DataImportError(SchemaError):
    """External data cannot be imported; the one-line message names the file, the field and what was expected."""


@dataclass
class ExternalData:
    """Steps of external episodes as plain arrays (``N`` rows), with where they came from.

    ``format`` is ``d4rl`` or ``minari`` (families convert coordinates by it); ``episode_end[i]`` is true on the
    last row of each episode; ``observations`` is the flat observation (Minari: its ``observation`` entry when the
    observations are dicts, the other entries in ``parts``)."""

    source: str
    format: str
    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminals: np.ndarray
    timeouts: np.ndarray
    episode_end: np.ndarray
    qpos: np.ndarray | None = None
    qvel: np.ndarray | None = None
    goal: np.ndarray | None = None
    parts: dict[str, np.ndarray] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.actions)

    def episode_ids(self) -> np.ndarray:
        """Episode index of every row (0, 1, ... in order)."""
        return np.concatenate([[0], np.cumsum(self.episode_end[:-1])]).astype(np.int64) if len(self) else np.zeros(0)

    def steps(self) -> np.ndarray:
        """Step index of every row within its episode."""
        ids = self.episode_ids()
        if not len(ids):
            return np.zeros(0, dtype=np.int32)
        starts = np.flatnonzero(np.r_[True, np.diff(ids) != 0])
        return (np.arange(len(ids)) - np.repeat(starts, np.diff(np.r_[starts, len(ids)]))).astype(np.int32)

    def trajectories(
        self,
        task: str,
        observation: np.ndarray,
        action: np.ndarray,
        generator: dict[str, Any],
        sim_state: np.ndarray | None = None,
    ) -> Trajectories:
        """These steps as task ``task``'s expert dataset, with the family's converted ``observation`` and ``action``
        (and full ``sim_state`` when it has one): episodes, steps, rewards, and terminal/timeout on each episode's
        last row as the source ends it; ``generator`` (after this source's metadata) goes into the file metadata."""
        end = self.episode_end
        state_dim = 0 if sim_state is None else sim_state.shape[1]
        return Trajectories(
            episode_id=self.episode_ids(),
            step=self.steps(),
            observation=observation.astype(np.float32),
            action=action.astype(np.float32),
            reward=self.rewards.astype(np.float32),
            terminal=self.terminals & end,
            timeout=end & ~self.terminals,
            metadata=make_metadata(
                task,
                observation.shape[1],
                action.shape[1],
                "expert",
                {"recipe": "import", **self.metadata, **generator},
                state_dim=state_dim,
            ),
            sim_state=None if sim_state is None else sim_state.astype(np.float64),
        )

    def fail(self, name: str, problem: str) -> DataImportError:
        """The one-line error about field ``name`` of this source."""
        return DataImportError(f"{self.source}: field {name!r} {problem}")

    def check_dim(self, name: str, values: np.ndarray | None, expected: int, task: str) -> None:
        """Refuse a field whose per-step dimension is not ``expected`` (the task's environment)."""
        found = None if values is None else (values.shape[1] if values.ndim == 2 else 1)
        if found != expected:
            raise self.fail(name, f"has dimension {found}, expected {expected} for task {task}'s environment")


def episode_ends(terminals: np.ndarray, timeouts: np.ndarray, goal: np.ndarray | None = None) -> np.ndarray:
    """True on the last row of each episode: where ``terminals`` or ``timeouts`` is set, before a change of
    ``goal`` (when given) and on the last row."""
    end = np.asarray(terminals, dtype=bool) | np.asarray(timeouts, dtype=bool)
    if goal is not None and len(goal) > 1:
        changed = np.any(np.asarray(goal)[1:] != np.asarray(goal)[:-1], axis=tuple(range(1, np.ndim(goal))))
        end[:-1] |= changed
    if len(end):
        end[-1] = True
    return end


def read_d4rl(path: str | Path) -> ExternalData:
    """A D4RL HDF5 file as :class:`ExternalData`; :class:`DataImportError` naming the file and field when a required
    field is missing or the fields disagree on the number of steps."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"D4RL file not found: {path}")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise DataImportError(f"{path}: not a readable HDF5 file ({err})") from err
    with f:
        arrays: dict[str, np.ndarray] = {}
        for name in D4RL_FIELDS:
            if name not in f:
                if name == "timeouts":  # some D4RL files predate the timeouts field
                    continue
                raise DataImportError(f"{path}: field {name!r} is missing (D4RL files hold {', '.join(D4RL_FIELDS)})")
            arrays[name] = np.asarray(f[name][()])
        for name in D4RL_INFOS:
            key = f"infos/{name}"
            if key in f:
                arrays[name] = np.asarray(f[key][()])
    n = len(arrays["actions"])
    arrays.setdefault("timeouts", np.zeros(n, dtype=bool))
    for name, values in arrays.items():
        where = name if name in D4RL_FIELDS else f"infos/{name}"
        if len(values) != n:
            raise DataImportError(f"{path}: field {where!r} has {len(values)} rows, 'actions' has {n}")
    if n == 0:
        raise DataImportError(f"{path}: field 'actions' is empty")
    for name in ("observations", "actions"):
        if arrays[name].ndim != 2:
            raise DataImportError(
                f"{path}: field {name!r} must be a (steps, dim) array, got shape {arrays[name].shape}"
            )
    terminals, timeouts = arrays["terminals"].astype(bool).reshape(n), arrays["timeouts"].astype(bool).reshape(n)
    goal = arrays.get("goal")
    return ExternalData(
        source=str(path),
        format="d4rl",
        observations=arrays["observations"].astype(np.float64),
        actions=arrays["actions"].astype(np.float64),
        rewards=arrays["rewards"].astype(np.float64).reshape(n),
        terminals=terminals,
        timeouts=timeouts,
        episode_end=episode_ends(terminals, timeouts, goal),
        qpos=arrays.get("qpos"),
        qvel=arrays.get("qvel"),
        goal=goal,
        metadata={"format": "d4rl", "path": str(path)},
    )


def write_d4rl(path: str | Path, data: dict[str, np.ndarray]) -> Path:
    """Write arrays in D4RL's layout (``observations``... at the top, ``qpos``/``qvel``/``goal`` under ``infos/``):
    for tests and for handing our data to D4RL-based code."""
    import h5py

    from adaptdiffuser.io import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        for name, values in data.items():
            f.create_dataset(name if name in D4RL_FIELDS else f"infos/{name}", data=np.asarray(values))
    return path
