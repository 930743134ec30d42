"""Training seeds as a dimension (smoke profile, real training, simulator, Parquet and MLflow): every training
stage runs once per entry of ``seeds``; seed 0 is the run a one-seed project makes; metrics files hold each seed's
metrics and their mean and standard error over seeds; the summary and report carry the per-seed points."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
import yaml
from smoke_project import narrow

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import Params, apply_profile, params_from_dict
from adaptdiffuser.derived_seeds import training_seed
from adaptdiffuser.evaluation import standard_error
from adaptdiffuser.intervals import interval
from adaptdiffuser.layout import (
    SUMMARY,
    model_dir,
    phase_metrics_path,
    report_plot_path,
    results_dir,
    score_table_path,
    selected_path,
    unseen_plot_path,
)
from adaptdiffuser.seed_metrics import over_seeds
from adaptdiffuser.stages.collect import run_collect
from adaptdiffuser.stages.common import phase_entries
from adaptdiffuser.stages.discriminate import run_discriminate
from adaptdiffuser.stages.evaluate import run_evaluate
from adaptdiffuser.stages.evaluate_unseen import run_evaluate_unseen
from adaptdiffuser.stages.finetune import run_finetune
from adaptdiffuser.stages.generate import run_generate
from adaptdiffuser.stages.pretrain import run_pretrain
from adaptdiffuser.stages.reference import run_reference
from adaptdiffuser.stages.report import (
    d4rl_table,
    gains_table,
    merge_summaries,
    rescaled_difference,
    rescaled_score,
    run_report,
    seed_points,
    unseen_series,
    unseen_table,
)
from adaptdiffuser.stages.summarize import build_summary, run_summarize, unseen_gain

REPO = Path(__file__).resolve().parents[1]
CPU = torch.device("cpu")
TASK = "maze2d-umaze"


def _params(root: Path, seeds: list[int]) -> Params:
    raw = yaml.safe_load(apply_profile("smoke", REPO / "profiles", root / "params.yaml").read_text())
    phases = {"phase1": {"previous": 0}}
    return params_from_dict(narrow(raw, [TASK], unseen_tasks=[TASK], evolve=TASK, seeds=seeds, phases=phases))


@pytest.fixture(scope="module")
def two_seeds(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Params]:
    """Phase 0 and phase 1 (with its control) for training seeds 0 and 3."""
    root = tmp_path_factory.mktemp("seeds")
    params = _params(root, [0, 3])
    run_collect(params, TASK, root, progress=False)
    run_reference(params, TASK, root, progress=False)
    run_pretrain(params, TASK, root, CPU, progress=False)
    run_evaluate(params, TASK, root, 0, CPU, progress=False)
    run_evaluate_unseen(params, TASK, root, 0, CPU, progress=False)
    run_generate(params, TASK, root, 1, CPU, progress=False)
    run_discriminate(params, TASK, root, 1, progress=False)
    run_finetune(params, TASK, root, 1, CPU, progress=False)
    run_finetune(params, TASK, root, 1, CPU, progress=False, control=True)
    run_evaluate(params, TASK, root, 1, CPU, progress=False)
    run_evaluate(params, TASK, root, 1, CPU, progress=False, control=True)
    run_evaluate_unseen(params, TASK, root, 1, CPU, progress=False)
    run_evaluate_unseen(params, TASK, root, 1, CPU, progress=False, control=True)
    return root, params


def _weights(path: Path) -> list[torch.Tensor]:
    return [p.detach().clone() for p in load_bundle(path).diffusion.parameters()]


def test_training_seed_zero_keeps_the_params_seed() -> None:
    assert training_seed(7, 0) == 7
    assert len({training_seed(7, s) for s in range(5)}) == 5 and training_seed(7, 1) == training_seed(7, 1)


def test_every_training_stage_runs_once_per_seed(two_seeds: tuple[Path, Params]) -> None:
    root, _ = two_seeds
    for phase, control in ((0, False), (1, False), (1, True)):
        a, b = (_weights(root / model_dir(TASK, phase, s, control)) for s in (0, 3))
        assert not all(torch.equal(x, y) for x, y in zip(a, b, strict=True)), (phase, control)
    assert load_bundle(root / model_dir(TASK, 1, 3)).config["seed"] == 3
    for seed in (0, 3):  # each seed's phase 1 trains on the data its own phase 0 generated
        assert (root / selected_path(TASK, 1, seed)).exists()
        assert (root / results_dir(TASK, 1, seed) / "episodes.parquet").exists()


def test_seed_zero_of_several_is_the_one_seed_run(two_seeds: tuple[Path, Params], tmp_path: Path) -> None:
    root, _ = two_seeds
    alone = _params(tmp_path, [0])
    (tmp_path / "data").symlink_to(root / "data")
    run_pretrain(alone, TASK, tmp_path, CPU, progress=False)
    ours, theirs = _weights(tmp_path / model_dir(TASK, 0, 0)), _weights(root / model_dir(TASK, 0, 0))
    assert all(torch.equal(x, y) for x, y in zip(ours, theirs, strict=True))


def test_metrics_are_aggregated_over_seeds(two_seeds: tuple[Path, Params]) -> None:
    root, _ = two_seeds
    for phase, control in ((0, False), (1, False), (1, True)):
        metrics = json.loads((root / phase_metrics_path(TASK, phase, control)).read_text())
        per_seed = [metrics["seeds"][s]["score_mean"] for s in ("0", "3")]
        assert metrics["n_seeds"] == 2 and metrics["stderr_over"] == "seeds"
        assert metrics["score_mean"] == pytest.approx(np.mean(per_seed))
        assert metrics["score_stderr"] == pytest.approx(abs(per_seed[0] - per_seed[1]) / 2)
        assert metrics["n_episodes"] == metrics["seeds"]["0"]["n_episodes"]  # episodes per seed
    control = json.loads((root / phase_metrics_path(TASK, 1, control=True)).read_text())
    gains = [control["seeds"][s]["gain_mean"] for s in ("0", "3")]
    assert control["gain_mean"] == pytest.approx(np.mean(gains))
    assert control["gain_stderr"] == pytest.approx(standard_error(gains))


def _table(root: Path, phase: int, seed: int, name: str, control: bool = False) -> dict:
    return pq.read_table(root / results_dir(TASK, phase, seed, control) / name).to_pydict()


def test_each_training_seed_plays_start_states_of_its_own_and_held_out_ones(two_seeds: tuple[Path, Params]) -> None:
    root, params = two_seeds
    ev = params.resolve(TASK).evaluate
    starts = {}
    for seed in (0, 3):
        main, held_out = _table(root, 0, seed, "episodes.parquet"), _table(root, 0, seed, "held_out.parquet")
        starts[seed] = list(zip(main["start_x"], main["start_y"], strict=True))
        assert len(main["score"]) == ev.episodes and len(held_out["score"]) == ev.held_out_episodes
        assert not set(zip(held_out["start_x"], held_out["start_y"], strict=True)) & set(starts[seed])
        # a phase and its control play the same start states, on both sets
        for name in ("episodes.parquet", "held_out.parquet"):
            phase1, control = _table(root, 1, seed, name), _table(root, 1, seed, name, control=True)
            assert (phase1["start_x"], phase1["goal_x"]) == (control["start_x"], control["goal_x"])
    assert starts[0] != starts[3]


def test_scores_and_gains_carry_their_interval_over_seeds_and_episodes(two_seeds: tuple[Path, Params]) -> None:
    root, params = two_seeds
    phase1 = json.loads((root / phase_metrics_path(TASK, 1)).read_text())
    control = json.loads((root / phase_metrics_path(TASK, 1, control=True)).read_text())
    for seed in ("0", "3"):  # each seed keeps its episodes; the gain is paired episode by episode
        ours, theirs = phase1["seeds"][seed], control["seeds"][seed]
        for where, name in ((ours, "episodes.parquet"), (ours["held_out"], "held_out.parquet")):
            assert where["score_per_episode"] == pytest.approx(_table(root, 1, int(seed), name)["score"])
        gains = np.subtract(ours["score_per_episode"], theirs["score_per_episode"])
        assert theirs["gain_per_episode"] == pytest.approx(gains)
        assert theirs["held_out"]["gain_per_episode"] == pytest.approx(
            np.subtract(ours["held_out"]["score_per_episode"], theirs["held_out"]["score_per_episode"])
        )
    expected = interval([control["seeds"][s]["gain_per_episode"] for s in ("0", "3")])
    assert expected["over"] == "seeds"  # two seeds: the t-interval of their means, beside the one over episodes
    assert (control["gain_ci_low"], control["gain_ci_high"]) == (expected["ci_low"], expected["ci_high"])
    assert (control["gain_episode_ci_low"], control["gain_episode_ci_high"]) == (
        expected["episode_ci_low"],
        expected["episode_ci_high"],
    )
    assert control["gain_ci_low"] <= control["gain_mean"] <= control["gain_ci_high"]
    assert "gain_per_episode" not in control and "score_per_episode" not in phase1["held_out"]
    assert phase1["score_ci_low"] <= phase1["score_mean"] <= phase1["score_ci_high"]
    wins = [np.mean(np.sign(control["seeds"][s]["gain_per_episode"]) / 2 + 0.5) for s in ("0", "3")]
    assert control["win_rate"] == pytest.approx(np.mean(wins)) and "probability_of_improvement" not in control
    summary = build_summary(params, root)[TASK]["phase_1"]
    assert summary["gain_ci_high"] == control["gain_ci_high"] and "gain_ci_high" not in summary["control"]
    assert summary["held_out"]["gain_mean"] == control["held_out"]["gain_mean"]
    assert summary["held_out"]["win_rate"] == control["held_out"]["win_rate"]
    assert "gain_mean" not in summary["control"]["held_out"] and "win_rate" not in summary["control"]
    row = next(line for line in gains_table({TASK: build_summary(params, root)[TASK]}) if "| 1 |" in line)
    assert f"[{control['gain_ci_low']:.1f}, {control['gain_ci_high']:.1f}]" in row
    assert f"[{control['score_ci_low']:.1f}, {control['score_ci_high']:.1f}]" in row  # the control's interval
    assert f"| {control['win_rate']:.2f} |" in row and f"| {control['held_out']['win_rate']:.2f} |" in row
    assert "one seed" not in row


def test_a_seeds_episodes_become_an_interval_over_episodes_alone_never_one_over_seeds() -> None:
    merged = over_seeds({0: {"score_mean": 2.0, "score_stderr": 0.5, "score_per_episode": [1.0, 2.0, 3.0]}})
    assert "score_per_episode" not in merged and merged["seeds"]["0"]["score_per_episode"] == [1.0, 2.0, 3.0]
    assert 1.0 <= merged["score_episode_ci_low"] < 2.0 < merged["score_episode_ci_high"] <= 3.0
    assert "score_ci_low" not in merged and "score_ci_high" not in merged


def test_a_one_seed_interval_is_tabled_as_one_over_episodes() -> None:
    """`adaptdiffuser gains` on a one-seed run: each interval reads "one seed: over episodes"; the control's
    interval and the held-out win rate have their cells."""
    rng = np.random.default_rng(0)
    model, control = rng.normal(60.0, 10.0, size=40), rng.normal(58.0, 10.0, size=40)

    def seed_entry(scores: np.ndarray, **more: object) -> dict:
        return {"score_mean": float(scores.mean()), "score_stderr": standard_error(scores), "return_mean": 0.0,
                "n_episodes": 40, "score_per_episode": list(scores), **more}  # fmt: skip

    gain = {"gain_mean": float((model - control).mean()), "gain_stderr": 1.0, "win_rate": 0.55}
    held_out = {"gain_mean": 1.5, "gain_per_episode": list(model - control), "win_rate": 0.6}
    phase1 = over_seeds({0: seed_entry(model)})
    phase1.update(gain, control=over_seeds({0: seed_entry(control)}), held_out=held_out)
    phase1["gain_episode_ci_low"], phase1["gain_episode_ci_high"] = -1.0, 5.0
    held_out["gain_episode_ci_low"], held_out["gain_episode_ci_high"] = -2.0, 6.0
    row = gains_table({"maze": {"phase_1": phase1}})[2]
    c = phase1["control"]
    assert f"[{c['score_episode_ci_low']:.1f}, {c['score_episode_ci_high']:.1f}] (one seed: over episodes)" in row
    assert "[-1.0, 5.0] (one seed: over episodes) | 0.55 | 1.5 [-2.0, 6.0] (one seed: over episodes) | 0.60 |" in row
    assert row.count("one seed: over episodes") == 4 and "| 1 x 40 |" in row


def test_summary_and_report_show_each_seed(two_seeds: tuple[Path, Params], tmp_path: Path) -> None:
    root, params = two_seeds
    summary = run_summarize(params, root)[TASK]
    reference = json.loads((root / f"metrics/tasks/{TASK}/reference.json").read_text())
    assert summary["reference"] == {key: reference[key] for key in ("r_min", "r_max", "d4rl_r_min", "d4rl_r_max")}
    assert (summary["reference"]["d4rl_r_min"], summary["reference"]["d4rl_r_max"]) == (23.85, 161.86)  # U-Maze's
    phase1 = summary["phase_1"]
    assert set(phase1["per_seed"]) == {"0", "3"} and "seeds" not in phase1
    assert phase1["control"]["n_seeds"] == 2
    disc = phase1["discriminator"]  # each seed's counts, averaged
    assert disc["generated"] == params.phase(1).generate.tasks and 0 < disc["kept"] <= disc["tracked"]
    coin = json.loads((root / f"metrics/tasks/{TASK}/phase1-unseen.json").read_text())
    rates = [coin["seeds"][s]["gold_coin"]["both_rate"] for s in ("0", "3")]
    assert phase1["gold_coin"]["both_rate"] == pytest.approx(np.mean(rates))
    assert phase1["gold_coin"]["both_rate_stderr"] == pytest.approx(standard_error(rates))
    control_coin = json.loads((root / f"metrics/tasks/{TASK}/phase1-control-unseen.json").read_text())
    assert summary["unseen_task"] == "gold_coin" and phase1["control"]["gold_coin"] == control_coin["gold_coin"]
    assert control_coin["n_seeds"] == 2 and "gold_coin" not in summary["phase_0"].get("control", {})
    coin_gain = phase1["unseen_gain"]["score"]  # the gold coin's score, phase minus control seed by seed
    differences = [
        coin["seeds"][s]["gold_coin"]["score_mean"] - control_coin["seeds"][s]["gold_coin"]["score_mean"]
        for s in ("0", "3")
    ]
    assert coin_gain["per_seed"] == dict(zip(("0", "3"), differences, strict=True))
    assert coin_gain["gain_stderr"] == pytest.approx(standard_error(differences))
    assert "unseen_gain" not in summary["phase_0"]
    assert phase1["gain_mean"] == pytest.approx(np.mean([e["gain_mean"] for e in phase1["per_seed"].values()]))
    points = seed_points(summary)
    assert points["score_mean"][0] == [0, 0, 1, 1] and points["control_score_mean"][0] == [1, 1]
    rows = run_report(root)[TASK]
    assert [r["n_seeds"] for r in rows] == [2, 2]
    # a kept summary draws its figure and table again, wherever it is asked to
    kept = tmp_path / "kept.json"
    shutil.copy(root / SUMMARY, kept)
    assert run_report(root, kept, tmp_path / "again")[TASK] == rows
    again = tmp_path / "again"
    assert (again / report_plot_path(TASK)).stat().st_size > 0
    assert (again / score_table_path(TASK)).read_text() == (root / score_table_path(TASK)).read_text()


def test_scores_are_tabled_on_d4rl_constants_where_the_task_gives_them() -> None:
    """A score on our (R_min, R_max) is the same return normalized on D4RL's; gains and standard errors scale by the
    ratio of the ranges; tasks without D4RL's constants (or without a reference) add no rows."""
    # Maze2D Medium's reference: ours 16.10 / 447.64, D4RL's 13.13 / 277.39 (docs/maze2d.md)
    ours, theirs = (16.10, 447.64), (13.13, 277.39)
    assert rescaled_score(72.0, ours, theirs) == pytest.approx(118.70, abs=0.01)
    assert rescaled_score(0.0, ours, theirs) == pytest.approx(100 * (16.10 - 13.13) / (277.39 - 13.13))
    assert rescaled_difference(1.4, ours, theirs) == pytest.approx(1.4 * 431.54 / 264.26)
    reference = {"r_min": 16.10, "r_max": 447.64, "d4rl_r_min": 13.13, "d4rl_r_max": 277.39}
    summary = {
        "maze": {
            "reference": reference,
            "phase_0": {"score_mean": 72.0, "score_stderr": 1.4},
            "phase_1": {
                "score_mean": 74.0,
                "score_stderr": 1.0,
                "control": {"score_mean": 73.0, "score_stderr": 0.5},
                "gain_mean": 1.0,
                "gain_stderr": 0.2,
            },
        },
        "hopper": {"reference": {"r_min": -20.0, "r_max": 3234.0}, "phase_0": {"score_mean": 30.0}},
        "older": {"phase_0": {"score_mean": 30.0}},
    }
    for entry in summary.values():
        for _, phase in phase_entries(entry):  # the fields every phase entry has
            phase.setdefault("return_mean", 0.0)
            phase.setdefault("n_episodes", 50)
    assert d4rl_table(summary)[2:] == [
        "| maze | 0 | 118.7 ± 2.3 |  |  |",
        "| maze | 1 | 122.0 ± 1.6 | 120.3 ± 0.8 | 1.6 ± 0.3 |",
    ]
    assert d4rl_table({"hopper": summary["hopper"]}) == []


def test_merged_summaries_keep_every_run_and_recipe_of_a_task() -> None:
    """`adaptdiffuser gains A.json B.json`: a run's phase-0-only entry of a task another file evolved from the same
    phase 0 gives way to the evolved one; entries of one task that differ otherwise (two recipes; two runs' phase 0)
    are each kept, named by their file, never one overwriting the other."""

    def phase(score: float, gain: float | None = None) -> dict:
        entry = {"score_mean": score, "score_stderr": 0.1, "return_mean": 0.0, "n_episodes": 50, "n_seeds": 3}
        if gain is not None:
            entry |= {
                "control": {"score_mean": score - gain, "score_stderr": 0.1},
                "gain_mean": gain,
                "gain_stderr": 0.1,
            }
        return entry

    base = phase(81.2)
    plans = {"maze": {"phase_0": base, "phase_1": phase(80.9, -0.2)}, "hopper": {"phase_0": phase(22.2)}}
    rollouts = {"maze": {"phase_0": base, "phase_1": phase(81.5, 0.4)}}
    hopper = {"hopper": {"phase_0": phase(33.1), "phase_1": phase(31.5, -1.2)}, "maze": {"phase_0": base}}
    merged = merge_summaries([("plans", plans), ("rollouts", rollouts), ("hopper", hopper)])
    assert merged == {
        "maze (plans)": plans["maze"],
        "maze (rollouts)": rollouts["maze"],
        "hopper (plans)": plans["hopper"],  # another run's phase 0 (22.2, not 33.1): both shown
        "hopper (hopper)": hopper["hopper"],
    }
    rows = gains_table(merged)[2:]
    assert "| maze (plans) | 1 | 80.9 ± 0.1 | 81.1 ± 0.1 | -0.2 ± 0.1 |  |  |  | 3 x 50 |" in rows[1]
    assert "| maze (rollouts) | 1 | 81.5 ± 0.1 | 81.1 ± 0.1 | 0.4 ± 0.1 |  |  |  | 3 x 50 |" in rows[3]
    # the evolved entry wins over a phase-0-only one of the same phase 0, whichever file comes first
    same_start = {"hopper": {"phase_0": phase(33.1)}}
    for order in ([("a", same_start), ("b", hopper)], [("b", hopper), ("a", same_start)]):
        assert merge_summaries(order)["hopper"] == hopper["hopper"]
    assert merge_summaries([("a", plans), ("a again", plans)]) == plans


def test_unseen_task_scores_are_tabled_against_the_control() -> None:
    """A task's unseen-task scores get one row per phase and score (the headline and, e.g., per setup): the phase,
    its control and the gain; the gain is the seed-by-seed one of the summary (± over seeds) where it has one,
    otherwise the difference of the means with the standard errors added in quadrature, marked unpaired (no ``±``
    where the family reports none); a task without an unseen task adds no table."""
    place = {"score_mean": 30.0, "score_stderr": 3.0, "setup1_score_mean": 40.0, "setup1_score_stderr": 6.0}
    summary = {
        "arm": {
            "unseen_task": "place",
            "phase_1": {
                "score_mean": 1.0,
                "place": place,
                "control": {"place": {"score_mean": 26.0, "score_stderr": 4.0, "setup1_score_mean": 34.0}},
                "unseen_gain": {"setup1_score": {"gain_mean": 6.0, "gain_stderr": 1.5, "per_seed": {}}},
            },
            "phase_0": {"score_mean": 2.0, "place": {"score_mean": 20.0, "score_stderr": 2.0}},
        },
        "maze": {"unseen_task": "coin", "phase_0": {"score_mean": 80.0, "coin": {"score_mean": 40.0}}},
        "hopper": {"phase_0": {"score_mean": 30.0, "score_stderr": 1.0}},
    }
    assert unseen_table(summary)[2:] == [
        "| arm | 0 | place | score | 20.0 ± 2.0 |  |  |",
        "| arm | 1 | place | score | 30.0 ± 3.0 | 26.0 ± 4.0 | 4.0 ± 5.0 (unpaired) |",
        "| arm | 1 | place | setup1_score | 40.0 ± 6.0 | 34.0 | 6.0 ± 1.5 |",
        "| maze | 0 | coin | score | 40.0 |  |  |",
    ]
    assert unseen_table({"hopper": summary["hopper"]}) == []


def test_the_unseen_gain_is_taken_seed_by_seed() -> None:
    """Each score of the unseen task gets the phase's gain over its control seed by seed (the same training seed's
    pair), mean and standard error over the seeds; with one seed the standard error is unknown (None)."""

    def metrics(per_seed: dict[str, tuple[float, float]]) -> dict:
        seeds = {
            s: {"place": {"score_mean": a, "setup2_score_mean": b, "n_episodes": 40}} for s, (a, b) in per_seed.items()
        }
        return {"place": {"score_mean": 0.0, "setup2_score_mean": 0.0, "n_episodes": 40}, "seeds": seeds}

    phase = metrics({"0": (10.0, 5.0), "1": (20.0, 0.0), "2": (6.0, 2.5)})
    control = metrics({"0": (4.0, 5.0), "1": (21.0, 2.5), "2": (0.0, 0.0)})
    gain = unseen_gain(phase, control, "place")
    assert set(gain) == {"score", "setup2_score"}
    assert gain["score"]["per_seed"] == {"0": 6.0, "1": -1.0, "2": 6.0}
    assert gain["score"]["gain_mean"] == pytest.approx(11.0 / 3)
    assert gain["score"]["gain_stderr"] == pytest.approx(standard_error([6.0, -1.0, 6.0]))
    assert gain["setup2_score"]["per_seed"] == {"0": 0.0, "1": -2.5, "2": 2.5}
    one = unseen_gain(metrics({"0": (10.0, 5.0)}), metrics({"0": (4.0, 5.0)}), "place")
    assert one["score"] == {"gain_mean": 6.0, "gain_stderr": None, "per_seed": {"0": 6.0}}


def test_over_seeds_with_one_seed_changes_nothing_but_adds_the_seed() -> None:
    metrics = {"score_mean": 50.0, "score_stderr": 2.0, "n_episodes": 10, "gold_coin": {"both_rate": 0.5}}
    merged = over_seeds({0: metrics})
    assert {k: merged[k] for k in metrics} == metrics
    assert merged["stderr_over"] == "episodes" and merged["n_seeds"] == 1 and merged["seeds"] == {"0": metrics}


def test_a_number_a_seed_could_not_measure_is_left_out_of_the_mean_over_seeds() -> None:
    """A seed whose coin episodes never reached both has no steps to average (None): the mean over seeds is that of
    the seeds that measured it, not pulled down by a stand-in value; None where no seed measured it."""

    def seed(steps: float | None, rate: float) -> dict:
        return {"gold_coin": {"steps_to_goal_mean": steps, "both_rate": rate, "never": None}, "score_mean": rate}

    merged = over_seeds({0: seed(120.0, 0.5), 1: seed(None, 0.0), 2: seed(140.0, 0.25)})
    coin = merged["gold_coin"]
    assert coin["steps_to_goal_mean"] == pytest.approx(130.0)
    assert coin["both_rate"] == pytest.approx(0.25) and coin["never"] is None
    assert merged["seeds"]["1"]["gold_coin"]["steps_to_goal_mean"] is None  # each seed's own, as it measured
    one = over_seeds({0: {"x_mean": 2.0, "x_stderr": 0.1}, 1: {"x_mean": None, "x_stderr": None}})
    assert one["x_mean"] == 2.0 and one["x_stderr"] is None  # no spread over one measured seed


def test_a_summary_with_its_dataset_draws_the_datasets_score(tmp_path: Path) -> None:
    """The figure of a task whose summary gives its dataset's score shows it (a dashed line): does the planner beat
    its data? Without it, the figure is the plain score by phase."""
    phase0 = {"score_mean": 33.0, "score_stderr": 0.2, "return_mean": 3800.0, "n_episodes": 10}
    plain = tmp_path / "plain.json"
    plain.write_text(json.dumps({"cheetah": {"phase_0": phase0}}))
    with_data = tmp_path / "data.json"
    with_data.write_text(json.dumps({"cheetah": {"phase_0": phase0, "dataset": {"score_mean": 20.0}}}))
    rows = run_report(tmp_path, plain, tmp_path / "plain")["cheetah"]
    assert run_report(tmp_path, with_data, tmp_path / "data")["cheetah"] == rows  # the table is the phases'
    drawn = [(tmp_path / name / report_plot_path("cheetah")).read_bytes() for name in ("plain", "data")]
    assert drawn[0] != drawn[1]


def test_an_unseen_task_gets_its_own_figure_of_each_score_by_phase(tmp_path: Path) -> None:
    """A task whose summary names an unseen task (KUKA's pick-and-place: a score and one per setup) gets a second
    figure, one panel per score, each phase beside its control; a task without one gets none."""

    def place(mean: float, setup1: float, setup2: float) -> dict:
        return {
            "n_episodes": 40,
            "score_mean": mean,
            "score_stderr": 0.5,
            "setup1_score_mean": setup1,
            "setup1_score_stderr": 0.4,
            "setup2_score_mean": setup2,
            "setup2_score_stderr": None,  # a family that reports no spread: drawn without a bar
        }

    stacking = {"score_mean": 60.0, "score_stderr": 5.0, "return_mean": 1.8, "n_episodes": 50}
    task = {
        "unseen_task": "pick_place",
        "phase_0": {**stacking, "pick_place": place(1.0, 0.0, 2.0)},
        "phase_1": {
            **stacking,
            "pick_place": place(3.0, 4.0, 2.0),
            "control": {**stacking, "pick_place": place(0.5, 1.0, 0.0)},
        },
    }
    series = unseen_series(task)
    assert list(series) == ["score", "setup1_score", "setup2_score"]
    assert series["setup1_score"] == {
        "phases": [0, 1],
        "means": [0.0, 4.0],
        "stderrs": [0.4, 0.4],
        "control_phases": [1],
        "control_means": [1.0],
        "control_stderrs": [0.4],
    }
    assert series["setup2_score"]["stderrs"] == [0.0, 0.0]
    summary = tmp_path / "summary.json"
    summary.write_text(json.dumps({"arm": task, "cheetah": {"phase_0": stacking}}))
    run_report(tmp_path, summary, tmp_path / "out")
    assert (tmp_path / "out" / unseen_plot_path("arm")).stat().st_size > 0
    assert (tmp_path / "out" / report_plot_path("cheetah")).exists()
    assert unseen_series({"phase_0": stacking}) == {}
    assert not (tmp_path / "out" / unseen_plot_path("cheetah")).exists()
