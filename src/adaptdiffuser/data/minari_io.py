"""Minari datasets: read one (by folder or by id in the local Minari store) into :class:`ExternalData`, and write
one of our trajectory files as a Minari dataset that ``minari.load_dataset`` opens.

Minari stores ``N + 1`` observations per episode of ``N`` steps (the last one after the last action). Reading keeps
the ``N`` observations the actions were taken at; writing turns an episode of ``n`` rows into ``n`` observations and
the ``n - 1`` transitions between them (our files keep no observation after an episode's last step), so a round trip
gives the same observations and all but each episode's last action.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from adaptdiffuser.data.d4rl import DataImportError, ExternalData
from adaptdiffuser.data.schema import Trajectories


def minari_data_path(path_or_id: str | Path) -> Path:
    """The ``data`` folder of a Minari dataset given as its folder (or its ``data`` folder), or as an id of the local
    Minari store (``$MINARI_DATASETS_PATH``, default ``~/.minari/datasets``)."""
    path = Path(path_or_id).expanduser()
    for candidate in (path / "data", path):
        if (candidate / "metadata.json").is_file():
            return candidate
    if not path.is_absolute():
        from minari.storage.datasets_root_dir import get_dataset_path

        local = get_dataset_path(str(path_or_id)) / "data"
        if (local / "metadata.json").is_file():
            return local
        raise FileNotFoundError(
            f"Minari dataset {str(path_or_id)!r} is neither a folder nor in the local store {local}"
        )
    raise FileNotFoundError(f"Minari dataset folder not found: {path} (expected {path / 'data' / 'metadata.json'})")


def read_minari(path_or_id: str | Path) -> ExternalData:
    """A Minari dataset (its folder, or its id in the local store) as :class:`ExternalData`: dict observations are
    split into ``observation`` (the flat one) and the other entries in ``parts``; ``infos`` ``qpos``, ``qvel`` and
    ``goal`` are kept where recorded."""
    from minari.dataset.minari_dataset import MinariDataset

    data_path = minari_data_path(path_or_id)
    source = str(data_path.parent)
    dataset = MinariDataset(data_path)
    columns: dict[str, list[np.ndarray]] = {}
    parts: dict[str, list[np.ndarray]] = {}
    ends: list[np.ndarray] = []
    for episode in dataset.iterate_episodes():
        n = len(episode.actions)
        if n == 0:
            continue
        obs = episode.observations
        if isinstance(obs, dict):
            if "observation" not in obs:
                raise DataImportError(f"{source}: dict observations have no 'observation' entry (have {sorted(obs)})")
            for key, values in obs.items():
                if key != "observation":
                    parts.setdefault(key, []).append(np.asarray(values)[:n].reshape(n, -1))
            obs = obs["observation"]
        if not isinstance(obs, np.ndarray):
            raise DataImportError(f"{source}: field 'observations' must be arrays, got {type(obs).__name__}")
        columns.setdefault("observations", []).append(np.asarray(obs)[:n].reshape(n, -1))
        columns.setdefault("actions", []).append(np.asarray(episode.actions).reshape(n, -1))
        columns.setdefault("rewards", []).append(np.asarray(episode.rewards, dtype=np.float64).reshape(n))
        columns.setdefault("terminals", []).append(np.asarray(episode.terminations, dtype=bool).reshape(n))
        columns.setdefault("timeouts", []).append(np.asarray(episode.truncations, dtype=bool).reshape(n))
        infos = episode.infos or {}
        for key in ("qpos", "qvel", "goal"):
            if key in infos:
                columns.setdefault(key, []).append(np.asarray(infos[key])[:n].reshape(n, -1))
        end = np.zeros(n, dtype=bool)
        end[-1] = True
        ends.append(end)
    if not ends:
        raise DataImportError(f"{source}: the dataset holds no steps")
    cat = {key: np.concatenate(values) for key, values in columns.items()}
    n_episodes = len(ends)
    optional = {key: cat[key] if len(columns.get(key, [])) == n_episodes else None for key in ("qpos", "qvel", "goal")}
    metadata = {"format": "minari", "path": source, "dataset_id": dataset.spec.dataset_id}
    env_spec = dataset.spec.env_spec
    if env_spec is not None:
        metadata["env_id"] = env_spec.id
    return ExternalData(
        source=source,
        format="minari",
        observations=cat["observations"].astype(np.float64),
        actions=cat["actions"].astype(np.float64),
        rewards=cat["rewards"],
        terminals=cat["terminals"],
        timeouts=cat["timeouts"],
        episode_end=np.concatenate(ends),
        parts={key: np.concatenate(values) for key, values in parts.items() if len(values) == n_episodes},
        metadata=metadata,
        **optional,
    )


@contextlib.contextmanager
def minari_root(path: str | Path | None) -> Iterator[None]:
    """Use ``path`` as the Minari store (``MINARI_DATASETS_PATH``) inside the block; None keeps the current one."""
    if path is None:
        yield
        return
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(Path(path).expanduser().resolve())
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


def export_minari(
    traj: Trajectories,
    dataset_id: str,
    env_spec: Any,
    observation_space: Any,
    action_space: Any,
    description: str,
    root: str | Path | None = None,
    force: bool = False,
) -> Path:
    """Write ``traj`` as the Minari dataset ``dataset_id`` (``namespace/name-v0``) in the store ``root`` (default:
    the local Minari store) with ``env_spec`` and the spaces; refuse an existing id unless ``force``. Returns the
    dataset's folder. Episodes of a single row (no transition) are left out."""
    import minari
    from minari.data_collector import EpisodeBuffer
    from minari.storage.datasets_root_dir import get_dataset_path

    with minari_root(root):
        folder = get_dataset_path(dataset_id)
        if folder.exists():
            if not force:
                raise FileExistsError(f"Minari dataset {dataset_id!r} exists at {folder}; pass --force to replace it")
            minari.delete_dataset(dataset_id)
        buffers = []
        for index, rows in enumerate(traj.episodes()):
            n = rows.stop - rows.start
            if n < 2:
                continue
            moves = slice(rows.start, rows.stop - 1)  # the n - 1 transitions between the n observations
            terminal = np.zeros(n - 1, dtype=bool)
            timeout = np.zeros(n - 1, dtype=bool)
            terminal[-1] = bool(traj.terminal[rows.stop - 1])
            timeout[-1] = not terminal[-1]  # our files end every episode by a termination or the data's cut
            buffers.append(
                EpisodeBuffer(
                    id=index,
                    observations=traj.observation[rows].astype(np.float32),
                    actions=traj.action[moves].astype(np.float32),
                    rewards=traj.reward[moves].astype(np.float64).tolist(),
                    terminations=terminal.tolist(),
                    truncations=timeout.tolist(),
                )
            )
        if not buffers:
            raise DataImportError(f"nothing to export to {dataset_id!r}: no episode has two steps or more")
        with warnings.catch_warnings():  # minari warns about every optional field left out (email, code link...)
            warnings.simplefilter("ignore", UserWarning)
            minari.create_dataset_from_buffers(
                dataset_id=dataset_id,
                buffer=buffers,
                env=env_spec,
                algorithm_name=str(traj.metadata.get("generator", {}).get("recipe", traj.metadata.get("source"))),
                author="adaptdiffuser",
                observation_space=observation_space,
                action_space=action_space,
                description=description,
            )
        return get_dataset_path(dataset_id)
