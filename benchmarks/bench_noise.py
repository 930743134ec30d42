"""Noise draws per second for a batch of rows, side by side in one run: the counter-based ``RowNoise`` (one
vectorized Philox pass per draw) against the scheme it replaced (one ``torch.Generator`` per row, one ``randn``
call per row and draw, stacked), on the same shapes. Rounds alternate so a noisy neighbour slows both alike;
the median round is printed (figures are printed, never asserted).

The default shape is a value-guided locomotion decision of quick-locomotion at Diffuser's scale: 50 episodes x 64
samples = 3 200 rows, horizon 32, Hopper's 14 channels (3 actions + 11 observations).

    python benchmarks/bench_noise.py [--rows 3200] [--horizon 32] [--channels 14] [--rounds 7] [--device cpu]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from adaptdiffuser.diffusion.noise import RowNoise


class PerRowGenerators:
    """The earlier scheme, kept here only as the benchmark's baseline: row ``i`` draws from its own generator."""

    def __init__(self, seeds: list[int], device: torch.device) -> None:
        self.device = device
        self.generators = [torch.Generator(device=device).manual_seed(s) for s in seeds]

    def randn(self, shape: tuple[int, ...]) -> torch.Tensor:
        return torch.stack([torch.randn(shape, device=self.device, generator=g) for g in self.generators])


def _time(make, shape: tuple[int, ...], draws: int, device: torch.device) -> float:
    """Seconds for ``draws`` draws of ``shape`` per row (the noise source built once, as a sampler does)."""
    noise = make()
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(draws):
        noise.randn(shape)
    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=3200)
    parser.add_argument("--horizon", type=int, default=32)
    parser.add_argument("--channels", type=int, default=14)
    parser.add_argument("--draws", type=int, default=20, help="draws per round (a 20-step DDPM chain)")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    device = torch.device(args.device)
    seeds = list(range(1000, 1000 + args.rows))
    shape = (args.horizon, args.channels)
    paths = {
        "per-row generators": lambda: PerRowGenerators(seeds, device),
        "counter-based": lambda: RowNoise(seeds, device),
    }
    for make in paths.values():  # warm-up: allocator, kernels
        _time(make, shape, 1, device)
    times: dict[str, list[float]] = {name: [] for name in paths}
    for _ in range(args.rounds):
        for name, make in paths.items():
            times[name].append(_time(make, shape, args.draws, device))
    print(f"{args.rows} rows x {shape}, {args.draws} draws per round, median of {args.rounds} rounds, "
          f"{device}, {torch.get_num_threads()} torch threads")  # fmt: skip
    normals = args.rows * args.horizon * args.channels * args.draws
    rates = {}
    for name, seconds in times.items():
        median = statistics.median(seconds)
        rates[name] = normals / median
        print(f"  {name:24s} {median * 1e3 / args.draws:8.2f} ms per draw  {rates[name] / 1e6:8.1f} M normals/s")
    speedup = rates["counter-based"] / rates["per-row generators"]
    print(f"speedup_noise={speedup:.2f}")


if __name__ == "__main__":
    main()
