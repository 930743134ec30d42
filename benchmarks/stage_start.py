"""Where a stage process's start goes, before its work: each step below in a fresh Python process, repeated, median
wall-clock and CPU seconds printed (never asserted). Every DVC stage, sweep trial and end-to-end test pays these, so
they set most of the test suite's time (docs/reliability.md).

    python benchmarks/stage_start.py [--repeats 5]

Steps, each including the ones before it in the same process: the interpreter alone; ``import torch``;
``import mlflow``; the project's command line (``adaptdiffuser.cli``, as ``pipeline/*.py`` import it); one MLflow
run logging a parameter and a metric, as a stage records itself, on the SQLite store an earlier stage made (the first
call, ``set_experiment``, imports SQLAlchemy's store and configures its ORM mappers), and on a new store (what the
first stage of a project pays once: MLflow creates its tables). Then what a stage of this code itself pays: the
command line alone (a stage that needs no torch), and a stage's start as ``pipeline/collect.py`` makes it (the
command line, the stage's module, and its ``stage_run`` logging a parameter and a metric: since stages write run
records instead of importing MLflow, no MLflow; the same code on an older commit measures its MLflow run). Run it on
an otherwise idle machine; compare steps, not machines.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import tempfile
import time

STEPS: dict[str, str] = {
    "interpreter": "pass",
    "+ import torch": "import torch",
    "+ import mlflow": "import torch, mlflow",
    "+ adaptdiffuser.cli": "import torch, mlflow, adaptdiffuser.cli",
    "+ MLflow run": (
        "import torch, mlflow, adaptdiffuser.cli\n"
        "mlflow.set_tracking_uri('sqlite:///mlflow.db')\n"
        "mlflow.set_experiment('stage-start')\n"
        "with mlflow.start_run():\n"
        "    mlflow.log_param('p', 1)\n"
        "    mlflow.log_metric('m', 1.0)\n"
    ),
}
NEW_STORE = "+ MLflow run, new store"
#: a stage's own start, from a fresh interpreter: with the code's own ``stage_run`` (a run record, or on code before
#: run records an MLflow run, whose context object has no ``log_metric``)
STAGE_STEPS: dict[str, str] = {
    "cli alone (no torch)": "import adaptdiffuser.cli",
    "stage start (collect)": (
        "from pathlib import Path\n"
        "import adaptdiffuser.cli\n"
        "from adaptdiffuser.stages import collect\n"
        "with collect.stage_run('stage-start', 'collect', 0, {'p': 1}, Path('.')) as run:\n"
        "    log = getattr(run, 'log_metric', None)\n"
        "    if log is None:\n"
        "        import mlflow\n"
        "        log = mlflow.log_metric\n"
        "    log('m', 1.0)\n"
    ),
}


def measure(code: str, folder: str) -> tuple[float, float]:
    """Wall-clock and CPU seconds (user + system) of one fresh Python process running ``code`` in ``folder``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], cwd=folder, check=True, capture_output=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def in_new_folder(code: str) -> tuple[float, float]:
    """:func:`measure` in a new empty folder (a project with no MLflow store yet)."""
    with tempfile.TemporaryDirectory() as folder:
        return measure(code, folder)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as project:
        measure(STEPS["+ MLflow run"], project)  # the store an earlier stage made; warms the file cache too
        print(f"{'step':<26} {'wall s':>8} {'cpu s':>8}   (median of {args.repeats})")
        steps = [(name, code, lambda c: measure(c, project)) for name, code in (STEPS | STAGE_STEPS).items()]
        steps.insert(len(STEPS), (NEW_STORE, STEPS["+ MLflow run"], in_new_folder))
        for name, code, run in steps:
            runs = [run(code) for _ in range(args.repeats)]
            wall = statistics.median(r[0] for r in runs)
            cpu = statistics.median(r[1] for r in runs)
            print(f"{name:<26} {wall:8.2f} {cpu:8.2f}", flush=True)


if __name__ == "__main__":
    main()
