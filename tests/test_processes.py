"""A child started with ``die_with_parent`` does not outlive its parent (a stopped study or sweep worker leaves
nothing training on), and one run by ``run_stoppable`` has a stop once and is let finish."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

PARENT = """
import subprocess, sys, time
from adaptdiffuser.tooling.processes import die_with_parent
kwargs = {"preexec_fn": die_with_parent} if sys.argv[1] == "tied" else {}
child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"], **kwargs)
print(child.pid, flush=True)
child.wait()
"""


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def child_after_parent_is_killed(mode: str, wait_s: float) -> tuple[int, bool]:
    """The child's pid, and whether it is still alive ``wait_s`` seconds after its parent was killed (or as soon as
    it is gone)."""
    parent = subprocess.Popen([sys.executable, "-c", PARENT, mode], stdout=subprocess.PIPE, text=True)
    child = int(parent.stdout.readline())
    parent.send_signal(signal.SIGTERM)
    parent.wait(timeout=30)
    deadline = time.monotonic() + wait_s
    while alive(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    return child, alive(child)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_child_dies_with_its_parent_and_an_untied_one_lives_on() -> None:
    _, tied_alive = child_after_parent_is_killed("tied", wait_s=10)
    assert not tied_alive
    untied, untied_alive = child_after_parent_is_killed("untied", wait_s=1)
    try:
        assert untied_alive  # the failure die_with_parent prevents: an orphan that trains on
    finally:
        os.kill(untied, signal.SIGKILL)


STOPPABLE = """
import sys
from adaptdiffuser.tooling.processes import run_stoppable
sys.exit(run_stoppable([sys.executable, "-c", sys.argv[1], sys.argv[2]]))
"""

# a child that counts the stops it receives and takes a while to go, as a training step ends and writes its state
SLOW_TO_STOP = """
import signal, sys, time
from pathlib import Path
out = Path(sys.argv[1])
stops = []
signal.signal(signal.SIGTERM, lambda signum, frame: stops.append(signum))
out.with_suffix(".ready").write_text("")
while not stops:
    time.sleep(0.01)
time.sleep(1.0)  # a second stop would arrive meanwhile
out.write_text(str(len(stops)))
sys.exit(143)
"""


@pytest.mark.parametrize("to", ["parent", "group"])
def test_a_stop_reaches_the_child_once_and_the_parent_waits_for_it(to: str, tmp_path) -> None:
    out = tmp_path / "stops.txt"
    parent = subprocess.Popen([sys.executable, "-c", STOPPABLE, SLOW_TO_STOP, str(out)], start_new_session=True)
    deadline = time.monotonic() + 60
    while not out.with_suffix(".ready").exists():
        assert parent.poll() is None and time.monotonic() < deadline
        time.sleep(0.01)
    if to == "parent":  # `kill PID` of a study
        parent.send_signal(signal.SIGTERM)
    else:  # `adaptdiffuser run stop`: the whole process group
        os.killpg(parent.pid, signal.SIGTERM)
    assert parent.wait(timeout=30) == 128 + signal.SIGTERM
    assert out.read_text() == "1"  # the child had its one stop and finished before the parent went
