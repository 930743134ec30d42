"""Every profile of ``profiles/`` runs end to end at tiny scale (``adaptdiffuser profile NAME --tiny``): the
profile's own tasks, phases, model shapes, samplers and families, every stage DVC plans for it, so a configuration
or shape error in a paper profile shows here rather than on a user's GPU.

DVC plans the run (the stage graph of a real git + DVC repository: the stages and their commands, dependencies
first); the stages then run in this process, each exactly as its ``pipeline/*.py`` script runs it, which saves each
stage the seconds of starting an interpreter (``tests/test_pipeline.py`` runs ``dvc repro`` itself on the smoke
profile)."""

from __future__ import annotations

import json
import runpy
import shlex
import sys
from pathlib import Path

import pytest
import yaml
from smoke_project import REPO, make_smoke_project, only_tasks, run_tool

#: smoke is left out: tests/test_pipeline.py runs it through `dvc repro` itself, every stage a process of its own
PROFILES = sorted(path.stem for path in (REPO / "profiles").glob("*.yaml") if path.stem != "smoke")
#: profiles whose tiny run would repeat another's: the same families, recipes and stage graph, with another maze size,
#: a subset of its tasks or seeds, or another U-Net width (each still resolves and passes every params check at tiny
#: scale in tests/test_resolved_profiles.py); the end-to-end run is the profile's named here
COVERED_BY = {
    "paper-umaze": "paper-large",
    "paper-medium": "paper-large",
    "science-umaze": "science-large",
    "science-medium": "science-large",
    "science-hopper": "science-locomotion",
    "science-halfcheetah": "science-locomotion",
    "science-walker2d": "science-locomotion",
    "science-walker2d-w32": "science-locomotion",
    "science-kuka": "quick-kuka",
}
#: the profiles run end to end at tiny scale
RUN = [name for name in PROFILES if name not in COVERED_BY]
#: profiles whose tiny run keeps one task of each kind: paper-locomotion's nine tasks are three environments by three
#: datasets, and one task per environment and per dataset recipe runs every code path of the nine (the nine alone took
#: 27 min of the suite's 69 on the 2-core AVX2-only EPYC)
NARROWED = {"paper-locomotion": ["hopper-medium", "walker2d-medium-replay", "halfcheetah-medium-expert"]}


#: the profile that the committed params.yaml holds, whose run wrote the committed metrics/summary.json
DEFAULT_PROFILE = "quick"


def key_paths(tree: object, prefix: str = "") -> set[str]:
    """The dotted path of every leaf of a nested JSON object (``phase_1.control.score_mean``, ...)."""
    if not isinstance(tree, dict):
        return {prefix}
    return set().union(*(key_paths(value, f"{prefix}.{key}" if prefix else str(key)) for key, value in tree.items()))


def planned_commands(root: Path) -> list[list[str]]:
    """The commands of every stage of ``root``'s pipeline, each after the stages it depends on."""
    import networkx as nx
    from dvc.repo import Repo

    with Repo(str(root)) as repo:
        graph = repo.index.graph  # an edge runs from a stage to a stage it depends on
        return [shlex.split(stage.cmd) for stage in reversed(list(nx.topological_sort(graph))) if stage.cmd]


def run_stage_in_process(argv: list[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """``python pipeline/<stage>.py ARGS`` in this process (cwd: the project), failing the test on a non-zero exit."""
    script = argv[1]
    with monkeypatch.context() as m:
        m.setattr(sys, "argv", argv[1:])
        try:
            runpy.run_path(script, run_name="__main__")
        except SystemExit as exc:
            assert exc.code in (0, None), f"{' '.join(argv)} exited with {exc.code}"


def test_tiny_keeps_the_profiles_shapes_and_shrinks_its_work(tmp_path: Path) -> None:
    from adaptdiffuser.config import apply_profile, load_params

    full = load_params(apply_profile("paper-kuka", REPO / "profiles", tmp_path / "full.yaml"))
    tiny = load_params(apply_profile("paper-kuka", REPO / "profiles", tmp_path / "tiny.yaml", tiny=True))
    a, b = full.resolve("kuka-stacking"), tiny.resolve("kuka-stacking")
    assert (b.model, b.diffusion.horizon, b.planner.sampler) == (a.model, a.diffusion.horizon, a.planner.sampler)
    assert b.pretrain.steps < a.pretrain.steps and b.diffusion.n_steps < a.diffusion.n_steps
    assert b.settings.collect.episodes < a.settings.collect.episodes
    assert b.evaluate.episodes == 1 and not tiny.compile.training
    assert a.evaluate.held_out_episodes > 1 and b.evaluate.held_out_episodes == 1  # held-out states played, once
    assert [p.name for p in tiny.phases] == [full.phases[0].name] and len(full.phases) == 2
    assert tiny.phases[0].discriminate == full.phases[0].discriminate  # the phase's own settings are kept
    assert "--tiny" in (tmp_path / "tiny.yaml").read_text().splitlines()[0]


def test_a_profile_left_out_of_the_tiny_runs_repeats_the_families_and_stages_of_the_one_that_covers_it(
    tmp_path: Path,
) -> None:
    from adaptdiffuser.config import apply_profile, load_params, stage_names

    def shape(name: str) -> tuple[set[str], set[str]]:
        params = load_params(apply_profile(name, REPO / "profiles", tmp_path / f"{name}.yaml", tiny=True))
        stages = {stage.split("@")[0] for stage in stage_names(params)}
        return {params.resolve(task).family for task in params.tasks}, stages

    assert set(COVERED_BY) < set(PROFILES) and set(COVERED_BY.values()) <= set(RUN)
    for name, runner in COVERED_BY.items():
        (families, stages), (run_families, run_stages) = shape(name), shape(runner)
        assert families <= run_families and stages <= run_stages, f"{name} is not covered by {runner}'s tiny run"


@pytest.mark.e2e
@pytest.mark.parametrize("profile", RUN)
def test_every_profile_runs_end_to_end_at_tiny_scale(
    profile: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    edit = only_tasks(NARROWED[profile]) if profile in NARROWED else None
    root = make_smoke_project(tmp_path, run_tool, edit=edit, profile=profile, tiny=True)
    params = yaml.safe_load((root / "params.yaml").read_text())
    commands = planned_commands(root)
    scripts = [argv[1] for argv in commands]
    assert "pipeline/pretrain.py" in scripts and "pipeline/report.py" in scripts
    monkeypatch.chdir(root)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    for argv in commands:
        run_stage_in_process(argv, monkeypatch)
    summary = json.loads((root / "metrics" / "summary.json").read_text())
    assert set(summary) == set(params["tasks"])
    if params.get("evolve") and params.get("phases"):
        phases = [key for key in summary[params["evolve"]] if key.startswith("phase_")]
        assert len(phases) == len(params["phases"]) + 1, phases
    if profile == DEFAULT_PROFILE:
        # the committed default metrics are what today's code writes: a key added or dropped by a code change
        # shows here until the default run is redone (`dvc repro`) and its metrics committed
        committed = json.loads((REPO / "metrics" / "summary.json").read_text())
        written, kept = key_paths(summary), key_paths(committed)
        assert written == kept, f"written only: {sorted(written - kept)}; committed only: {sorted(kept - written)}"
