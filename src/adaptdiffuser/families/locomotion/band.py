"""Choosing the ``medium`` behaviour policy inside a score band, whatever path training takes on this CPU.

Float rounding differs between CPUs, so the same seeded learner follows another path on another machine, and one
evaluation every ``eval_every`` steps can jump over a narrow score range (30.8 -> 65.4 seen on Hopper). The search
trains in chunks and evaluates after each; a score near the band is measured again on more episodes, as the data
will be recorded; a score above the band sends training back to its last checkpoint below it, with a shorter
interval and a fresh seed. A policy whose score lies inside the band by at least one standard error then records
the dataset itself, and is chosen only when the dataset's episodes lie inside the band by their standard error too:
the band is a promise about the dataset, and the search tries many policies on the same evaluation episodes, so the
one it stops at scored high partly by luck (a Hopper policy at 32.5 on 50 episodes, 31.3 on 100 fresh ones,
recorded a dataset of 29.2 +- 0.2). Otherwise the dataset's score decides the next move. The search refuses when
the step budget runs out. The rule is written against :class:`Trainee`, so it runs the same on a real learner and on
a score curve. The search's own state between evaluations is a :class:`SearchState`, handed out before each chunk of
training so that a caller can save it beside the learner and continue an interrupted search where it stopped.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from adaptdiffuser.errors import StageError


@dataclass(frozen=True)
class Band:
    """Normalized scores ``target +- half_width``."""

    target: float
    half_width: float

    @property
    def low(self) -> float:
        return self.target - self.half_width

    @property
    def high(self) -> float:
        return self.target + self.half_width

    def __contains__(self, score: float) -> bool:
        return self.low <= score <= self.high

    def holds(self, score: float, stderr: float) -> bool:
        """``score`` is inside the band by at least ``stderr`` on both sides."""
        return self.low + stderr <= score <= self.high - stderr

    def near(self, score: float) -> bool:
        """Within one more half-width of the band: worth measuring on more episodes."""
        return self.low - self.half_width <= score <= self.high + self.half_width


class Trainee(Protocol):
    """What the search needs of a learner."""

    def train(self, steps: int) -> int:
        """Train about ``steps`` more environment steps; return how many were taken."""

    def steps(self) -> int:
        """Environment steps of the current policy's training path."""

    def quick_score(self) -> float:
        """A cheap estimate of the current policy's normalized score."""

    def band_score(self) -> tuple[float, float]:
        """The current policy's normalized score as the data will be recorded, on enough episodes to be sure: the
        mean and its standard error."""

    def confirm_score(self) -> tuple[float, float]:
        """The score of the dataset the current policy records (its episodes' mean and standard error): what the
        band promises, and what is kept when this policy is chosen."""

    def snapshot(self) -> Any:
        """The current state, for :meth:`restore`."""

    def restore(self, snapshot: Any, attempt: int) -> None:
        """Go back to ``snapshot``; ``attempt`` (1, 2, ...) seeds the path taken from there."""


class BandNotReachedError(StageError):
    """No policy scored inside the band within the step budget."""


@dataclass(frozen=True)
class BandChoice:
    """The chosen policy: its training steps, its dataset's score and that score's standard error, the steps
    spent in all (discarded paths included) and how many times training went back."""

    steps: int
    score: float
    stderr: float
    spent: int
    rewinds: int


@dataclass
class SearchState:
    """Where a search stands between two evaluations: steps spent, times gone back, the training interval, the
    highest score seen and the snapshot to go back to."""

    interval: int
    below: Any
    spent: int = 0
    rewinds: int = 0
    highest: float = -float("inf")


def search_band(
    trainee: Trainee,
    band: Band,
    eval_every: int,
    min_eval_every: int,
    budget: int,
    on_eval: Callable[[dict[str, Any]], None] = lambda record: None,
    setting: str = "behaviour",
    state: SearchState | None = None,
    on_state: Callable[[SearchState], None] = lambda state: None,
) -> BandChoice:
    """Train ``trainee`` until a policy's dataset scores in ``band`` (see the module's docstring); every evaluation
    is passed to ``on_eval`` as ``{steps, spent, quick_score, band_score?, band_stderr?, confirm_score?,
    confirm_stderr?, action}`` (``confirm_*``: the dataset's). Raises :class:`BandNotReachedError` naming the
    settings to change when ``budget`` steps are spent first. ``on_state`` sees the search's state before each chunk
    of training; passing a saved one as ``state`` (with the trainee as it was then) continues that search."""
    if state is None:
        state = SearchState(interval=eval_every, below=trainee.snapshot())
    while state.spent < budget:
        on_state(state)
        state.spent += trainee.train(min(state.interval, budget - state.spent))
        quick = trainee.quick_score()
        record: dict[str, Any] = {"steps": trainee.steps(), "spent": state.spent, "quick_score": quick}
        score = quick
        if band.near(quick):
            score, record["band_stderr"] = trainee.band_score()
            record["band_score"] = score
        state.highest = max(state.highest, score)
        if "band_score" in record and band.holds(score, record["band_stderr"]):
            data_score, data_stderr = trainee.confirm_score()
            record |= {"confirm_score": data_score, "confirm_stderr": data_stderr}
            if band.holds(data_score, data_stderr):
                on_eval(record | {"action": "choose"})
                return BandChoice(trainee.steps(), data_score, data_stderr, state.spent, state.rewinds)
            score = data_score  # the dataset's score decides: below or inside goes on, above goes back
        if score < band.low or ("band_score" in record and score in band):  # below, or inside but not surely
            on_eval(record | {"action": "continue"})
            state.below = trainee.snapshot()
            continue
        state.rewinds += 1
        state.interval = max(min_eval_every, state.interval // 4)
        on_eval(record | {"action": "rewind", "next_interval": state.interval})
        trainee.restore(state.below, state.rewinds)
    raise BandNotReachedError(
        f"{setting}: no behaviour policy scored inside {band.low:g}..{band.high:g} within {budget} training steps "
        f"(highest {state.highest:.1f}, went back {state.rewinds} times); raise {setting}.max_train_steps, widen "
        f"{setting}.medium_band or lower {setting}.min_eval_every"
    )
