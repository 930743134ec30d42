"""The KUKA scene on PyBullet: an iiwa arm at the origin, a plane and four 0.2 x 0.2 x 0.06 blocks, with a suction
cup at the flange (a fixed constraint to a block while its flag is on and it is within reach of the cup).

Observation (39 dims): the 7 joint positions, then per block its centre (xyz), orientation (quaternion xyzw) and
attached flag (1.0 while held by the cup). Headless (``DIRECT``) and deterministic: every reset rebuilds the world.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
from collections.abc import Iterator

import numpy as np

N_JOINTS = 7
N_BLOCKS = 4
BLOCK_HALF = (0.1, 0.1, 0.03)
#: per block: xyz (3), quaternion xyzw (4), attached flag (1)
BLOCK_DIMS = 8
OBS_DIM = N_JOINTS + N_BLOCKS * BLOCK_DIMS
#: observation columns of the blocks' attached flags
FLAG_COLUMNS = tuple(N_JOINTS + i * BLOCK_DIMS + 7 for i in range(N_BLOCKS))
#: the arm's resting configuration (elbow up, the cup pointing down over the floor in front of the base)
HOME_JOINTS = np.array([0.0, 0.35, 0.0, -1.55, 0.0, 1.25, 0.0])
COLORS = ((0.9, 0.8, 0.1, 1), (0.2, 0.4, 0.9, 1), (0.2, 0.7, 0.3, 1), (0.85, 0.2, 0.2, 1))  # yellow blue green red
#: the suction cup sits this far beyond the flange, along the flange's z axis
CUP_OFFSET = 0.05
TIME_STEP = 1.0 / 240.0


def block_position_columns(i: int) -> slice:
    """Observation columns of block ``i``'s centre (xyz)."""
    start = N_JOINTS + i * BLOCK_DIMS
    return slice(start, start + 3)


def covered_blocks(positions: np.ndarray) -> np.ndarray:
    """``[4]`` bool: which of the blocks with centres ``[4, 3]`` carry another block (its centre within a block's
    width in xy and more than half a block's height higher), so that their top is out of the cup's reach."""
    offset = positions[None, :, :] - positions[:, None, :]  # [i, j]: block j relative to block i
    near = np.linalg.norm(offset[..., :2], axis=-1) < 2 * BLOCK_HALF[0]
    np.fill_diagonal(near, False)
    return (near & (offset[..., 2] > BLOCK_HALF[2])).any(axis=1)


@contextlib.contextmanager
def _silent_output() -> Iterator[None]:
    """Drop what PyBullet's C code prints at import and connection (its build time, ``argv[0]=``); Python
    exceptions raised inside still propagate and are shown after the streams are restored."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 1)
            os.dup2(devnull.fileno(), 2)
            yield
    finally:
        ctypes.CDLL(None).fflush(None)  # C's buffered output goes to /dev/null too
        for fd, copy in zip((1, 2), saved, strict=True):
            os.dup2(copy, fd)
            os.close(copy)


class KukaScene:
    """One PyBullet world (its own ``DIRECT`` client)."""

    def __init__(
        self,
        joint_force: float = 300.0,
        position_gain: float = 0.3,
        suction_reach: float = 0.1,
        free_top_only: bool = False,
        max_joint_step: float | None = None,
    ) -> None:
        with _silent_output():
            import pybullet as pb
            import pybullet_data
            from pybullet_utils import bullet_client

            self.client = bullet_client.BulletClient(connection_mode=pb.DIRECT)
        self.pb = pb
        self.client.setAdditionalSearchPath(pybullet_data.getDataPath())
        self.joint_force = joint_force
        self.position_gain = position_gain
        self.suction_reach = suction_reach
        self.free_top_only = free_top_only
        self.max_joint_step = max_joint_step
        self.constraints: list[int | None] = [None] * N_BLOCKS

    def build(self, joints: np.ndarray, blocks: np.ndarray) -> np.ndarray:
        """A fresh world with the arm at ``joints`` (7) and the blocks at ``blocks`` ``[4, 7]`` (xyz, quaternion
        xyzw), at rest and detached; return the observation."""
        c, pb = self.client, self.pb
        c.resetSimulation()
        c.setGravity(0, 0, -9.81)
        c.setTimeStep(TIME_STEP)
        c.loadURDF("plane.urdf")
        self.robot = c.loadURDF("kuka_iiwa/model.urdf", [0, 0, 0], useFixedBase=True)
        shape = c.createCollisionShape(pb.GEOM_BOX, halfExtents=BLOCK_HALF)
        self.blocks = []
        for i, pose in enumerate(np.asarray(blocks, dtype=np.float64)):
            visual = c.createVisualShape(pb.GEOM_BOX, halfExtents=BLOCK_HALF, rgbaColor=COLORS[i])
            body = c.createMultiBody(0.2, shape, visual, pose[:3].tolist(), pose[3:7].tolist())
            c.changeDynamics(body, -1, lateralFriction=0.8)
            self.blocks.append(body)
        for j, q in enumerate(np.asarray(joints, dtype=np.float64)):
            c.resetJointState(self.robot, j, float(q))
        self.constraints = [None] * N_BLOCKS
        return self.observation()

    def observation(self) -> np.ndarray:
        c = self.client
        obs = np.empty(OBS_DIM)
        obs[:N_JOINTS] = [s[0] for s in c.getJointStates(self.robot, range(N_JOINTS))]
        for i, body in enumerate(self.blocks):
            pos, quat = c.getBasePositionAndOrientation(body)
            k = N_JOINTS + i * BLOCK_DIMS
            obs[k : k + 3], obs[k + 3 : k + 7] = pos, quat
            obs[k + 7] = float(self.constraints[i] is not None)
        return obs

    def _flange(self) -> tuple[np.ndarray, np.ndarray]:
        """The flange's position and orientation (quaternion xyzw)."""
        state = self.client.getLinkState(self.robot, N_JOINTS - 1, computeForwardKinematics=True)
        return np.asarray(state[4]), np.asarray(state[5])

    def _cup_of(self, flange_pos: np.ndarray, flange_quat: np.ndarray) -> np.ndarray:
        axis = np.asarray(self.client.getMatrixFromQuaternion(flange_quat)).reshape(3, 3)[:, 2]
        return flange_pos + CUP_OFFSET * axis

    def cup(self) -> tuple[np.ndarray, np.ndarray]:
        """The suction cup's position and the flange's orientation (quaternion xyzw)."""
        pos, quat = self._flange()
        return self._cup_of(pos, quat), quat

    def set_suction(self, flags: np.ndarray) -> None:
        """Attach each block whose flag is > 0.5 (if not held yet and within reach of the cup, and, with
        ``free_top_only``, not under another block), release the others. One block at most is held: with several
        flags on, the nearest in reach is taken."""
        c, pb = self.client, self.pb
        want = np.asarray(flags) > 0.5
        for i in np.flatnonzero(~want):
            if self.constraints[i] is not None:
                c.removeConstraint(self.constraints[i])
                self.constraints[i] = None
        if not want.any() or any(k is not None for k in self.constraints):
            return
        flange_pos, flange_quat = self._flange()
        cup = self._cup_of(flange_pos, flange_quat)
        positions = np.array([c.getBasePositionAndOrientation(body)[0] for body in self.blocks])
        if self.free_top_only:
            want &= ~covered_blocks(positions)
        best, best_dist = None, self.suction_reach
        for i in np.flatnonzero(want):
            top = positions[i] + np.array([0.0, 0.0, BLOCK_HALF[2]])
            dist = float(np.linalg.norm(top - cup))
            if dist <= best_dist:
                best, best_dist = i, dist
        if best is None:
            return
        pos, quat = c.getBasePositionAndOrientation(self.blocks[best])
        inv_pos, inv_quat = c.invertTransform(flange_pos.tolist(), flange_quat.tolist())
        rel_pos, rel_quat = c.multiplyTransforms(inv_pos, inv_quat, pos, quat)
        self.constraints[best] = c.createConstraint(
            self.robot, N_JOINTS - 1, self.blocks[best], -1, pb.JOINT_FIXED, [0, 0, 0], rel_pos, [0, 0, 0], rel_quat
        )
        c.changeConstraint(self.constraints[best], maxForce=500.0)

    def command(self, joint_targets: np.ndarray, flags: np.ndarray, substeps: int) -> np.ndarray:
        """Position-control the joints toward ``joint_targets`` (each at most ``max_joint_step`` from its current
        angle, when set), set the suction from ``flags``, simulate ``substeps`` steps; return the observation."""
        self.set_suction(flags)
        targets = np.asarray(joint_targets, dtype=np.float64)
        if self.max_joint_step is not None:
            current = np.array([s[0] for s in self.client.getJointStates(self.robot, range(N_JOINTS))])
            targets = current + np.clip(targets - current, -self.max_joint_step, self.max_joint_step)
        self.client.setJointMotorControlArray(
            self.robot,
            list(range(N_JOINTS)),
            self.pb.POSITION_CONTROL,
            targetPositions=targets.tolist(),
            forces=[self.joint_force] * N_JOINTS,
            positionGains=[self.position_gain] * N_JOINTS,
        )
        for _ in range(substeps):
            self.client.stepSimulation()
        return self.observation()

    def inverse_kinematics(self, cup_target: np.ndarray, rest: np.ndarray) -> np.ndarray:
        """Joint positions putting the cup at ``cup_target`` and pointing straight down (near ``rest``)."""
        down = self.client.getQuaternionFromEuler([0.0, np.pi, 0.0])
        flange = np.asarray(cup_target) + np.array([0.0, 0.0, CUP_OFFSET])  # the flange's z axis points down
        lower = [-2.96, -2.09, -2.96, -2.09, -2.96, -2.09, -3.05]
        q = self.client.calculateInverseKinematics(
            self.robot,
            N_JOINTS - 1,
            flange.tolist(),
            down,
            lowerLimits=lower,
            upperLimits=[-x for x in lower],
            jointRanges=[2 * -x for x in lower],
            restPoses=np.asarray(rest).tolist(),
            maxNumIterations=100,
            residualThreshold=1e-4,
        )
        return np.asarray(q[:N_JOINTS])

    def render(self, width: int = 320, height: int = 240) -> np.ndarray:
        """An RGB picture of the scene (TinyRenderer, no window) ``[height, width, 3]`` uint8."""
        c = self.client
        view = c.computeViewMatrix([1.6, -1.4, 1.3], [0.25, 0.0, 0.1], [0, 0, 1])
        proj = c.computeProjectionMatrixFOV(50, width / height, 0.05, 10.0)
        img = c.getCameraImage(width, height, view, proj, renderer=self.pb.ER_TINY_RENDERER)[2]
        return np.asarray(img, dtype=np.uint8).reshape(height, width, 4)[:, :, :3]

    def close(self) -> None:
        with contextlib.suppress(Exception):  # already disconnected
            self.client.disconnect()

    def __del__(self) -> None:
        self.close()
