"""The fixed gold-coin evaluation cases: which kinds each maze allows, the paper's Medium case, reproducibility."""

from __future__ import annotations

import numpy as np
import pytest

from adaptdiffuser.families.maze2d.gold_coin import PAPER_MEDIUM_CASE, coin_cases, coin_kind
from adaptdiffuser.families.maze2d.simulator import Maze2D, resolve_layout


def _maze(name: str) -> Maze2D:
    return Maze2D(resolve_layout(name), name=name)


def test_medium_cases_cover_every_kind_and_include_the_papers_case() -> None:
    env = _maze("medium")
    cases = coin_cases(env, per_kind=3, rng=np.random.default_rng(0))
    assert len(cases) == 3 * 3 + 1
    assert set(cases.kinds) == {"on_path", "off_path", "behind_start"}
    start, coin = PAPER_MEDIUM_CASE["start"], PAPER_MEDIUM_CASE["coin"]
    assert (cases.start_cells[-1], cases.coin_cells[-1]) == (start, coin)
    assert cases.kinds[-1] == coin_kind(env, start, coin) == "off_path"  # a detour away from the shortest path
    np.testing.assert_allclose(cases.coins[-1], env.cell_to_xy(coin))
    for kind, s, c in zip(cases.kinds, cases.start_cells, cases.coin_cells, strict=True):
        assert coin_kind(env, s, c) == kind


def test_umaze_has_no_off_path_case_and_the_same_seed_gives_the_same_cases() -> None:
    env = _maze("umaze")
    first = coin_cases(env, per_kind=4, rng=np.random.default_rng(3))
    again = coin_cases(env, per_kind=4, rng=np.random.default_rng(3))
    assert set(first.kinds) == {"on_path", "behind_start"}
    np.testing.assert_array_equal(first.starts, again.starts)
    assert first.coin_cells == again.coin_cells


def test_non_positive_cases_per_kind_is_rejected() -> None:
    with pytest.raises(ValueError, match="cases per kind must be positive"):
        coin_cases(_maze("umaze"), per_kind=0, rng=np.random.default_rng(0))
