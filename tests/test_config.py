"""The config loader: the repo's params and profiles, rejected values naming their key, and the `check` CLI."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from adaptdiffuser.cli import app
from adaptdiffuser.config import ConfigError, Params, apply_profile, deep_merge, load_params

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
    ({"phases": [{"previous": 0}]}, "phases must be a mapping"),
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
    with pytest.raises(ConfigError, match=key):
        load_params(write_params(tmp_path, overlay))


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
    with pytest.raises(ConfigError, match="pretrain must be a mapping"):
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
    assert result.exit_code == 2, result.output
    assert key in result.output
    assert "error:" in result.output


def test_cli_check_accepts_good_params() -> None:
    result = CliRunner().invoke(app, ["check", "--params", str(REPO / "params.yaml")])
    assert result.exit_code == 0, result.output
    assert "ok" in result.output


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
