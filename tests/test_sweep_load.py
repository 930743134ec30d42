"""Load test of the sweep's storage, worker and retry machinery: 4 worker processes on one journal file, and on a
real PostgreSQL server, one of them killed with SIGKILL in the middle of a trial. Afterwards no trial is lost,
duplicated or left running: each is COMPLETE or PRUNED, or FAILED and retried exactly once with the same params.

The workers are real separate processes started by the sweep's own
:func:`adaptdiffuser.tooling.optuna_sweep.run_workers`, open the study as real workers do and run
Optuna's optimize loop; only the trial itself is cheap (``load_worker``)."""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
from pathlib import Path

import optuna
import pytest
from load_worker import SWEEP
from load_worker import run as run_load_worker
from test_sweep import postgres  # noqa: F401  (the real PostgreSQL server fixture)

from adaptdiffuser.tooling.optuna_sweep import make_storage, retried_trial_number, run_workers

SHARES = [3, 3, 3, 3]  # 4 workers, 12 trials requested
State = optuna.trial.TrialState


def _kill_when_ready(ready: Path, killed: list[int], timeout_s: float = 120.0) -> None:
    """SIGKILL the worker whose pid appears in ``ready`` (it is then in the middle of a trial)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if ready.exists():
            pid = int(ready.read_text())
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
            return
        time.sleep(0.01)


@pytest.mark.parametrize("backend", ["journal", "postgresql"])
def test_a_worker_killed_mid_trial_loses_and_duplicates_no_trial(
    backend: str, tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    spec = str(tmp_path / "load.journal") if backend == "journal" else request.getfixturevalue("postgres")
    name = f"load-{backend}"
    study = optuna.create_study(
        study_name=name, storage=make_storage(spec, tmp_path, name, SWEEP.heartbeat_s), direction="maximize"
    )
    ready = tmp_path / "ready"
    killed: list[int] = []
    killer = threading.Thread(target=_kill_when_ready, args=(ready, killed), daemon=True)
    killer.start()
    # fresh processes, as the sweep's spawned workers are, forked from a server that imported the worker module
    # once (importing MLflow and Optuna in each of 5 processes on 2 shared cores would take most of the minute)
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["load_worker"])

    def make_worker(index: int, n: int) -> multiprocessing.process.BaseProcess:
        return context.Process(target=run_load_worker, args=(spec, str(tmp_path), name, n, index, str(ready)))

    dead = run_workers(study, make_worker, SHARES)
    killer.join(timeout=1)
    assert len(killed) == 1 and dead == killed  # the one worker killed, and only it, was seen dead

    trials = study.get_trials(deepcopy=False)
    requested = sum(SHARES)
    assert not [t.number for t in trials if t.state in (State.RUNNING, State.WAITING)]  # nothing left behind
    failed = [t for t in trials if t.state == State.FAIL]
    assert [t.user_attrs["worker_pid"] for t in failed] == killed  # only the killed trial failed
    for trial in failed:  # ... and it was retried exactly once, later, with its params, to the end
        (retry,) = [t for t in trials if retried_trial_number(t) == trial.number]
        assert retry.number > trial.number and retry.params == trial.params
        assert retry.state in (State.COMPLETE, State.PRUNED)
    assert all(t.state in (State.COMPLETE, State.PRUNED, State.FAIL) for t in trials)
    assert len(trials) == requested + len(failed)  # none lost: the dead worker's share was run by a replacement
    assert sorted(t.number for t in trials) == list(range(len(trials)))  # no trial number twice
    originals = [tuple(sorted(t.params.items())) for t in trials if retried_trial_number(t) is None]
    assert len(set(originals)) == len(originals) == requested  # no trial sampled or run twice
    pids = [t.user_attrs["worker_pid"] for t in trials]
    assert pids.count(killed[0]) == 2  # one trial completed before the kill, one killed
    assert len(set(pids)) == len(SHARES) + 1  # the replacement worker ran the retry and the rest of the share
