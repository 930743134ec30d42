"""Arithmetic precision against speed on a GPU (printed, never asserted): a training step of the profile's Maze2D
network at several batch sizes, and a batch of 16-step DDIM plans, each in float32 (TF32 off for matrix products and
convolutions), TF32 (both on) and bf16 autocast. Each figure is the mean of 20 calls after 5 warm-up calls; the first
mode is timed again at the end, so an order effect shows as two different figures for it.

    python benchmarks/bench_precision.py [--params params.yaml] [--device cuda] [--sizes 32 256]

On a CPU without bf16 instructions autocast is many times slower (measured: 9x for a training step and 17x for
sampling on the AVX2-only EPYC), so the figures there say only that it is not for such a CPU.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
import torch
from speed_paths import maze_paths, sync

from adaptdiffuser.stages.common import resolve_device

MODES = ("bf16", "tf32", "fp32", "bf16")  # the first again at the end: the order's effect, if any


def timed_ms(fn: Callable[[], object], device: torch.device, calls: int = 20) -> float:
    """Mean milliseconds per call of ``fn`` after five warm-up calls."""
    for _ in range(5):
        fn()
    sync(device)
    begin = time.perf_counter()
    for _ in range(calls):
        fn()
    sync(device)
    return (time.perf_counter() - begin) / calls * 1000


def set_tf32(on: bool) -> None:
    torch.backends.cuda.matmul.allow_tf32 = on
    torch.backends.cudnn.allow_tf32 = on


def training_step(
    model: torch.nn.Module, optimizer: torch.optim.Optimizer, x: torch.Tensor, cond: dict, bf16: bool
) -> Callable[[], None]:
    """One Adam step on the fixed batch ``x`` (start/goal conditions ``cond``), under bf16 autocast if asked."""

    def step() -> None:
        with torch.autocast(x.device.type, dtype=torch.bfloat16, enabled=bf16):
            loss = model.loss(x, cond)
        loss.backward()
        optimizer.step()
        optimizer.zero_grad()

    return step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--task", default=None, help="a maze2d task of params (default: the evolved task)")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 256], help="training batch sizes")
    args = parser.parse_args()
    device = resolve_device(args.device)
    maze = maze_paths(args.params, args.task, device)
    model = maze.bundle.diffusion.to(device).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-5)
    print(f"{maze.task.name}: {maze.source}; device {device}, model dim {maze.task.model.dim}, horizon {model.horizon}")
    tf32_default = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32

    for size in args.sizes:
        x, cond = maze.training_batch(device, size)
        for mode in MODES:
            set_tf32(mode == "tf32")
            step = training_step(model, optimizer, x, cond, bf16=mode == "bf16")
            print(f"training step, batch {size}, {mode}: {timed_ms(step, device):.1f} ms", flush=True)

    set_tf32(False)
    planner = maze.planner("ddim", 16, device)
    for size in (1, args.sizes[-1]):
        starts, goals = maze.start.repeat(size, 0), maze.goal.repeat(size, 0)
        for bf16 in (True, False, True):

            def sample(bf16: bool = bf16, starts: np.ndarray = starts, goals: np.ndarray = goals) -> None:
                with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                    planner.sample(starts, goals, list(range(len(starts))))

            label = "bf16" if bf16 else "fp32"
            print(f"sampling, ddim 16, batch {size}, {label}: {timed_ms(sample, device, calls=5):.1f} ms", flush=True)
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = tf32_default


if __name__ == "__main__":
    main()
