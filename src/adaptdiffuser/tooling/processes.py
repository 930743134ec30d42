"""Child processes that do not outlive the process that started them."""

from __future__ import annotations

import sys


def die_with_parent() -> None:
    """In the child, before exec (``preexec_fn``): on Linux, ask for SIGKILL when the parent dies, so a stopped
    worker or study leaves nothing training on behind it; elsewhere nothing."""
    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
