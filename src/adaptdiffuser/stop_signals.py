"""A stop request that waits for the end of a training step, so that a stopped run loses no training.

While a training loop that keeps a resume state runs, SIGTERM (``adaptdiffuser run stop``, a scheduler, ``kill``) and
SIGINT (Ctrl-C) are held by :class:`DeferredStop`: the loop finishes its step, writes its resume state there, then
the signal is sent again and takes its course (SIGTERM ends the process as it would have; a Python handler, such as
the one raising ``KeyboardInterrupt`` for SIGINT, runs). A second signal while one waits acts at once. Outside the
main thread, or for a signal that is ignored or handled outside Python, nothing changes; an error raised in the loop
while a signal waits ends it with its own traceback.
"""

from __future__ import annotations

import os
import signal
import threading
from types import FrameType, TracebackType
from typing import Any

HELD = (signal.SIGTERM, signal.SIGINT)


class DeferredStop:
    """Context manager: while it is open, :data:`HELD` signals only set :attr:`received`; :meth:`deliver` sends it
    again with the former handlers back. A signal still held when the context closes normally is delivered then. With
    ``enabled`` false (a loop without a resume state) it holds nothing."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self.received: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> DeferredStop:
        if self.enabled and threading.current_thread() is threading.main_thread():
            for signum in HELD:
                handler = signal.getsignal(signum)
                if handler not in (signal.SIG_IGN, None):  # ignored, or set outside Python: left alone
                    self._previous[signum] = signal.signal(signum, self._hold)
        return self

    def _hold(self, signum: int, frame: FrameType | None) -> None:
        first = self.received is None
        self.received = signum
        if not first:  # asked twice: stop now
            self.deliver()

    @property
    def name(self) -> str:
        """The held signal's name (``SIGTERM``), or an empty string."""
        return signal.Signals(self.received).name if self.received is not None else ""

    def deliver(self) -> None:
        """Put the former handlers back and send the held signal to this process again (nothing if none)."""
        signum = self.received
        self._restore()  # from here a signal goes to the former handler
        self.received = None
        if signum is not None:
            os.kill(os.getpid(), signum)

    def _restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        if kind is None:
            self.deliver()
        else:  # the error ends the loop, with its traceback: a signal held meanwhile is dropped
            self._restore()
            self.received = None
