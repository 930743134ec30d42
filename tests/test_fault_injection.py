"""Fault injection: every stage of dvc.yaml that writes is killed with SIGKILL partway, as a real subprocess, in a
temporary project on the smoke profile; no output is left half-written at its final path, and a rerun completes.

Per stage, in pipeline order (the stages it needs are run once first): its command is started as DVC would start
it, killed as soon as its outputs change (its first file, or the temporary file of its first atomic write, or for
a training stage its resume state at half its steps), every file left under its outputs is read with the
project's readers, the command is rerun to completion, its outputs are read again and DVC's status is checked.
A training stage must come back to exactly the weights of an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import networkx as nx
import pyarrow.parquet as pq
import pytest
import torch
import yaml
from dvc.repo import Repo
from PIL import Image
from smoke_project import make_smoke_project

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.data.schema import METADATA_KEY, read_trajectories
from adaptdiffuser.value_training import load_value

pytestmark = [pytest.mark.e2e, pytest.mark.filterwarnings("ignore::DeprecationWarning:dvc")]

REPO = Path(__file__).resolve().parents[1]
MAZE, HOPPER = "maze2d-umaze", "hopper-medium"
# Every stage of dvc.yaml, in pipeline order; each is killed in one instance: the first one dvc.yaml resolves,
# except collect and pretrain, killed on the locomotion task (its behaviour policy; its value function).
STAGES = [
    "code",
    "collect",
    "reference",
    "pretrain",
    "evaluate-phase0",
    "evaluate-unseen-phase0",
    "generate",
    "discriminate",
    "finetune",
    "evaluate",
    "control",
    "evaluate-control",
    "evaluate-unseen",
    "evaluate-unseen-control",
    "summarize",
    "report",
]
KILLED_INSTANCE = {"collect": f"collect@{HOPPER}", "pretrain": f"pretrain@{HOPPER}"}
TRAINING = ("pretrain", "finetune", "control")
TRAIN_STEPS = 40  # pretraining and fine-tuning alike; resume states are written at half of them and at the end
RESUME_DIR = Path("models/.resume")
# What io.atomic_path and io.atomic_dir leave when killed: ``.<name>.<random>.tmp`` and ``.<name>.old``.
TEMPORARY = re.compile(r"^\..+\.(\w+\.tmp|old)$")
# One of each kind of place those land: beside a file output, in a folder another stage depends on (summarize on
# metrics/tasks), inside a directory output (a picture; a model bundle), and among the resume states.
TEMPORARY_EXAMPLES = [
    f"data/{MAZE}/.dataset.parquet.0a1b2c3d.tmp",
    f"metrics/tasks/{MAZE}/.reference.json.0a1b2c3d.tmp",
    f"plots/{MAZE}/unseen/phase1/seed0/.coin_00.png.0a1b2c3d.tmp",
    f"models/{MAZE}/phase1/.seed0.0a1b2c3d.tmp/model.pt",
    f"models/{MAZE}/phase1/.seed0.old/model.pt",
    f"{RESUME_DIR}/.{MAZE}-phase1-seed0.pt.0a1b2c3d.tmp",
]
POLL_S = 0.02
STAGE_TIMEOUT_S = 300.0


@dataclass
class Stage:
    """One resolved stage of dvc.yaml: its command, its outputs and the stages it needs (transitively)."""

    name: str
    argv: list[str]
    outs: list[Path]
    upstream: set[str]

    @property
    def group(self) -> str:
        return self.name.split("@")[0]


@dataclass
class Run:
    """One run of a stage's command: exit status, duration, when its outputs changed (seconds after its start)
    and what it printed."""

    returncode: int
    seconds: float
    writes: list[float]
    log: str

    @property
    def killed(self) -> bool:
        return self.returncode == -signal.SIGKILL


@dataclass
class Project:
    """The temporary project, its stages in pipeline order and those that have completed there."""

    root: Path
    stages: dict[str, Stage]
    done: set[str] = field(default_factory=set)
    runs: int = 0

    def run_upstream(self, name: str) -> None:
        """Run, once, every stage that ``name`` needs and that has not completed yet, in pipeline order."""
        for other in self.stages.values():
            if other.name in self.stages[name].upstream and other.name not in self.done:
                run = run_stage(self, other)
                assert run.returncode == 0, f"{other.name} failed:\n{run.log[-3000:]}"
                self.done.add(other.name)


def _env(root: Path, stage: str | None = None) -> dict[str, str]:
    """The environment DVC gives a stage's command, with this interpreter's bin first on PATH and one thread per
    process (torch's default of one per core spins for minutes when other jobs share the cores)."""
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env['PATH']}"
    env.pop("MLFLOW_TRACKING_URI", None)
    env.update(DVC_NO_ANALYTICS="1", DVC_ROOT=str(root), OMP_NUM_THREADS="1")
    if stage is not None:
        env["DVC_STAGE"] = stage
    return env


def _sh(cmd: list[str], cwd: Path) -> None:
    out = subprocess.run(cmd, cwd=cwd, env=_env(cwd), capture_output=True, text=True)
    assert out.returncode == 0, f"{' '.join(cmd)} failed:\n{out.stdout}\n{out.stderr}"


@contextlib.contextmanager
def _dvc(root: Path) -> Iterator[Repo]:
    """DVC's Python API on the project (it resolves some paths against the working directory)."""
    cwd = os.getcwd()
    os.chdir(root)
    try:
        with Repo(str(root)) as repo:
            yield repo
    finally:
        os.chdir(cwd)


def _shrink(params_path: Path) -> None:
    """The smoke profile, smaller on the same code paths: one evolution phase, shorter locomotion episodes, and
    pretraining and fine-tuning of ``TRAIN_STEPS`` steps each that write a resume state at half of them (and one
    at the end, kept until the stage has saved its models)."""
    params = yaml.safe_load(params_path.read_text())
    params["phases"] = {"phase1": {"previous": 0}}
    params["pretrain"].update(steps=TRAIN_STEPS, checkpoint_every=TRAIN_STEPS // 2, log_every=5)
    params["evolution"]["finetune"]["steps_fraction"] = 1.0
    hopper = params["task"][HOPPER]
    hopper["episode_steps"] = 24
    hopper["behaviour"].update(max_train_steps=1024, ppo_n_steps=256, eval_every=512, dataset_steps=1000)
    params_path.write_text(yaml.safe_dump(params, sort_keys=False))


def _resolved_stages(root: Path) -> dict[str, Stage]:
    """Every stage instance of dvc.yaml with its command and outputs, in pipeline order (dvc.yaml's order among
    stages that do not need each other)."""
    with _dvc(root) as repo:
        resolved = repo.index.stages
        position = {stage.name: i for i, stage in enumerate(resolved)}
        graph = repo.index.graph  # edges point from a stage to the stages it needs
        ordered = nx.lexicographical_topological_sort(graph.reverse(), key=lambda stage: position[stage.name])
        stages = {}
        for stage in ordered:
            assert Path(stage.wdir) == root, f"{stage.name}: a working directory other than the project root"
            upstream = {other.name for other in nx.descendants(graph, stage)}
            outs = [Path(out.def_path) for out in stage.outs]
            stages[stage.name] = Stage(stage.name, shlex.split(stage.cmd), outs, upstream)
    return stages


def _watched(root: Path, stage: Stage) -> list[Path]:
    """What a stage writes: its outputs, and for a training stage the resume states of its models."""
    paths = [root / out for out in stage.outs]
    return [*paths, root / RESUME_DIR] if stage.group in TRAINING else paths


def _snapshot(paths: list[Path]) -> dict[str, tuple[int, int]]:
    """(mtime, size) of every file and folder of ``paths``, with the temporary siblings atomic writes make."""
    found: dict[str, tuple[int, int]] = {}

    def add(path: str) -> None:
        with contextlib.suppress(FileNotFoundError):
            st = os.stat(path)
            found[path] = (st.st_mtime_ns, st.st_size)

    for path in paths:
        try:
            entries = list(os.scandir(path.parent))
        except FileNotFoundError:
            continue
        for entry in entries:
            if entry.name != path.name and not entry.name.startswith(f".{path.name}."):
                continue
            add(entry.path)
            for folder, dirs, files in os.walk(entry.path):
                for name in dirs + files:
                    add(os.path.join(folder, name))
    return found


def kill_point(stage: Stage) -> Callable[[set[str]], bool]:
    """When to SIGKILL a stage, given the paths under its outputs that just changed: a training stage once it has
    saved its resume state (at half of its steps), any other at its first change (a folder, a file, or the temporary
    file of its first atomic write), so the kill falls inside its writing whatever start-up costs."""
    if stage.group not in TRAINING:
        return lambda changed: True
    folder = str(RESUME_DIR)
    return lambda changed: any(
        Path(p).parent.as_posix().endswith(folder) and not TEMPORARY.match(Path(p).name) for p in changed
    )


def run_stage(project: Project, stage: Stage, kill: bool = False) -> Run:
    """Run a stage's command as DVC would (a process of its own, the project as working directory, DVC's
    environment), watching its outputs every ``POLL_S``; with ``kill``, SIGKILL its whole process group at its
    :func:`kill_point`."""
    project.runs += 1
    log_path = project.root.parent / "logs" / f"{project.runs:03d}-{stage.name}.log"
    log_path.parent.mkdir(exist_ok=True)
    watched, due = _watched(project.root, stage), kill_point(stage)
    last = _snapshot(watched)
    writes: list[float] = []
    start = time.monotonic()
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            stage.argv,
            cwd=project.root,
            env=_env(project.root, stage.name),
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        while proc.poll() is None:
            now = time.monotonic() - start
            state = _snapshot(watched)
            changed = {path for path, stat in state.items() if last.get(path) != stat}
            if changed:
                writes.append(now)
                last = state
            if (kill and changed and due(changed)) or now > STAGE_TIMEOUT_S:
                with contextlib.suppress(ProcessLookupError):  # it ended between the poll and the kill
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
                break
            time.sleep(POLL_S)
    seconds = time.monotonic() - start
    assert seconds <= STAGE_TIMEOUT_S, f"{stage.name} ran past {STAGE_TIMEOUT_S} s"
    return Run(proc.returncode, seconds, writes, log_path.read_text())


def _is_temporary(path: Path, root: Path) -> bool:
    return any(TEMPORARY.match(part) for part in path.relative_to(root).parts)


def _read(path: Path) -> None:
    """Read one output file with the project's reader for its kind; raise if it is not a whole file."""
    suffix = path.suffix
    if suffix == ".parquet":
        table = pq.read_table(path)  # every row group: a truncated file fails here
        if METADATA_KEY in (table.schema.metadata or {}):
            read_trajectories(path)
    elif suffix == ".pt":
        if path.name in ("model.pt", "ema.pt", "optimizer.pt"):
            load_bundle(path.parent)  # the whole bundle: every file it needs is there and loads
        elif path.name == "value.pt":
            load_value(path.parent)
        else:  # a resume state, loaded as training loads it
            assert "step" in torch.load(path, map_location="cpu", weights_only=False)
    elif suffix == ".json":
        json.loads(path.read_text())
    elif suffix == ".png":
        with Image.open(path) as image:
            image.load()
    elif suffix == ".csv":
        with open(path, newline="") as f:
            assert csv.DictReader(f).fieldnames
    elif suffix == ".zip":  # a behaviour policy (stable-baselines3's archive)
        with zipfile.ZipFile(path) as archive:
            assert archive.testzip() is None
    else:
        raise AssertionError(f"{path}: no reader for this kind of output; add one to the fault test")


def check_outputs(root: Path, stage: Stage, complete: bool) -> list[str]:
    """Read every file at a final path under the stage's outputs (and its resume states); with ``complete``, every
    output must exist. Returns the temporary files and folders of atomic writes found there."""
    temporary = []
    for path in sorted(map(Path, _snapshot(_watched(root, stage)))):
        if _is_temporary(path, root):
            if TEMPORARY.match(path.name):
                temporary.append(str(path.relative_to(root)))
        elif path.is_file():
            try:
                _read(path)
            except Exception as err:
                raise AssertionError(f"{stage.name}: {path.relative_to(root)} is not a whole file: {err!r}") from err
    if complete:
        for out in stage.outs:
            assert (root / out).exists(), f"{stage.name}: output {out} missing after a complete run"
    return temporary


def _resume_states(root: Path, stage: Stage) -> list[Path]:
    """The resume states of a training stage's models (``models/.resume/<task>-<phase>-seed<s>.pt``)."""
    names = [f"{out.parts[1]}-{out.parts[2]}-seed" for out in stage.outs if out.parts[0] == "models"]
    folder = root / RESUME_DIR
    return [p for p in folder.glob("*.pt") if any(p.name.startswith(n) for n in names)] if folder.is_dir() else []


def _same_weights(clean: Path, rerun: Path) -> None:
    """Every model (and value function) under ``rerun`` has exactly the weights of the one under ``clean``."""
    bundles = sorted(p.parent.relative_to(clean) for p in clean.rglob("model.pt"))
    assert bundles, f"no model under {clean}"
    for rel in bundles:
        a, b = load_bundle(clean / rel), load_bundle(rerun / rel)
        for net in ("diffusion", "ema"):
            sa, sb = getattr(a, net).state_dict(), getattr(b, net).state_dict()
            assert all(torch.equal(sa[k], sb[k]) for k in sa), f"{rel}: {net} weights differ from the clean run's"
    for value in clean.rglob("value.pt"):
        rel = value.parent.relative_to(clean)
        sa, sb = load_value(clean / rel)[0].state_dict(), load_value(rerun / rel)[0].state_dict()
        assert all(torch.equal(sa[k], sb[k]) for k in sa), f"{rel}: value weights differ from the clean run's"


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory) -> Project:
    """The project on the shrunk smoke profile in a temporary git + DVC repository; nothing has run yet."""
    root = tmp_path_factory.mktemp("faults") / "project"
    root.mkdir()
    make_smoke_project(root, _sh, edit=_shrink)
    return Project(root, _resolved_stages(root))


def test_every_stage_of_dvc_yaml_is_killed(project: Project) -> None:
    """A stage added to dvc.yaml gets no pass: the killed stages follow the pipeline."""
    assert {stage.group for stage in project.stages.values()} == set(STAGES)
    assert set(KILLED_INSTANCE.values()) <= set(project.stages)
    assert all(stage.outs for stage in project.stages.values()), "every stage writes something"


@pytest.mark.parametrize("group", STAGES)
def test_killed_stage_leaves_whole_files_and_reruns(project: Project, group: str, tmp_path: Path) -> None:
    root = project.root
    name = KILLED_INSTANCE.get(group) or next(n for n, s in project.stages.items() if s.group == group)
    stage = project.stages[name]
    project.run_upstream(name)
    if group in TRAINING:  # the weights an uninterrupted run reaches
        clean = run_stage(project, stage)
        assert clean.returncode == 0, f"{name} failed:\n{clean.log[-3000:]}"
        for out in stage.outs:
            shutil.copytree(root / out, tmp_path / out)

    killed = run_stage(project, stage, kill=True)
    assert killed.killed, f"{name} ended (status {killed.returncode}) before it was killed:\n{killed.log[-2000:]}"
    left = check_outputs(root, stage, complete=False)
    states = _resume_states(root, stage)
    resumable = {p.name: torch.load(p, map_location="cpu", weights_only=False)["step"] for p in states}

    rerun = run_stage(project, stage)
    assert rerun.returncode == 0, f"{name} failed after being killed:\n{rerun.log[-3000:]}"
    assert set(check_outputs(root, stage, complete=True)) <= set(left), "a complete run leaves no temporary file"
    project.done.add(name)
    print(
        f"\n{name}: killed after {killed.seconds:.1f} s, rerun {rerun.seconds:.1f} s; "
        f"temporary files left by the kill: {left or 'none'}; resume states: {resumable or 'none'}"
    )

    if group in TRAINING:
        assert resumable, f"{name} was killed before its resume state was saved"
        # killed at its first resume state (half of the steps), or if the poll came late, at the one of the end
        for step in resumable.values():
            assert step in (TRAIN_STEPS // 2, TRAIN_STEPS)
            assert f"resuming training from step {step}" in rerun.log, f"{name} did not resume"
        assert not _resume_states(root, stage), "a finished training removes its resume state"
        for out in stage.outs:
            _same_weights(tmp_path / out, root / out)

    with _dvc(root) as repo:
        repo.commit(name, force=True)
        assert repo.status([name]) == {}, f"dvc status of {name} is not clean after the rerun"


def test_what_a_kill_leaves_is_ignored_by_git_and_dvc(tmp_path: Path) -> None:
    """The temporary files a kill can leave (``TEMPORARY``) are ignored by git and by DVC."""
    for name in (".gitignore", ".dvcignore"):
        shutil.copy2(REPO / name, tmp_path / name)
    _sh(["git", "init", "-q"], tmp_path)
    _sh(["dvc", "init", "-q"], tmp_path)
    for rel in TEMPORARY_EXAMPLES:
        assert TEMPORARY.match(Path(rel).name) or TEMPORARY.match(Path(rel).parent.name)
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"half")
    seen = {
        (tool, rel): subprocess.run([tool, "check-ignore", "-q", rel], cwd=tmp_path, env=_env(tmp_path)).returncode
        for tool in ("git", "dvc")
        for rel in TEMPORARY_EXAMPLES
    }
    assert [key for key, status in seen.items() if status != 0] == []
