"""The pipeline's stages as DVC resolves ``dvc.yaml`` for a given set of params.

The sweep builds its trials from these (the same commands, inputs and outputs as ``dvc repro``) instead of keeping
a second copy of the phase chain in Python.
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from graphlib import TopologicalSorter
from pathlib import Path
from typing import Any

import yaml

from adaptdiffuser.errors import StageError


@dataclass(frozen=True)
class DvcStage:
    """One resolved stage: its DVC name (``generate@phase1``), command, file deps, params keys and outs."""

    name: str
    cmd: str
    deps: tuple[str, ...]
    params: tuple[str, ...]
    outs: tuple[str, ...]

    @property
    def kind(self) -> str:
        """The ``dvc.yaml`` name without the foreach key: ``evaluate-control@phase1`` -> ``evaluate-control``."""
        return self.name.split("@", 1)[0]

    @property
    def key(self) -> str | None:
        """The foreach key of an expanded stage (``phase1``), None for a plain stage."""
        return self.name.split("@", 1)[1] if "@" in self.name else None

    def produces(self, path: str) -> bool:
        """Whether ``path`` is one of this stage's outs or lies inside (or contains) one."""
        return any(_overlaps(path, out) for out in self.outs)


def _overlaps(a: str, b: str) -> bool:
    a, b = a.rstrip("/"), b.rstrip("/")
    return a == b or a.startswith(b + "/") or b.startswith(a + "/")


def key_touches(key: str, entry: str) -> bool:
    """Whether changing params key ``key`` changes params entry ``entry`` of a stage (one contains the other)."""
    return key == entry or key.startswith(entry + ".") or entry.startswith(key + ".")


def resolve_stages(dvc_yaml: Path, params: dict[str, Any]) -> list[DvcStage]:
    """Every stage of ``dvc_yaml`` as DVC expands it (foreach, ``${...}``) with ``params`` as ``params.yaml``."""
    from dvc.repo import Repo

    if not dvc_yaml.is_file():
        raise StageError(f"{dvc_yaml} not found: the sweep runs the stages declared there")
    with tempfile.TemporaryDirectory(prefix="dvc-stages-") as tmp:
        shutil.copyfile(dvc_yaml, Path(tmp) / "dvc.yaml")
        (Path(tmp) / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
        with Repo(tmp, uninitialized=True) as repo:
            stages = []
            for stage in repo.index.stages:
                params_keys: list[str] = []
                deps: list[str] = []
                for dep in stage.deps:
                    if hasattr(dep, "params"):
                        params_keys.extend(str(key) for key in dep.params)
                    else:
                        deps.append(str(dep.def_path))
                outs = tuple(str(out.def_path) for out in stage.outs)
                stages.append(DvcStage(stage.name, str(stage.cmd), tuple(deps), tuple(params_keys), outs))
    return stages


def upstream(stages: list[DvcStage], targets: list[DvcStage]) -> list[DvcStage]:
    """``targets`` and every stage they depend on through file deps, in an order that runs producers first."""
    by_name = {stage.name: stage for stage in stages}
    producers = {
        stage.name: sorted({other.name for dep in stage.deps for other in stages if other.produces(dep)} - {stage.name})
        for stage in stages
    }
    needed: set[str] = set()
    todo = [stage.name for stage in targets]
    while todo:
        name = todo.pop()
        if name not in needed:
            needed.add(name)
            todo.extend(producers[name])
    order = TopologicalSorter({name: [p for p in producers[name] if p in needed] for name in sorted(needed)})
    return [by_name[name] for name in order.static_order()]
