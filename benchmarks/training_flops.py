"""The training compute of each profile's phase 0 (printed, never asserted): the U-Net's parameters, its forward
FLOPs per trajectory (counted by ``torch.utils.flop_counter`` on one forward pass at the task's horizon) and the
whole pretraining's FLOPs, taken as three forward passes per trajectory (forward and backward) times steps x batch x
gradient accumulation. With a measured training time on one machine it says what another scale would cost there:
the ratio of two profiles' FLOPs is the ratio of their training times at equal throughput (larger shapes usually
run at a higher throughput, so the ratio is an upper bound).

    python benchmarks/training_flops.py [PROFILE ...]      (default: quick quick-kuka paper-kuka paper-large)
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

from adaptdiffuser.config import apply_profile, load_params
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.models.unet import TemporalUnet

PROFILES = Path(__file__).resolve().parents[1] / "profiles"


def phase0_compute(profile: str) -> dict[str, float | str]:
    """Parameters, forward FLOPs per trajectory and pretraining FLOPs of ``profile``'s first task."""
    with tempfile.TemporaryDirectory() as tmp:
        params = load_params(apply_profile(profile, PROFILES, Path(tmp) / "params.yaml"))
    task = params.resolve(params.tasks[0])
    sim = get_family(task.family).make_simulator(task)
    channels = sim.obs_dim + sim.act_dim
    net = TemporalUnet(
        channels, dim=task.model.dim, dim_mults=tuple(task.model.dim_mults), kernel_size=task.model.kernel_size
    )
    x = torch.zeros(1, task.diffusion.horizon, channels)
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        net(x, torch.zeros(1, dtype=torch.long))
    forward = counter.get_total_flops()
    cfg = task.pretrain
    samples = cfg.steps * cfg.batch_size * cfg.grad_accum
    return {
        "profile": profile,
        "task": task.name,
        "parameters_m": sum(p.numel() for p in net.parameters()) / 1e6,
        "forward_gflop": forward / 1e9,
        "trajectories_m": samples / 1e6,
        "pretrain_pflop": 3 * forward * samples / 1e15,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("profiles", nargs="*", default=["quick", "quick-kuka", "paper-kuka", "paper-large"])
    args = parser.parse_args()
    rows = [phase0_compute(name) for name in args.profiles]
    print(f"{'profile':<18}{'task':<16}{'params (M)':>11}{'fwd GFLOP':>11}{'traj. (M)':>11}{'PFLOP':>10}{'x first':>9}")
    for row in rows:
        ratio = row["pretrain_pflop"] / rows[0]["pretrain_pflop"]
        print(
            f"{row['profile']:<18}{row['task']:<16}{row['parameters_m']:>11.2f}{row['forward_gflop']:>11.3f}"
            f"{row['trajectories_m']:>11.2f}{row['pretrain_pflop']:>10.2f}{ratio:>9.1f}"
        )


if __name__ == "__main__":
    main()
