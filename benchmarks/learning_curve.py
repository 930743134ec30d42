"""Score against training steps and CPU time of a task's phase-0 model (printed and written, never asserted): how many
steps a profile needs before its Diffuser baseline is worth evolving, chosen on validation episodes.

Trains the task's phase-0 model exactly as ``pretrain@<task>`` does (its model, diffusion and pretrain settings, for
one training seed) up to ``--steps``, and every ``--every`` steps evaluates the EMA under the task's protocol on
``--episodes`` episodes from ``--seed`` (default 7: a validation seed, never ``evaluate.seed``). Each point goes to
``--out`` (JSON lines: step, score mean and standard error, success rate where the family reports it, the
training's CPU seconds so far (this process's: other work on the machine does not count) and its wall seconds,
evaluation seconds) as soon as it is measured. Stopped at any point, the same command continues where it stopped:
a stop (SIGTERM, SIGINT) lets the step end and writes its resume state in ``models/.resume/`` with the clock beside
it, a kill leaves the last point's state, and the points already written are kept.

For a family whose planner is guided by a value function (locomotion), the curve first trains the task's value
network as ``pretrain@<task>`` does (its ``value`` and ``value_model`` settings; it needs the diffusion model's
schedule and normalizer only, not its weights) into the curve's own folder under ``models/.resume/``, and every point
is evaluated with it: its CPU seconds open the curve's ``train_cpu_s`` and each point carries its held-out R^2
(``value_r2``, ``value_r2_t0``).

``--set KEY=VALUE`` (repeatable) changes one of the task's settings for this curve only, a dotted key under the
task (``pretrain.lr=0.001``, ``model.dim=32``; the value is read as YAML), and ``--label`` names the variant in the
output and resume files, so variants of one task and seed never share a resume state
(``benchmarks/recipe_study.py`` runs many).

``--extend SHORTER.jsonl --extend-state STATE`` continues a shorter curve of the same settings instead of training
from step 0: under a constant learning rate (``lr_schedule: constant``) the training to any step does not depend on
how long the curve is, so the shorter curve's points are this curve's first points and its resume state (any of its
states: the last, which a constant-rate curve keeps when it finishes, or an earlier one) is where this one starts.
The state must be the shorter curve's: it is checked against the run id that curve had (its length and spacing read
from its points), and refused in one line otherwise. The points must have been measured as this curve measures
(episodes, seed): ``recipe_study.py``'s ``extends`` sees to it.

    python benchmarks/learning_curve.py WORKSPACE --task maze2d-medium --steps 40000 --every 4000
        [--seed 7] [--episodes 30] [--training-seed 0] [--set pretrain.lr=0.001 ...] [--label NAME]
        [--out curve.jsonl] [--keep-model DIR (models at every point)] [--device cpu] [--quiet]
        [--extend SHORTER.jsonl --extend-state STATE]

WORKSPACE is a pipeline folder whose task has its dataset and reference (`dvc repro reference@<task>`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import time
from collections.abc import Callable
from pathlib import Path
from types import FrameType

import numpy as np
import torch
import yaml

from adaptdiffuser.checkpoint import ModelBundle, save_bundle
from adaptdiffuser.config import params_from_dict, set_dotted
from adaptdiffuser.config.sections import PretrainParams
from adaptdiffuser.config.tasks import TaskParams
from adaptdiffuser.contract import TaskFiles
from adaptdiffuser.data.schema import Trajectories
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.evaluation import normalized_score, run_episodes, standard_error
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.io import atomic_path, read_json, write_json
from adaptdiffuser.layout import reference_path
from adaptdiffuser.planning import Planner
from adaptdiffuser.stages.common import resolve_device
from adaptdiffuser.stages.pretrain import phase0_model
from adaptdiffuser.stages.training_data import expert_training_data, pretrain_config
from adaptdiffuser.stages.value_function import fit_value
from adaptdiffuser.training import fingerprint, save_resume_state, train
from adaptdiffuser.value_training import save_value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--task", required=True)
    parser.add_argument("--steps", type=int, required=True, help="training steps in all")
    parser.add_argument("--every", type=int, required=True, help="steps between evaluations (and resume states)")
    parser.add_argument("--seed", type=int, default=7, help="episode seed (default 7: validation, not evaluation)")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--training-seed", type=int, default=0)
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="a setting of the task for this curve, e.g. pretrain.lr=0.001 (repeatable)")  # fmt: skip
    parser.add_argument("--label", default=None, help="the variant's name in the output and resume files")
    parser.add_argument("--out", type=Path, default=None, help="default: learning_curve-<task>[-label]-seed<s>.jsonl")
    parser.add_argument(
        "--keep-model",
        type=Path,
        default=None,
        metavar="DIR",
        help="save the model (a bundle, as pretrain writes) into DIR/step<N> at every point, so a curve stopped "
        "early still leaves its models",
    )
    parser.add_argument("--device", default="auto")
    parser.add_argument("--quiet", action="store_true", help="no progress bar while training")
    parser.add_argument("--extend", type=Path, default=None, metavar="SHORTER.jsonl",
                        help="continue this shorter curve of the same settings (constant learning rate)")  # fmt: skip
    parser.add_argument("--extend-state", type=Path, default=None, metavar="STATE",
                        help="a resume state of the curve --extend names: where this curve starts")  # fmt: skip
    args = parser.parse_args()
    if (args.extend is None) != (args.extend_state is None):
        parser.error("--extend and --extend-state go together: the shorter curve's points and one of its states")
    root = args.workspace.resolve()
    raw = yaml.safe_load((root / "params.yaml").read_text())
    for override in args.overrides:
        key, sep, value = override.partition("=")
        if not sep or not key:
            parser.error(f"--set {override!r}: expected KEY=VALUE, e.g. pretrain.lr=0.001")
        raw = set_dotted(raw, f"task.{args.task}.{key}", yaml.safe_load(value))
    if args.seed == params_from_dict(raw).resolve(args.task).evaluate.seed:
        parser.error(f"--seed {args.seed} is the task's evaluation seed: choose settings on other episodes")
    raw = set_dotted(raw, f"task.{args.task}.evaluate.seed", args.seed)
    raw = set_dotted(raw, f"task.{args.task}.evaluate.episodes", args.episodes)
    params = params_from_dict(raw)
    task = params.resolve(args.task)
    family = get_family(task.family)
    device = resolve_device(args.device)
    ref = read_json(root / reference_path(task.name), f"reference of {task.name} (dvc repro reference@{task.name})")
    variant = f"{task.name}-{args.label}" if args.label else task.name
    out = args.out or root / f"learning_curve-{variant}-seed{args.training_seed}.jsonl"
    resume = resume_state_path(root, variant, args.training_seed)
    cfg = dataclasses.replace(pretrain_config(task, args.training_seed), steps=args.steps, checkpoint_every=args.every)
    if args.steps in {point["step"] for point in read_points(out)}:
        if not keeps_final_state(cfg):
            resume.unlink(missing_ok=True)  # a curve killed after its last point and before removing its state
        print(f"{out} already holds every point up to {args.steps} steps")
        return
    if (held := state_step(resume)) is not None and held > args.steps:
        parser.error(f"{resume} is at step {held}, past --steps {args.steps}: another curve's state")

    traj, expert = expert_training_data(task, root, args.training_seed)
    bundle, dataset = phase0_model(task, traj, cfg, {"expert": expert}, args.training_seed)

    def run_id_of(config: PretrainParams) -> str:
        return fingerprint(task.section("model"), task.section("diffusion"), dataclasses.asdict(config), expert)

    run_id = run_id_of(cfg)
    resume.parent.mkdir(parents=True, exist_ok=True)
    if args.extend is not None:
        try:
            start_from_shorter(args.extend, args.extend_state, out, resume, cfg, run_id_of)
        except ValueError as err:
            parser.error(str(err))
    points = read_points(out)
    done = {point["step"] for point in points}
    files = TaskFiles(root, task.name, None, args.training_seed)
    value_fields: dict[str, float] = {}
    if family.uses_value_function:
        files = curve_value(task, root, resume.with_suffix(""), bundle, traj, args.training_seed, device)
        config = read_json(files.value / "config.json", "curve value config")["curve"]
        value_fields = {key: config.get(name, float("nan")) for key, name in
                        [("value_cpu_s", "train_cpu_s"), ("value_r2", "r2"), ("value_r2_t0", "r2_t0")]}  # fmt: skip
        print(f"value function: {value_fields}", flush=True)
    ev, pl = task.evaluate, task.planner
    print(
        f"{task.name}: {cfg.steps} steps, evaluated every {args.every} on {ev.episodes} episodes from seed {ev.seed}; "
        f"model dim {task.model.dim} x {task.model.dim_mults}, horizon {task.diffusion.horizon}, {pl.sampler} "
        f"{pl.sampler_steps}; torch threads {torch.get_num_threads()}; writing {out}",
        flush=True,
    )
    clock_path = resume.with_name(f"{resume.stem}-clock.json")
    clock = resumed_clock(resume, clock_path, points, value_fields.get("value_cpu_s", 0.0))
    clock |= {"cpu_since": time.process_time(), "since": time.perf_counter()}

    def tick() -> None:
        clock["train_cpu_s"] += time.process_time() - clock["cpu_since"]
        clock["train_s"] += time.perf_counter() - clock["since"]
        clock["cpu_since"], clock["since"] = time.process_time(), time.perf_counter()

    def evaluate(step: int) -> None:
        tick()
        if step not in done:
            start = time.perf_counter()
            planner = Planner(bundle, make_sampler(pl.sampler, pl.sampler_steps), device)
            result = run_episodes(
                lambda: family.make_simulator(task),
                family.controller(task, planner, files, device),
                ev.episodes,
                ev.seed,
                ev.batch_size,
                progress=False,
            )
            scores = normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"])
            point = {"step": step, "score_mean": float(scores.mean()), "score_stderr": standard_error(scores),
                     **family.episode_metrics(result), "train_cpu_s": round(clock["train_cpu_s"], 1),
                     "train_s": round(clock["train_s"], 1), **value_fields,
                     "eval_s": round(time.perf_counter() - start, 1)}  # fmt: skip
            points.append(point)
            with atomic_path(out) as tmp:  # a kill mid-write leaves the last whole file
                tmp.write_text("".join(json.dumps(p) + "\n" for p in points))
            print(json.dumps(point), flush=True)
        if args.keep_model is not None:
            save_bundle(args.keep_model / f"step{step}", bundle)
        clock["cpu_since"], clock["since"] = time.process_time(), time.perf_counter()  # evaluation is not training

    def keep_clock(signum: int, frame: FrameType | None) -> None:
        """A stop, delivered once training has written its resume state: the clock of that state, then the stop."""
        tick()
        write_json(clock_path, {"step": state_step(resume), "train_cpu_s": clock["train_cpu_s"],
                                "train_s": clock["train_s"]})  # fmt: skip
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)

    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, keep_clock)
    train(bundle, dataset, cfg, device, resume, run_id, progress=not args.quiet, compiled=params.compile.training,
          on_checkpoint=evaluate)  # fmt: skip
    if not keeps_final_state(cfg):  # a constant-rate curve keeps its last state: a longer curve can --extend it
        resume.unlink(missing_ok=True)
    clock_path.unlink(missing_ok=True)


def resume_state_path(root: Path, variant: str, training_seed: int) -> Path:
    """Where the curve of ``variant`` (the task, with ``-label``) and training seed keeps its resume state."""
    return root / "models" / ".resume" / f"learning-curve-{variant}-seed{training_seed}.pt"


def read_points(path: Path) -> list[dict]:
    """The points of a curve's JSON-lines file, none where it does not exist."""
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def keeps_final_state(cfg: PretrainParams) -> bool:
    """Whether the training to any step is independent of the curve's length (a constant learning rate; warm-up
    depends on the step alone), so that a finished curve's last state can start a longer one."""
    return cfg.lr_schedule == "constant"


def start_from_shorter(
    shorter: Path, state_file: Path, out: Path, resume: Path, cfg: PretrainParams, run_id_of: Callable[..., str]
) -> None:
    """Start the curve of ``cfg`` (points ``out``, resume state ``resume``) from the shorter curve of the same
    settings whose points are ``shorter``, at its resume state ``state_file``: the state tagged as this curve's, then
    the points copied. Nothing where this curve has points already (it started: it resumes from its own state).
    ValueError (one line) where it cannot continue: another learning-rate schedule, no points, a shorter curve no
    shorter, a state the shorter curve did not write."""
    if out.exists():
        return
    if not keeps_final_state(cfg):
        raise ValueError(f"--extend needs lr_schedule constant, not {cfg.lr_schedule!r}: that rate depends on the "
                         "curve's length, so a shorter curve's training is not this one's")  # fmt: skip
    points = read_points(shorter)
    if not points:
        raise ValueError(f"--extend {shorter}: no points (the shorter curve's JSON lines)")
    steps = sorted(point["step"] for point in points)
    if steps[-1] >= cfg.steps:
        raise ValueError(f"--extend {shorter} reaches step {steps[-1]}, not fewer than --steps {cfg.steps}")
    state = torch.load(state_file, map_location="cpu", weights_only=False) if state_file.exists() else None
    if state is None:
        raise ValueError(f"--extend-state {state_file}: no such resume state")
    shorter_id = run_id_of(dataclasses.replace(cfg, steps=steps[-1], checkpoint_every=steps[0]))
    if state.get("run_id") != shorter_id or state["step"] > steps[-1]:
        raise ValueError(f"--extend-state {state_file} was not written by the curve of {shorter} "
                         f"({steps[-1]} steps every {steps[0]}) with these settings and data")  # fmt: skip
    print(f"extending {shorter} ({steps[-1]} steps) from its state at step {state['step']}", flush=True)
    clock = state_file.with_name(f"{state_file.stem}-clock.json")
    if clock.exists():
        write_json(resume.with_name(f"{resume.stem}-clock.json"), read_json(clock, "curve clock"))
    save_resume_state(resume, state | {"run_id": run_id_of(cfg)})
    with atomic_path(out) as tmp:  # the points last: a kill before leaves this curve unstarted, and it starts again
        tmp.write_text("".join(json.dumps(point) + "\n" for point in points))


def state_step(resume: Path) -> int | None:
    """The step of the resume state at ``resume``, or None where there is none."""
    return torch.load(resume, map_location="cpu", weights_only=False)["step"] if resume.exists() else None


def resumed_clock(resume: Path, clock_path: Path, points: list[dict], start_cpu_s: float) -> dict[str, float]:
    """The training's CPU and wall seconds at its resume state: written at the stop that left the state (a stop
    between two points), else the point of the state's step; from ``start_cpu_s`` and 0 without a state."""
    step = state_step(resume)
    if step is None:
        return {"train_cpu_s": start_cpu_s, "train_s": 0.0}
    stopped = read_json(clock_path, "curve clock") if clock_path.exists() else {}
    if stopped.get("step") == step:
        return {"train_cpu_s": stopped["train_cpu_s"], "train_s": stopped["train_s"]}
    at_step = [point for point in points if point["step"] == step]
    last = at_step[0] if at_step else (points[-1] if points else {})
    return {"train_cpu_s": last.get("train_cpu_s", start_cpu_s), "train_s": last.get("train_s", 0.0)}


def curve_value(
    task: TaskParams, root: Path, folder: Path, bundle: ModelBundle, traj: Trajectories, seed: int, device: torch.device
) -> TaskFiles:
    """The task's files with the curve's own value function (``folder/value``, relative paths under ``root``): trained
    as ``pretrain@<task>`` trains it unless a stopped curve already did, its CPU seconds and held-out R^2 in its
    config under ``curve``. The global torch RNG is left as it was, so the diffusion model trains as in the stage."""
    files = TaskFiles(root, task.name, folder.relative_to(root), seed)
    if not files.value.exists():
        cpu = time.process_time()
        with torch.random.fork_rng():
            net, fit, _ = fit_value(task, bundle, traj, seed, device, progress=False)
        fit["train_cpu_s"] = round(time.process_time() - cpu, 1)
        save_value(files.value, net.cpu(), {"curve": fit})
    return files


if __name__ == "__main__":
    main()
