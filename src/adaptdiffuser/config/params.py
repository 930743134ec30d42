"""The whole of ``params.yaml``: the tasks to run, each task's settings, the generic sections they share, the
phase chain and the checks that span sections."""

from __future__ import annotations

import dataclasses
from dataclasses import field
from typing import Annotated, Any

from pydantic import Field, ValidationInfo, field_validator, model_validator
from pydantic.dataclasses import dataclass

from adaptdiffuser.config.errors import ConfigError, show
from adaptdiffuser.config.fields import Float, Seed, Str, one_of
from adaptdiffuser.config.phases import PhaseParams, build_phases, check_chain
from adaptdiffuser.config.sections import (
    SECTION,
    CompileParams,
    DiffusionParams,
    EvaluateParams,
    EvolutionParams,
    ModelParams,
    PlannerParams,
    PretrainParams,
)
from adaptdiffuser.config.start_states import check_start_states, start_state_sets
from adaptdiffuser.config.sweep_settings import SweepParams
from adaptdiffuser.config.tasks import GENERIC_SECTIONS, TaskParams, build_task

DEFAULT_TASK = "maze2d-umaze"

#: formats of a task's external data (``imports``): a D4RL HDF5 file, or a Minari dataset (by folder or id)
IMPORT_FORMATS = ("d4rl", "minari")


@dataclass(frozen=True, config=SECTION)
class ImportParams:
    """Where an imported task's expert data comes from, instead of its collect stage. ``path``: the D4RL ``.hdf5``
    file, or the Minari dataset's folder (the one holding ``data/``) or its id in the local Minari store."""

    format: Annotated[Str, one_of(*IMPORT_FORMATS)]
    path: Str


def _default_tasks() -> dict[str, Any]:
    return {DEFAULT_TASK: {"family": "maze2d"}}


@dataclass(frozen=True, config=SECTION)
class Params:
    model: ModelParams = field(default_factory=ModelParams)
    diffusion: DiffusionParams = field(default_factory=DiffusionParams)
    pretrain: PretrainParams = field(default_factory=PretrainParams)
    planner: PlannerParams = field(default_factory=PlannerParams)
    evaluate: EvaluateParams = field(default_factory=EvaluateParams)
    # name -> TaskParams, built from the entries
    task: dict[str, Any] = Field(default_factory=_default_tasks, validate_default=True)
    tasks: tuple[Str, ...] = (DEFAULT_TASK,)  # the tasks `dvc repro` runs: collect, reference, pretrain, evaluate
    unseen_tasks: tuple[Str, ...] = (DEFAULT_TASK,)  # those whose family has an unseen task (its evaluation)
    # the tasks of `tasks` whose data the collect stage makes (None: every task that is not imported)
    collect_tasks: tuple[Str, ...] | None = None
    imports: dict[Str, ImportParams] = field(default_factory=dict)  # task -> its external data (the import stage)
    # task -> a folder of trained phase-0 models (seed<s>/ each), imported by import-model instead of pretraining
    pretrained: dict[Str, Str] = field(default_factory=dict)
    # the tasks of `tasks` that the pretrain stage trains (None: every task without a `pretrained` folder)
    pretrain_tasks: tuple[Str, ...] | None = None
    evolve: Str | None = DEFAULT_TASK  # the task the evolution phases run on; null = phase 0 only
    evolution: EvolutionParams = field(default_factory=EvolutionParams)
    alpha: Float = 0.0
    compile: CompileParams = field(default_factory=CompileParams)  # torch.compile of the U-Net (docs/speed.md)
    seeds: tuple[Seed, ...] = (0,)  # training seeds: every training stage runs once per seed (see derived_seeds.py)
    phases: tuple[PhaseParams, ...] = ()  # from a mapping phase<k>: {previous: j, <evolution overrides>}
    sweep: SweepParams = field(default_factory=SweepParams)

    @field_validator("task", mode="before")
    @classmethod
    def _build_tasks(cls, value: Any, info: ValidationInfo) -> Any:
        if value is None:
            raise ConfigError("task: must be a mapping of task names to their settings, got None")
        if not isinstance(value, dict):
            raise ConfigError(f"task: must be a mapping of task names to their settings, got {show(value)}")
        if any(key not in info.data for key in GENERIC_SECTIONS):  # a generic section is invalid: reported first
            return {}
        # resolved tasks (after dataclasses.replace) are resolved again, over the generic sections given now
        entries = {name: e.entry if isinstance(e, TaskParams) else e for name, e in value.items()}
        return {name: build_task(name, entry, info.data) for name, entry in entries.items()}

    @field_validator("phases", mode="before")
    @classmethod
    def _build_phases(cls, value: Any, info: ValidationInfo) -> Any:
        if isinstance(value, tuple | list) and all(isinstance(phase, PhaseParams) for phase in value):
            return tuple(value)
        evolution = info.data.get("evolution")
        if evolution is None:  # evolution itself is invalid: that error is reported first
            return ()
        return build_phases(value, evolution)

    @field_validator("sweep", mode="before")
    @classmethod
    def _sweep_defaults(cls, value: Any) -> Any:
        return SweepParams() if value is None else value

    @field_validator("tasks", "unseen_tasks", mode="before")
    @classmethod
    def _empty_list(cls, value: Any) -> Any:
        return () if value is None else value

    @field_validator("imports", "pretrained", mode="before")
    @classmethod
    def _empty_imports(cls, value: Any) -> Any:
        return {} if value is None else value

    @field_validator("seeds")
    @classmethod
    def _distinct_seeds(cls, value: tuple[int, ...]) -> tuple[int, ...]:
        if not value:
            raise ValueError("needs at least one training seed, e.g. [0]")
        if len(set(value)) != len(value):
            raise ValueError(f"lists a seed twice: {list(value)}")
        return value

    @model_validator(mode="after")
    def _cross_checks(self) -> Params:
        if self.collect_tasks is None:  # not written: every task of `tasks` that is not imported
            object.__setattr__(self, "collect_tasks", tuple(t for t in self.tasks if t not in self.imports))
        if self.pretrain_tasks is None:  # not written: every task of `tasks` without a pretrained folder
            object.__setattr__(self, "pretrain_tasks", tuple(t for t in self.tasks if t not in self.pretrained))
        check_cross_fields(self)
        return self

    def resolve(self, name: str) -> TaskParams:
        """The task ``name`` with its overrides applied; :class:`ConfigError` if ``task`` does not define it."""
        if name not in self.task:
            raise ConfigError(f"task.{name}: no such task in params (defined: {sorted(self.task)})")
        return self.task[name]

    @property
    def evolved(self) -> TaskParams:
        """The task the evolution phases run on; :class:`ConfigError` when ``evolve`` is null."""
        if self.evolve is None:
            raise ConfigError("evolve: is null, so no evolution phase runs; name a task to evolve")
        return self.resolve(self.evolve)

    def section(self, name: str) -> dict[str, Any]:
        """One params section as a plain dict (for logging)."""
        return dataclasses.asdict(getattr(self, name))

    def phase(self, index: int) -> PhaseParams:
        """The evolution phase ``index`` (1..K); :class:`ConfigError` if params.yaml does not declare it."""
        for phase in self.phases:
            if phase.index == index:
                return phase
        raise ConfigError(f"phase {index} is not declared under 'phases' in params (have {self.phase_names})")

    @property
    def phase_names(self) -> list[str]:
        return [phase.name for phase in self.phases]

    def lineage(self, index: int) -> list[int]:
        """The evolution phases whose selected data trains phase ``index``: it and its ancestors, oldest first."""
        chain = []
        while index > 0:
            chain.append(index)
            index = self.phase(index).previous
        return chain[::-1]


def check_sweep(p: Params) -> None:
    """The swept task runs evolution phases, and an unseen objective needs a task of ``unseen_tasks`` (that trials
    play start states of their own: :func:`~adaptdiffuser.config.start_states.check_start_states`)."""
    s = p.sweep
    task = s.task if s.task is not None else p.evolve
    if task is None:
        return  # phase 0 only: `adaptdiffuser sweep` says it needs a task to evolve
    if task not in p.tasks:
        raise ConfigError(f"sweep.task: {task!r} must be one of tasks {list(p.tasks)} (its phase 0 is reused)")
    if "evolve" not in task_stages(p.task[task]):
        raise ConfigError(f"sweep.task: the {p.task[task].family} family of {task} has no evolution phases to sweep")
    if s.objective in ("unseen", "mix") and task not in p.unseen_tasks:
        raise ConfigError(
            f"sweep.objective: {s.objective!r} needs a task with an unseen task and {task} is not in unseen_tasks; "
            "use gain or score"
        )


def check_shapes(p: Params | TaskParams, prefix: str) -> None:
    """The U-Net's horizon divides evenly through its downsamplings, and the planner's sampler steps fit the
    diffusion chain (``prefix``: where the keys are, ``""`` or ``"task.<name>."``)."""
    factor = 2 ** (len(p.model.dim_mults) - 1)
    if p.diffusion.horizon % factor:
        raise ConfigError(
            f"{prefix}diffusion.horizon: must be divisible by {factor} (the U-Net halves it "
            f"{len(p.model.dim_mults) - 1} times; see model.dim_mults), got {p.diffusion.horizon}"
        )
    if p.planner.sampler_steps > p.diffusion.n_steps:
        raise ConfigError(
            f"{prefix}planner.sampler_steps: {p.planner.sampler_steps} exceeds diffusion.n_steps={p.diffusion.n_steps}"
        )


def check_cross_fields(p: Params) -> None:
    """The checks that span sections; :class:`ConfigError` naming the key."""
    check_shapes(p, "")
    check_task_lists(p)
    check_chain(p.phases)
    check_sweep(p)
    swept = p.sweep.task if p.sweep.task is not None else p.evolve
    sweep = p.sweep if p.sweep.space else None  # no space: no sweep runs
    sets = {t: start_state_sets(t, p.task[t].evaluate, sweep if t == swept else None) for t in p.tasks}
    check_start_states(sets, p.seeds)
    for name in p.tasks:  # entries not listed in `tasks` are type-checked only (another profile's tasks)
        check_task(p.task[name], p)
    if p.phases and p.evolve is not None:
        n_steps, recipes = p.evolved.diffusion.n_steps, evolution_recipes(p.evolved)
        for phase in p.phases:
            if phase.generate.sampler_steps > n_steps:
                raise ConfigError(
                    f"phases.{phase.name}.generate.sampler_steps: must be in 1..diffusion.n_steps={n_steps} of "
                    f"{p.evolve}, got {phase.generate.sampler_steps}"
                )
            if phase.generate.recipe not in recipes:
                raise ConfigError(
                    f"phases.{phase.name}.generate.recipe: {phase.generate.recipe!r} is not a recipe of the "
                    f"{p.evolved.family} family ({p.evolve}); choose one of {list(recipes)}"
                )
    check_data_sources(p)
    check_model_sources(p)


def check_task(task: TaskParams, params: Params) -> None:
    """The checks that span a task's sections: the U-Net's horizon, sampler steps, and the family's own."""
    where = f"task.{task.name}"
    check_shapes(task, f"{where}.")
    check = getattr(task.settings, "check", None)
    if check is not None:
        check(task, params)


def check_data_sources(p: Params) -> None:
    """Every task of ``tasks`` gets its data from exactly one place: the collect stage (``collect_tasks``) or an
    import (a key of ``imports``)."""
    collect = p.collect_tasks or ()
    if len(set(collect)) != len(collect):
        raise ConfigError(f"collect_tasks: lists a task twice: {list(collect)}")
    for name in collect:
        if name not in p.tasks:
            raise ConfigError(f"collect_tasks: {name!r} is not one of tasks {list(p.tasks)}; remove it")
    for name in p.imports:
        if name not in p.tasks:
            raise ConfigError(
                f"imports.{name}: {name!r} is not one of tasks {list(p.tasks)}; add it to tasks or remove its entry"
            )
        if name in collect:
            raise ConfigError(
                f"collect_tasks: {name!r} is imported (imports.{name}); remove it from collect_tasks or drop the import"
            )
    for name in p.tasks:
        if name not in collect and name not in p.imports:
            raise ConfigError(
                f"collect_tasks: {name!r} of tasks has no data source; add it to collect_tasks or give it an entry "
                "under imports"
            )


def check_model_sources(p: Params) -> None:
    """Every task of ``tasks`` gets its phase-0 models from exactly one place: the pretrain stage
    (``pretrain_tasks``) or an import (a key of ``pretrained``)."""
    trained = p.pretrain_tasks or ()
    for name, folder in p.pretrained.items():
        if name not in p.tasks:
            raise ConfigError(
                f"pretrained.{name}: {name!r} is not one of tasks {list(p.tasks)}; add it to tasks or remove its entry"
            )
        if not folder.strip():
            raise ConfigError(f"pretrained.{name}: is empty; name the folder that holds its seed<s>/ models")
        if folder.startswith("~"):
            raise ConfigError(
                f"pretrained.{name}: {folder!r} starts with ~, which DVC does not expand in a dependency; write the "
                "path in full or relative to the project"
            )
    for name in trained:
        if name not in p.tasks:
            raise ConfigError(f"pretrain_tasks: {name!r} is not one of tasks {list(p.tasks)}; remove it")
    expected = [t for t in p.tasks if t not in p.pretrained]
    if sorted(trained) != sorted(expected):
        raise ConfigError(
            f"pretrain_tasks: must list the tasks of 'tasks' that have no pretrained folder: {expected}, got "
            f"{list(trained)} (remove the key to have it computed)"
        )


def check_task_lists(p: Params) -> None:
    """``tasks`` names defined tasks once each; ``unseen_tasks`` are exactly the tasks of ``tasks`` whose family has
    an unseen task; ``evolve`` is one of ``tasks``."""
    if not p.tasks:
        raise ConfigError("tasks: must list at least one task (a key of 'task')")
    for key in ("tasks", "unseen_tasks"):
        names = getattr(p, key)
        for name in names:
            if name not in p.task:
                raise ConfigError(f"{key}: {name!r} is not a task defined under 'task' (defined: {sorted(p.task)})")
        if len(set(names)) != len(names):
            raise ConfigError(f"{key}: lists a task twice: {list(names)}")
    needs = {"unseen_tasks": [n for n in p.tasks if unseen_task_of(p.task[n]) is not None]}
    for key, expected in needs.items():
        if sorted(getattr(p, key)) != sorted(expected):
            raise ConfigError(
                f"{key}: must list exactly the tasks of 'tasks' whose family has an unseen task: {expected}, "
                f"got {list(getattr(p, key))}"
            )
    if p.evolve is not None and p.evolve not in p.tasks:
        raise ConfigError(f"evolve: {p.evolve!r} must be one of tasks {list(p.tasks)} (or null)")
    if p.phases and p.evolve is None:
        raise ConfigError("evolve: is null but phases are declared; name the task to evolve or set phases: {}")
    if p.evolve is not None and "evolve" not in task_stages(p.evolved):
        raise ConfigError(
            f"evolve: the evolution phases are not implemented for the {p.evolved.family} family yet; "
            "set evolve: null (phase 0 only) or name a task of a family that has them"
        )


def task_stages(task: TaskParams) -> tuple[str, ...]:
    """The optional stages a task's family has (``evolve``), declared by its task model."""
    return tuple(getattr(task.settings, "OPTIONAL_STAGES", ()))


def evolution_recipes(task: TaskParams) -> tuple[str, ...]:
    """The ways a task's family makes an evolution phase's data (``evolution.generate.recipe``), declared by its
    task model (``EVOLUTION_RECIPES``); every family has ``plans``."""
    return tuple(getattr(task.settings, "EVOLUTION_RECIPES", ("plans",)))


def unseen_task_of(task: TaskParams) -> str | None:
    """The name of the unseen task of a task's family (``gold_coin``, ``pick_place``), declared by its task model
    (``UNSEEN_TASK``), or None."""
    return getattr(task.settings, "UNSEEN_TASK", None)
