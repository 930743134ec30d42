"""Evolving from an already trained phase 0 (``pretrained.<task>``, the import-model stage): a model trained by the
real pretrain stage is imported byte for byte and the evolution stages load it; a model of another shape or
normalizer is refused with one line, and nothing is written."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest
import torch
import yaml
from deps_trace import check_stage, dvc_stages, load_traces, traced_env
from smoke_project import narrow

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import Params, apply_profile, params_from_dict
from adaptdiffuser.errors import StageError
from adaptdiffuser.layout import dataset_path, generated_path, model_dir, phase_models_dir
from adaptdiffuser.stages.collect import run_collect
from adaptdiffuser.stages.generate import run_generate
from adaptdiffuser.stages.import_model import IMPORT_SUMMARY, run_import_model
from adaptdiffuser.stages.pretrain import run_pretrain

REPO = Path(__file__).resolve().parents[1]
CPU = torch.device("cpu")
TASK = "maze2d-umaze"
SEEDS = [0, 1]


def maze_params(root: Path, pretrained: str | None = None, **changes: object) -> Params:
    """The smoke profile on the maze task alone, two training seeds; its phase 0 from ``pretrained`` when given."""
    raw = yaml.safe_load(apply_profile("smoke", REPO / "profiles", root / "params.yaml").read_text())
    imported = {"pretrained": {TASK: pretrained}, "pretrain_tasks": []} if pretrained else {}
    raw = narrow(raw, [TASK], unseen_tasks=[TASK], evolve=TASK, seeds=SEEDS, **imported)
    for key, value in changes.items():  # dotted keys: model.dim=...
        *path, last = key.split(".")
        node = raw
        for part in path:
            node = node[part]
        node[last] = value
    (root / "params.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))
    return params_from_dict(raw)


def files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A project after the real collect and pretrain stages (two seeds): its ``models/<task>/phase0``."""
    root = tmp_path_factory.mktemp("trained")
    params = maze_params(root)
    run_collect(params, TASK, root, progress=False)
    run_pretrain(params, TASK, root, CPU, progress=False)
    return root / phase_models_dir(TASK, 0)


def project_with_data(tmp_path: Path, trained: Path) -> Path:
    """A fresh project folder holding the trained project's dataset (what collect writes there)."""
    root = tmp_path / "project"
    (root / dataset_path(TASK)).parent.mkdir(parents=True)
    shutil.copy2(trained.parents[2] / dataset_path(TASK), root / dataset_path(TASK))
    return root


def test_an_imported_phase0_is_the_trained_one_byte_for_byte_and_evolves(trained: Path, tmp_path: Path) -> None:
    root = project_with_data(tmp_path, trained)
    params = maze_params(root, str(trained))
    assert params.pretrain_tasks == () and list(params.pretrained) == [TASK]
    out = run_import_model(params, TASK, root, CPU, progress=False)
    for seed in SEEDS:
        source = files(trained / f"seed{seed}")
        assert {"model.pt", "ema.pt", "normalizer.json", "config.json", "optimizer.pt"} <= set(source)
        assert files(root / model_dir(TASK, 0, seed)) == source
    summary = json.loads((out / IMPORT_SUMMARY).read_text())
    assert summary["folder"] == str(trained) and set(summary["seeds"]) == {"seed0", "seed1"}
    assert all(entry["same_data"] for entry in summary["seeds"].values())  # trained on this very dataset
    assert load_bundle(root / model_dir(TASK, 0, 1)).config["seed"] == 1
    # generate@phase1 plans with the imported models (and fine-tuning loads them the same way: load_bundle)
    run_generate(params, TASK, root, 1, CPU, progress=False)
    assert all((root / generated_path(TASK, 1, seed)).is_file() for seed in SEEDS)


def _refused(params: Params, root: Path) -> str:
    with pytest.raises(StageError) as err:
        run_import_model(params, TASK, root, CPU, progress=False)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"pretrained.{TASK}: ")
    assert not (root / "models").exists()  # nothing written, not even the first seed's model
    return message


def test_a_model_of_another_shape_or_normalizer_is_refused_in_one_line(trained: Path, tmp_path: Path) -> None:
    root = project_with_data(tmp_path, trained)
    # the task's params name another U-Net and another horizon than the trained model's
    other = maze_params(root, str(trained), **{"model.dim": 16, "diffusion.horizon": 64})
    message = _refused(other, root)
    assert "seed0 does not have task maze2d-umaze's shape" in message
    assert "diffusion.horizon is 32, task has 64" in message and "model.dim is 8, task has 16" in message
    maze_params(root, str(trained))  # params.yaml as the task trained it
    # a seed the folder does not hold
    assert "has no seed2/ for training seed 2" in _refused(params_from_dict({**_raw(root), "seeds": [0, 2]}), root)
    # a normalizer fitted on other data; checked after seed 0 passed
    bad = tmp_path / "bad"
    shutil.copytree(trained, bad)
    norm = json.loads((bad / "seed1" / "normalizer.json").read_text())
    norm["high"][0] += 0.5
    (bad / "seed1" / "normalizer.json").write_text(json.dumps(norm))
    message = _refused(maze_params(root, str(bad)), root)
    assert "seed1/normalizer.json does not match the task's data" in message and "high[0] is" in message
    # weights of another network under a matching config
    shutil.copytree(trained, bad, dirs_exist_ok=True)
    ema = torch.load(bad / "seed0" / "ema.pt", weights_only=True)
    torch.save({name: value[..., :1] for name, value in ema.items()}, bad / "seed0" / "ema.pt")
    assert "seed0's weights do not load into task maze2d-umaze's model" in _refused(maze_params(root, str(bad)), root)
    # a truncated weights file (a copy cut short): an unpickling error, told in one line too
    shutil.copytree(trained, bad, dirs_exist_ok=True)
    (bad / "seed0" / "ema.pt").write_bytes((trained / "seed0" / "ema.pt").read_bytes()[:100])
    assert "seed0's weights do not load into task maze2d-umaze's model" in _refused(maze_params(root, str(bad)), root)
    # a config that is not an object of settings
    shutil.copytree(trained, bad, dirs_exist_ok=True)
    (bad / "seed0" / "config.json").write_text("[]")
    assert "seed0/config.json is not a JSON object" in _refused(maze_params(root, str(bad)), root)
    # not a model folder at all
    shutil.copytree(trained, bad, dirs_exist_ok=True)
    (bad / "seed0" / "model.pt").unlink()
    assert "is not a model folder: no model.pt" in _refused(maze_params(root, str(bad)), root)


def _raw(root: Path) -> dict:
    return yaml.safe_load((root / "params.yaml").read_text())


@pytest.mark.e2e
def test_dvc_imports_instead_of_pretraining_and_reruns_when_the_folder_changes(trained: Path, tmp_path: Path) -> None:
    """``dvc repro`` on params with ``pretrained.<task>``: import-model@<task> replaces pretrain@<task>, declares
    every file it reads, is cached, and is out of date once a file of the imported folder changes."""
    from smoke_project import make_smoke_project

    traces = tmp_path / "traces"
    folder = tmp_path / "external" / "phase0"
    shutil.copytree(trained, folder)

    def run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess:
        out = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=os.environ | traced_env(traces))
        assert out.returncode == 0, f"{cmd}: {out.stdout}\n{out.stderr}"
        return out

    def edit(params_path: Path) -> None:
        raw = yaml.safe_load(params_path.read_text())
        raw.update(pretrained={TASK: str(folder)}, pretrain_tasks=[t for t in raw["tasks"] if t != TASK], seeds=SEEDS)
        params_path.write_text(yaml.safe_dump(raw, sort_keys=False))

    (tmp_path / "project").mkdir()
    root = make_smoke_project(tmp_path / "project", run, edit)
    stages = run(["dvc", "stage", "list", "--name-only"], root).stdout.split()
    name = f"import-model@{TASK}"
    assert name in stages and f"pretrain@{TASK}" not in stages and "pretrain@hopper-medium" in stages
    run(["dvc", "repro", name], root)  # after the task's code fingerprint and collect
    assert not check_stage(dvc_stages(root)[name], load_traces(traces)[name], root).missing
    for seed in SEEDS:
        assert files(root / model_dir(TASK, 0, seed)) == files(trained / f"seed{seed}")
    assert "up to date" in run(["dvc", "status", name], root).stdout
    (folder / "seed1" / "train_loss.png").write_bytes(b"another picture")
    status = run(["dvc", "status", name], root).stdout
    assert "changed deps" in status and str(folder) in status


def test_pretrained_and_pretrain_tasks_are_checked(tmp_path: Path) -> None:
    """Every task's phase 0 has exactly one source: pretrain_tasks or pretrained (computed when left out)."""
    from adaptdiffuser.config import ConfigError

    maze_params(tmp_path)
    raw = _raw(tmp_path)
    del raw["pretrain_tasks"]
    assert params_from_dict(raw | {"pretrained": {TASK: "/x"}}).pretrain_tasks == ()
    bad = [
        ({"pretrained": {TASK: "/x"}}, "pretrain_tasks: must list the tasks of 'tasks' that have no pretrained"),
        ({"pretrained": {"hopper-medium": "/x"}}, "pretrained.hopper-medium: 'hopper-medium' is not one of tasks"),
        ({"pretrained": {TASK: " "}, "pretrain_tasks": []}, f"pretrained.{TASK}: is empty"),
        ({"pretrained": {TASK: "~/phase0"}, "pretrain_tasks": []}, f"pretrained.{TASK}: '~/phase0' starts with ~"),
        ({"pretrain_tasks": []}, "pretrain_tasks: must list the tasks of 'tasks' that have no pretrained folder"),
    ]
    for change, message in bad:
        with pytest.raises(ConfigError, match=f"^{message}"):
            params_from_dict(_raw(tmp_path) | change)
