"""The config loader: the repo's params and profiles, rejected values naming their key, and the `check` CLI."""

from __future__ import annotations

import dataclasses
import pickle
import shutil
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from adaptdiffuser.cli import app
from adaptdiffuser.config import (
    ConfigError,
    EnvParams,
    Params,
    apply_profile,
    deep_merge,
    describe,
    load_params,
    set_dotted,
    stage_names,
)

REPO = Path(__file__).resolve().parents[1]
PROFILES = REPO / "profiles"
PAPER = {"paper-umaze": ("umaze", 128), "paper-medium": ("medium", 256), "paper-large": ("large", 384)}


def quick() -> dict:
    return yaml.safe_load((PROFILES / "quick.yaml").read_text())


def write_params(tmp_path: Path, overlay: dict) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(deep_merge(quick(), overlay), sort_keys=False))
    return path


def test_repo_params_load() -> None:
    params = load_params(REPO / "params.yaml")
    assert isinstance(params, Params)
    assert params.env.maze == "umaze" and params.env.layout is None and params.env.episode_steps is None
    assert params.model.dim == 16 and params.model.dim_mults == [1, 4, 8]
    assert params.diffusion.horizon == 128 and params.pretrain.lr == pytest.approx(2e-4)
    assert params.planner.sampler == "ddim" and params.task == "maze2d-umaze"
    assert (params.planner.tracking_p_gain, params.planner.tracking_d_gain) == (2.0, 0.5)
    assert params.section("collect") == {"steps": 200_000, "seed": 0}


def test_params_is_the_quick_profile() -> None:
    assert (REPO / "params.yaml").read_text() == (PROFILES / "quick.yaml").read_text()


def test_profile_list() -> None:
    assert {p.stem for p in PROFILES.glob("*.yaml")} == {"quick", "smoke", *PAPER}


@pytest.mark.parametrize("profile", sorted(p.stem for p in PROFILES.glob("*.yaml")))
def test_every_profile_applies_and_validates(profile: str, tmp_path: Path) -> None:
    out = apply_profile(profile, PROFILES, tmp_path / "params.yaml")
    assert out == tmp_path / "params.yaml"
    params = load_params(out)
    if profile == "quick":
        assert out.read_text() == (PROFILES / "quick.yaml").read_text()  # comments kept
    else:
        assert out.read_text().startswith(f"# Written by `adaptdiffuser profile {profile}`")
    if profile in PAPER:
        maze, horizon = PAPER[profile]
        assert params.model.dim == 32 and params.model.dim_mults == [1, 4, 8]
        assert params.env.maze == maze and params.diffusion.horizon == horizon
        assert params.planner.sampler == "ddpm"
    if profile == "smoke":
        assert params.pretrain.steps == 20 and params.diffusion.horizon == 32
        assert params.env.maze == "umaze" and params.expert.p_gain == 10.0  # inherited from quick
    assert sorted(p.name for p in tmp_path.iterdir()) == ["params.yaml"]  # no temporary files left


def test_unknown_profile(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="unknown profile 'fast'.*paper-umaze"):
        apply_profile("fast", PROFILES, tmp_path / "params.yaml")
    assert not (tmp_path / "params.yaml").exists()


def test_invalid_profile_does_not_overwrite_params(tmp_path: Path) -> None:
    profiles = tmp_path / "profiles"
    shutil.copytree(PROFILES, profiles)
    (profiles / "broken.yaml").write_text("pretrain:\n  steps: -1\n")
    params = apply_profile("smoke", profiles, tmp_path / "params.yaml")
    before = params.read_text()
    with pytest.raises(ConfigError, match="pretrain.steps"):
        apply_profile("broken", profiles, params)
    assert params.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["params.yaml", "profiles"]


def test_partial_file_takes_defaults(tmp_path: Path) -> None:
    path = tmp_path / "params.yaml"
    path.write_text("pretrain:\n  steps: 5\n")
    params = load_params(path)
    assert params.pretrain.steps == 5 and params.pretrain.batch_size == Params().pretrain.batch_size
    assert params.model == Params().model
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert load_params(empty) == Params()


BAD = [
    ({"env": {"maze": "mars"}}, "env.maze"),
    ({"pretrain": {"steps": -5}}, "pretrain.steps"),
    ({"diffusion": {"horizon": 102}, "model": {"dim_mults": [1, 4, 8]}}, "diffusion.horizon"),
    ({"diffusion": {"horizon": 100}, "model": {"dim_mults": [1, 2, 4, 8]}}, "diffusion.horizon"),
    ({"pretrain": {"stepz": 10}}, "pretrain.stepz"),
    ({"trainer": {"steps": 10}}, "trainer"),
    ({"pretrain": {"lr": "fast"}}, "pretrain.lr"),
    ({"pretrain": {"steps": "many"}}, "pretrain.steps"),
    ({"pretrain": {"steps": 10.5}}, "pretrain.steps"),
    ({"pretrain": {"steps": True}}, "pretrain.steps"),
    ({"diffusion": {"predict_epsilon": "no"}}, "diffusion.predict_epsilon"),
    ({"model": {"dim_mults": 4}}, "model.dim_mults"),
    ({"model": {"dim_mults": [1, "x"]}}, r"model.dim_mults\[1\]"),
    ({"model": {"dim_mults": [1, 0]}}, "model.dim_mults"),
    ({"model": {"kernel_size": 4}}, "model.kernel_size"),
    ({"planner": {"sampler": "foo"}}, "planner.sampler"),
    ({"planner": {"sampler_steps": 65}}, "planner.sampler_steps"),
    ({"pretrain": {"ema_decay": 1.0}}, "pretrain.ema_decay"),
    ({"env": {"goal_radius": 0}}, "env.goal_radius"),
    ({"env": {"episode_steps": -1}}, "env.episode_steps"),
    ({"env": {"maze": 7}}, "env.maze"),
    ({"env": {"layout": ["#####", "#G..", "#####"]}}, "env.layout"),
    ({"evaluate": {"episodes": 0}}, "evaluate.episodes"),
    ({"planner": {"tracking_p_gain": 0.0}}, "planner.tracking_p_gain"),
    ({"planner": {"tracking_d_gain": -0.5}}, "planner.tracking_d_gain"),
    ({"env": {"tracking_p_gain": 1.0}}, "env.tracking_p_gain"),  # the gains live in planner now
    ({"pretrain": {"expert_fraction": 0.0}}, "pretrain.expert_fraction"),
    ({"phases": {"phase1": {"previous": 1}}}, "phases.phase1.previous"),
    ({"phases": {"phase3": {}}}, "phases.phase3.previous"),
    ({"phases": {"first": {"previous": 0}}}, "phases.first"),
    ({"phases": {"phase4": {"previous": 0}}}, "phase1..phase3"),
    ({"phases": [{"previous": 0}]}, "phases: must be a mapping"),
    ({"phases": {"phase1": {"previous": 0, "generate": {"taskz": 3}}}}, "phases.phase1.generate.taskz"),
    ({"phases": {"phase1": {"previous": 0, "generate": {"tasks": 0}}}}, "phases.phase1.generate.tasks"),
    ({"phases": {"phase1": {"previous": 0}}, "evolution": {"discriminate": {"rule": "best"}}}, "discriminate.rule"),
    (
        {"phases": {"phase1": {"previous": 0}}, "evolution": {"discriminate": {"quantile": 1.5}}},
        "discriminate.quantile",
    ),
    (
        {"phases": {"phase1": {"previous": 0}}, "evolution": {"discriminate": {"max_error": 0}}},
        "discriminate.max_error",
    ),
    ({"phases": {"phase1": {"previous": 0}}, "evolution": {"finetune": {"expert_weight": 1.0}}}, "expert_weight"),
    ({"phases": {"phase1": {"previous": 0}}, "evolution": {"generate": {"sampler_steps": 65}}}, "sampler_steps"),
    (
        {"phases": {"phase1": {"previous": 0}}, "env": {"layout": ["###", "#G#", "#.#", "###"]}},
        "rule 'paper'",
    ),
]


@pytest.mark.parametrize(("overlay", "key"), BAD, ids=[key.replace("\\", "") for _, key in BAD])
def test_bad_values_raise_config_error_naming_the_key(tmp_path: Path, overlay: dict, key: str) -> None:
    with pytest.raises(ConfigError, match=key) as err:
        load_params(write_params(tmp_path, overlay))
    assert len(str(err.value).splitlines()) == 1


NAN, INF = float("nan"), float("inf")
SEEDS = ["collect.seed", "pretrain.seed", "evaluate.seed", "gold_coin.seed", "sweep.seed"]
SEEDS += ["evolution.generate.seed", "evolution.finetune.seed"]
PHASE1 = {"phases": {"phase1": {"previous": 0}}}
# values the hand-written loader used to accept (or crash on): each is a one-line ConfigError starting with its key
REJECTED = [
    ({"pretrain": {"lr": NAN}}, "pretrain.lr", "must be a finite number, got nan"),
    ({"pretrain": {"lr": INF}}, "pretrain.lr", "must be a finite number, got inf"),
    ({"pretrain": {"lr": -INF}}, "pretrain.lr", "must be a finite number, got -inf"),
    ({"env": {"goal_radius": NAN}}, "env.goal_radius", "must be a finite number, got nan"),
    ({"alpha": INF}, "alpha", "must be a finite number, got inf"),
    ({"evolution": {"discriminate": {"max_error": NAN}}}, "evolution.discriminate.max_error", "finite"),
    *[(set_dotted({}, key, -1), key, "must be >= 0, got -1") for key in SEEDS],
    (PHASE1 | {"phases": {"phase1": {"previous": 0, "generate": {"seed": -3}}}}, "phases.phase1.generate.seed", ">= 0"),
    (PHASE1 | {"phases": {"phase1": {"previous": 0, "finetune": {"seed": -3}}}}, "phases.phase1.finetune.seed", ">= 0"),
    ({"sweep": {"heartbeat_s": 0}}, "sweep.heartbeat_s", "must be > 0, got 0"),
    ({"sweep": {"pruner_startup_trials": -1}}, "sweep.pruner_startup_trials", "must be >= 0"),
    ({"env": {"episode_steps": 100}}, "env.episode_steps", "100 is shorter than diffusion.horizon=128"),
    ({"diffusion": {"horizon": 320}}, "env.episode_steps", "null means the maze2d-umaze protocol's 300 steps"),
    (
        {"env": {"maze": "large"}, "diffusion": {"horizon": 1024}},
        "env.episode_steps",
        "maze2d-large protocol's 800 steps, shorter than diffusion.horizon=1024",
    ),
    ({"planner": {"sampler_steps": 65}}, "planner.sampler_steps", "exceeds diffusion.n_steps=64"),
    (
        {"phases": {"phase1": {"previous": 0, "generate": {"sampler_steps": 65}}}},
        "phases.phase1.generate.sampler_steps",
        "1..diffusion.n_steps=64",
    ),
    ({"phases": {"phase1": 3}}, "phases.phase1", "must be a mapping like {previous: 0}"),
    ({"phases": {"phase1": "previous 0"}}, "phases.phase1", "must be a mapping"),
    ({"phases": {"phase1": [0]}}, "phases.phase1", "must be a mapping"),
    ({"phases": {"phase1": {"previous": 0, "generate": 5}}}, "phases.phase1.generate", "must be a mapping, got 5"),
    ({"phases": {"phase1": {"previous": 0, "sampler": "ddim"}}}, "phases.phase1.sampler", "unknown key"),
    ({"phases": {"phase1": {"previous": -1}}}, "phases.phase1.previous", "must be >= 0, got -1"),
    ({"phases": {"phase1": {"previous": 0.5}}}, "phases.phase1.previous", "must be an integer, got 0.5"),
    ({"env": {"random_goal": "yes"}}, "env.random_goal", "must be true or false, got 'yes'"),
    ({"env": {"random_goal": 1}}, "env.random_goal", "must be true or false, got 1"),
    ({"collect": {"steps": 1.5}}, "collect.steps", "must be an integer, got 1.5"),
    ({"model": {"dim_mults": []}}, "model.dim_mults", "non-empty list of positive integers"),
    ({"sweep": {"trials": 0}}, "sweep.trials", "must be > 0"),
    ({"sweep": {"objective": "speed"}}, "sweep.objective", "must be one of 'navigation', 'coin', 'mix'"),
    ({"sweep": {"space": {"alpha": {"low": NAN, "high": 1.0}}}}, "sweep.space.alpha.low", "finite"),
    ({"sweep": {"space": {"alpha": {"lo": 1.0, "high": 2.0}}}}, "sweep.space.alpha", "unknown field 'lo'"),
    ({"sweep": {"space": {"alpha": 3}}}, "sweep.space.alpha", "must be a mapping"),
    ({"sweep": {"space": [1, 2]}}, "sweep.space", "must map params keys to ranges"),
    ({"sweep": {"storage": 5}}, "sweep.storage", "must be a string, got 5"),
]


@pytest.mark.parametrize(
    ("overlay", "key", "reason"), REJECTED, ids=[f"{k}-{i}" for i, (_, k, _) in enumerate(REJECTED)]
)
def test_rejected_values_give_a_one_line_error_starting_with_the_key(
    tmp_path: Path, overlay: dict, key: str, reason: str
) -> None:
    with pytest.raises(ConfigError) as err:
        load_params(write_params(tmp_path, overlay))
    message = str(err.value)
    assert len(message.splitlines()) == 1, message
    assert message.startswith(f"{key}: "), message
    assert reason in message, message


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("lr: 0.0002", "lr: .nan", "pretrain.lr: must be a finite number, got nan"),
        ("lr: 0.0002", "lr: .inf", "pretrain.lr: must be a finite number, got inf"),
        ("lr: 0.0002", "lr: 1e999", "pretrain.lr: must be a finite number, got inf"),  # YAML 1.1: a string
        ("goal_radius: 0.5", "goal_radius: .NaN", "env.goal_radius: must be a finite number, got nan"),
        ("  seed: 0\nmodel", "  seed: -1\nmodel", "collect.seed: must be >= 0, got -1"),
        ("heartbeat_s: 30", "heartbeat_s: 0", "sweep.heartbeat_s: must be > 0, got 0"),
        ("episode_steps: null", "episode_steps: 64", "env.episode_steps: 64 is shorter than diffusion.horizon=128"),
        ("phase1: {previous: 0}", "phase1: 3", "phases.phase1: must be a mapping"),
        ("random_goal: false", "random_goal: no", None),  # YAML 1.1 reads `no` as false: accepted
    ],
)
def test_rejected_values_as_written_in_yaml(tmp_path: Path, old: str, new: str, key: str | None) -> None:
    text = (PROFILES / "quick.yaml").read_text()
    assert old in text
    path = tmp_path / "params.yaml"
    path.write_text(text.replace(old, new, 1))
    if key is None:
        load_params(path)
        return
    with pytest.raises(ConfigError) as err:
        load_params(path)
    assert str(err.value).startswith(key) and "\n" not in str(err.value), str(err.value)


def test_replace_revalidates_and_models_are_frozen() -> None:
    params = Params()
    with pytest.raises(ValueError, match="finite"):
        dataclasses.replace(params.pretrain, lr=NAN)
    with pytest.raises(ValueError, match="unknown maze"):
        dataclasses.replace(params, env=EnvParams(maze="mars"))
    with pytest.raises(dataclasses.FrozenInstanceError):
        params.pretrain.lr = 1.0  # type: ignore[misc]
    assert dataclasses.replace(params.pretrain, steps=3).steps == 3
    assert pickle.loads(pickle.dumps(load_params(REPO / "params.yaml"))) == load_params(REPO / "params.yaml")


def test_describe_lists_the_task_and_the_stages_dvc_runs() -> None:
    params = load_params(REPO / "params.yaml")
    lines = describe(params)
    assert lines[0].startswith("task: maze2d-umaze") and "300-step episodes" in lines[0]
    stages = [line.strip().split(":")[0] for line in lines[lines.index("stages:") + 1 :]]
    assert stages == stage_names(params)
    assert stages[:5] == ["collect", "reference", "pretrain", "evaluate-phase0", "evaluate-coin-phase0"]
    assert stages[5:10] == [
        f"{s}@phase1" for s in ("generate", "discriminate", "finetune", "evaluate", "evaluate-coin")
    ]
    assert stages[-2:] == ["summarize", "report"] and len(stages) == 5 + 5 * 2 + 2
    dvc = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    expanded = {f"{name}@{k}" if "foreach" in spec else name for name, spec in dvc.items() for k in params.phase_names}
    assert set(stages) == expanded


def test_phases_merge_their_overrides_over_the_evolution_defaults(tmp_path: Path) -> None:
    overlay = {
        "evolution": {"generate": {"tasks": 64}, "discriminate": {"rule": "quantile"}},
        "phases": {
            "phase2": {"previous": 1, "discriminate": {"quantile": 0.8}},
            "phase1": {"previous": 0},
            "phase3": {"previous": 1, "generate": {"tasks": 8}},
        },
    }
    p = load_params(write_params(tmp_path, overlay))
    assert p.phase_names == ["phase1", "phase2", "phase3"]
    assert [p.phase(k).generate.tasks for k in (1, 2, 3)] == [64, 64, 8]
    assert [p.phase(k).discriminate.quantile for k in (1, 2, 3)] == [0.5, 0.8, 0.5]
    assert all(p.phase(k).discriminate.rule == "quantile" for k in (1, 2, 3))
    # phase 3 branches from phase 1: it trains on the data selected in phases 1 and 3, not 2
    assert p.lineage(3) == [1, 3] and p.lineage(2) == [1, 2] and p.lineage(0) == []
    with pytest.raises(ConfigError, match="phase 4 is not declared"):
        p.phase(4)


def test_horizon_divisibility_follows_the_unet_factor(tmp_path: Path) -> None:
    # dim_mults [1, 4, 8] halves the horizon twice, so 100 (divisible by 4) is a valid horizon
    params = load_params(write_params(tmp_path, {"diffusion": {"horizon": 100}, "model": {"dim_mults": [1, 4, 8]}}))
    assert params.diffusion.horizon == 100


def test_valid_custom_layout_and_episode_length(tmp_path: Path) -> None:
    layout = ["######", "#..#G#", "#....#", "#.##.#", "######"]
    # the paper's reward/length thresholds exist for the three D4RL mazes only, so a custom maze selects by quantile
    overlay = {"env": {"layout": layout, "episode_steps": 200}, "evolution": {"discriminate": {"rule": "quantile"}}}
    params = load_params(write_params(tmp_path, overlay))
    assert params.env.layout == layout and params.env.episode_steps == 200 and params.task == "maze2d-custom"


def test_structural_errors(tmp_path: Path) -> None:
    path = tmp_path / "params.yaml"
    path.write_text("- a\n- b\n")
    with pytest.raises(ConfigError, match="top level"):
        load_params(path)
    path.write_text("pretrain: 5\n")
    with pytest.raises(ConfigError, match="pretrain: must be a mapping, got 5"):
        load_params(path)
    with pytest.raises(ConfigError, match="not found"):
        load_params(tmp_path / "missing.yaml")


def test_integral_float_accepted_for_int(tmp_path: Path) -> None:
    params = load_params(write_params(tmp_path, {"pretrain": {"steps": 100.0, "lr": 1}}))
    assert params.pretrain.steps == 100 and isinstance(params.pretrain.steps, int)
    assert params.pretrain.lr == 1.0 and isinstance(params.pretrain.lr, float)


def test_deep_merge() -> None:
    base = {"a": {"x": 1, "y": 2}, "b": 3}
    assert deep_merge(base, {"a": {"y": 5}, "c": 4}) == {"a": {"x": 1, "y": 5}, "b": 3, "c": 4}
    assert base == {"a": {"x": 1, "y": 2}, "b": 3}


@pytest.mark.parametrize(
    ("overlay", "key"),
    [({"pretrain": {"steps": -1}}, "pretrain.steps"), ({"pretrain": {"stepz": 1}}, "pretrain.stepz")],
)
def test_cli_check_rejects_bad_params(tmp_path: Path, overlay: dict, key: str) -> None:
    bad = write_params(tmp_path, overlay).rename(tmp_path / "bad.yaml")
    result = CliRunner().invoke(app, ["check", "--params", str(bad)])
    assert result.exit_code == 1, result.output  # `check` exits 1 on a bad value (stages exit 2)
    assert key in result.output
    assert "error:" in result.output


def test_cli_check_accepts_good_params() -> None:
    result = CliRunner().invoke(app, ["check", "--params", str(REPO / "params.yaml")])
    assert result.exit_code == 0, result.output
    assert "ok" in result.output
    assert "pretrain:" in result.output and "evaluate@phase2" in result.output  # what it will run


def test_cli_profile_writes_params(tmp_path: Path) -> None:
    out = tmp_path / "params.yaml"
    args = ["profile", "paper-medium", "--params", str(out), "--profiles-dir", str(PROFILES)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert load_params(out).env.maze == "medium"
    result = CliRunner().invoke(app, ["profile", "nope", "--params", str(out), "--profiles-dir", str(PROFILES)])
    assert result.exit_code == 2 and "unknown profile" in result.output


def test_exponent_without_dot_is_a_number(tmp_path: Path) -> None:
    path = tmp_path / "params.yaml"
    path.write_text((PROFILES / "quick.yaml").read_text().replace("lr: 0.0002", "lr: 2e-4"))
    assert load_params(path).pretrain.lr == pytest.approx(2e-4)
    path.write_text((PROFILES / "quick.yaml").read_text().replace("lr: 0.0002", "lr: fast"))
    with pytest.raises(ConfigError, match="pretrain.lr"):
        load_params(path)
