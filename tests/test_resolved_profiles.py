"""Every profile, and the committed ``params.yaml``, resolves to the values pinned in
``tests/data/resolved_profiles.json`` (rewrite it with ``python tests/resolved_profiles.py`` only for a change
meant to change a resolved value: the science results depend on them)."""

from __future__ import annotations

import json

import pytest
from resolved_profiles import FIXTURE, PROFILES, REPO, digest, resolve_profile, resolved

from adaptdiffuser.config import load_params

PINNED = json.loads(FIXTURE.read_text())
NAMES = sorted(path.stem for path in PROFILES.glob("*.yaml"))


def changed(now: dict[str, str], pinned: dict[str, str]) -> list[str]:
    """The keys whose value differs, or that only one side has, as ``key: pinned -> now``."""
    keys = sorted(set(now) | set(pinned))
    absent = "<absent>"
    return [f"{k}: {pinned.get(k, absent)} -> {now.get(k, absent)}" for k in keys if now.get(k) != pinned.get(k)]


def test_every_profile_is_pinned() -> None:
    assert sorted(PINNED["profiles"]) == NAMES == sorted(PINNED["tiny_digests"])


@pytest.mark.parametrize("name", NAMES)
def test_profile_resolves_to_its_pinned_values(name: str) -> None:
    assert changed(resolve_profile(name), PINNED["profiles"][name]) == []
    assert digest(resolve_profile(name, tiny=True)) == PINNED["tiny_digests"][name]


def test_params_yaml_is_the_quick_profile_resolved() -> None:
    """The committed params.yaml is what ``adaptdiffuser profile quick`` writes, and resolves to the pinned values."""
    now = resolved(load_params(REPO / "params.yaml"))
    assert changed(now, PINNED["params.yaml"]) == []
    assert now == resolve_profile("quick")


@pytest.mark.parametrize("name", [n for n in NAMES if n == "smoke" or n.startswith("quick")])
def test_quick_profiles_spend_no_more_on_held_out_states_than_on_their_own(name: str) -> None:
    """In the quick and smoke profiles each task's held-out set is at most as large as its own evaluation (the
    science profiles choose their own sizes)."""
    now = resolve_profile(name)
    for task in json.loads(now["tasks"]):
        own, held_out = (int(now[f"task.{task}.evaluate.{key}"]) for key in ("episodes", "held_out_episodes"))
        assert held_out <= own, f"{name}: {task} plays {held_out} held-out episodes beside its own {own}"
