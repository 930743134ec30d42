"""The KUKA tasks' scenes and criteria: random block placements, stacking (the seen task, with demonstrations)
and pick-and-place at four marked locations (the unseen task)."""

from __future__ import annotations

import numpy as np

from adaptdiffuser.families.kuka.scene import BLOCK_HALF, FLAG_COLUMNS, N_BLOCKS, block_position_columns

#: pick-and-place: block i goes to PLACE_TARGETS[i] (x, y, z of its centre)
PLACE_TARGETS = np.array([[0.5, -0.8, 0.032], [0.5, -0.3, 0.032], [0.5, 0.3, 0.032], [0.5, 0.8, 0.032]])
#: stacking: xy within this distance, one block at least this much higher, neither held
STACK_XY = 0.2
STACK_DZ = 0.05
#: pick-and-place: a block within this distance (xy) of its target, resting (not held)
PLACE_RADIUS = 0.2
UPRIGHT = np.array([0.0, 0.0, 0.0, 1.0])


def block_positions(obs: np.ndarray) -> np.ndarray:
    """``[..., 4, 3]`` block centres of observations ``[..., 39]``."""
    return np.stack([obs[..., block_position_columns(i)] for i in range(N_BLOCKS)], axis=-2)


def block_flags(obs: np.ndarray) -> np.ndarray:
    """``[..., 4]`` attached flags of observations ``[..., 39]``."""
    return obs[..., list(FLAG_COLUMNS)]


def stacked_count(obs: np.ndarray) -> int:
    """Blocks resting on another one: within ``STACK_XY`` of a lower block in xy and more than ``STACK_DZ`` above
    it, neither held by the cup. At most 3 (a tower of four)."""
    pos, held = block_positions(obs), block_flags(obs) > 0.5
    count = 0
    for i in range(N_BLOCKS):
        if held[i]:
            continue
        for j in range(N_BLOCKS):
            if j != i and not held[j]:
                near = np.linalg.norm(pos[i, :2] - pos[j, :2]) < STACK_XY
                if near and pos[i, 2] - pos[j, 2] > STACK_DZ:
                    count += 1
                    break
    return min(count, N_BLOCKS - 1)


def placed_blocks(obs: np.ndarray) -> np.ndarray:
    """``[4]`` bool: which blocks of observation ``[39]`` rest within ``PLACE_RADIUS`` (xy) of their own
    pick-and-place target."""
    pos, held = block_positions(obs), block_flags(obs) > 0.5
    dist = np.linalg.norm(pos[:, :2] - PLACE_TARGETS[:, :2], axis=1)
    return (dist < PLACE_RADIUS) & ~held


def placed_count(obs: np.ndarray) -> int:
    """Blocks resting within ``PLACE_RADIUS`` (xy) of their own pick-and-place target."""
    return int(np.sum(placed_blocks(obs)))


def scattered_blocks(
    rng: np.random.Generator, radius: tuple[float, float], min_gap: float, max_x: float | None = None
) -> np.ndarray:
    """Four blocks ``[4, 7]`` (xyz, quaternion) on the floor, upright and axis-aligned, at random in the ring
    ``radius`` around the base (only ``x <= max_x`` when given), centres at least ``min_gap`` apart."""
    placed: list[np.ndarray] = []
    for _ in range(10_000):
        r = np.sqrt(rng.uniform(radius[0] ** 2, radius[1] ** 2))
        angle = rng.uniform(-np.pi, np.pi)
        xy = np.array([r * np.cos(angle), r * np.sin(angle)])
        if max_x is not None and xy[0] > max_x:
            continue
        if all(np.linalg.norm(xy - p) >= min_gap for p in placed):
            placed.append(xy)
            if len(placed) == N_BLOCKS:
                break
    if len(placed) < N_BLOCKS:
        raise ValueError(f"cannot place {N_BLOCKS} blocks {min_gap} apart in the ring {radius} (max_x={max_x})")
    return np.array([[*xy, BLOCK_HALF[2], *UPRIGHT] for xy in placed])


def tower_blocks(rng: np.random.Generator, radius: tuple[float, float], max_x: float | None = None) -> np.ndarray:
    """Four blocks ``[4, 7]`` stacked in one tower (block 0 at the bottom) at a random place in the ring."""
    base = scattered_blocks(rng, radius, 0.0, max_x)[0]
    return np.array([[base[0], base[1], BLOCK_HALF[2] * (2 * i + 1) + 0.001 * i, *UPRIGHT] for i in range(N_BLOCKS)])
