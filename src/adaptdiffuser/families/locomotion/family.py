"""The locomotion family as the generic pipeline sees it (registered in ``families/registry.py``)."""

from __future__ import annotations

from typing import Any

from adaptdiffuser.families.base import Family
from adaptdiffuser.families.locomotion.simulator import LocomotionSimulator, parse_task_name


class LocomotionFamily(Family):
    """Hopper, Walker2d and HalfCheetah (gymnasium MuJoCo ``-v5``) with D4RL-recipe datasets regenerated here:
    plans start at the current state, are guided by a learned value and replanned at every step."""

    name = "locomotion"
    conditioning = "start"

    def normalizer_kind(self) -> str:
        return "gaussian"

    def uses_value_function(self, task: Any) -> bool:
        return True

    def make_simulator(self, task: Any) -> LocomotionSimulator:
        """The simulator of a task named like ``hopper-medium`` (``task`` is the name or has a ``name``)."""
        env_id, _ = parse_task_name(getattr(task, "name", task))
        return LocomotionSimulator(env_id)

    def describe(self, task: Any) -> dict[str, Any]:
        env_id, dataset = parse_task_name(getattr(task, "name", task))
        return {"env_id": env_id, "dataset": dataset}
