"""How much faster can the network get at equal arithmetic? A roofline for the two paths issue 16 asks to speed up
1.5x (a training step and a batched plan), printed, never asserted.

For each path: its wall time with the network as it is and with its GroupNorm and Mish layers replaced by
identities (the convolutions, linear layers and additions left: timed in alternating rounds, medians), the
convolutions' floating-point operations (``torch.utils.flop_counter``, forward and backward) and the rate they run
at, beside the rate of a large float32 matrix product on the same threads. The ratio of the two wall times bounds
any speedup that keeps the arithmetic (float32, the same operations) but leaves the convolutions as they are
(``bound_free_rest``: GroupNorm and Mish free).

    python benchmarks/roofline.py [--params params.yaml] [--rounds 5] [--batch 256]
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch
from speed_paths import alternate, maze_paths
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from adaptdiffuser.models.unet import Mish
from adaptdiffuser.stages.common import resolve_device


def matmul_gflops(device: torch.device, size: int = 2048, rounds: int = 9) -> float:
    """Median float32 GFLOP/s of a ``size`` x ``size`` matrix product on the current torch threads."""
    a = torch.randn(size, size, device=device)
    b = torch.randn(size, size, device=device)
    seconds = alternate({"matmul": lambda: a @ b}, rounds, device, calls=3)["matmul"] / 1000
    return 2 * size**3 / seconds / 1e9


def convolution_flops(fn: Callable[[], object]) -> float:
    """Floating-point operations of the convolutions (forward and backward) in one call of ``fn``."""
    with FlopCounterMode(display=False) as counter:
        fn()
    return float(sum(n for op, n in counter.get_flop_counts()["Global"].items() if "convolution" in str(op)))


@contextmanager
def without_norm_and_activation(*modules: nn.Module) -> Iterator[None]:
    """Within the block, every GroupNorm and Mish layer of ``modules`` is an identity (restored afterwards)."""
    swapped: list[tuple[nn.Module, str, nn.Module]] = []
    for module in modules:
        for parent in module.modules():
            for name, child in parent.named_children():
                if isinstance(child, nn.GroupNorm | Mish):
                    swapped.append((parent, name, child))
                    setattr(parent, name, nn.Identity())
    try:
        yield
    finally:
        for parent, name, child in swapped:
            setattr(parent, name, child)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--task", default=None)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--batch", type=int, default=256, help="plans in the batched plan")
    args = parser.parse_args()
    device = resolve_device(args.device)
    maze = maze_paths(args.params, args.task, device)
    train_step = maze.training_step(device)
    model, ema = maze.bundle.diffusion, maze.bundle.ema.to(device).eval()

    gen = maze.generation
    planner = maze.planner(gen.sampler, gen.sampler_steps, device)
    starts, goals, seeds = maze.start.repeat(args.batch, 0), maze.goal.repeat(args.batch, 0), list(range(args.batch))
    paths = {
        f"training step (batch {maze.task.pretrain.batch_size})": (train_step, 10),
        f"batched plan ({args.batch} plans, {gen.sampler} {gen.sampler_steps})": (
            lambda: planner.sample(starts, goals, seeds),
            1,
        ),
    }
    matmul = matmul_gflops(device)
    print(f"device {device}, torch threads {torch.get_num_threads()}; a 2048 x 2048 float32 matrix product runs at "
          f"{matmul:.0f} GFLOP/s")  # fmt: skip
    for name, (fn, calls) in paths.items():
        flops = convolution_flops(fn)

        def stripped(fn: Callable[[], object] = fn) -> None:
            with without_norm_and_activation(model, ema):
                fn()

        ms = alternate({"network": fn, "stripped": stripped}, args.rounds, device, calls=calls)
        print(f"\n{name}: {ms['network']:.1f} ms per call; without GroupNorm and Mish {ms['stripped']:.1f} ms")
        print(f"  convolutions: {flops / 1e9:.2f} GFLOP per call, at least {flops / 1e6 / ms['stripped']:.0f} GFLOP/s")
        print(f"  bound_free_rest={ms['network'] / ms['stripped']:.2f}  (GroupNorm and Mish free)")


if __name__ == "__main__":
    main()
