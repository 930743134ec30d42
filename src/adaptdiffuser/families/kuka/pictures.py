"""Pictures of a KUKA episode: the final scene (PyBullet's TinyRenderer, no window) beside the blocks' heights."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from adaptdiffuser.families.kuka.scene import COLORS, N_BLOCKS
from adaptdiffuser.families.kuka.tasks import block_positions
from adaptdiffuser.plots import plt, save_figure

NAMES = ("yellow", "blue", "green", "red")


def save_episode_picture(
    path: str | Path, final_image: np.ndarray, executed: np.ndarray, plan: np.ndarray | None, title: str
) -> None:
    """One PNG: ``final_image`` (the last scene) and each block's height over the episode (and the first plan)."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.4), gridspec_kw={"width_ratios": [1.2, 1]})
    left.imshow(final_image)
    left.set_axis_off()
    left.set_title("final scene", fontsize=9)
    heights = block_positions(executed)[..., 2]
    for i in range(N_BLOCKS):
        right.plot(heights[:, i], color=COLORS[i][:3], lw=1.4, label=NAMES[i])
        if plan is not None:
            right.plot(block_positions(plan)[:, i, 2], color=COLORS[i][:3], lw=1.0, ls="--")
    right.set_xlabel("step (dashed: first plan)")
    right.set_ylabel("block height (m)")
    right.legend(loc="upper left", fontsize="x-small")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
