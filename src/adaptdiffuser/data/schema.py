"""The project's one trajectory schema, as Parquet: one row per step.

Columns: ``episode_id`` (int64), ``step`` (int32), ``observation`` and ``action`` (fixed-size float32 lists),
``reward`` (float32), ``terminal`` and ``timeout`` (bool), and, when the metadata's ``state_dim`` is positive,
``sim_state`` (fixed-size float64 list): the simulator's full state (e.g. MuJoCo qpos + qvel) before the step, so
any dataset state can be restored exactly. Extra columns (for example the task a synthetic
trajectory was generated for) are allowed and kept. File metadata, under the key ``adaptdiffuser``, is a JSON
object naming the environment, the dimensions, the source (``expert`` or ``synthetic``), the generator's params
and the schema version.
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


class SchemaError(ValueError):
    """A trajectory file does not match the schema; the message names the column or field."""


def arrow_schema(obs_dim: int, act_dim: int, state_dim: int = 0) -> pa.Schema:
    """The Arrow schema of the required columns for the given dimensions."""
    fields = [
        ("episode_id", pa.int64()),
        ("step", pa.int32()),
        ("observation", pa.list_(pa.float32(), obs_dim)),
        ("action", pa.list_(pa.float32(), act_dim)),
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
        pa.FixedSizeListArray.from_arrays(pa.array(traj.action.astype(np.float32).ravel()), act_dim),
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


def read_trajectories(path: str | Path) -> Trajectories:
    """Read and validate a trajectory file; raise :class:`SchemaError` naming what does not match."""
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
    state_dim = meta.get("state_dim", 0)
    expected = arrow_schema(meta["obs_dim"], meta["act_dim"], state_dim)
    for fld in expected:
        if fld.name not in table.column_names:
            raise SchemaError(f"{path}: missing column {fld.name!r}")
        actual = table.schema.field(fld.name).type
        if actual != fld.type:
            raise SchemaError(f"{path}: column {fld.name!r} has type {actual}, expected {fld.type}")
    for name in ("observation", "action"):
        if table.column(name).null_count:
            raise SchemaError(f"{path}: column {name!r} contains nulls")
    n = table.num_rows
    traj = Trajectories(
        episode_id=table.column("episode_id").to_numpy(),
        step=table.column("step").to_numpy(),
        observation=_fixed_list(table, "observation", n, meta["obs_dim"]),
        action=_fixed_list(table, "action", n, meta["act_dim"]),
        reward=table.column("reward").to_numpy(),
        terminal=table.column("terminal").to_numpy(zero_copy_only=False),
        timeout=table.column("timeout").to_numpy(zero_copy_only=False),
        metadata=meta,
        extra={name: _column_numpy(table, name) for name in table.column_names if name not in expected.names},
        sim_state=_fixed_list(table, "sim_state", n, state_dim) if state_dim else None,
    )
    if n and np.any(np.diff(traj.episode_id) < 0):
        raise SchemaError(f"{path}: column 'episode_id' must be grouped in ascending order")
    return traj


def _fixed_list(table: pa.Table, name: str, n: int, dim: int) -> np.ndarray:
    flat = table.column(name).combine_chunks().flatten().to_numpy()
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
    for key in ("obs_dim", "act_dim"):
        if not isinstance(meta[key], int) or meta[key] <= 0:
            raise SchemaError(f"{path}: metadata field {key!r} must be a positive integer, got {meta[key]!r}")
    state_dim = meta.get("state_dim", 0)
    if not isinstance(state_dim, int) or state_dim < 0:
        raise SchemaError(f"{path}: metadata field 'state_dim' must be a non-negative integer, got {state_dim!r}")
