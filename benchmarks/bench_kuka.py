"""KUKA simulator speed: physics steps per second, plan steps per second (one planned state executed = ``substeps``
physics steps plus the observation), and the scripted demonstrator's plan steps per second (with inverse
kinematics). Prints machine-readable lines at the end.

    python benchmarks/bench_kuka.py [--steps 2000] [--substeps 10]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from adaptdiffuser.families.kuka.demonstrator import record_demonstration
from adaptdiffuser.families.kuka.params import KukaTaskParams
from adaptdiffuser.families.kuka.simulator import KukaSimulator


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="plan steps to time")
    parser.add_argument("--substeps", type=int, default=10)
    args = parser.parse_args()
    settings = KukaTaskParams(control={"substeps": args.substeps})
    sim = KukaSimulator(settings)
    rng = np.random.default_rng(0)
    obs = sim.reset(rng)

    start = time.perf_counter()
    for _ in range(args.steps * args.substeps):
        sim.scene.client.stepSimulation()
    physics = args.steps * args.substeps / (time.perf_counter() - start)

    obs = sim.reset(rng)
    commands = np.concatenate([obs[:7] + rng.uniform(-0.3, 0.3, (args.steps, 7)), np.zeros((args.steps, 4))], axis=1)
    start = time.perf_counter()
    for command in commands:
        sim.step(command)
    plan = args.steps / (time.perf_counter() - start)

    start, recorded = time.perf_counter(), 0
    while recorded < args.steps:
        recorded += len(record_demonstration(sim, rng, settings)) - 1
    demo = recorded / (time.perf_counter() - start)
    print(f"physics steps/s {physics:,.0f}; plan steps/s ({args.substeps} substeps) {plan:,.0f}", end="")
    print(f"; demonstrator plan steps/s {demo:,.0f}")
    print(f"kuka_physics_steps_per_s={physics:.0f}")
    print(f"kuka_plan_steps_per_s={plan:.0f}")
    print(f"kuka_demonstrator_steps_per_s={demo:.0f}")


if __name__ == "__main__":
    main()
