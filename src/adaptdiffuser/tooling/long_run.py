"""A long run in the background of a DVC project: ``adaptdiffuser run start|status|stop``.

``start`` runs ``dvc repro`` (or another command that reruns cleanly, such as ``bash scripts/science_maze.sh``)
detached from the terminal, in a process group of its own, its output appended to a log; its pid, and its exit status
once it ends by itself, are kept beside the log in ``.dvc/tmp/long-run/`` (ignored by git and DVC). There is no
``resume``: starting again continues, since DVC skips the stages that finished and a training stage resumes from its
last state in ``models/.resume/``. ``stop`` sends SIGTERM to the run's process group, so a training stage ends its
step and writes its resume state first (``adaptdiffuser.stop_signals``), and SIGKILL to what is left after a grace
period. Linux only: a run's processes are read from ``/proc``.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import signal
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path

from adaptdiffuser.errors import StageError
from adaptdiffuser.io import atomic_path

STATE_DIR = Path(".dvc") / "tmp" / "long-run"
DEFAULT_COMMAND = ("dvc", "repro")
RESUME_DIR = Path("models") / ".resume"


def log_path(root: Path) -> Path:
    """The run's log (every start appends to it)."""
    return root / STATE_DIR / "log"


def _pid_path(root: Path) -> Path:
    return root / STATE_DIR / "pid"


def _rc_path(root: Path) -> Path:
    """Written by the run when it ends by itself; absent while it runs, or when it was stopped or killed."""
    return root / STATE_DIR / "rc"


def _proc_stat(pid: int) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after ``pid (comm)`` (state, ppid, pgrp, ...), or None if it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text.rsplit(")", 1)[1].split()


def group_members(pgid: int) -> list[int]:
    """The live processes (zombies not counted) of process group ``pgid``."""
    members = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            fields = _proc_stat(int(entry.name))
            if fields is not None and int(fields[2]) == pgid and fields[0] != "Z":
                members.append(int(entry.name))
    return members


def _start_time(pid: int) -> str | None:
    """When process ``pid`` started (clock ticks since boot), or None if it is gone: with the boot's id, what tells
    a run's pid from the same number reused by another process."""
    fields = _proc_stat(pid)
    return None if fields is None else fields[19]


def _boot_id() -> str:
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def running_pid(root: Path) -> int | None:
    """The pid (and process group) of the run of ``root`` while any process of it lives, else None. The leader may be
    gone while its stages still write their resume state; a pid file of another boot, or whose leader is another
    process under a reused pid, is not a run."""
    try:
        pid_text, started, boot = _pid_path(root).read_text().split()
        pid = int(pid_text)
    except (OSError, ValueError):
        return None
    if boot != _boot_id():
        return None
    leader = _start_time(pid)
    if leader is not None and leader != started:
        return None  # the pid was reused
    return pid if group_members(pid) else None


def _check_project(root: Path) -> None:
    if not (root / ".dvc").is_dir():
        raise StageError(f"{root.resolve()} is not a DVC project (no .dvc folder)")


def start(root: Path, command: Sequence[str] = DEFAULT_COMMAND) -> int:
    """Start ``command`` in ``root`` in the background and return its pid; refused while a run of ``root`` runs.
    The project's own ``src/`` comes first on ``PYTHONPATH``, so a clone or worktree at another commit runs its own
    code with a shared virtual environment."""
    _check_project(root)
    log = log_path(root)
    log.parent.mkdir(parents=True, exist_ok=True)
    with (root / STATE_DIR / "lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one start at a time: from the check until the pid file is written
        return _start_locked(root, command, log)


def _start_locked(root: Path, command: Sequence[str], log: Path) -> int:
    if (pid := running_pid(root)) is not None:
        raise StageError(f"{root.resolve()} already runs (pid {pid}): adaptdiffuser run status")
    clear_stale_dvc_locks(root)
    _rc_path(root).unlink(missing_ok=True)
    env = dict(os.environ, DVC_NO_ANALYTICS="1", LONG_RUN_RC=str(_rc_path(root).resolve()))
    src = (root / "src").resolve()
    if (src / "adaptdiffuser").is_dir():
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(src), env.get("PYTHONPATH")]))
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True)
    stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    with log.open("a") as sink:
        sink.write(f"== {stamp} {' '.join(command)} at {head.stdout.strip() or 'no commit'}\n")
        sink.flush()
        # sh writes the exit status only when the command ends by itself: a stop ends sh too (SIGTERM)
        wrapper = ["sh", "-c", '"$@"; echo $? > "$LONG_RUN_RC"', "long-run", *command]
        child = subprocess.Popen(
            wrapper, cwd=root, env=env, stdin=subprocess.DEVNULL, stdout=sink, stderr=subprocess.STDOUT,
            start_new_session=True,
        )  # fmt: skip
    with atomic_path(_pid_path(root)) as tmp:
        tmp.write_text(f"{child.pid} {_start_time(child.pid) or 0} {_boot_id()}\n")
    return child.pid


def stop(root: Path, grace_s: float = 60.0) -> bool:
    """Stop the run of ``root``: SIGTERM (and SIGCONT, for a paused run) to its process group, then wait up to
    ``grace_s`` for every process in it to end (a training stage writes its resume state first) before SIGKILL.
    Returns whether SIGKILL was needed; refused when the run does not run."""
    pid = running_pid(root)
    if pid is None:
        raise StageError(f"{root.resolve()} does not run")
    for signum in (signal.SIGTERM, signal.SIGCONT):
        try:
            os.killpg(pid, signum)
        except ProcessLookupError:
            return False
    deadline = time.monotonic() + grace_s
    while group_members(pid):
        if time.monotonic() > deadline:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pid, signal.SIGKILL)
            for _ in range(100):  # SIGKILL is not instant: return once the group is gone (at most 10 s)
                if not group_members(pid):
                    break
                time.sleep(0.1)
            return True
        time.sleep(0.2)
    return False


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, which a container without an init that reaps may keep, does not)."""
    fields = _proc_stat(pid)
    return fields is not None and fields[0] != "Z"


def clear_stale_dvc_locks(root: Path) -> None:
    """Drop from DVC's ``.dvc/tmp/rwlock`` the entries of processes that no longer run. A stopped run leaves them
    when its ``dvc`` ends by a signal; DVC drops those of vanished pids itself, but not those of unreaped zombies,
    and would refuse every later command. Entries of live processes are kept."""
    path = root / ".dvc" / "tmp" / "rwlock"
    try:
        lock = json.loads(path.read_text())
    except (OSError, ValueError):
        return
    write = {p: info for p, info in lock.get("write", {}).items() if _alive(int(info["pid"]))}
    read = {
        p: kept for p, infos in lock.get("read", {}).items() if (kept := [i for i in infos if _alive(int(i["pid"]))])
    }
    cleared = {key: value for key, value in (("write", write), ("read", read)) if value}
    if cleared != lock:
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(cleared))


def _dvc_status(root: Path) -> str:
    """What ``dvc status`` says is left to run, in one line."""
    clear_stale_dvc_locks(root)
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


def status(root: Path) -> list[str]:
    """Whether the run of ``root`` runs, finished or stopped; what DVC has left (from the log while it runs, as the
    run holds DVC's lock); each resume state; the log's last lines."""
    _check_project(root)
    log = log_path(root)
    if (pid := running_pid(root)) is not None:
        started = [line for line in log.read_text(errors="replace").splitlines() if line.startswith("Running stage")]
        last = started[-1] if started else "none yet"
        lines = [f"running: pid {pid}; {len(started)} stages started by the log, the last: {last}"]
    elif not log.exists():
        lines = ["not started (adaptdiffuser run start)"]
    else:
        rc = _rc_path(root).read_text().strip() if _rc_path(root).exists() else None
        if rc == "0":
            lines = ["finished: ended by itself with exit status 0"]
        elif rc is not None:
            lines = [f"failed: exit status {rc} (see {log}); continue: adaptdiffuser run start"]
        else:
            lines = ["stopped or killed; continue: adaptdiffuser run start"]
        lines.append(_dvc_status(root))
    lines += resume_states(root)
    lines += [f"log: {line}" for line in _log_tail(root)]
    return lines
