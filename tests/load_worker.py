"""A cheap sweep worker for ``tests/test_sweep_load.py``, in its own module so that spawned workers import only this
(not the test module and its fixtures): the real worker-side path (``tooling.optuna_sweep.load_worker_study``,
so ``make_storage`` with its heartbeat and retry settings, and Optuna's optimize loop) around a trial that only
sleeps instead of running stages."""

from __future__ import annotations

import os
import time
from pathlib import Path

import optuna

from adaptdiffuser.config import SweepParams
from adaptdiffuser.errors import StageError
from adaptdiffuser.tooling.optuna_sweep import load_worker_study

#: what every load-test worker uses: 1 s heartbeats on PostgreSQL, TPE seeded per worker
SWEEP = SweepParams(workers=4, heartbeat_s=1, seed=0)


def run(storage: str, root: str, study_name: str, n_trials: int, worker: int, ready: str) -> None:
    """Run ``n_trials`` trials of the shared study. Worker 0, in its second trial, writes its pid to ``ready`` once
    the trial has reported a value and then waits to be killed there (the test sends SIGKILL)."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = load_worker_study(storage, Path(root), study_name, SWEEP, worker)
    started = 0

    def objective(trial: optuna.Trial) -> float:
        nonlocal started
        started += 1
        trial.set_user_attr("worker_pid", os.getpid())  # as the real objective does, first thing
        x = trial.suggest_float("x", 0.0, 1.0)
        trial.report(x, 1)
        if worker == 0 and started == 2:
            tmp = Path(f"{ready}.tmp")
            tmp.write_text(str(os.getpid()))
            tmp.rename(ready)
            time.sleep(120)  # killed here, mid-trial
        if trial.should_prune():
            raise optuna.TrialPruned()
        time.sleep(0.05)
        trial.report(x + 0.1, 2)
        return x + 0.1

    study.optimize(objective, n_trials=n_trials, catch=(StageError,))
