"""Behaviour data of a stated quality whatever path PPO takes: the collect recipe under variations that change PPO's
path as another CPU's rounding would (another seed, another torch thread count), per locomotion task.

For each task and variation: train the behaviour policy with the band search (``medium_score +- medium_band``),
which records the ``medium`` dataset, and print the chosen checkpoint, the score the search recorded (the dataset's),
the stored dataset's mean normalized score over its episodes (as the reference stage reports it), how often training
went back, and the time (printed, never asserted). Writes every figure as JSON after each variation; run again with
the same ``--out``, it skips the variations already there (a stopped run goes on).

    python benchmarks/bench_behaviour_band.py [--tasks hopper-medium walker2d-medium halfcheetah-medium]
        [--variations 0:2 0:1 1:2] [--dataset-steps 200000] [--max-train-steps 1000000] [--algorithm ppo] [--quiet]

``--algorithm sac`` (or ``td3``) trains the behaviour policy with that stable-baselines3 algorithm instead of PPO
(``task.<name>.behaviour.algorithm``): D4RL's own medium policies are SAC's.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from adaptdiffuser.errors import StageError
from adaptdiffuser.families.locomotion.behaviour import collect_locomotion_dataset
from adaptdiffuser.families.locomotion.family import episode_returns
from adaptdiffuser.families.locomotion.params import BehaviourSettings
from adaptdiffuser.families.locomotion.reference import normalized_score
from adaptdiffuser.families.locomotion.simulator import env_id_of
from adaptdiffuser.io import atomic_path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["hopper-medium", "walker2d-medium", "halfcheetah-medium"])
    parser.add_argument("--variations", nargs="+", default=["0:2", "0:1", "1:2"], help="seed:threads")
    parser.add_argument("--dataset-steps", type=int, default=200_000)
    parser.add_argument("--max-train-steps", type=int, default=BehaviourSettings().max_train_steps)
    parser.add_argument("--algorithm", default="ppo", choices=["ppo", "sac", "td3"])
    parser.add_argument("--out", default="bench_behaviour_band.json")
    parser.add_argument("--quiet", action="store_true", help="no progress bars (training, recording)")
    args = parser.parse_args()
    out = Path(args.out)
    results: list[dict] = json.loads(out.read_text()) if out.exists() else []  # a stopped run goes on from there
    done = {(r["task"], r.get("algorithm", "ppo"), r["seed"], r["threads"]) for r in results}
    for task in args.tasks:
        for variation in args.variations:
            seed, threads = (int(x) for x in variation.split(":"))
            if (task, args.algorithm, seed, threads) in done:
                print(f"{task} seed {seed} threads {threads}: already in {out}", flush=True)
                continue
            settings = BehaviourSettings(
                algorithm=args.algorithm,
                seed=seed,
                torch_threads=threads,
                dataset_steps=args.dataset_steps,
                max_train_steps=args.max_train_steps,
            )
            band = [settings.medium_score - settings.medium_band, settings.medium_score + settings.medium_band]
            row: dict = {"task": task, "algorithm": args.algorithm, "seed": seed, "threads": threads, "band": band}
            start = time.perf_counter()
            with tempfile.TemporaryDirectory() as tmp:
                try:
                    traj = collect_locomotion_dataset(task, Path(tmp), settings, progress=not args.quiet)
                except StageError as err:
                    row |= {"error": str(err), "wall_s": time.perf_counter() - start}
                    print(f"{task} seed {seed} threads {threads}: {err}", flush=True)
                    results.append(row)
                    _save(out, results)
                    continue
                summary = json.loads((Path(tmp) / "behaviour.json").read_text())
            scores = normalized_score(episode_returns(traj), env_id_of(task))  # as the reference stage scores it
            medium = summary["medium"]
            row |= {"chosen_steps": medium["steps"], "policy_score": medium["normalized_score"],
                    "rewinds": medium["rewinds"], "spent_steps": medium["spent_steps"],
                    "dataset_score": float(scores.mean()), "dataset_episodes": int(len(scores)),
                    "dataset_stderr": float(scores.std(ddof=1) / np.sqrt(len(scores))) if len(scores) > 1 else 0.0,
                    "wall_s": time.perf_counter() - start, "curve": summary["curve"]}  # fmt: skip
            inside = row["band"][0] <= row["dataset_score"] <= row["band"][1]
            print(
                f"{task} seed {seed} threads {threads}: policy {medium['normalized_score']:.1f} at "
                f"{medium['steps']} steps ({medium['rewinds']} rewinds, {medium['spent_steps']} spent); dataset "
                f"{row['dataset_score']:.1f} +- {row['dataset_stderr']:.1f} over {len(scores)} episodes "
                f"({'inside' if inside else 'OUTSIDE'} {row['band'][0]:g}..{row['band'][1]:g}); "
                f"{row['wall_s']:.0f} s",
                flush=True,
            )
            results.append(row)
            _save(out, results)


def _save(out: Path, results: list[dict]) -> None:
    with atomic_path(out) as tmp:  # a kill mid-write leaves the last whole file
        tmp.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
