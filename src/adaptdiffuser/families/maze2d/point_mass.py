"""gymnasium-robotics' point mass in a maze, its MuJoCo model compiled once per maze and process.

PointMaze writes a new MJCF file (into the system temp folder, never removed) and compiles it for every
environment it makes, about 75 ms each on 2 cores; an evaluation makes one simulator per episode. Here each maze's
file is written, compiled and removed once per process; every point mass gets its own copy of that compiled model
and fresh ``MjData``, which is what compiling the same file again gives, so each simulator starts and steps exactly
as a new ``PointMazeEnv``'s ``point_env`` would (gymnasium-robotics and gymnasium, MIT licence: the asset path, the
camera distance and the framebuffer sizes below follow ``PointMazeEnv`` and ``MujocoEnv``).
"""

from __future__ import annotations

import copy
import functools
import os
import threading
from typing import Any

WallMap = list[list[int]]

_MAZE_HEIGHT = 0.4  # PointMazeEnv's wall height and cell scale
_SCALE = 1
_compiled: dict[str, Any] = {}  # repr(wall map) -> the compiled MjModel
_compiling = threading.Lock()


def _agent_xml() -> str:
    """The packaged MJCF of the point mass alone (what PointMazeEnv adds the maze to)."""
    from gymnasium_robotics.envs.maze import point_maze

    return os.path.join(os.path.dirname(os.path.realpath(point_maze.__file__)), "../assets/point/point.xml")


def _maze_model(wall_map: WallMap) -> Any:
    """The compiled model of the point mass in ``wall_map`` (compiled on first use, its file then removed)."""
    key = repr(wall_map)
    with _compiling:
        if key not in _compiled:
            import mujoco
            from gymnasium_robotics.envs.maze.maze_v4 import Maze

            _, path = Maze.make_maze(_agent_xml(), wall_map, _SCALE, _MAZE_HEIGHT)
            try:
                _compiled[key] = mujoco.MjModel.from_xml_path(path)
            finally:
                os.remove(path)
        return _compiled[key]


@functools.cache
def _point_env_class() -> type:
    """``PointEnv`` taking its compiled model as an argument instead of compiling its file."""
    import mujoco
    from gymnasium_robotics.envs.maze.point import PointEnv

    class CompiledPointEnv(PointEnv):
        def __init__(self, compiled: Any, **kwargs: Any) -> None:
            self._compiled = compiled
            super().__init__(**kwargs)

        def _initialize_simulation(self) -> tuple[Any, Any]:
            model = copy.copy(self._compiled)
            model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.width)
            model.vis.global_.offheight = max(model.vis.global_.offheight, self.height)
            return model, mujoco.MjData(model)

    return CompiledPointEnv


def make_point_mass(wall_map: WallMap) -> Any:
    """A ``PointEnv`` (``set_state``, ``step``, ``data``) in the maze ``wall_map``, as ``PointMazeEnv`` builds it.
    (``xml_file`` only has to exist: the model is the compiled maze's, never read from it.)"""
    camera = {"distance": 12.5 if len(wall_map) > 8 else 8.8}
    return _point_env_class()(_maze_model(wall_map), xml_file=_agent_xml(), default_camera_config=camera)
