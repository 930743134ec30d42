"""The sets of evaluation start states, and the check that no two parts play the same ones.

Each set has a base seed; training seed ``s`` plays episode ``i`` of it from ``numpy.random.default_rng([base + s,
i])`` (:func:`adaptdiffuser.evaluation.episode_rng`): the start state is a fresh draw from the task's start
distribution, fixed by the pair. The episode index is a word of its own in that seed, not added to the base, so two
sets share a start state only where ``base + s`` coincide, however many episodes each plays; the check compares
those numbers, ``{base + s for s in seeds}``, for every set of a task:

- the pipeline's evaluation (``evaluate.seed``) and held-out (``evaluate.held_out_seed``, where it plays any) sets;
- the sweep trials' own evaluation and held-out sets (``sweep.evaluate_seed``, ``sweep.held_out_seed``; the swept
  task, where ``sweep.space`` sets anything to sweep);
- ``adaptdiffuser evaluate-kept``'s default re-tests of kept models (:data:`KEPT_EVAL_SEED`,
  :data:`KEPT_HELD_OUT_SEED`), whose training seeds are those of the runs that made them.

Sets of different tasks may share numbers: they draw from different start distributions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from adaptdiffuser.config.errors import ConfigError

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from adaptdiffuser.config.sections import EvaluateParams
    from adaptdiffuser.config.sweep_settings import SweepParams

#: ``evaluate-kept --eval-seed``'s default: kept models' re-tests on start states of their own (plus training seed)
KEPT_EVAL_SEED = 9000
#: ``evaluate-kept --held-out-seed``'s default: their held-out re-test states (plus training seed)
KEPT_HELD_OUT_SEED = 10000

_KEPT_WHY = (
    f"evaluate-kept's default re-tests (--eval-seed {KEPT_EVAL_SEED}, --held-out-seed {KEPT_HELD_OUT_SEED}) must "
    "play start states no other part plays"
)


def start_seeds(base: int, seeds: Sequence[int]) -> set[int]:
    """The evaluation seeds of a set of start states (``evaluate.seed``, ...) over the training seeds: seed s plays
    ``base + s``."""
    return {base + seed for seed in seeds}


@dataclass(frozen=True)
class StartStates:
    """One set of start states of a task: the key that sets its base seed, the base, and who plays it
    (``pipeline``, ``sweep`` or ``kept``: a fixed default, not a params key)."""

    key: str
    base: int
    who: str


def start_state_sets(task: str, ev: EvaluateParams, sweep: SweepParams | None) -> list[StartStates]:
    """Every set of start states played on ``task`` (its ``evaluate`` section ``ev``; ``sweep``: the sweep's settings
    when a sweep runs on this task, else None), in the order the check blames them: the pipeline's, the sweep's,
    evaluate-kept's defaults."""
    where = f"task.{task}.evaluate"
    sets = [StartStates(f"{where}.seed", ev.seed, "pipeline")]
    if ev.held_out_episodes:
        sets.append(StartStates(f"{where}.held_out_seed", ev.held_out_seed, "pipeline"))
    if sweep is not None:
        sets.append(StartStates("sweep.evaluate_seed", sweep.evaluate_seed, "sweep"))
        if ev.held_out_episodes:
            sets.append(StartStates("sweep.held_out_seed", sweep.held_out_seed, "sweep"))
    sets += [
        StartStates("evaluate-kept --eval-seed", KEPT_EVAL_SEED, "kept"),
        StartStates("evaluate-kept --held-out-seed", KEPT_HELD_OUT_SEED, "kept"),
    ]
    return sets


def _why(a: StartStates, b: StartStates) -> str:
    """Why sets ``a`` and ``b`` (``a`` listed first) must not meet."""
    if "kept" in (a.who, b.who):
        return _KEPT_WHY
    if a.who != b.who:
        return "trials must not be tuned on the episodes the results are reported on"
    if b.who == "sweep":
        return "the sweep's held-out start states must be others than its evaluation's"
    return "the held-out start states must be others"


def check_start_states(sets_by_task: Mapping[str, list[StartStates]], seeds: Sequence[int]) -> None:
    """No two sets of start states of a task (``sets_by_task``: :func:`start_state_sets` of each task of ``tasks``)
    share a seed for any training seed of ``seeds``; a one-line :class:`ConfigError` naming the key to change."""
    for task, sets in sets_by_task.items():
        for j, b in enumerate(sets):
            for a in sets[:j]:
                common = start_seeds(a.base, seeds) & start_seeds(b.base, seeds)
                if not common:
                    continue
                if a.who == b.who == "kept":
                    raise ConfigError(
                        f"seeds: training seeds {min(seeds)}..{max(seeds)} spread past the {b.base - a.base} "
                        "seeds between evaluate-kept's two default sets; use training seeds closer together"
                    )
                blamed, other = (a, b) if b.who == "kept" else (b, a)
                raise ConfigError(
                    f"{blamed.key}: {blamed.base} plus a training seed is {other.key} ({other.base}) plus one "
                    f"(both play the start states of seed {min(common)} on {task}); {_why(a, b)}"
                )
