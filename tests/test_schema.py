"""The Parquet trajectory schema: round trips on real files, and every way a file can fail to match."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from adaptdiffuser.data.schema import (
    METADATA_KEY,
    SCHEMA_VERSION,
    SchemaError,
    Trajectories,
    arrow_schema,
    make_metadata,
    read_trajectories,
    write_trajectories,
)

OBS_DIM, ACT_DIM = 4, 2


def make_traj(lengths: list[int], seed: int = 0) -> Trajectories:
    """Random trajectories with the given episode lengths (episode ids 0, 1, ...)."""
    rng = np.random.default_rng(seed)
    n = sum(lengths)
    return Trajectories(
        episode_id=np.repeat(np.arange(len(lengths)), lengths).astype(np.int64),
        step=np.concatenate([np.arange(k) for k in lengths] or [np.zeros(0)]).astype(np.int32),
        observation=rng.normal(size=(n, OBS_DIM)).astype(np.float32),
        action=rng.uniform(-1, 1, size=(n, ACT_DIM)).astype(np.float32),
        reward=rng.integers(0, 2, size=n).astype(np.float32),
        terminal=np.zeros(n, dtype=bool),
        timeout=np.isin(np.arange(1, n + 1), np.cumsum(lengths)),
        metadata=make_metadata("maze2d-umaze", OBS_DIM, ACT_DIM, "expert", {"seed": 7, "nested": {"a": [1, 2]}}),
    )


def write_raw(path: Path, table: pa.Table, meta: dict | bytes | None) -> None:
    """Write ``table`` with plain pyarrow, with ``meta`` (or nothing) under the project's metadata key."""
    if meta is None:
        table = table.replace_schema_metadata(None)
    else:
        raw = meta if isinstance(meta, bytes) else json.dumps(meta).encode()
        table = table.replace_schema_metadata({METADATA_KEY: raw})
    pq.write_table(table, path)


def corrupt(source: Path, target: Path, column: str, row: int, value: float | int, element: int = 0) -> Path:
    """Copy the valid file ``source`` to ``target`` with one value of ``column`` (row ``row``, list element
    ``element``) replaced by ``value``, through plain pyarrow, keeping the file metadata."""
    table = pq.read_table(source)
    col = table.column(column).combine_chunks()
    if pa.types.is_fixed_size_list(col.type):
        values = col.flatten().to_numpy().copy()
        values[row * col.type.list_size + element] = value
        new = pa.FixedSizeListArray.from_arrays(pa.array(values, type=col.type.value_type), col.type.list_size)
    else:
        values = col.to_numpy().copy()
        values[row] = value
        new = pa.array(values, type=col.type)
    write_raw(
        target, table.set_column(table.column_names.index(column), column, new), table.schema.metadata[METADATA_KEY]
    )
    return target


def assert_one_line_naming(err: BaseException, *parts: object) -> None:
    """The error message is one line and names every one of ``parts``."""
    message = str(err)
    assert "\n" not in message, message
    for part in parts:
        assert str(part) in message, (part, message)


@pytest.fixture
def valid_file(tmp_path: Path) -> Path:
    path = tmp_path / "traj.parquet"
    write_trajectories(path, make_traj([5, 3, 7]))
    return path


def test_round_trip_keeps_columns_dtypes_and_metadata(tmp_path: Path) -> None:
    traj = make_traj([5, 3, 7])
    path = tmp_path / "sub" / "traj.parquet"
    write_trajectories(path, traj)
    back = read_trajectories(path)

    assert len(back) == 15
    for name in ("episode_id", "step", "observation", "action", "reward", "terminal", "timeout"):
        np.testing.assert_array_equal(getattr(back, name), getattr(traj, name), err_msg=name)
    assert back.episode_id.dtype == np.int64 and back.step.dtype == np.int32
    assert back.observation.dtype == np.float32 and back.observation.shape == (15, OBS_DIM)
    assert back.action.dtype == np.float32 and back.action.shape == (15, ACT_DIM)
    assert back.reward.dtype == np.float32
    assert back.terminal.dtype == bool and back.timeout.dtype == bool
    assert back.metadata == traj.metadata
    assert back.metadata["schema_version"] == SCHEMA_VERSION
    assert back.extra == {}

    schema = pq.read_schema(path)
    assert schema.field("observation").type == pa.list_(pa.float32(), OBS_DIM)
    assert schema.field("action").type == pa.list_(pa.float32(), ACT_DIM)
    assert json.loads(schema.metadata[METADATA_KEY]) == traj.metadata


def test_extra_columns_one_and_two_dimensional_survive(tmp_path: Path) -> None:
    traj = make_traj([4, 6])
    task = np.arange(10, dtype=np.int64) % 3
    weight = np.linspace(0, 1, 10).astype(np.float32)
    goal = np.arange(20, dtype=np.float32).reshape(10, 2)
    traj.extra = {"task": task, "weight": weight, "goal": goal}
    write_trajectories(tmp_path / "x.parquet", traj)
    back = read_trajectories(tmp_path / "x.parquet")

    assert set(back.extra) == {"task", "weight", "goal"}
    np.testing.assert_array_equal(back.extra["task"], task)
    np.testing.assert_array_equal(back.extra["weight"], weight)
    assert back.extra["goal"].shape == (10, 2)
    np.testing.assert_array_equal(back.extra["goal"], goal)
    np.testing.assert_array_equal(back.observation, traj.observation)


def test_episodes_slices() -> None:
    traj = make_traj([5, 3, 7])
    assert traj.episodes() == [slice(0, 5), slice(5, 8), slice(8, 15)]
    for ep, k in zip(traj.episodes(), [5, 3, 7], strict=True):
        np.testing.assert_array_equal(traj.step[ep], np.arange(k))
        assert len(set(traj.episode_id[ep])) == 1
    assert make_traj([]).episodes() == []
    assert make_traj([9]).episodes() == [slice(0, 9)]


def test_file_without_project_metadata_is_rejected(valid_file: Path, tmp_path: Path) -> None:
    path = tmp_path / "plain.parquet"
    write_raw(path, pq.read_table(valid_file), None)
    with pytest.raises(SchemaError, match="adaptdiffuser") as err:
        read_trajectories(path, env="maze2d-umaze")
    assert_one_line_naming(err.value, path, "metadata")


def test_metadata_that_is_not_json_is_rejected(valid_file: Path, tmp_path: Path) -> None:
    path = tmp_path / "bad.parquet"
    write_raw(path, pq.read_table(valid_file), b"{not json")
    with pytest.raises(SchemaError, match="JSON"):
        read_trajectories(path)


@pytest.mark.parametrize("missing", ["obs_dim", "act_dim", "env", "source", "generator", "schema_version"])
def test_metadata_missing_a_field_names_it(valid_file: Path, tmp_path: Path, missing: str) -> None:
    meta = read_trajectories(valid_file).metadata
    del meta[missing]
    path = tmp_path / "bad.parquet"
    write_raw(path, pq.read_table(valid_file), meta)
    with pytest.raises(SchemaError, match=missing):
        read_trajectories(path)


def test_wrong_schema_version_is_rejected(valid_file: Path, tmp_path: Path) -> None:
    meta = dict(read_trajectories(valid_file).metadata, schema_version=SCHEMA_VERSION + 1)
    path = tmp_path / "future.parquet"
    write_raw(path, pq.read_table(valid_file), meta)
    with pytest.raises(SchemaError, match="schema_version"):
        read_trajectories(path)


@pytest.mark.parametrize(("key", "value"), [("source", "dreamed"), ("obs_dim", 0), ("act_dim", "2"), ("act_dim", -1)])
def test_invalid_metadata_values_are_rejected(valid_file: Path, tmp_path: Path, key: str, value: object) -> None:
    meta = dict(read_trajectories(valid_file).metadata, **{key: value})
    path = tmp_path / "bad.parquet"
    write_raw(path, pq.read_table(valid_file), meta)
    with pytest.raises(SchemaError, match=key):
        read_trajectories(path)


def test_state_only_files_round_trip_and_refuse_actions(tmp_path: Path) -> None:
    """``act_dim`` 0 (plans of states only, like KUKA's): the action column holds empty lists; a file whose action
    lists hold values while its metadata says 0 is refused, naming the column."""
    n = 5
    traj = Trajectories(
        episode_id=np.zeros(n, dtype=np.int64),
        step=np.arange(n),
        observation=np.random.default_rng(0).normal(size=(n, OBS_DIM)),
        action=np.zeros((n, 0)),
        reward=np.zeros(n),
        terminal=np.zeros(n, dtype=bool),
        timeout=np.arange(n) == n - 1,
        metadata=make_metadata("states", OBS_DIM, 0, "expert", {}),
    )
    path = tmp_path / "states.parquet"
    write_trajectories(path, traj)
    back = read_trajectories(path)
    assert back.action.shape == (n, 0)
    np.testing.assert_allclose(back.observation, traj.observation.astype(np.float32))
    table = pq.read_table(path)
    filled = pa.array([[1.0]] * n, type=pa.list_(pa.float32()))
    bad = tmp_path / "bad.parquet"
    write_raw(bad, table.set_column(table.schema.get_field_index("action"), "action", filled), back.metadata)
    with pytest.raises(SchemaError, match="column 'action' holds 5 values for 5 rows of 0"):
        read_trajectories(bad)


@pytest.mark.parametrize("column", ["reward", "observation", "episode_id", "timeout"])
def test_missing_column_is_named(valid_file: Path, tmp_path: Path, column: str) -> None:
    table = pq.read_table(valid_file)
    meta = table.schema.metadata[METADATA_KEY]
    path = tmp_path / "missing.parquet"
    write_raw(path, table.drop_columns([column]), meta)
    with pytest.raises(SchemaError, match=f"missing column '{column}'"):
        read_trajectories(path)


@pytest.mark.parametrize(
    "bad_type",
    [
        pa.list_(pa.float32(), OBS_DIM - 1),  # wrong fixed size
        pa.list_(pa.float64(), OBS_DIM),  # wrong value type
        pa.list_(pa.float32()),  # variable-size list
    ],
    ids=["size", "float64", "variable"],
)
def test_observation_with_wrong_list_type_is_rejected(valid_file: Path, tmp_path: Path, bad_type: pa.DataType) -> None:
    table = pq.read_table(valid_file)
    meta = table.schema.metadata[METADATA_KEY]
    n = table.num_rows
    size = bad_type.list_size if pa.types.is_fixed_size_list(bad_type) else OBS_DIM
    values = pa.array(np.zeros(n * size), type=bad_type.value_type)
    if pa.types.is_fixed_size_list(bad_type):
        column = pa.FixedSizeListArray.from_arrays(values, size)
    else:
        column = pa.ListArray.from_arrays(pa.array(np.arange(n + 1, dtype=np.int32) * size), values)
    assert column.type == bad_type
    idx = table.column_names.index("observation")
    path = tmp_path / "wrongtype.parquet"
    write_raw(path, table.set_column(idx, "observation", column), meta)
    with pytest.raises(SchemaError, match="observation") as err:
        read_trajectories(path)
    assert "type" in str(err.value)


def test_episode_ids_out_of_order_are_rejected(valid_file: Path, tmp_path: Path) -> None:
    table = pq.read_table(valid_file)
    meta = table.schema.metadata[METADATA_KEY]
    ids = table.column("episode_id").to_numpy()[::-1].copy()
    path = tmp_path / "unordered.parquet"
    write_raw(path, table.set_column(0, "episode_id", pa.array(ids)), meta)
    with pytest.raises(SchemaError, match="episode_id"):
        read_trajectories(path)


@pytest.mark.parametrize("content", [b"this is not parquet at all" * 20, b""], ids=["garbage", "empty"])
def test_non_parquet_file_is_a_schema_error(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "garbage.parquet"
    path.write_bytes(content)
    with pytest.raises(SchemaError, match="Parquet"):
        read_trajectories(path)


def test_missing_file_is_file_not_found(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nope.parquet"):
        read_trajectories(tmp_path / "nope.parquet")


def test_bad_write_raises_and_leaves_no_file(tmp_path: Path) -> None:
    traj = make_traj([4, 4])
    traj.observation = traj.observation[:, :3]
    path = tmp_path / "out.parquet"
    with pytest.raises(SchemaError, match="observation"):
        write_trajectories(path, traj)
    assert not path.exists()
    assert list(tmp_path.iterdir()) == []


def test_bad_write_does_not_destroy_existing_file(tmp_path: Path) -> None:
    good = make_traj([5, 3, 7])
    path = tmp_path / "out.parquet"
    write_trajectories(path, good)
    before = path.read_bytes()

    bad = make_traj([4, 4], seed=1)
    bad.action = np.zeros((8, ACT_DIM + 1), dtype=np.float32)
    with pytest.raises(SchemaError, match="action"):
        write_trajectories(path, bad)

    assert path.read_bytes() == before
    np.testing.assert_array_equal(read_trajectories(path).observation, good.observation)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.parquet"]


def test_make_metadata_rejects_unknown_source() -> None:
    with pytest.raises(SchemaError, match="source"):
        make_metadata("maze2d-umaze", OBS_DIM, ACT_DIM, "imagined", {})


def test_arrow_schema_names_the_required_columns() -> None:
    schema = arrow_schema(3, 1)
    assert schema.names == ["episode_id", "step", "observation", "action", "reward", "terminal", "timeout"]
    assert schema.field("observation").type.list_size == 3 and schema.field("action").type.list_size == 1


def test_writing_episodes_out_of_order_is_refused(tmp_path: Path) -> None:
    traj = make_traj([3, 4])
    traj.episode_id = traj.episode_id[::-1].copy()
    path = tmp_path / "unordered.parquet"
    with pytest.raises(SchemaError, match="episode_id"):
        write_trajectories(path, traj)
    assert not path.exists()


def test_full_simulator_state_round_trips_exactly_in_float64(tmp_path: Path) -> None:
    traj = make_traj([4, 2])
    state = np.random.default_rng(3).normal(size=(6, 13))  # float64: MuJoCo qpos + qvel must restore exactly
    traj.sim_state = state
    traj.metadata = make_metadata("hopper-medium", OBS_DIM, ACT_DIM, "expert", {}, state_dim=13)
    write_trajectories(tmp_path / "s.parquet", traj)
    back = read_trajectories(tmp_path / "s.parquet")
    assert back.metadata["state_dim"] == 13 and back.sim_state.dtype == np.float64
    np.testing.assert_array_equal(back.sim_state, state)
    assert "sim_state" not in back.extra


def test_state_column_must_match_the_declared_state_dim(tmp_path: Path) -> None:
    traj = make_traj([3])
    traj.metadata = make_metadata("hopper-medium", OBS_DIM, ACT_DIM, "expert", {}, state_dim=5)
    with pytest.raises(SchemaError, match="'sim_state' must have shape"):
        write_trajectories(tmp_path / "s.parquet", traj)
    traj.metadata = make_metadata("hopper-medium", OBS_DIM, ACT_DIM, "expert", {})
    traj.sim_state = np.zeros((3, 5))
    with pytest.raises(SchemaError, match="state_dim' is 0"):
        write_trajectories(tmp_path / "s.parquet", traj)
    assert not (tmp_path / "s.parquet").exists()


@pytest.fixture
def state_file(tmp_path: Path) -> Path:
    """A valid file with the simulator-state column (episodes of 5, 3 and 7 steps)."""
    traj = make_traj([5, 3, 7])
    traj.sim_state = np.random.default_rng(4).normal(size=(15, 6))
    traj.metadata = make_metadata("hopper-medium", OBS_DIM, ACT_DIM, "expert", {}, state_dim=6)
    path = tmp_path / "state.parquet"
    write_trajectories(path, traj)
    return path


@pytest.mark.parametrize(
    ("column", "row", "element", "value", "episode", "step"),
    [
        ("observation", 6, 2, np.nan, 1, 1),
        ("action", 14, 1, np.inf, 2, 6),
        ("reward", 0, 0, -np.inf, 0, 0),
        ("sim_state", 9, 5, np.nan, 2, 1),
    ],
    ids=["observation-nan", "action-inf", "reward-minus-inf", "sim_state-nan"],
)
def test_non_finite_value_is_refused_naming_file_column_and_row(
    state_file: Path, tmp_path: Path, column: str, row: int, element: int, value: float, episode: int, step: int
) -> None:
    path = corrupt(state_file, tmp_path / "nonfinite.parquet", column, row, value, element)
    with pytest.raises(SchemaError, match="must be finite") as err:
        read_trajectories(path)
    where = f"row {row} (episode {episode}, step {step}" + (f"), element {element}" if column != "reward" else ")")
    assert_one_line_naming(err.value, path, f"column {column!r}", where, value)


def test_only_the_first_non_finite_row_is_named(valid_file: Path, tmp_path: Path) -> None:
    path = corrupt(valid_file, tmp_path / "first.parquet", "observation", 11, np.nan)
    path = corrupt(path, tmp_path / "both.parquet", "observation", 4, -np.inf, element=3)
    with pytest.raises(SchemaError, match=r"'observation' holds -inf at row 4 \(episode 0, step 4\), element 3"):
        read_trajectories(path)


def test_nan_in_an_extra_column_is_kept(tmp_path: Path) -> None:
    traj = make_traj([2, 2])  # synthetic files mark tasks without a gold coin by NaN coins
    traj.extra = {"task_coin": np.array([[np.nan, np.nan]] * 2 + [[1.0, 2.0]] * 2, dtype=np.float32)}
    write_trajectories(tmp_path / "coins.parquet", traj)
    back = read_trajectories(tmp_path / "coins.parquet")
    assert np.isnan(back.extra["task_coin"][:2]).all() and (back.extra["task_coin"][2:] == [1.0, 2.0]).all()


@pytest.mark.parametrize(("row", "value"), [(7, 1), (12, 1), (6, -3)], ids=["repeated", "decreasing", "negative"])
def test_steps_not_increasing_within_an_episode_are_refused(
    valid_file: Path, tmp_path: Path, row: int, value: int
) -> None:
    path = corrupt(valid_file, tmp_path / "steps.parquet", "step", row, value)
    episode = read_trajectories(valid_file).episode_id[row]
    with pytest.raises(SchemaError, match="does not increase") as err:
        read_trajectories(path)
    assert_one_line_naming(err.value, path, "column 'step'", f"episode {episode} at row {row}", f"step {value} after")


def test_steps_may_restart_at_a_new_episode_and_skip(valid_file: Path, tmp_path: Path) -> None:
    path = corrupt(valid_file, tmp_path / "gap.parquet", "step", 7, 40)  # last step of episode 1; 0 follows
    np.testing.assert_array_equal(read_trajectories(path).step[5:9], [0, 1, 40, 0])


def test_file_of_another_task_is_refused_naming_both(valid_file: Path) -> None:
    assert read_trajectories(valid_file, env="maze2d-umaze").metadata["env"] == "maze2d-umaze"
    with pytest.raises(SchemaError, match="another task") as err:
        read_trajectories(valid_file, env="hopper-medium")
    assert_one_line_naming(err.value, valid_file, "'env'", "'maze2d-umaze'", "'hopper-medium'")


def test_null_inside_an_observation_names_the_row(valid_file: Path, tmp_path: Path) -> None:
    table = pq.read_table(valid_file)
    values = pa.array(
        [None if i == 9 * OBS_DIM + 1 else 0.5 for i in range(table.num_rows * OBS_DIM)], type=pa.float32()
    )
    column = pa.FixedSizeListArray.from_arrays(values, OBS_DIM)
    path = tmp_path / "null.parquet"
    meta = table.schema.metadata[METADATA_KEY]
    write_raw(path, table.set_column(table.column_names.index("observation"), "observation", column), meta)
    with pytest.raises(SchemaError, match="nulls") as err:
        read_trajectories(path)
    assert_one_line_naming(err.value, path, "column 'observation'", "row 9")
