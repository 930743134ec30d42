"""Child processes that do not outlive the process that started them, and that are let finish when it is stopped."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Sequence
from types import FrameType

STOPS = (signal.SIGTERM, signal.SIGINT)


def die_with_parent() -> None:
    """In the child, before exec (``preexec_fn``): on Linux, ask for SIGKILL when the parent dies, so a stopped
    worker or study leaves nothing training on behind it; elsewhere nothing."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def run_stoppable(command: Sequence[str]) -> int:
    """Run ``command`` to its end and return its exit code; a stop (SIGTERM, SIGINT) sent to this process or to its
    process group reaches the child exactly once, and this process waits for the child to finish (a training child
    ends its step and writes its resume state, ``stop_signals``) before the stop takes its course here: it exits with
    the signal's status. The child runs in a session of its own, so a signal to this process's group does not reach it
    twice (a second stop would act at once); it still dies with this process should this one be killed outright."""
    received: list[int] = []
    child: subprocess.Popen[bytes] | None = None

    def forward(signum: int, frame: FrameType | None) -> None:
        if not received:
            received.append(signum)
            if child is not None:
                child.send_signal(signum)

    def in_child() -> None:
        die_with_parent()
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOPS)  # the child starts with the stops it inherited blocked

    previous = {signum: signal.signal(signum, forward) for signum in STOPS}
    try:
        signal.pthread_sigmask(signal.SIG_BLOCK, STOPS)  # a stop while the child starts waits until it is known
        try:
            if not received:
                child = subprocess.Popen(command, start_new_session=True, preexec_fn=in_child)
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, STOPS)  # and is forwarded here
        code = child.wait() if child is not None else 0
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if received:
        raise SystemExit(128 + received[0])
    return code
