"""The ``adaptdiffuser`` command line: one subcommand per pipeline stage, plus profile switching."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated, TypeVar

import typer

from adaptdiffuser.config import ConfigError, Params, apply_profile, load_params
from adaptdiffuser.data.schema import SchemaError

app = typer.Typer(help="AdaptDiffuser: pipeline stages and tools.", no_args_is_help=True, add_completion=False)

ParamsPath = Annotated[Path, typer.Option("--params", help="params file (validated before any work)")]
Device = Annotated[
    str,
    typer.Option("--device", envvar="ADAPTDIFFUSER_DEVICE", help="torch device: auto, cpu, cuda, cuda:N"),
]
Progress = Annotated[bool, typer.Option("--progress/--no-progress", help="show progress bars")]

T = TypeVar("T")


def _guarded(fn: Callable[[], T]) -> T:
    """Run a stage body; turn known input errors into a one-line message and exit code 2."""
    try:
        return fn()
    except (ConfigError, SchemaError, FileNotFoundError) as err:
        typer.secho(f"error: {err}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=2) from err


def _params(path: Path) -> Params:
    return _guarded(lambda: load_params(path))


@app.command()
def collect(params: ParamsPath = Path("params.yaml"), progress: Progress = True) -> None:
    """Collect expert data (D4RL's waypoint recipe) into data/expert.parquet."""
    from adaptdiffuser.stages.collect import run_collect

    p = _params(params)
    out = _guarded(lambda: run_collect(p, Path.cwd(), progress=progress))
    typer.echo(f"wrote {out}")


@app.command()
def reference(params: ParamsPath = Path("params.yaml"), progress: Progress = True) -> None:
    """Measure R_min (random policy) and R_max (expert) under the evaluation protocol."""
    from adaptdiffuser.stages.reference import run_reference

    p = _params(params)
    ref = _guarded(lambda: run_reference(p, Path.cwd(), progress=progress))
    typer.echo(f"R_min {ref['r_min']:.2f}, R_max {ref['r_max']:.2f} over {ref['n_episodes']} episodes")


@app.command()
def pretrain(params: ParamsPath = Path("params.yaml"), device: Device = "auto", progress: Progress = True) -> None:
    """Train the Diffuser baseline (phase 0) on expert data into models/phase0."""
    from adaptdiffuser.stages.common import resolve_device
    from adaptdiffuser.stages.pretrain import run_pretrain

    p = _params(params)
    out = _guarded(lambda: run_pretrain(p, Path.cwd(), resolve_device(device), progress=progress))
    typer.echo(f"wrote {out}")


@app.command()
def evaluate(
    params: ParamsPath = Path("params.yaml"),
    phase: Annotated[int, typer.Option(help="which phase's model to evaluate")] = 0,
    device: Device = "auto",
    progress: Progress = True,
) -> None:
    """Evaluate a phase's model under the protocol; write results, pictures and metrics/phase<k>.json."""
    from adaptdiffuser.stages.common import resolve_device
    from adaptdiffuser.stages.evaluate import run_evaluate

    p = _params(params)
    nav = _guarded(lambda: run_evaluate(p, Path.cwd(), phase, resolve_device(device), progress=progress))
    typer.echo(
        f"phase {phase}: score {nav['score_mean']:.1f} +- {nav['score_stderr']:.1f} "
        f"(success {nav['success_rate']:.2f}, {nav['n_episodes']} episodes)"
    )


@app.command()
def summarize(phases: Annotated[list[int], typer.Option("--phase", help="phases to include")] = [0]) -> None:  # noqa: B006
    """Merge per-phase metrics into metrics/summary.json."""
    from adaptdiffuser.stages.summarize import run_summarize

    _guarded(lambda: run_summarize(Path.cwd(), sorted(set(phases))))
    typer.echo("wrote metrics/summary.json")


@app.command()
def profile(
    name: Annotated[str, typer.Argument(help="quick, smoke, paper-umaze, paper-medium or paper-large")],
    params: ParamsPath = Path("params.yaml"),
    profiles_dir: Annotated[Path, typer.Option(help="folder of profile files")] = Path("profiles"),
) -> None:
    """Switch params.yaml to a profile (profiles/quick.yaml overlaid with profiles/<name>.yaml)."""
    out = _guarded(lambda: apply_profile(name, profiles_dir, params))
    typer.echo(f"{out} now holds profile {name!r}; run `dvc repro`")


@app.command()
def check(params: ParamsPath = Path("params.yaml")) -> None:
    """Validate a params file and exit."""
    _params(params)
    typer.echo(f"{params}: ok")


def run_stage(stage: str) -> None:
    """Entry used by ``pipeline/<stage>.py``: the CLI subcommand ``stage`` with the script's arguments."""
    import sys

    app(args=[stage, *sys.argv[1:]], prog_name=f"pipeline/{stage}.py")
