"""The supervisor of a background run (``adaptdiffuser run start``): a small process in a session of its own that
runs the run's command as its child, waits for it and for everything it leaves behind, passes a stop on to it and
records how it ended.

``python -m adaptdiffuser.tooling.run_supervisor FOLDER ROOT -- COMMAND...`` forks once and exits, so whoever starts
it reaps that first process at once and keeps no child of the run. The supervisor then holds an exclusive ``flock``
on ``FOLDER/lock`` for as long as it lives (released by the system when it ends, however it ends): that, not a pid,
tells a running run from one that ended. It is a child subreaper (Linux), so a process its command orphans is
reparented to it and reaped too, and no zombie of the run is left, which DVC would take for a live holder of its
``rwlock``. The command runs in a process group of its own (its pgid is its pid); SIGTERM or SIGINT sent to the
supervisor reach that group (with SIGCONT, to wake a paused run). ``FOLDER/run.json``, replaced atomically, holds the
supervisor's pid, the command's process group and, once every process of the run has ended, how the command ended;
the command's output, and the supervisor's, is appended to ``FOLDER/log``.
"""

from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import IO, Any

from adaptdiffuser.io import atomic_path
from adaptdiffuser.tooling.processes import STOPS, die_with_parent

LOCK = "lock"
RECORD = "run.json"
LOG = "log"
PR_SET_CHILD_SUBREAPER = 36


def read_record(folder: Path) -> dict[str, Any] | None:
    """The run's record in ``folder``, or None where there is none (yet)."""
    try:
        return json.loads((folder / RECORD).read_text())
    except (OSError, ValueError):
        return None


def write_record(folder: Path, record: dict[str, Any]) -> None:
    """Replace the run's record in ``folder`` atomically (a reader sees the old record or the new, never half)."""
    with atomic_path(folder / RECORD) as tmp:
        tmp.write_text(json.dumps(record, indent=1) + "\n")


def is_running(folder: Path) -> bool:
    """Whether a supervisor holds the run's lock in ``folder`` (tested by taking it for an instant)."""
    try:
        with (folder / LOCK).open("a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            fcntl.flock(lock, fcntl.LOCK_UN)
    except BlockingIOError:
        return True
    except FileNotFoundError:
        return False
    return False


def child_env(root: Path) -> dict[str, str]:
    """The command's environment: this one, no DVC analytics, and the project's own ``src/`` first on
    ``PYTHONPATH`` (a worktree pinned at another commit runs its own code with a shared virtual environment)."""
    env = dict(os.environ, DVC_NO_ANALYTICS="1")
    src = (root / "src").resolve()
    if (src / "adaptdiffuser").is_dir():
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(src), env.get("PYTHONPATH")]))
    return env


def _become_subreaper() -> None:
    """Ask that the run's orphaned processes be reparented to this one (Linux; elsewhere they go to init)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0)


def _take_lock(folder: Path, wait_s: float = 5.0) -> IO[str] | None:
    """The run's lock, held until this process ends; None if another supervisor holds it. A ``run status`` may hold
    it for an instant, so a busy lock is tried again for ``wait_s``."""
    lock = (folder / LOCK).open("a")  # not inherited by the command (Python's files are close-on-exec)
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return lock
        except BlockingIOError:
            if time.monotonic() > deadline:
                lock.close()
                return None
            time.sleep(0.05)


def _stamp() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _say(folder: Path, line: str) -> None:
    """Append ``line`` to the log (this process's output) on a line of its own, after a progress bar too."""
    try:
        with (folder / LOG).open("rb") as log:
            log.seek(-1, os.SEEK_END)
            ends_line = log.read(1) == b"\n"
    except OSError:  # no log, or an empty one
        ends_line = True
    print(("" if ends_line else "\n") + line, flush=True)


def _outcome(code: int, stops: Sequence[int]) -> str:
    """How the command ended: ``finished``, ``failed`` (an exit status), ``stopped`` (after a stop this process
    passed on) or ``killed`` (by a signal nobody sent through here)."""
    if stops:
        return "stopped"
    if code == 0:
        return "finished"
    return "failed" if code > 0 else "killed"


def supervise(folder: Path, root: Path, command: Sequence[str]) -> int:
    """Run ``command`` in ``root`` to its end and every process it started with it, as described above; return 0,
    or 1 when the run could not start (another supervisor holds the lock, or the command cannot be started)."""
    lock = _take_lock(folder)
    if lock is None:
        _say(folder, f"{_stamp()} another run holds {folder / LOCK}: not started")
        return 1
    _become_subreaper()
    received: list[int] = []
    group: list[int] = []

    def on_stop(signum: int, frame: FrameType | None) -> None:
        received.append(signum)
        if group:
            _signal_group(group[0], signum)

    for signum in STOPS:
        signal.signal(signum, on_stop)
    record: dict[str, Any] = {
        "supervisor": os.getpid(), "pgid": None, "command": list(command), "started": _stamp(), "commit": None,
        "state": "starting", "exit_status": None, "stopped_by": None,
    }  # fmt: skip
    write_record(folder, record)  # a stop from now on is passed on once the command runs
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True)
    record["commit"] = head.stdout.strip() or None
    _say(folder, f"== {record['started']} {' '.join(command)} at {record['commit'] or 'no commit'}")
    try:
        child = subprocess.Popen(
            list(command), cwd=root, env=child_env(root), stdin=subprocess.DEVNULL, process_group=0,
            preexec_fn=die_with_parent,  # should this supervisor be killed outright, nothing of the run goes on alone
        )  # fmt: skip
    except OSError as err:
        _say(folder, f"cannot start {command[0]}: {err}")
        write_record(folder, record | {"state": "not-started", "error": f"cannot start {command[0]}: {err}"})
        return 1
    signal.pthread_sigmask(signal.SIG_BLOCK, STOPS)  # each stop passed on once: by the handler, or here
    group.append(child.pid)
    for signum in received:  # a stop that came while the command started
        _signal_group(child.pid, signum)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOPS)
    write_record(folder, record | {"pgid": child.pid, "state": "running"})
    status = _reap_all(child.pid)
    child.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
    record |= {
        "pgid": child.pid, "state": _outcome(child.returncode, received), "exit_status": child.returncode,
        "stopped_by": signal.Signals(received[0]).name if received else None, "ended": _stamp(),
    }  # fmt: skip
    write_record(folder, record)
    _say(folder, f"== {record['ended']} {record['state']} (exit status {child.returncode})")
    return 0


def _signal_group(pgid: int, signum: int) -> None:
    """Pass a stop on to the command's process group, waking it first should it be paused."""
    for sent in (signal.SIGCONT, signum):
        try:
            os.killpg(pgid, sent)
        except ProcessLookupError:
            return


def _reap_all(pid: int) -> int:
    """Wait for every child of this process, the command ``pid`` and the orphans reparented here alike, until none is
    left; return the command's wait status."""
    status = 0
    while True:
        try:
            done, code = os.waitpid(-1, 0)
        except ChildProcessError:
            return status
        if done == pid:
            status = code


def main(argv: Sequence[str]) -> int:
    """``FOLDER ROOT -- COMMAND...``: fork, let the first process exit, and supervise in the second."""
    folder, root, dashes, *command = argv
    if dashes != "--" or not command:
        print("usage: python -m adaptdiffuser.tooling.run_supervisor FOLDER ROOT -- COMMAND...", file=sys.stderr)
        return 2
    if os.fork() > 0:
        os._exit(0)  # the starter reaps this one at once; the supervisor is no child of it
    return supervise(Path(folder), Path(root), command)


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
