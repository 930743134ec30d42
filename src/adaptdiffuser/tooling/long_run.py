"""A long run in the background of a DVC project: ``adaptdiffuser run start|status|stop``.

``start`` runs ``dvc repro`` (or another command that reruns cleanly, such as ``bash scripts/science_maze.sh``)
detached from the terminal under a supervisor (:mod:`adaptdiffuser.tooling.run_supervisor`) that waits for it and
every process it leaves, so none lingers as a zombie that DVC takes for a live holder of its lock. The run's record,
its lock and its log (every start appends to it) are in ``.long-run/`` at the project's root, which ignores itself in
git; nothing is written under ``.dvc/``. There is no ``resume``: starting again continues, since DVC skips the stages
that finished and a training stage resumes from its last state in ``models/.resume/``. ``stop`` has the supervisor
pass SIGTERM on to the command's process group, so a training stage ends its step and writes its resume state first
(``adaptdiffuser.stop_signals``), and sends SIGKILL to what is left of that group after a grace period.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from adaptdiffuser.errors import StageError
from adaptdiffuser.tooling.run_supervisor import LOG, RECORD, is_running, read_record

RUN_DIR = Path(".long-run")
DEFAULT_COMMAND = ("dvc", "repro")
RESUME_DIR = Path("models") / ".resume"


def run_folder(root: Path) -> Path:
    """The folder of the run's record, lock and log."""
    return root / RUN_DIR


def log_path(root: Path) -> Path:
    """The run's log (every start appends to it)."""
    return run_folder(root) / LOG


def running_record(root: Path) -> dict[str, Any] | None:
    """The record of the run of ``root`` while its supervisor lives (``pgid`` None until the command has started),
    else None."""
    folder = run_folder(root)
    if not is_running(folder):
        return None
    for _ in range(100):  # the supervisor writes its record as soon as it holds the lock
        if (record := read_record(folder)) is not None:
            return record
        time.sleep(0.05)
    return {"supervisor": None, "pgid": None, "state": "starting"}


def _check_project(root: Path) -> None:
    if not (root / ".dvc").is_dir():
        raise StageError(f"{root.resolve()} is not a DVC project (no .dvc folder)")


def start(root: Path, command: Sequence[str] = DEFAULT_COMMAND, wait_s: float = 60.0) -> int:
    """Start ``command`` in ``root`` in the background under its supervisor and return the command's pid (its process
    group); refused while a run of ``root`` runs, and when the command cannot be started."""
    _check_project(root)
    folder = run_folder(root)
    folder.mkdir(exist_ok=True)
    if not (folder / ".gitignore").exists():
        (folder / ".gitignore").write_text("# adaptdiffuser run: the run's record, lock and log\n*\n")
    with (folder / "start.lock").open("a") as guard:
        fcntl.flock(guard, fcntl.LOCK_EX)  # one start at a time: from the check until the supervisor runs
        if (record := running_record(root)) is not None:
            pid = record["pgid"] or record["supervisor"]
            raise StageError(f"{root.resolve()} already runs (pid {pid}): adaptdiffuser run status")
        (folder / RECORD).unlink(missing_ok=True)
        supervisor = [sys.executable, "-m", "adaptdiffuser.tooling.run_supervisor", str(folder.resolve()), "."]
        with log_path(root).open("a") as sink:
            first = subprocess.Popen(
                [*supervisor, "--", *command], cwd=root, stdin=subprocess.DEVNULL, stdout=sink,
                stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip
        if first.wait() != 0:  # it forks the supervisor and exits at once
            raise StageError(f"the run's supervisor did not start (see {log_path(root)})")
        deadline = time.monotonic() + wait_s
        while (record := read_record(folder)) is None or record["state"] == "starting":
            if time.monotonic() > deadline:
                raise StageError(f"the run did not start in {wait_s:g} s (see {log_path(root)})")
            time.sleep(0.05)
    if record["state"] == "not-started":
        raise StageError(record["error"])
    return int(record["pgid"])


def stop(root: Path, grace_s: float = 60.0) -> bool:
    """Stop the run of ``root``: its supervisor passes SIGTERM (and SIGCONT, for a paused run) on to the command's
    process group, and ``stop`` waits up to ``grace_s`` for every process of the run to end and be reaped (a training
    stage writes its resume state first) before SIGKILL to the group. Returns whether SIGKILL was needed; refused
    when the run does not run."""
    record = running_record(root)
    if record is None:
        raise StageError(f"{root.resolve()} does not run")
    if record["supervisor"] is None:
        raise StageError(f"{root.resolve()} is starting its run: try again in a moment")
    folder = run_folder(root)
    for signum in (signal.SIGCONT, signal.SIGTERM):  # a paused supervisor is woken to take it
        try:
            os.kill(record["supervisor"], signum)
        except ProcessLookupError:
            return False
    if _wait_ended(folder, grace_s):
        return False
    pgid = (read_record(folder) or record)["pgid"]  # None while the command has not started
    if pgid is not None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(pgid, signal.SIGKILL)
    if not _wait_ended(folder, 10.0):  # SIGKILL is not instant
        raise StageError(
            f"the run's supervisor (pid {record['supervisor']}) still waits for processes that left the run's "
            "process group after SIGKILL to it"
        )
    return True


def _wait_ended(folder: Path, timeout_s: float) -> bool:
    """Wait up to ``timeout_s`` for the supervisor in ``folder`` to end (it ends once it has reaped every process)."""
    deadline = time.monotonic() + timeout_s
    while is_running(folder):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


def _dvc_status(root: Path) -> str:
    """What ``dvc status`` says is left to run, in one line."""
    out = subprocess.run(["dvc", "status", "--json"], cwd=root, capture_output=True, text=True)
    if out.returncode != 0:
        return f"dvc status failed: {(out.stderr.strip().splitlines() or ['?'])[-1]}"
    changed = list(json.loads(out.stdout or "{}"))
    if not changed:
        return "dvc status: every stage is up to date"
    shown = ", ".join(changed[:6]) + (", ..." if len(changed) > 6 else "")
    return f"dvc status: {len(changed)} stages to run ({shown})"


def resume_states(root: Path) -> list[str]:
    """One line per resume state in ``models/.resume/``: a training's step, another state's or record's name."""
    folder = root / RESUME_DIR
    if not folder.is_dir():
        return []
    lines = []
    for path in sorted(folder.iterdir()):
        if path.name.startswith("."):  # an atomic write's temporary file
            continue
        if path.suffix == ".pt":
            import torch

            try:
                step = torch.load(path, map_location="cpu", weights_only=False)["step"]
            except Exception as err:  # a state from another torch, or not a training's: say so and go on
                step = f"unreadable: {err.__class__.__name__}"
            lines.append(f"resume state: {path.name} (step {step})")
        elif path.is_dir():
            lines.append(f"evaluated before a stop: {path.name}")
        else:
            lines.append(f"resume state: {path.name}")
    return lines


def _log_tail(root: Path, lines: int = 5) -> list[str]:
    """The log's last lines, each progress bar (rewritten with carriage returns) at its latest state."""
    try:
        with log_path(root).open("rb") as log:
            log.seek(max(0, log.seek(0, os.SEEK_END) - 20000))
            text = log.read().decode(errors="replace")
    except FileNotFoundError:
        return []
    return [line.rsplit("\r", 1)[-1] for line in text.splitlines()[-lines:]]


def _ended(record: dict[str, Any] | None, log: Path) -> str:
    """One line on how the last run ended, from its record."""
    record = record or {}
    state = record.get("state")
    again = "continue: adaptdiffuser run start"
    if state == "finished":
        return "finished: ended by itself with exit status 0"
    if state == "failed":
        return f"failed: exit status {record['exit_status']} (see {log}); {again}"
    if state == "not-started":
        return f"not started: {record['error']}"
    if state == "stopped":
        how = f"by adaptdiffuser run stop, {record['stopped_by']}"
    elif state == "killed":
        how = f"by {signal.Signals(-record['exit_status']).name}"
    else:  # no record, or one of a supervisor that ended before it could say how the run ended
        how = "its supervisor ended before it could say how"
    return f"stopped or killed ({how}); {again}"


def status(root: Path) -> list[str]:
    """Whether the run of ``root`` runs, finished or stopped; what DVC has left (from the log while it runs, as the
    run holds DVC's lock); each resume state; the log's last lines."""
    _check_project(root)
    log = log_path(root)
    if (record := running_record(root)) is not None:
        this_run = log.read_text(errors="replace").rsplit("\n== ", 1)[-1] if log.exists() else ""
        started = [line for line in this_run.splitlines() if line.startswith("Running stage")]
        last = started[-1] if started else "none yet"
        pid = f"pid {record['pgid']}" if record["pgid"] else f"starting, supervisor pid {record['supervisor']}"
        lines = [f"running: {pid}; {len(started)} stages started by the log, the last: {last}"]
    elif not log.exists():
        lines = ["not started (adaptdiffuser run start)"]
    else:
        lines = [_ended(read_record(run_folder(root)), log), _dvc_status(root)]
    lines += resume_states(root)
    lines += [f"log: {line}" for line in _log_tail(root)]
    return lines
