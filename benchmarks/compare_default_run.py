"""The default pipeline of two commits, run one after the other on this machine: wall clock, CPU time and phase-0
score of each (printed; ``--out`` also writes them as JSON).

Each commit is cloned from this repository into a temporary folder and runs ``dvc repro`` with its own
``params.yaml`` (the default profile of its day) and its own ``src/`` ahead of the installed package, under the
current environment (so both commits must run with today's ``requirements.lock``). The runs are sequential, never
side by side, so neither slows the other; CPU time is that of the ``dvc repro`` process tree (all threads).

    python benchmarks/compare_default_run.py 4387df0 HEAD [--out figures.json] [--keep DIR]

Run it on an otherwise idle machine: each run takes minutes to tens of minutes on 2 cores. ``--profile NAME``
(``--tiny``) switches both workspaces to another profile first, with each commit's own ``adaptdiffuser profile``;
``--profile quick --tiny`` checks the comparison itself in a few minutes (commits that have ``--tiny``).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def clone_at(commit: str, dest: Path) -> str:
    """Clone this repository into ``dest`` at ``commit``; return the full hash."""
    subprocess.run(["git", "clone", "-q", str(REPO), str(dest)], check=True)
    if subprocess.run(["git", "-C", str(dest), "checkout", "-q", commit], capture_output=True).returncode != 0:
        sys.exit(f"{commit!r} is not a commit of {REPO}")
    return subprocess.run(
        ["git", "-C", str(dest), "rev-parse", "HEAD"], check=True, capture_output=True, text=True
    ).stdout.strip()


def machine() -> str:
    """The CPU in words: model name, cores, and whether it has AVX-512 (training speed differs 3-4x by it)."""
    info = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    model = next((line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith("model name")), "?")
    avx = "AVX-512" if "avx512f" in info else "no AVX-512"
    return f"{model}, {os.cpu_count()} cores, {avx}"


def children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def workspace_env(workspace: Path) -> dict[str, str]:
    """The environment that runs ``workspace``'s own sources ahead of the installed package."""
    env = dict(os.environ, PYTHONPATH=str(workspace / "src"))
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    return env


def switch_profile(workspace: Path, name: str, tiny: bool) -> None:
    """``adaptdiffuser profile NAME [--tiny]`` with the workspace's own command."""
    command = ["adaptdiffuser", "profile", name] + (["--tiny"] if tiny else [])
    subprocess.run(command, cwd=workspace, env=workspace_env(workspace), check=True, stdout=subprocess.DEVNULL)


def run_default(workspace: Path, log: Path) -> dict[str, float]:
    """``dvc repro`` in ``workspace`` with its own sources first on the path; wall and CPU seconds."""
    env = workspace_env(workspace)
    cpu0, wall0 = children_cpu_s(), time.perf_counter()
    with log.open("w") as out:
        done = subprocess.run(["dvc", "repro"], cwd=workspace, env=env, stdout=out, stderr=subprocess.STDOUT)
    wall, cpu = time.perf_counter() - wall0, children_cpu_s() - cpu0
    if done.returncode != 0:
        sys.exit(f"dvc repro failed in {workspace} (exit {done.returncode}); its output: {log}")
    return {"wall_s": round(wall, 1), "cpu_s": round(cpu, 1)}


def phase_scores(workspace: Path) -> dict[str, dict[str, float]]:
    """Each task's phase scores (mean, standard error, gain over the control) from ``metrics/summary.json``."""
    summary = json.loads((workspace / "metrics" / "summary.json").read_text())
    scores: dict[str, dict[str, float]] = {}
    for task, phases in summary.items():
        for phase, entry in sorted(phases.items()):
            if not phase.startswith("phase_") or "score_mean" not in entry:
                continue
            row = {"score_mean": entry["score_mean"], "score_stderr": entry["score_stderr"]}
            if "gain_mean" in entry:
                row |= {"gain_mean": entry["gain_mean"], "gain_stderr": entry["gain_stderr"]}
            scores[f"{task}/{phase}"] = row
    return scores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("commits", nargs=2, metavar="COMMIT", help="the earlier commit, then the later one")
    parser.add_argument("--out", type=Path, help="also write the figures here as JSON")
    parser.add_argument("--keep", type=Path, help="clone into this (new) folder and keep the workspaces")
    parser.add_argument("--profile", help="switch both workspaces to this profile first (default: their params.yaml)")
    parser.add_argument("--tiny", action="store_true", help="with --profile: the profile at tiny scale")
    args = parser.parse_args()
    if args.tiny and args.profile is None:
        sys.exit("--tiny needs --profile NAME")
    if shutil.which("dvc", path=str(Path(sys.executable).parent)) is None:
        sys.exit(f"no dvc beside {sys.executable}: run this with the project's environment (.venv/bin/python)")
    if args.keep is not None and args.keep.exists():
        sys.exit(f"--keep {args.keep} exists already: name a new folder")
    root = args.keep or Path(tempfile.mkdtemp(prefix="default-run-"))
    root.mkdir(parents=True, exist_ok=True)
    figures: list[dict] = []
    cpu, day = machine(), time.strftime("%Y-%m-%d", time.gmtime())
    try:
        for i, commit in enumerate(args.commits):
            workspace = root / f"run{i}"
            full = clone_at(commit, workspace)
            if args.profile is not None:
                switch_profile(workspace, args.profile, args.tiny)
            print(f"{commit} ({full[:7]}): dvc repro in {workspace} ...", flush=True)
            times = run_default(workspace, root / f"run{i}.log")
            figures.append(
                {
                    "name": commit,
                    "commit": full,
                    "profile": args.profile,
                    "machine": cpu,
                    "date": day,
                    **times,
                    "phases": phase_scores(workspace),
                }
            )
            print(f"  wall {times['wall_s'] / 60:.1f} min, CPU {times['cpu_s'] / 60:.1f} min", flush=True)
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    before, after = figures
    wall_ratio, cpu_ratio = after["wall_s"] / before["wall_s"], after["cpu_s"] / before["cpu_s"]
    print(f"\nlater / earlier: wall {wall_ratio:.2f}x, CPU {cpu_ratio:.2f}x")
    for entry in figures:
        for key, row in entry["phases"].items():
            gain = f", gain {row['gain_mean']:+.2f} +- {row['gain_stderr']:.2f}" if "gain_mean" in row else ""
            print(f"{entry['name']:>10}  {key}: {row['score_mean']:.2f} +- {row['score_stderr']:.2f}{gain}")
    if args.out is not None:
        args.out.write_text(json.dumps(figures, indent=1, sort_keys=True) + "\n")


if __name__ == "__main__":
    main()
