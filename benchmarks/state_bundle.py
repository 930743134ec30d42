"""A training resume state (``models/.resume/*.pt``: a stage's or a learning curve's, between its checkpoints) as a
model bundle, so the comparison scripts can evaluate it (``--model DIR``): the model a curve had at its last state,
under other planner settings, without training it again.

    python benchmarks/state_bundle.py WORKSPACE --task maze2d-large --state models/.resume/STATE.pt --out DIR
        [--training-seed 0]

The bundle is built as ``pretrain@<task>`` builds its phase-0 model (the task's model and diffusion settings, the
normalizer fitted to the training seed's expert data), then given the state's raw and EMA weights; its config
records the state's step. WORKSPACE is a pipeline folder with the task's dataset.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
import yaml

from adaptdiffuser.checkpoint import save_bundle
from adaptdiffuser.config import params_from_dict
from adaptdiffuser.stages.pretrain import phase0_model
from adaptdiffuser.stages.training_data import expert_training_data, pretrain_config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--task", required=True)
    parser.add_argument("--state", type=Path, required=True, help="a resume state, relative to WORKSPACE or absolute")
    parser.add_argument("--out", type=Path, required=True, help="the bundle's folder")
    parser.add_argument("--training-seed", type=int, default=0)
    args = parser.parse_args()
    root = args.workspace.resolve()
    state_path = args.state if args.state.is_absolute() else root / args.state
    if not state_path.exists():
        parser.error(f"no resume state at {state_path}")
    state = torch.load(state_path, map_location="cpu", weights_only=False)
    if not {"model", "ema", "step"} <= set(state):
        parser.error(f"{state_path} is not a training resume state (no model, ema and step)")
    task = params_from_dict(yaml.safe_load((root / "params.yaml").read_text())).resolve(args.task)
    traj, expert = expert_training_data(task, root, args.training_seed)
    bundle, _ = phase0_model(task, traj, pretrain_config(task, args.training_seed), {"expert": expert},
                             args.training_seed)  # fmt: skip
    bundle.diffusion.model.load_state_dict(state["model"])
    bundle.ema.model.load_state_dict(state["ema"])
    bundle.config["resume_state"] = {"path": str(state_path), "step": int(state["step"])}
    save_bundle(args.out, bundle)
    print(f"wrote {args.out}: {task.name}'s model at step {state['step']} of {state_path.name}")


if __name__ == "__main__":
    main()
