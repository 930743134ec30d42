"""The project's one trajectory schema, as Parquet: one row per step.

Columns: ``episode_id`` (int64), ``step`` (int32), ``observation`` and ``action`` (fixed-size float32 lists; for
state-only datasets, whose metadata says ``act_dim`` 0, ``action`` holds empty lists),
``reward`` (float32), ``terminal`` and ``timeout`` (bool), and, when the metadata's ``state_dim`` is positive,
``sim_state`` (fixed-size float64 list): the simulator's full state (e.g. MuJoCo qpos + qvel) before the step, so
any dataset state can be restored exactly. Extra columns (for example the task a synthetic
trajectory was generated for) are allowed and kept. File metadata, under the key ``adaptdiffuser``, is a JSON
object naming the environment, the dimensions, the source (``expert`` or ``synthetic``), the generator's params
and the schema version.

Reading refuses, with a one-line :class:`SchemaError` naming the file, the column and the first bad row: nulls,
NaN or infinite values in the float columns of the schema (extra columns are the writer's own: a family may use
NaN there for "none"), steps that do not strictly increase within an episode, and, when the caller names the
environment it expects, a file whose metadata names another.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from adaptdiffuser.io import atomic_path

SCHEMA_VERSION = 2
#: versions this code reads: version 1 files are version 2 files without the optional ``sim_state`` column
READABLE_VERSIONS = (1, 2)
METADATA_KEY = b"adaptdiffuser"
SOURCES = ("expert", "synthetic")
REQUIRED_METADATA = ("env", "obs_dim", "act_dim", "source", "generator", "schema_version")
#: the schema's float columns, which must hold finite values only
FLOAT_COLUMNS = ("observation", "action", "reward", "sim_state")


class SchemaError(ValueError):
    """A trajectory file does not match the schema; the message names the column or field."""


def arrow_schema(obs_dim: int, act_dim: int, state_dim: int = 0) -> pa.Schema:
    """The Arrow schema of the required columns for the given dimensions."""
    fields = [
        ("episode_id", pa.int64()),
        ("step", pa.int32()),
        ("observation", pa.list_(pa.float32(), obs_dim)),
        ("action", pa.list_(pa.float32(), act_dim) if act_dim else pa.list_(pa.float32())),
        ("reward", pa.float32()),
        ("terminal", pa.bool_()),
        ("timeout", pa.bool_()),
    ]
    if state_dim > 0:
        fields.append(("sim_state", pa.list_(pa.float64(), state_dim)))
    return pa.schema(fields)


@dataclass
class Trajectories:
    """Steps of many episodes in columnar numpy form, plus the file metadata."""

    episode_id: np.ndarray
    step: np.ndarray
    observation: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    terminal: np.ndarray
    timeout: np.ndarray
    metadata: dict[str, Any]
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    sim_state: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.episode_id)

    def episodes(self) -> list[slice]:
        """Row slices of each episode (rows are stored grouped by episode, in step order)."""
        if len(self) == 0:
            return []
        bounds = np.flatnonzero(np.diff(self.episode_id)) + 1
        starts = np.concatenate([[0], bounds])
        ends = np.concatenate([bounds, [len(self)]])
        return [slice(int(s), int(e)) for s, e in zip(starts, ends, strict=True)]


def make_metadata(
    env: str, obs_dim: int, act_dim: int, source: str, generator: dict[str, Any], state_dim: int = 0
) -> dict:
    """File metadata for a trajectory file (``state_dim`` > 0 when rows carry the simulator's full state)."""
    if source not in SOURCES:
        raise SchemaError(f"metadata field 'source' must be one of {SOURCES}, got {source!r}")
    return {
        "env": env,
        "obs_dim": int(obs_dim),
        "act_dim": int(act_dim),
        "state_dim": int(state_dim),
        "source": source,
        "generator": generator,
        "schema_version": SCHEMA_VERSION,
    }


def write_trajectories(path: str | Path, traj: Trajectories) -> None:
    """Validate and write ``traj`` to ``path`` atomically."""
    meta = traj.metadata
    _check_metadata(meta, path)
    n = len(traj)
    obs_dim, act_dim = meta["obs_dim"], meta["act_dim"]
    if traj.observation.shape != (n, obs_dim):
        raise SchemaError(f"column 'observation' must have shape ({n}, {obs_dim}), got {traj.observation.shape}")
    if traj.action.shape != (n, act_dim):
        raise SchemaError(f"column 'action' must have shape ({n}, {act_dim}), got {traj.action.shape}")
    if n and np.any(np.diff(traj.episode_id) < 0):
        raise SchemaError("column 'episode_id' must be grouped in ascending order")
    state_dim = meta.get("state_dim", 0)
    if state_dim and (traj.sim_state is None or traj.sim_state.shape != (n, state_dim)):
        got = None if traj.sim_state is None else traj.sim_state.shape
        raise SchemaError(f"column 'sim_state' must have shape ({n}, {state_dim}) (metadata state_dim), got {got}")
    if not state_dim and traj.sim_state is not None:
        raise SchemaError("column 'sim_state' is given but metadata field 'state_dim' is 0")
    schema = arrow_schema(obs_dim, act_dim, state_dim)
    columns = [
        pa.array(traj.episode_id.astype(np.int64)),
        pa.array(traj.step.astype(np.int32)),
        pa.FixedSizeListArray.from_arrays(pa.array(traj.observation.astype(np.float32).ravel()), obs_dim),
        _action_array(traj.action, act_dim),
        pa.array(traj.reward.astype(np.float32)),
        pa.array(traj.terminal.astype(bool)),
        pa.array(traj.timeout.astype(bool)),
    ]
    if state_dim:
        columns.append(
            pa.FixedSizeListArray.from_arrays(pa.array(traj.sim_state.astype(np.float64).ravel()), state_dim)
        )
    for name, values in traj.extra.items():
        values = np.asarray(values)
        if values.ndim == 2:
            arr = pa.FixedSizeListArray.from_arrays(pa.array(values.ravel()), values.shape[1])
        else:
            arr = pa.array(values)
        schema = schema.append(pa.field(name, arr.type))
        columns.append(arr)
    schema = schema.with_metadata({METADATA_KEY: json.dumps(meta).encode()})
    table = pa.Table.from_arrays(columns, schema=schema)
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)


def _action_array(action: np.ndarray, act_dim: int) -> pa.Array:
    """The action column: fixed-size lists, or for state-only datasets (``act_dim`` 0) empty lists (Parquet cannot
    store fixed-size lists of size 0)."""
    if act_dim == 0:
        return pa.ListArray.from_arrays(pa.array(np.zeros(len(action) + 1, np.int32)), pa.array([], pa.float32()))
    return pa.FixedSizeListArray.from_arrays(pa.array(action.astype(np.float32).ravel()), act_dim)


def read_trajectories(path: str | Path, env: str | None = None) -> Trajectories:
    """Read and validate a trajectory file; raise :class:`SchemaError` naming what does not match. With ``env``
    (a task name, such as ``maze2d-umaze``), also refuse a file whose metadata names another environment."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"trajectory file not found: {path}")
    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as err:
        raise SchemaError(f"{path}: not a readable Parquet file ({err})") from err
    raw = (table.schema.metadata or {}).get(METADATA_KEY)
    if raw is None:
        raise SchemaError(f"{path}: missing file metadata key 'adaptdiffuser'")
    try:
        meta = json.loads(raw)
    except json.JSONDecodeError as err:
        raise SchemaError(f"{path}: file metadata 'adaptdiffuser' is not valid JSON") from err
    _check_metadata(meta, path)
    if env is not None and meta["env"] != env:
        raise SchemaError(f"{path}: metadata field 'env' is {meta['env']!r}, expected {env!r} (a file of another task)")
    state_dim = meta.get("state_dim", 0)
    expected = arrow_schema(meta["obs_dim"], meta["act_dim"], state_dim)
    for fld in expected:
        if fld.name not in table.column_names:
            raise SchemaError(f"{path}: missing column {fld.name!r}")
        actual = table.schema.field(fld.name).type
        if actual != fld.type:
            raise SchemaError(f"{path}: column {fld.name!r} has type {actual}, expected {fld.type}")
    for name in expected.names:
        _check_no_nulls(table, name, path)
    n = table.num_rows
    traj = Trajectories(
        episode_id=table.column("episode_id").to_numpy(),
        step=table.column("step").to_numpy(),
        observation=_fixed_list(table, "observation", n, meta["obs_dim"], path),
        action=_fixed_list(table, "action", n, meta["act_dim"], path),
        reward=table.column("reward").to_numpy(),
        terminal=table.column("terminal").to_numpy(zero_copy_only=False),
        timeout=table.column("timeout").to_numpy(zero_copy_only=False),
        metadata=meta,
        extra={name: _column_numpy(table, name) for name in table.column_names if name not in expected.names},
        sim_state=_fixed_list(table, "sim_state", n, state_dim, path) if state_dim else None,
    )
    if n and np.any(np.diff(traj.episode_id) < 0):
        raise SchemaError(f"{path}: column 'episode_id' must be grouped in ascending order")
    _check_steps(traj, path)
    for name in FLOAT_COLUMNS:
        if getattr(traj, name) is not None:
            _check_finite(traj, name, getattr(traj, name), path)
    return traj


def _where(traj: Trajectories, row: int) -> str:
    """``row R (episode E, step S)`` for error messages."""
    return f"row {row} (episode {traj.episode_id[row]}, step {traj.step[row]})"


def _check_no_nulls(table: pa.Table, name: str, path: Path) -> None:
    """No null in column ``name``, nor inside its lists; otherwise name the first row holding one."""
    offset = 0
    for chunk in table.column(name).chunks:
        values, size = chunk, 1
        if not chunk.null_count and pa.types.is_fixed_size_list(chunk.type):
            values, size = chunk.flatten(), chunk.type.list_size
        if values.null_count:
            row = offset + int(np.flatnonzero(values.is_null().to_numpy(zero_copy_only=False))[0]) // size
            raise SchemaError(f"{path}: column {name!r} contains nulls, first at row {row}")
        offset += len(chunk)


def _check_steps(traj: Trajectories, path: Path) -> None:
    """Steps strictly increase within each episode (rows grouped by episode)."""
    same_episode = traj.episode_id[1:] == traj.episode_id[:-1]
    bad = np.flatnonzero(same_episode & (traj.step[1:] <= traj.step[:-1]))
    if len(bad):
        row = int(bad[0]) + 1
        raise SchemaError(
            f"{path}: column 'step' does not increase within episode {traj.episode_id[row]} at row {row} "
            f"(step {traj.step[row]} after {traj.step[row - 1]})"
        )


def _check_finite(traj: Trajectories, name: str, values: np.ndarray, path: Path) -> None:
    """Every value of the float column ``name`` is finite; otherwise name the first bad row and its value."""
    finite = np.isfinite(values)
    if finite.all():
        return
    rows = finite.reshape(len(values), -1).all(axis=1)
    row = int(np.flatnonzero(~rows)[0])
    flat = values[row].reshape(-1)
    element = int(np.flatnonzero(~np.isfinite(flat))[0])
    where = f"{_where(traj, row)}, element {element}" if values.ndim > 1 else _where(traj, row)
    raise SchemaError(f"{path}: column {name!r} holds {flat[element]} at {where}; values must be finite")


def _fixed_list(table: pa.Table, name: str, n: int, dim: int, path: Path) -> np.ndarray:
    flat = table.column(name).combine_chunks().flatten().to_numpy()
    if flat.size != n * dim:  # only variable-size lists (state-only actions) can disagree with the metadata
        raise SchemaError(f"{path}: column {name!r} holds {flat.size} values for {n} rows of {dim} (metadata)")
    return flat.reshape(n, dim)


def _column_numpy(table: pa.Table, name: str) -> np.ndarray:
    col = table.column(name).combine_chunks()
    if pa.types.is_fixed_size_list(col.type):
        return col.flatten().to_numpy(zero_copy_only=False).reshape(len(col), col.type.list_size)
    return col.to_numpy(zero_copy_only=False)


def _check_metadata(meta: dict, path: str | Path) -> None:
    for key in REQUIRED_METADATA:
        if key not in meta:
            raise SchemaError(f"{path}: file metadata is missing field {key!r}")
    if meta["schema_version"] not in READABLE_VERSIONS:
        raise SchemaError(
            f"{path}: metadata field 'schema_version' is {meta['schema_version']}, this code reads {READABLE_VERSIONS}"
        )
    if meta["source"] not in SOURCES:
        raise SchemaError(f"{path}: metadata field 'source' must be one of {SOURCES}, got {meta['source']!r}")
    if not isinstance(meta["obs_dim"], int) or meta["obs_dim"] <= 0:
        raise SchemaError(f"{path}: metadata field 'obs_dim' must be a positive integer, got {meta['obs_dim']!r}")
    if not isinstance(meta["act_dim"], int) or meta["act_dim"] < 0:
        raise SchemaError(
            f"{path}: metadata field 'act_dim' must be a non-negative integer (0: states only), got {meta['act_dim']!r}"
        )
    state_dim = meta.get("state_dim", 0)
    if not isinstance(state_dim, int) or state_dim < 0:
        raise SchemaError(f"{path}: metadata field 'state_dim' must be a non-negative integer, got {state_dim!r}")
