"""What a pipeline stage really uses, checked against the ``deps`` that ``dvc.yaml`` lists for it.

With ``ADAPTDIFFUSER_TRACE_DEPS=<folder>`` set and ``tests/trace_hook`` and ``tests`` on ``PYTHONPATH``
(:func:`traced_env`), :func:`install_from_env` (called at start-up by ``tests/trace_hook/sitecustomize.py``) records,
for one stage process: the project modules loaded by its end (``src/adaptdiffuser/**`` and the stage script in
``pipeline/``), the files under the project root it opened for reading (Python's ``open`` audit event; Parquet
files go through pyarrow's C++ readers, which no audit hook sees, so the pyarrow readers are wrapped) and the
folders it listed. At exit it writes ``<folder>/<DVC stage>-<pid>.json``.

:func:`check` reads those traces and the stages of ``dvc.yaml`` (DVC's own resolution, templating included) and
returns, per stage, the traced paths no dep covers (a folder dep covers everything under it) and the deps the stage
never touched. ``python tests/deps_trace.py <project> <trace folder>`` prints both.
"""

from __future__ import annotations

import ast
import atexit
import fnmatch
import functools
import json
import os
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import adaptdiffuser

ENV_VAR = "ADAPTDIFFUSER_TRACE_DEPS"
CODE_STAGE = "code"  # the stage whose outs (code/<task>.json) fingerprint the code other stages run
# What every stage loads to validate params.yaml: each task entry's family model (and what it imports). Another
# family's model can make params.yaml invalid (the stage stops), never change this task's outputs, so a stage whose
# code is a fingerprint needs no dep on it; its own family's model is in its fingerprint.
TASK_MODELS = ("src/adaptdiffuser/families/*/params.py", "src/adaptdiffuser/families/maze2d/layouts.py")
PACKAGE_DIR = Path(adaptdiffuser.__file__).resolve().parent
HOOK_DIR = Path(__file__).resolve().parent / "trace_hook"
SOURCE_PREFIX = "src/adaptdiffuser"  # where the package lives in the project (dvc.yaml names it so)
# Project paths a stage may touch without listing them: DVC and git state, the MLflow store (every stage logs to
# it), training's resume points (git-ignored, never an input of a finished stage), bytecode, MuJoCo's log.
IGNORED = (
    ".git",
    ".dvc",
    "mlflow.db",
    "mlflow.db-journal",
    "mlflow.db-wal",
    "mlflow.db-shm",
    "mlflow-pending",
    "mlartifacts",
    "mlruns",
    "models/.resume",
    "MUJOCO_LOG.TXT",
)
# Reads that reach a stage through another of its deps, by stage (the name before "@"): fine-tuning phase k reads
# the selections of phase k's ancestors, which DVC cannot list per phase; they trained models/<previous>, a dep.
INDIRECT_READS: dict[str, tuple[str, ...]] = {"finetune": ("data/*/phase*/selected/*",)}
# pyarrow.parquet readers whose first argument names the file: they open it in C++, out of the audit hook's sight.
PARQUET_READERS = ("read_table", "read_schema", "read_metadata", "read_pandas", "ParquetFile", "ParquetDataset")


def under(path: str, prefix: str) -> bool:
    """Whether the relative POSIX path ``path`` is ``prefix`` or lies inside it."""
    return path == prefix or path.startswith(prefix.rstrip("/") + "/")


class Tracer:
    """Records the project modules, reads and listings of this process; :meth:`write` saves them as JSON."""

    def __init__(self, root: Path, out_dir: Path) -> None:
        self.root = Path(os.path.realpath(root))
        # fast filter before realpath (most opens are the interpreter's): the root as given and as resolved
        self.prefixes = tuple({os.path.join(os.path.abspath(root), ""), os.path.join(str(self.root), "")})
        self.out_dir = out_dir
        self.reads: set[str] = set()
        self.written: set[str] = set()
        self.listed: set[str] = set()
        self.active = True

    def relative(self, path: Any) -> str | None:
        """``path`` relative to the project root (POSIX), or None when it is not a project path."""
        if isinstance(path, int):  # open(fd)
            return None
        try:
            full = os.path.abspath(os.fsdecode(path))
            if not full.startswith(self.prefixes):
                return None
            rel = os.path.relpath(os.path.realpath(full), self.root)
        except (TypeError, ValueError):
            return None
        if rel in (".", "..") or rel.startswith(".." + os.sep) or os.path.isabs(rel):
            return None
        rel = Path(rel).as_posix()
        if "__pycache__" in rel.split("/") or any(under(rel, ignored) for ignored in IGNORED):
            return None
        return rel

    def record_read(self, path: Any) -> None:
        """A read of ``path``, unless this process wrote that file first (then it is no input) or it does not exist
        (an open that is about to fail: libraries probe for files such as a git ``HEAD``)."""
        rel = self.relative(path)
        if rel is not None and rel not in self.written and os.path.isfile(self.root / rel):
            self.reads.add(rel)

    def audit(self, event: str, args: tuple) -> None:
        """The audit hook: ``open`` (read or write, from the OS flags) and folder listings."""
        if not self.active or event not in ("open", "os.listdir", "os.scandir"):
            return
        try:
            if event != "open":
                rel = self.relative(args[0] if args and args[0] is not None else ".")
                if rel is not None:
                    self.listed.add(rel)
                return
            path, _, flags = args
            access = flags & os.O_ACCMODE if isinstance(flags, int) else os.O_RDONLY
            if access in (os.O_RDONLY, os.O_RDWR):
                self.record_read(path)
            if access in (os.O_WRONLY, os.O_RDWR) and (rel := self.relative(path)) is not None:
                self.written.add(rel)
        except Exception:  # an audit hook must never break the stage
            return

    def modules(self) -> set[str]:
        """Project paths of the modules loaded now: the package's as ``src/adaptdiffuser/...``, and any module file
        under the project root (the stage script)."""
        found: set[str] = set()
        files = [getattr(module, "__file__", None) for module in list(sys.modules.values())]
        script = os.path.realpath(sys.argv[0]) if sys.argv and sys.argv[0] else None  # the stage script
        for file in [script, *files]:
            if not file:
                continue
            path = Path(os.path.realpath(file))
            if not path.is_file():  # modules with a made-up __file__ (torch._ops: "_ops.py")
                continue
            if path == Path(__file__).resolve() or path.parent == HOOK_DIR:  # the tracer and its start-up hook
                continue
            if path.is_relative_to(PACKAGE_DIR):
                found.add(f"{SOURCE_PREFIX}/{path.relative_to(PACKAGE_DIR).as_posix()}")
            elif (rel := self.relative(path)) is not None:
                found.add(rel)
        return found

    def payload(self) -> dict[str, Any]:
        """The trace as written: stage, command line, project root, modules, reads, listings."""
        return {
            "stage": os.environ.get("DVC_STAGE"),
            "argv": sys.argv,
            "root": str(self.root),
            "modules": sorted(self.modules()),
            "reads": sorted(self.reads),
            "listed": sorted(self.listed),
        }

    def write(self) -> Path:
        """Save the trace as ``<out_dir>/<stage or script>-<pid>.json`` and stop recording."""
        self.active = False
        name = os.environ.get("DVC_STAGE") or Path(sys.argv[0]).stem or "python"
        out = self.out_dir / f"{name.replace(os.sep, '_')}-{os.getpid()}.json"
        self.out_dir.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(self.payload(), indent=1))
        return out


def _record_sources(tracer: Tracer, source: Any) -> None:
    """Record the path (or each path of a list) a reader is given; file objects were seen when opened."""
    for path in source if isinstance(source, list | tuple) else [source]:
        if isinstance(path, str | bytes | os.PathLike):
            tracer.record_read(path)


def _wrap_parquet_readers(tracer: Tracer) -> None:
    """Make the pyarrow.parquet readers report the path they are given (their C++ open escapes the audit hook)."""
    import pyarrow.parquet as pq

    def traced_function(reader: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(reader)
        def call(source: Any, *args: Any, **kwargs: Any) -> Any:
            _record_sources(tracer, source)
            return reader(source, *args, **kwargs)

        return call

    def traced_class(cls: type) -> type:
        def __init__(self: Any, source: Any, *args: Any, **kwargs: Any) -> None:
            _record_sources(tracer, source)
            cls.__init__(self, source, *args, **kwargs)

        return type(cls.__name__, (cls,), {"__init__": __init__, "__module__": cls.__module__})

    for name in PARQUET_READERS:
        reader = getattr(pq, name)
        setattr(pq, name, traced_class(reader) if isinstance(reader, type) else traced_function(reader))


_installed: Tracer | None = None


def install(out_dir: str | Path, root: str | Path | None = None) -> Tracer:
    """Start tracing this process (once): audit hook, wrapped Parquet readers, trace written at exit.

    ``root`` defaults to ``$DVC_ROOT`` (set by DVC for every stage) or the working directory."""
    global _installed
    if _installed is not None:
        return _installed
    tracer = Tracer(Path(root or os.environ.get("DVC_ROOT") or os.getcwd()), Path(out_dir).resolve())
    sys.addaudithook(tracer.audit)
    _wrap_parquet_readers(tracer)
    atexit.register(tracer.write)
    _installed = tracer
    return tracer


def traced_env(out_dir: str | Path) -> dict[str, str]:
    """The environment variables that make a pipeline run's stage processes trace themselves into ``out_dir``."""
    path = os.pathsep.join([str(HOOK_DIR), str(HOOK_DIR.parent), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return {ENV_VAR: str(out_dir), "PYTHONPATH": path}


def install_from_env() -> Tracer | None:
    """:func:`install` into ``$ADAPTDIFFUSER_TRACE_DEPS`` when it is set; nothing otherwise."""
    out_dir = os.environ.get(ENV_VAR)
    return install(out_dir) if out_dir else None


# --- the check -------------------------------------------------------------------------------------------------


@dataclass
class StageTrace:
    """What the traced runs of one stage touched (relative POSIX paths), merged over its runs."""

    modules: set[str] = field(default_factory=set)
    reads: set[str] = field(default_factory=set)
    listed: set[str] = field(default_factory=set)

    def paths(self) -> set[str]:
        return self.modules | self.reads | self.listed


@dataclass
class StageDeps:
    """One resolved dvc.yaml stage: its path deps, params files and outs (relative POSIX paths)."""

    deps: list[str]
    params_files: list[str]
    outs: list[str]
    upstream_outs: list[str] = field(default_factory=list)  # outs of every stage upstream of this one
    code: list[str] = field(default_factory=list)  # the code its fingerprint deps (code/<task>.json) stand for


@dataclass
class StageReport:
    """The check of one stage: traced paths no dep covers, and deps nothing traced falls under."""

    missing: list[str]
    unused: list[str]


def load_traces(trace_dir: str | Path) -> dict[str, StageTrace]:
    """Every trace in ``trace_dir``, merged per DVC stage (traces of processes run outside DVC are skipped)."""
    traces: dict[str, StageTrace] = {}
    for file in sorted(Path(trace_dir).glob("*.json")):
        data = json.loads(file.read_text())
        if not data.get("stage"):
            continue
        trace = traces.setdefault(data["stage"], StageTrace())
        trace.modules.update(data["modules"])
        trace.reads.update(data["reads"])
        trace.listed.update(data["listed"])
    return traces


def dvc_stages(root: str | Path) -> dict[str, StageDeps]:
    """The stages of ``root``'s dvc.yaml as DVC resolves them (foreach expanded, ``${...}`` interpolated)."""
    import networkx as nx
    from dvc.dependency.param import ParamsDependency
    from dvc.repo import Repo

    root = Path(os.path.realpath(root))

    def rel(fs_path: str) -> str:
        return Path(os.path.relpath(os.path.realpath(fs_path), root)).as_posix()

    stages: dict[str, StageDeps] = {}
    with Repo(str(root)) as repo:
        graph = repo.index.graph  # edges point from a stage to the stages it depends on
        # what a code fingerprint stands for: code/<task>.json -> the deps of the stage that writes it
        fingerprinted = {
            rel(out.fs_path): [rel(dep.fs_path) for dep in stage.deps if not isinstance(dep, ParamsDependency)]
            for stage in repo.index.stages
            if stage.name.split("@")[0] == CODE_STAGE
            for out in stage.outs
        }
        for stage in repo.index.stages:
            params = [dep for dep in stage.deps if isinstance(dep, ParamsDependency)]
            deps = [rel(dep.fs_path) for dep in stage.deps if not isinstance(dep, ParamsDependency)]
            stages[stage.name] = StageDeps(  # the name DVC passes its commands as $DVC_STAGE
                deps=deps,
                params_files=[rel(dep.fs_path) for dep in params],
                outs=[rel(out.fs_path) for out in stage.outs],
                upstream_outs=[rel(out.fs_path) for up in nx.descendants(graph, stage) for out in up.outs],
                code=[path for dep in deps for path in fingerprinted.get(dep, [])],
            )
    return stages


def is_inert(path: Path) -> bool:
    """Whether a module can change no stage's output: only a docstring, ``__future__`` imports and literal
    dunder assignments (``__version__ = "0.1.0"``, ``__all__ = [...]``), as in the package ``__init__.py`` files."""
    try:
        body = ast.parse(path.read_text()).body
    except (OSError, SyntaxError, ValueError):
        return False
    for node in body:
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            continue
        if isinstance(node, ast.ImportFrom) and node.module == "__future__":
            continue
        dunders = isinstance(node, ast.Assign) and all(
            isinstance(t, ast.Name) and t.id.startswith("__") and t.id.endswith("__") for t in node.targets
        )
        if dunders and _is_literal(node.value):
            continue
        return False
    return True


def _is_literal(node: ast.expr) -> bool:
    try:
        ast.literal_eval(node)
    except ValueError:
        return False
    return True


def check_stage(stage: StageDeps, trace: StageTrace, root: Path, indirect: Sequence[str] = ()) -> StageReport:
    """Compare one stage's deps with its trace. Its outs and params files are neither missing nor needed, nor are
    inert modules (:func:`is_inert`); a read matching a glob of ``indirect`` may come from an upstream stage's outs
    (data that reaches the stage through another dep, such as the ancestors' selections of a fine-tuned model)."""
    own = [*stage.outs, *stage.params_files]
    touched = {path for path in trace.paths() if not any(under(path, out) for out in own)}
    touched = {path for path in touched if not (path in trace.modules and is_inert(root / path))}

    def covered(path: str) -> bool:
        if path in trace.listed and not (path in trace.reads or path in trace.modules):
            # a listed folder: covered by a dep on it, on a folder above it, or on something inside it
            return any(under(path, dep) or under(dep, path) for dep in stage.deps)
        if any(fnmatch.fnmatchcase(path, pattern) for pattern in indirect):
            return any(under(path, out) for out in [*stage.deps, *stage.upstream_outs])
        if stage.code and any(fnmatch.fnmatchcase(path, pattern) for pattern in TASK_MODELS):
            return True
        return any(under(path, dep) for dep in [*stage.deps, *stage.code])

    missing = sorted(path for path in touched if not covered(path))
    fingerprints = {dep for dep in stage.deps if stage.code and dep.startswith(f"{CODE_STAGE}/")}
    unused = [dep for dep in stage.deps if dep not in fingerprints and not any(under(p, dep) for p in trace.paths())]
    return StageReport(missing=missing, unused=unused)


def check(
    root: str | Path, trace_dir: str | Path, indirect: Mapping[str, Sequence[str]] | None = None
) -> dict[str, StageReport]:
    """:func:`check_stage` for every stage of ``root``'s dvc.yaml; ``indirect`` maps a stage's name before ``@``
    (``finetune``) to its globs (default :data:`INDIRECT_READS`). A stage without a trace raises ``KeyError``."""
    traces = load_traces(trace_dir)
    stages = dvc_stages(root)
    untraced = sorted(set(stages) - set(traces))
    if untraced:
        raise KeyError(f"no trace for stages {untraced} in {trace_dir} (did they run with {ENV_VAR} set?)")
    indirect = INDIRECT_READS if indirect is None else indirect
    return {
        name: check_stage(stage, traces[name], Path(root), indirect.get(name.split("@")[0], ()))
        for name, stage in stages.items()
    }


def missing_message(reports: dict[str, StageReport]) -> str:
    """One line per stage whose trace has paths its deps miss (empty when none)."""
    lines = [
        f"{name}: add to its deps in dvc.yaml: {', '.join(report.missing)}"
        for name, report in reports.items()
        if report.missing
    ]
    return "\n".join(lines)


def unused_by_group(reports: dict[str, StageReport]) -> dict[str, list[str]]:
    """Deps unused by every expansion of a foreach stage (``generate@phase1``, ``generate@phase2`` -> ``generate``);
    ``${...}`` paths differ per expansion, so only paths common to all of them are compared."""
    groups: dict[str, list[StageReport]] = {}
    for name, report in reports.items():
        groups.setdefault(name.split("@")[0], []).append(report)
    unused: dict[str, list[str]] = {}
    for group, members in groups.items():
        common = set.intersection(*(set(report.unused) for report in members))
        if common:
            unused[group] = sorted(common)
    return unused


def main(argv: Iterable[str] | None = None) -> int:
    """``python tests/deps_trace.py <project> <trace folder>``: print missing and unused deps."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 2:
        print("usage: python tests/deps_trace.py <project root> <trace folder>", file=sys.stderr)
        return 2
    reports = check(*args)
    message = missing_message(reports)
    print(message or "every traced module and read is listed in dvc.yaml")
    for name, report in reports.items():
        if report.unused:
            print(f"{name}: never touched: {', '.join(report.unused)}")
    return 1 if message else 0


if __name__ == "__main__":
    sys.exit(main())
