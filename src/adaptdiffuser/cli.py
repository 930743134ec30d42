"""The ``adaptdiffuser`` command line: one subcommand per pipeline stage, plus profile switching."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer

from adaptdiffuser.config import ConfigError, Params, apply_profile, load_params
from adaptdiffuser.config.start_states import KEPT_EVAL_SEED, KEPT_HELD_OUT_SEED
from adaptdiffuser.data.schema import SchemaError
from adaptdiffuser.errors import StageError

app = typer.Typer(help="AdaptDiffuser: pipeline stages and tools.", no_args_is_help=True, add_completion=False)

ParamsPath = Annotated[Path, typer.Option("--params", help="params file (validated before any work)")]
Device = Annotated[
    str,
    typer.Option("--device", envvar="ADAPTDIFFUSER_DEVICE", help="torch device: auto, cpu, cuda, cuda:N"),
]
Progress = Annotated[bool, typer.Option("--progress/--no-progress", help="show progress bars")]


def _phase_index(value: str | int) -> int:
    """``--phase`` accepts ``2`` or ``phase2`` (the name DVC's foreach passes)."""
    digits = str(value).removeprefix("phase")
    if not digits.isdigit():
        raise typer.BadParameter(f"expected a phase number or name like 2 or phase2, got {value!r}")
    return int(digits)


PhaseOption = typer.Option("--phase", parser=_phase_index, metavar="K", help="phase number or name (2 or phase2)")
EvolutionPhase = Annotated[int, PhaseOption]

T = TypeVar("T")


def _guarded(fn: Callable[[], T]) -> T:
    """Run a stage body; turn known input errors into a one-line message and exit code 2."""
    try:
        return fn()
    except (ConfigError, SchemaError, FileNotFoundError, FileExistsError, StageError) as err:
        typer.secho(f"error: {err}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=2) from err


def _params(path: Path) -> Params:
    return _guarded(lambda: load_params(path))


TaskOption = Annotated[
    str | None,
    typer.Option("--task", help="task name (a key of 'task' in params); default: the only task, or 'evolve'"),
]


def _task(p: Params, name: str | None, evolution: bool = False) -> str:
    """The task a stage runs on: ``--task``, else ``evolve`` for evolution stages, else the only listed task."""
    if name is not None:
        return name
    if evolution and p.evolve is not None:
        return p.evolve
    if len(p.tasks) == 1:
        return p.tasks[0]
    return _guarded(lambda: _raise(ConfigError(f"tasks: several tasks {list(p.tasks)}; choose one with --task")))


def _raise(err: Exception) -> None:
    raise err


@app.command()
def code(
    task: Annotated[str, typer.Option("--task", help="the task whose code is fingerprinted")],
    family: Annotated[str, typer.Option("--family", help="the task's family (task.<name>.family)")],
) -> None:
    """Write ``code/<task>.json``: the digest of the core and of the family's folder (the ``code`` stage)."""
    from adaptdiffuser.io import write_json
    from adaptdiffuser.tooling.code_fingerprint import fingerprint, fingerprint_path

    digest = _guarded(lambda: fingerprint(Path.cwd(), family))
    write_json(fingerprint_path(task), digest)
    typer.echo(f"{fingerprint_path(task)}: {len(digest['files'])} files of the core and family {family}")


@app.command()
def collect(params: ParamsPath = Path("params.yaml"), task: TaskOption = None, progress: Progress = True) -> None:
    """Collect a task's offline dataset (its family's recipe) into data/<task>/dataset.parquet."""
    from adaptdiffuser.stages.collect import run_collect

    p = _params(params)
    out = _guarded(lambda: run_collect(p, _task(p, task), Path.cwd(), progress=progress))
    typer.echo(f"wrote {out}")


@app.command("import-data")
def import_data(params: ParamsPath = Path("params.yaml"), task: TaskOption = None, progress: Progress = True) -> None:
    """Import a task's dataset from imports.<task> (a D4RL HDF5 file or a Minari dataset) into
    data/<task>/dataset.parquet, instead of the collect stage."""
    from adaptdiffuser.stages.import_data import run_import

    p = _params(params)
    out = _guarded(lambda: run_import(p, _task(p, task), Path.cwd(), progress=progress))
    typer.echo(f"wrote {out}")


@app.command("export-minari")
def export_minari(
    data: Annotated[Path, typer.Argument(help="a trajectory file: data/<task>/dataset.parquet or a selected file")],
    dataset_id: Annotated[str, typer.Option("--dataset-id", help="Minari id, namespace/name-v0")],
    task: TaskOption = None,
    path: Annotated[
        Path | None, typer.Option("--path", help="Minari store folder (default: $MINARI_DATASETS_PATH or ~/.minari)")
    ] = None,
    force: Annotated[bool, typer.Option("--force", help="replace an existing dataset of that id")] = False,
    params: ParamsPath = Path("params.yaml"),
) -> None:
    """Write one of our trajectory files as a Minari dataset (minari.load_dataset opens it), with the task's env
    spec."""
    from adaptdiffuser.stages.export import run_export_minari

    p = _params(params)
    out = _guarded(lambda: run_export_minari(p, _task(p, task), data, dataset_id, path, force))
    typer.echo(f"wrote Minari dataset {dataset_id} at {out}")


@app.command()
def reference(params: ParamsPath = Path("params.yaml"), task: TaskOption = None, progress: Progress = True) -> None:
    """What 0 and 100 of a task's score mean (R_min, R_max) into metrics/tasks/<task>/reference.json."""
    from adaptdiffuser.stages.reference import run_reference

    p = _params(params)
    ref = _guarded(lambda: run_reference(p, _task(p, task), Path.cwd(), progress=progress))
    typer.echo(f"R_min {ref['r_min']:.2f}, R_max {ref['r_max']:.2f}")


@app.command()
def pretrain(
    params: ParamsPath = Path("params.yaml"),
    task: TaskOption = None,
    device: Device = "auto",
    progress: Progress = True,
) -> None:
    """Train the Diffuser baseline (phase 0) on a task's dataset into models/<task>/phase0/seed<s>, once per
    training seed (``seeds``)."""
    from adaptdiffuser.stages.common import resolve_device
    from adaptdiffuser.stages.pretrain import run_pretrain

    p = _params(params)
    out = _guarded(lambda: run_pretrain(p, _task(p, task), Path.cwd(), resolve_device(device), progress=progress))
    typer.echo(f"wrote {out}")


@app.command("import-model")
def import_model(
    params: ParamsPath = Path("params.yaml"),
    task: TaskOption = None,
    device: Device = "auto",
    progress: Progress = True,
) -> None:
    """Import a task's trained phase-0 models from pretrained.<task> (a folder of seed<s>/ model folders), checked
    against the task's model and data, into models/<task>/phase0/seed<s>, instead of the pretrain stage."""
    from adaptdiffuser.stages.common import resolve_device
    from adaptdiffuser.stages.import_model import run_import_model

    p = _params(params)
    out = _guarded(lambda: run_import_model(p, _task(p, task), Path.cwd(), resolve_device(device), progress=progress))
    typer.echo(f"wrote {out}")


@app.command()
def evaluate(
    params: ParamsPath = Path("params.yaml"),
    task: TaskOption = None,
    phase: Annotated[int, PhaseOption] = 0,
    device: Device = "auto",
    progress: Progress = True,
) -> None:
    """Evaluate a phase's model on a task under its protocol; write results, pictures and
    metrics/tasks/<task>/phase<k>.json."""
    from adaptdiffuser.stages.common import resolve_device
    from adaptdiffuser.stages.evaluate import run_evaluate

    p = _params(params)
    name = _task(p, task, evolution=phase > 0)
    m = _guarded(lambda: run_evaluate(p, name, Path.cwd(), phase, resolve_device(device), progress=progress))
    typer.echo(f"{name} phase {phase}: score {m['score_mean']:.1f} +- {m['score_stderr']:.1f} ({_spread(m)})")


def _figures(items: Iterable[tuple[str, float | None]]) -> str:
    """``key value`` pairs for a stage's closing line, numbers to 3 significant digits; a metric no episode could
    measure (None) as ``none``."""
    return ", ".join(f"{key} {'none' if value is None else format(value, '.3g')}" for key, value in items)


def _spread(metrics: dict) -> str:
    """What a standard error is over: the episodes of one training seed, or the seeds."""
    if metrics.get("n_seeds", 1) > 1:
        return f"over {metrics['n_seeds']} training seeds of {metrics['n_episodes']} episodes each"
    return f"{metrics['n_episodes']} episodes"


@app.command("evaluate-control")
def evaluate_control(
    phase: EvolutionPhase,
    params: ParamsPath = Path("params.yaml"),
    task: TaskOption = None,
    device: Device = "auto",
    progress: Progress = True,
) -> None:
    """Evaluate phase k's equal-compute control on the same episodes as phase k; write its metrics with the gain
    of phase k over it into metrics/tasks/<task>/phase<k>-control.json."""
    from adaptdiffuser.stages.common import resolve_device
    from adaptdiffuser.stages.evaluate import run_evaluate

    p = _params(params)
    name = _task(p, task, evolution=True)
    dev = resolve_device(device)
    m = _guarded(lambda: run_evaluate(p, name, Path.cwd(), phase, dev, progress=progress, control=True))
    typer.echo(
        f"{name} phase {phase} control: score {m['score_mean']:.1f} +- {m['score_stderr']:.1f}; "
        f"gain of phase {phase} {m['gain_mean']:+.1f} +- {m['gain_stderr']:.1f} ({_spread(m)}, paired)"
    )


def _evaluate_unseen(params: Path, task: str | None, phase: int, device: str, progress: bool, control: bool) -> None:
    from adaptdiffuser.family_registry import get_family
    from adaptdiffuser.stages.common import resolve_device
    from adaptdiffuser.stages.evaluate_unseen import run_evaluate_unseen

    p = _params(params)
    name = _task(p, task, evolution=True)
    dev = resolve_device(device)
    m = _guarded(lambda: run_evaluate_unseen(p, name, Path.cwd(), phase, dev, progress=progress, control=control))
    who = f"phase {phase}{' control' if control else ''}"
    if "skipped" in m:
        typer.echo(f"{who}: skipped, {m['skipped']}")
        return
    family = get_family(p.task[name].family)
    figures = _figures(sorted(m.items()))
    typer.echo(f"{who}, alpha {p.alpha:g}: {family.unseen_task} objective {family.unseen_objective(m):.2f} ({figures})")


@app.command("evaluate-unseen")
def evaluate_unseen(
    params: ParamsPath = Path("params.yaml"),
    task: TaskOption = None,
    phase: Annotated[int, PhaseOption] = 0,
    device: Device = "auto",
    progress: Progress = True,
) -> None:
    """Evaluate a phase's model on its family's unseen task (Maze2D gold coin, KUKA pick-and-place), guided with
    the top-level alpha."""
    _evaluate_unseen(params, task, phase, device, progress, control=False)


@app.command("evaluate-unseen-control")
def evaluate_unseen_control(
    phase: EvolutionPhase,
    params: ParamsPath = Path("params.yaml"),
    task: TaskOption = None,
    device: Device = "auto",
    progress: Progress = True,
) -> None:
    """Evaluate an evolution phase's equal-compute control on the unseen task, as evaluate-unseen does the phase."""
    _evaluate_unseen(params, task, phase, device, progress, control=True)


@app.command()
def generate(
    phase: EvolutionPhase,
    params: ParamsPath = Path("params.yaml"),
    task: TaskOption = None,
    device: Device = "auto",
    progress: Progress = True,
) -> None:
    """Sample plans for random tasks with phase k-1's model into data/<task>/phase<k>/generated/seed<s>.parquet
    (one per training seed)."""
    from adaptdiffuser.stages.common import resolve_device
    from adaptdiffuser.stages.generate import run_generate

    p = _params(params)
    name = _task(p, task, evolution=True)
    per_seed = _guarded(lambda: run_generate(p, name, Path.cwd(), phase, resolve_device(device), progress=progress))
    for seed, stats in per_seed.items():
        details = _figures((key, value) for key, value in stats.items() if key != "generated")
        typer.echo(f"phase {phase}, seed {seed}: generated {stats['generated']} plans ({details})")


@app.command()
def discriminate(
    phase: EvolutionPhase, params: ParamsPath = Path("params.yaml"), task: TaskOption = None, progress: Progress = True
) -> None:
    """Track generated plans in the simulator, reject and select into data/<task>/phase<k>/selected/seed<s>.parquet
    (one per training seed)."""
    from adaptdiffuser.stages.discriminate import run_discriminate

    p = _params(params)
    name = _task(p, task, evolution=True)
    report = _guarded(lambda: run_discriminate(p, name, Path.cwd(), phase, progress=progress))
    for seed, r in report["seeds"].items():
        typer.echo(
            f"phase {phase}, seed {seed}: kept {r['kept']} of {r['generated']} "
            f"({r['rejected_tracking']} failed tracking, {r['rejected_reward']} failed the reward rule)"
        )


def _train_phase(phase: int, params: Path, task: str | None, device: str, progress: bool, control: bool) -> None:
    """The body of ``finetune`` and ``control``: they differ only in the data (``control``: expert only)."""
    from adaptdiffuser.stages.common import resolve_device
    from adaptdiffuser.stages.finetune import run_finetune

    p = _params(params)
    name = _task(p, task, evolution=True)
    dev = resolve_device(device)
    out = _guarded(lambda: run_finetune(p, name, Path.cwd(), phase, dev, progress=progress, control=control))
    typer.echo(f"wrote {out}")


@app.command()
def finetune(
    phase: EvolutionPhase,
    params: ParamsPath = Path("params.yaml"),
    task: TaskOption = None,
    device: Device = "auto",
    progress: Progress = True,
) -> None:
    """Fine-tune phase k-1's model on expert plus selected data into models/<task>/phase<k>/seed<s> (one per
    training seed)."""
    _train_phase(phase, params, task, device, progress, control=False)


@app.command()
def control(
    phase: EvolutionPhase,
    params: ParamsPath = Path("params.yaml"),
    task: TaskOption = None,
    device: Device = "auto",
    progress: Progress = True,
) -> None:
    """Phase k's equal-compute control: phase k-1's model trained as finetune@phase<k> does (same steps, seed and
    settings) on expert data only, into models/<task>/phase<k>-control/seed<s>."""
    _train_phase(phase, params, task, device, progress, control=True)


@app.command()
def summarize(params: ParamsPath = Path("params.yaml")) -> None:
    """Merge every task's phase metrics into metrics/summary.json (task, then phase)."""
    from adaptdiffuser.stages.summarize import run_summarize

    p = _params(params)
    _guarded(lambda: run_summarize(p, Path.cwd()))
    typer.echo("wrote metrics/summary.json")


@app.command()
def report(
    summary: Annotated[
        Path | None, typer.Option("--summary", help="a kept summary to draw (default: metrics/summary.json)")
    ] = None,
    into: Annotated[Path | None, typer.Option("--into", help="write under this folder (default: here)")] = None,
) -> None:
    """Score by phase, per task: plots/report/<task>/score_by_phase.png and metrics/report/<task>/score_by_phase.csv
    (e.g. `adaptdiffuser report --summary metrics/science/maze2d-medium.json --into out/medium`)."""
    from adaptdiffuser.stages.report import run_report

    tables = _guarded(lambda: run_report(Path.cwd(), summary, into))
    for task, rows in tables.items():
        for row in rows:
            typer.echo(f"{task} phase {row['phase']}: score {row['score_mean']:.1f} +- {row['score_stderr']:.1f}")


@app.command()
def sweep(
    params: ParamsPath = Path("params.yaml"),
    trials: Annotated[int | None, typer.Option(help="trials in all (default: sweep.trials)")] = None,
    workers: Annotated[int | None, typer.Option(help="worker processes sharing the study (default: sweep.workers)")] = (
        None
    ),
    storage: Annotated[
        str | None,
        typer.Option(help="Optuna storage: a journal file path (default sweeps/<study>.journal) or postgresql://..."),
    ] = None,
    apply: Annotated[bool, typer.Option("--apply", help="write the best values into the params file")] = False,
    dvc_exp: Annotated[
        str,
        typer.Option(
            help="record the best trial as the DVC experiment <study>-best-trial<n>: run (now, in a temporary "
            "copy, on the pipeline's evaluation episodes), queue (for `dvc queue start`) or none"
        ),
    ] = "run",
    device: Device = "auto",
) -> None:
    """Optuna sweep over the params in sweep.space: each trial reruns the evolution phases on the cached phase 0."""
    from adaptdiffuser.tooling.dvc_experiments import EXPERIMENT_MODES
    from adaptdiffuser.tooling.optuna_sweep import apply_best, run_sweep

    _params(params)
    if dvc_exp not in EXPERIMENT_MODES:
        _guarded(
            lambda: _raise(ConfigError(f"--dvc-exp: expected one of {', '.join(EXPERIMENT_MODES)}, got {dvc_exp!r}"))
        )
    mode: Any = dvc_exp  # one of EXPERIMENT_MODES, checked above
    result = _guarded(lambda: run_sweep(Path.cwd(), params, trials, workers, storage, device, mode))
    counts: dict[str, int] = {}
    for trial in result.study.trials:
        counts[trial.state.name] = counts.get(trial.state.name, 0) + 1
    typer.echo(f"study {result.study.study_name}: {counts}")
    typer.echo(f"best objective {result.best_value:.2f} with {result.best_values}")
    if result.dvc_experiment is None:
        typer.echo(f"reproduce it as a DVC experiment:\n  {result.command}")
    elif dvc_exp == "queue":
        typer.echo(f"queued as DVC experiment {result.dvc_experiment}: `dvc queue start`, then `dvc exp show`")
    else:
        typer.echo(f"recorded as DVC experiment {result.dvc_experiment} (evaluation episodes): `dvc exp show`")
    if apply:
        _guarded(lambda: apply_best(params, result.best_values))
        typer.echo(f"wrote the best values into {params}")


@app.command()
def profile(
    name: Annotated[str, typer.Argument(help="a profile of profiles/: quick, smoke, science, paper-large...")],
    params: ParamsPath = Path("params.yaml"),
    profiles_dir: Annotated[Path, typer.Option(help="folder of profile files")] = Path("profiles"),
    tiny: Annotated[
        bool, typer.Option(help="the profile at tiny scale: same shapes and code paths, runs in minutes")
    ] = False,
) -> None:
    """Switch params.yaml to a profile (profiles/quick.yaml overlaid with the parts profiles/<name>.yaml extends,
    then its own keys)."""
    out = _guarded(lambda: apply_profile(name, profiles_dir, params, tiny=tiny))
    scale = " at tiny scale" if tiny else ""
    typer.echo(f"{out} now holds profile {name!r}{scale}; run `dvc repro`")


@app.command("set")
def set_value(
    assignments: Annotated[
        list[str], typer.Argument(help="key=value, e.g. evolve=hopper-medium or seeds=[0,1,2]; several at once")
    ],
    params: ParamsPath = Path("params.yaml"),
) -> None:
    """Set params keys in place, keeping the file's comments; the result (all keys set) is validated before it is
    written."""
    import yaml

    from adaptdiffuser.tooling.optuna_sweep import apply_best

    values = {}
    for assignment in assignments:
        key, sep, value = assignment.partition("=")
        if not sep or not key.strip():
            _guarded(lambda assignment=assignment: _raise(ConfigError(f"set: expected key=value, got {assignment!r}")))
        values[key.strip()] = yaml.safe_load(value)
    _guarded(lambda: apply_best(params, values))
    for assignment in assignments:
        key, _, value = assignment.partition("=")
        typer.echo(f"{params}: {key.strip()} = {value}")


@app.command()
def gains(
    summaries: Annotated[
        list[Path] | None, typer.Argument(help="metrics/summary.json files (default: metrics/summary.json)")
    ] = None,
) -> None:
    """Print each phase's score, its equal-compute control and the gain over it (mean ± standard error and the 95 %
    interval over training seeds; with one seed the interval over episodes, labelled "one seed: over episodes"),
    the win rate, and the gain and win rate on the held-out start states as a Markdown table; then the same on
    D4RL's constants where the task gives them (Maze2D), and the score on the unseen task (gold coin,
    pick-and-place), phase against control. A task whose entries in several files differ beyond phase 0 (two
    recipes, two runs) is listed once per file, as ``<task> (<file name>)``."""
    from adaptdiffuser.io import read_json
    from adaptdiffuser.stages.report import d4rl_table, gains_table, merge_summaries, unseen_table

    paths = summaries or [Path("metrics/summary.json")]
    stems = [path.stem for path in paths]
    labels = stems if len(set(stems)) == len(stems) else [str(path) for path in paths]  # each file its own name
    read = lambda path: _guarded(lambda: read_json(path, f"{path} (run the summarize stage)"))  # noqa: E731
    merged = merge_summaries([(label, read(path)) for label, path in zip(labels, paths, strict=True)])
    for line in gains_table(merged):
        typer.echo(line)
    for table in (d4rl_table(merged), unseen_table(merged)):
        if table:
            typer.echo("")
            for line in table:
                typer.echo(line)


@app.command()
def pool(
    into: Annotated[Path, typer.Option(help="folder for the pooled run (replaced whole)")],
    runs: Annotated[
        list[Path] | None, typer.Argument(help="runs' folders (params.yaml, metrics/) differing in seeds")
    ] = None,
    exp: Annotated[
        list[str] | None, typer.Option("--exp", help="a DVC experiment of this repository (repeat it), e.g. NAME-seed1")
    ] = None,
) -> None:
    """Pool runs of one profile that differ only in their training seeds and phase-0 source (folders, or the DVC
    experiments `adaptdiffuser seeds queue` queued) into the metrics and summaries one run over all their seeds
    writes; then `adaptdiffuser gains INTO/metrics/summary.json` tables them."""
    from adaptdiffuser.stages.pool import pool_runs

    for line in _guarded(lambda: pool_runs(runs or [], into, experiments=exp or [])):
        typer.echo(line)


run_app = typer.Typer(
    help="A long run in the background (dvc repro by default); after any stop, `run start` again continues it.",
    no_args_is_help=True,
)
app.add_typer(run_app, name="run")
RepoOption = Annotated[Path, typer.Option("--repo", help="the DVC project (default: the working directory)")]


@run_app.command("start")
def run_start(
    command: Annotated[list[str] | None, typer.Argument(help="command to run (default: dvc repro); after --")] = None,
    repo: RepoOption = Path("."),
) -> None:
    """Start the run in the background (log: .long-run/log). Starting again after a stop continues it: DVC
    skips finished stages and training resumes from models/.resume/."""
    from adaptdiffuser.tooling.long_run import DEFAULT_COMMAND, log_path, start

    pid = _guarded(lambda: start(repo, command or DEFAULT_COMMAND))
    typer.echo(f"running in the background (pid {pid}, log {log_path(repo)}): adaptdiffuser run status")


@run_app.command("status")
def run_status(repo: RepoOption = Path(".")) -> None:
    """Whether the run runs, finished or stopped; the stages left; each resume state; the log's last lines."""
    from adaptdiffuser.tooling.long_run import status

    for line in _guarded(lambda: status(repo)):
        typer.echo(line)


@run_app.command("stop")
def run_stop(
    repo: RepoOption = Path("."),
    grace: Annotated[float, typer.Option(help="seconds to wait for the run to end before SIGKILL")] = 60.0,
) -> None:
    """Stop the run and all it started (SIGTERM: a training stage writes its resume state first)."""
    from adaptdiffuser.tooling.long_run import stop

    killed = _guarded(lambda: stop(repo, grace))
    how = f"killed after {grace:g} s" if killed else "stopped"
    typer.echo(f"{how}; continue: adaptdiffuser run start")


seeds_app = typer.Typer(help="A multi-seed run as DVC experiments, one per training seed.", no_args_is_help=True)
app.add_typer(seeds_app, name="seeds")


@seeds_app.command("queue")
def seeds_queue(
    seeds: Annotated[list[int], typer.Argument(help="training seeds, one experiment each")],
    name: Annotated[str, typer.Option(help="experiments are named NAME-seed<s>")] = "run",
    repo: RepoOption = Path("."),
) -> None:
    """Queue one DVC experiment per training seed (`-S seeds=[s]`) for `dvc queue start -j N`."""
    from adaptdiffuser.tooling.dvc_experiments import queue_seeds

    names = _guarded(lambda: queue_seeds(repo, name, seeds))
    typer.echo(f"queued {' '.join(names)}: dvc queue start -j N; then")
    typer.echo(f"  adaptdiffuser pool {' '.join(f'--exp {n}' for n in names)} --into metrics/runs/{name}")


@app.command("evaluate-kept")
def evaluate_kept(
    names: Annotated[
        list[str], typer.Argument(help="models of metrics/kept-models.json (maze2d-large/seed2/phase1-plans ...)")
    ],
    episodes: Annotated[int, typer.Option(min=1, help="episodes to play per model")] = 500,
    eval_seed: Annotated[
        int,
        typer.Option(
            min=0, help="the seed of the start states (plus each training seed); the default no other part plays"
        ),
    ] = KEPT_EVAL_SEED,
    held_out_seed: Annotated[
        int, typer.Option(min=0, help="the seed of the held-out start states (plus each training seed)")
    ] = KEPT_HELD_OUT_SEED,
    held_out_episodes: Annotated[
        int | None, typer.Option(min=0, help="held-out episodes per model (default: --episodes; 0: none)")
    ] = None,
    own_start_states: Annotated[
        bool, typer.Option("--own-start-states/--same-start-states", help="offset the seed by the training seed")
    ] = True,
    into: Annotated[Path | None, typer.Option(help="also write the metrics and episode scores to this JSON")] = None,
    device: Device = "auto",
    progress: Progress = True,
) -> None:
    """Score kept models (each with its equal-compute control on the same episodes: the paired gain and its win
    rate) on start states of your own and on held-out ones, each training seed on its own, under the params and
    reference scores of the run that made it; with several models, the mean over them and its 95 % interval over
    seeds (a t-interval of the models' means), and with one, its interval over episodes, labelled so. The default
    seeds give start states no other part plays (config/start_states.py)."""
    from adaptdiffuser.intervals import describe
    from adaptdiffuser.io import write_json
    from adaptdiffuser.stages.common import resolve_device
    from adaptdiffuser.stages.kept_models import evaluate_kept_seeds

    out = _guarded(
        lambda: evaluate_kept_seeds(
            Path.cwd(),
            names,
            episodes,
            eval_seed,
            resolve_device(device),
            own_start_states,
            progress,
            held_out_seed=held_out_seed,
            held_out_episodes=held_out_episodes,
        )
    )
    sets = [("own", episodes, out)]
    if "held_out" in out:
        sets.append(("held out", out["held_out"]["episodes"], out["held_out"]))
    for label, n, played in sets:
        for name, run in played["models"].items():
            parts = [
                f"{role} {m['score_mean']:.1f} +- {m['score_stderr']:.1f}"
                for role, m in run.items()
                if role in ("model", "control")
            ]
            if "gain" in run:
                gain = run["gain"]
                parts.append(
                    f"gain {gain['gain_mean']:.1f} +- {gain['gain_stderr']:.1f}, win rate {gain['win_rate']:.2f}"
                )
            seed = played["eval_seeds"][name]
            typer.echo(f"{name} ({label}: start states of seed {seed}, {n} episodes): {', '.join(parts)}")
        for what, m in played["interval"].items():
            extra = f", win rate {m['win_rate']:.2f}" if what == "gain" else ""
            models = f"{m['n_seeds']} model" + ("s" if m["n_seeds"] != 1 else "")
            typer.echo(f"{what} ({label}) over {models}: {describe(m)}{extra}")
    if into is not None:
        write_json(into, {"episodes": episodes, **out})


@app.command()
def times() -> None:
    """How long each stage of this pipeline run took (this commit and params.yaml), from its MLflow runs."""
    from adaptdiffuser.tooling.mlflow_logging import stage_times

    rows = stage_times(Path.cwd())
    if not rows:
        typer.echo("no stage has run at this commit and params.yaml (MLflow: mlflow.db)")
        return
    for row in rows:
        typer.echo(f"{row['seconds']:8.1f} s  {row['task']}  {row['run']}  {row['status']}")
    typer.echo(f"{sum(row['seconds'] for row in rows):8.1f} s  in all ({len(rows)} stage runs)")


@app.command("mlflow-log")
def mlflow_log(
    paths: Annotated[
        list[Path] | None,
        typer.Argument(help="project roots or mlflow-pending folders (default: this project)", show_default=False),
    ] = None,
) -> None:
    """Log the stage run records waiting in mlflow-pending/ (and in its sweeps' sweeps/*/trial_*/mlflow-pending/) to
    MLflow. The summarize stage does it at the end of a pipeline run; run this after `dvc repro <stage>` of an earlier
    stage, or after a pipeline or sweep that failed. Exit 2 if a record could not be logged (moved to
    mlflow-pending/.failed/<id>/ with its error.txt)."""
    from adaptdiffuser.tooling.mlflow_logging import log_pending, pending_sources, tracking_uri
    from adaptdiffuser.tooling.run_records import redact_text

    failed: list[str] = []
    for path in paths or [Path.cwd()]:
        if not path.is_dir():
            typer.secho(f"error: {path} is no folder (a project root or an mlflow-pending folder)", fg="red", err=True)
            raise typer.Exit(code=1)
        for root, store in pending_sources(path):
            logged = log_pending(root, store)
            if logged or root == store:
                typer.echo(f"logged {len(logged)} stage run(s) to {redact_text(tracking_uri(store))} from {root}")
            failed += [f"{root}: {record}: {error}" for record, error in logged.failed.items()]
    if failed:
        typer.secho(f"{len(failed)} record(s) not logged, moved to mlflow-pending/.failed/:", fg="red", err=True)
        for line in failed:
            typer.secho(f"  {line}", fg="red", err=True)
        raise typer.Exit(code=2)


@app.command()
def check(params: ParamsPath = Path("params.yaml")) -> None:
    """Validate a params file (exit 1 on a bad value, naming the key), name the family keys its task entries leave
    to the defaults, and print what it will run."""
    from adaptdiffuser.config import describe
    from adaptdiffuser.config.defaults import unwritten
    from adaptdiffuser.config.loader import read_yaml_mapping

    try:
        p = load_params(params)
    except ConfigError as err:
        typer.secho(f"error: {err}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1) from err
    typer.echo(f"{params}: ok")
    filled = unwritten(read_yaml_mapping(Path(params), "top level must be a mapping of sections"))
    if filled:
        typer.secho(
            f"{params}: {len(filled)} task keys not written, taken from their family's defaults: {', '.join(filled)}",
            fg=typer.colors.YELLOW,
        )
    for line in describe(p):
        typer.echo(line)


def run_stage(stage: str) -> None:
    """Entry used by ``pipeline/<stage>.py``: the CLI subcommand ``stage`` with the script's arguments."""
    import sys

    app(args=[stage, *sys.argv[1:]], prog_name=f"pipeline/{stage}.py")
