"""A quiet terminal: gymnasium-robotics' notice about its Adroit environments (printed to stderr when it is
imported, so by every stage that builds a maze; this project never uses them) never reaches a command's output, and
other notices still would."""

from __future__ import annotations

import subprocess
import sys

ADROIT = "AdroitHand"


def _output(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout + out.stderr


def test_gymnasium_robotics_prints_its_adroit_notice_without_us() -> None:
    """The notice exists in this environment (otherwise the test below proves nothing)."""
    assert ADROIT in _output("import gymnasium_robotics")


def test_our_commands_and_the_maze_simulator_print_only_our_messages() -> None:
    code = (
        "import sys\n"
        "sys.argv = ['adaptdiffuser', '--help']\n"
        "from adaptdiffuser.cli import app\n"
        "from adaptdiffuser.config import Params\n"
        "from adaptdiffuser.family_registry import get_family\n"
        "task = Params().resolve('maze2d-umaze')\n"
        "get_family(task.family).make_simulator(task)\n"  # imports gymnasium_robotics, as the stages do
        "try:\n"
        "    app()\n"
        "except SystemExit as end:\n"
        "    assert end.code == 0, end.code\n"
    )
    printed = _output(code)
    assert ADROIT not in printed and "Usage" in printed


def test_other_notices_still_print() -> None:
    code = (
        "import farama_notifications as f\n"
        "import gymnasium_robotics as g\n"
        "from adaptdiffuser.families.maze2d.simulator import silence_adroit_notice\n"
        "f.notifications.setdefault('gymnasium_robotics', {})[g.__version__] = 'another notice'\n"
        "silence_adroit_notice()\n"
        "print(f.notifications['gymnasium_robotics'][g.__version__])\n"
    )
    assert "another notice" in _output(code)


def test_halfcheetah_compiles_without_mujocos_settotalmass_warning_and_other_warnings_still_print() -> None:
    code = (
        "import gymnasium as gym\n"
        "import mujoco\n"
        "gym.make('HalfCheetah-v5')\n"  # MuJoCo's own warning, without us
        "from adaptdiffuser.families.locomotion.simulator import LocomotionSimulator\n"
        "LocomotionSimulator('HalfCheetah-v5')\n"
        "LocomotionSimulator('HalfCheetah-v5')\n"
        "mujoco.get_mju_user_warning()('another warning')\n"
    )
    printed = _output(code)
    assert printed.count("settotalmass") == 1 and "WARNING: another warning" in printed
