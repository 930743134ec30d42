"""What the comparison scripts share: a pipeline workspace after `dvc repro`, one task of it with its episodes moved
to a validation seed, and one trained model (phase, training seed) of that task."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import yaml

from adaptdiffuser.checkpoint import ModelBundle, load_bundle
from adaptdiffuser.config import params_from_dict, set_dotted
from adaptdiffuser.config.tasks import TaskParams
from adaptdiffuser.contract import TaskFiles
from adaptdiffuser.io import read_json
from adaptdiffuser.layout import model_dir, reference_path
from adaptdiffuser.stages.common import resolve_device


def add_workspace_args(parser: argparse.ArgumentParser, task: str | None = None, episodes: int | None = None) -> None:
    """The options every comparison takes: the workspace, the task, the episodes and the model."""
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--task", default=task, help="a task of params (default: the evolved task)")
    parser.add_argument("--seed", type=int, default=7, help="episode seed (default 7: validation, not evaluation)")
    parser.add_argument("--episodes", type=int, default=episodes, help="default: the task's own number")
    parser.add_argument("--phase", type=int, default=0)
    parser.add_argument("--training-seed", type=int, default=0)
    parser.add_argument("--model", type=Path, default=None, help="a model folder (default: the phase's, that seed's)")
    parser.add_argument("--device", default="auto")


def parse_settings(pairs: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` options (``--set``) as dotted keys with YAML values."""
    bad = [pair for pair in pairs if "=" not in pair]
    if bad:
        raise SystemExit(f"--set takes KEY=VALUE, got {bad[0]!r}")
    return {key: yaml.safe_load(value) for key, value in (pair.split("=", 1) for pair in pairs)}


def with_task_settings(raw: dict[str, Any], task: str, settings: dict[str, Any]) -> dict[str, Any]:
    """Raw params ``raw`` with each dotted ``task.<task>.<key>`` of ``settings`` set to its value."""
    for key, value in settings.items():
        raw = set_dotted(raw, f"task.{task}.{key}", value)
    return raw


@dataclass
class TrainedWorkspace:
    """A workspace's params (episodes moved to ``--seed``), the chosen task and its trained model."""

    root: Path
    raw: dict[str, Any]
    name: str
    model: Path
    training_seed: int
    device: torch.device
    bundle: ModelBundle

    def task(self, key: str | None = None, value: Any = None) -> TaskParams:
        """The task, with ``task.<name>.<key>`` set to ``value`` when ``key`` is given."""
        raw = self.raw if key is None else set_dotted(self.raw, f"task.{self.name}.{key}", value)
        return params_from_dict(raw).resolve(self.name)

    def task_with(self, settings: dict[str, Any]) -> TaskParams:
        """The task with each dotted ``task.<name>.<key>`` of ``settings`` set to its value."""
        return params_from_dict(with_task_settings(self.raw, self.name, settings)).resolve(self.name)

    def files(self) -> TaskFiles:
        return TaskFiles(self.root, self.name, self.model, self.training_seed)

    def reference(self) -> dict[str, Any]:
        return read_json(self.root / reference_path(self.name), f"reference scores of {self.name}")


def load_trained(args: argparse.Namespace, episodes_section: str = "evaluate") -> TrainedWorkspace:
    """The workspace of ``args`` (see :func:`add_workspace_args`); ``episodes_section`` names the task section whose
    ``seed`` and ``episodes`` the options override (``evaluate``, or a family's own like ``pick_place``)."""
    root = args.workspace.resolve()
    raw = yaml.safe_load((root / "params.yaml").read_text())
    name = args.task or raw.get("evolve") or raw["tasks"][0]
    raw = set_dotted(raw, f"task.{name}.{episodes_section}.seed", args.seed)
    if args.episodes is not None:
        raw = set_dotted(raw, f"task.{name}.{episodes_section}.episodes", args.episodes)
    device = resolve_device(args.device)
    model = args.model.resolve() if args.model is not None else model_dir(name, args.phase, args.training_seed)
    return TrainedWorkspace(root, raw, name, model, args.training_seed, device, load_bundle(root / model, device))
