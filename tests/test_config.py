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
    Params,
    TaskParams,
    apply_profile,
    deep_merge,
    describe,
    load_params,
    params_from_dict,
    set_dotted,
    stage_names,
)
from adaptdiffuser.config.defaults import family_defaults
from adaptdiffuser.config.start_states import KEPT_EVAL_SEED, KEPT_HELD_OUT_SEED, start_seeds, start_state_sets
from adaptdiffuser.evaluation import episode_rng
from adaptdiffuser.families.maze2d.params import EnvParams, Maze2DTaskParams
from adaptdiffuser.family_registry import get_family

REPO = Path(__file__).resolve().parents[1]
PROFILES = REPO / "profiles"
PAPER = {"paper-umaze": ("umaze", 128), "paper-medium": ("medium", 256), "paper-large": ("large", 384)}
UMAZE = "maze2d-umaze"  # the one task of the quick profile
T = f"task.{UMAZE}"  # the prefix of its keys in error messages


def umaze(**sections: dict) -> dict:
    """An overlay of the quick profile's U-Maze task entry (``env``, ``collect``, ``diffusion``... overrides)."""
    return {"task": {UMAZE: sections}}


def quick() -> dict:
    """The quick profile resolved, as the committed params.yaml holds it (profiles/quick.yaml is an overlay)."""
    return yaml.safe_load((REPO / "params.yaml").read_text())


def write_params(tmp_path: Path, overlay: dict) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(deep_merge(quick(), overlay), sort_keys=False))
    return path


def write_params_raw(tmp_path: Path, raw: dict) -> Path:
    path = tmp_path / "raw.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def test_repo_params_load() -> None:
    params = load_params(REPO / "params.yaml")
    assert isinstance(params, Params)
    assert params.tasks == (UMAZE,) and params.unseen_tasks == (UMAZE,) and params.evolve == UMAZE
    task = params.resolve(UMAZE)
    assert isinstance(task, TaskParams) and params.evolved == task
    assert (task.name, task.family) == (UMAZE, "maze2d") and isinstance(task.settings, Maze2DTaskParams)
    env = task.settings.env
    assert env.maze == "umaze" and env.layout is None and env.episode_steps is None
    assert task.settings.episode_steps == 300 and task.settings.maze_name == "umaze"
    assert params.model.dim == 16 and params.model.dim_mults == [1, 4, 8]
    assert params.diffusion.horizon == 128 and params.pretrain.lr == pytest.approx(1e-3)
    assert params.planner.sampler == "ddim"
    assert (task.settings.follower.p_gain, task.settings.follower.d_gain) == (2.0, 0.5)
    assert (task.settings.evolution.cell_spread, task.settings.evolution.coin_fraction) == (0.4, 0.25)
    # the task has no overrides: its generic sections are the top-level ones
    assert (task.model, task.diffusion, task.pretrain, task.planner, task.evaluate) == (
        params.model,
        params.diffusion,
        params.pretrain,
        params.planner,
        params.evaluate,
    )
    assert task.section("collect") == {"steps": 200_000, "seed": 0}
    assert task.section("planner") == params.section("planner")


def test_default_params_have_one_umaze_task() -> None:
    params = Params()
    assert params.tasks == (UMAZE,) and params.unseen_tasks == (UMAZE,) and params.evolve == UMAZE
    assert list(params.task) == [UMAZE] and params.phases == ()
    task = params.resolve(UMAZE)
    assert task.family == "maze2d" and task.settings == Maze2DTaskParams()
    assert task.settings.env == EnvParams() and task.settings.episode_steps == 300
    assert task.diffusion == params.diffusion and task.model == params.model
    with pytest.raises(ConfigError, match=r"^task\.maze2d-medium: no such task") as err:
        params.resolve("maze2d-medium")
    assert len(str(err.value).splitlines()) == 1


def test_params_is_the_quick_profile(tmp_path: Path) -> None:
    """The committed params.yaml is what `adaptdiffuser profile quick` writes (every value resolved)."""
    written = apply_profile("quick", PROFILES, tmp_path / "params.yaml").read_text()
    assert (REPO / "params.yaml").read_text() == written


def test_profile_list() -> None:
    assert {p.stem for p in PROFILES.glob("*.yaml")} == {
        "quick",
        "smoke",
        "quick-locomotion",
        "quick-kuka",
        "science-kuka",
        "paper-kuka",
        "paper-locomotion",
        "science",
        "science-medium",
        "science-large",
        "science-locomotion",
        "science-hopper",
        "science-walker2d",
        "science-walker2d-w32",
        "science-halfcheetah",
        "science-umaze",
        "science-umaze-compute",
        *PAPER,
    }


@pytest.mark.parametrize("profile", sorted(p.stem for p in PROFILES.glob("*.yaml")))
def test_every_profile_applies_and_validates(profile: str, tmp_path: Path) -> None:
    out = apply_profile(profile, PROFILES, tmp_path / "params.yaml")
    assert out == tmp_path / "params.yaml"
    params = load_params(out)
    assert out.read_text().startswith(f"# Written by `adaptdiffuser profile {profile}`")
    if profile in PAPER:
        maze, horizon = PAPER[profile]
        task = params.evolved
        assert task.family == "maze2d" and task.name in params.tasks and task.name in params.unseen_tasks
        assert task.model.dim == 32 and task.model.dim_mults == [1, 4, 8]
        assert task.settings.env.maze == maze and task.diffusion.horizon == horizon
        assert task.planner.sampler == "ddpm"
    if profile in ("science-medium", "science-large"):
        maze = profile.removeprefix("science-")
        task = params.evolved
        assert task.name == f"maze2d-{maze}" and params.tasks == params.unseen_tasks == (task.name,)
        assert task.settings.env.maze == maze and task.settings.episode_steps == {"medium": 600, "large": 800}[maze]
        assert task.diffusion.horizon == {"medium": 256, "large": 384}[maze] and params.seeds == (0, 1, 2, 3, 4)
        assert task.evaluate.episodes == task.evaluate.held_out_episodes == 500  # a seed's episode noise kept small
        assert task.model.dim == 16 and task.planner.sampler_steps == 4  # the quick profile's model and planner
    if profile == "science-umaze":  # the quick profile on three seeds
        assert params.tasks == (UMAZE,) and params.evolve == UMAZE and params.seeds == (0, 1, 2)
        assert params.pretrain == load_params(REPO / "params.yaml").pretrain
    if profile == "smoke":
        assert params.pretrain.steps == 20 and params.diffusion.horizon == 32
        maze = params.resolve(UMAZE)
        assert maze.settings.collect.steps == 4000 and maze.diffusion.horizon == 32
        assert maze.settings.env.maze == "umaze" and maze.settings.expert.p_gain == 10.0  # inherited from quick
        hopper = params.resolve("hopper-medium")  # one task of each family, with its own generic overrides
        assert params.tasks == (UMAZE, "hopper-medium", "kuka-stacking")
        assert params.unseen_tasks == (UMAZE, "kuka-stacking")  # the families with an unseen task
        assert params.resolve("kuka-stacking").family == "kuka"
        assert hopper.family == "locomotion" and hopper.settings.episode_steps == 40
        assert hopper.diffusion.horizon == 16 and hopper.model.dim_mults == [1, 2]
        assert hopper.pretrain == params.pretrain  # not overridden: the top-level section
        for name in ("walker2d-medium-replay", "halfcheetah-medium-expert"):  # stages run by tests, not DVC
            assert params.resolve(name).family == "locomotion" and name not in params.tasks
    if profile == "quick-locomotion":
        # `unseen_tasks: []` replaces the quick profile's (an empty list is not merged)
        assert params.tasks == ("hopper-medium",) and params.unseen_tasks == () and params.evolve == "hopper-medium"
        assert params.phase_names == ["phase1", "phase2"] and params.phase(1).generate.sampler == "ddpm"
        hopper = params.resolve("hopper-medium")
        assert hopper.family == "locomotion" and hopper.diffusion.horizon == 32
    if profile == "quick-kuka":
        assert params.tasks == params.unseen_tasks == ("kuka-stacking",) and params.evolve == "kuka-stacking"
        assert params.alpha == 10.0  # guides pick-and-place, in generation and its evaluation
        kuka = params.resolve("kuka-stacking")
        assert kuka.family == "kuka" and kuka.diffusion.horizon == 128 and kuka.settings.replans == 3
        # the arm follows the blocks: tracking is the blocks' centres in metres (the reference's 1.02 is joints)
        assert kuka.settings.planning.follow_blocks and params.phase(2).discriminate.max_error == 0.2
        assert params.phase_names == ["phase1", "phase2"]
    if profile == "science-kuka":  # quick-kuka over three training seeds, pretrained longer, fine-tuned as long
        science = yaml.safe_load(out.read_text())
        quick_path = apply_profile("quick-kuka", PROFILES, tmp_path / "quick.yaml")
        quick, quick_params = yaml.safe_load(quick_path.read_text()), load_params(quick_path)
        quick_path.unlink()
        for p, steps, fraction in ((params, 40000, 0.075), (quick_params, 24000, 0.125)):  # both fine-tune 3 000
            assert p.resolve("kuka-stacking").pretrain.steps == steps and p.phase(1).finetune.steps_fraction == fraction
        for raw in (science, quick):
            del raw["seeds"], raw["evolution"]["finetune"]["steps_fraction"]
            del raw["task"]["kuka-stacking"]["pretrain"]["steps"]
        assert params.seeds == (0, 1, 2) and science == quick
    if profile == "paper-kuka":
        kuka = params.resolve("kuka-stacking")
        assert kuka.settings.collect.episodes == 10000 and kuka.model.dim == 128 and kuka.diffusion.n_steps == 1000
        assert params.evolve == "kuka-stacking" and params.phase(1).discriminate.max_error == 1.02
    if profile == "paper-locomotion":
        assert len(params.tasks) == 9 and params.unseen_tasks == () and params.evolve == "hopper-medium"
        assert params.phase_names == ["phase1", "phase2"] and params.phase(1).discriminate.rule == "paper"
        assert {params.resolve(name).family for name in params.tasks} == {"locomotion"}
        assert (
            params.resolve("hopper-medium").model.dim == 32 and params.resolve("hopper-medium").diffusion.horizon == 32
        )
        assert params.resolve("halfcheetah-medium").diffusion.horizon == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["params.yaml"]  # no temporary files left


def test_unknown_profile(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="unknown profile 'fast'.*paper-umaze"):
        apply_profile("fast", PROFILES, tmp_path / "params.yaml")
    assert not (tmp_path / "params.yaml").exists()


def test_profiles_extend_parts_in_order(tmp_path: Path) -> None:
    """Parts are overlaid in the order named, each after its own parts, a shared part once, the profile's keys
    last; the header lists the files in that order; a part is not a profile."""
    profiles = tmp_path / "profiles"
    (profiles / "parts").mkdir(parents=True)
    shutil.copy2(PROFILES / "quick.yaml", profiles)
    (profiles / "parts" / "base.yaml").write_text("seeds: [0, 1]\nalpha: 1.0\n")
    (profiles / "parts" / "a.yaml").write_text("extends: base\nalpha: 2.0\npretrain: {lr: 0.0003}\n")
    # b extends base again: base must not be overlaid a second time, undoing a's alpha
    (profiles / "parts" / "b.yaml").write_text("extends: [base]\npretrain: {steps: 300}\n")
    (profiles / "mine.yaml").write_text("extends: [a, b]\npretrain: {steps: 400, log_every: 7}\n")
    out = apply_profile("mine", profiles, tmp_path / "params.yaml")
    params = load_params(out)
    assert params.seeds == (0, 1) and params.alpha == 2.0
    assert (params.pretrain.lr, params.pretrain.steps, params.pretrain.log_every) == (0.0003, 400, 7)
    assert params.pretrain.batch_size == 32  # the quick profile's, untouched by any layer
    header = out.read_text().splitlines()[0]
    assert header.endswith(
        "profiles/quick.yaml + profiles/parts/base.yaml + profiles/parts/a.yaml + profiles/parts/b.yaml + "
        "profiles/mine.yaml."
    )
    assert "extends" not in yaml.safe_load(out.read_text())
    with pytest.raises(ConfigError, match="unknown profile 'parts/a'"):
        apply_profile("parts/a", profiles, tmp_path / "other.yaml")


def test_family_defaults_are_expanded_into_each_task_of_the_family(tmp_path: Path) -> None:
    """Every task entry of a family starts from ``family_defaults.<family>`` (its own keys win, nested keys merged);
    tasks of other families are untouched; params.yaml holds the whole entries and no ``family_defaults``."""
    profiles = tmp_path / "profiles"
    (profiles / "parts").mkdir(parents=True)
    shutil.copy2(PROFILES / "quick.yaml", profiles)
    (profiles / "parts" / "loco.yaml").write_text(
        "family_defaults:\n  locomotion:\n    guide: {n_samples: 5, scale: 0.5}\n    pretrain: {steps: 300}\n"
    )
    (profiles / "mine.yaml").write_text(
        "extends: loco\ntasks: [maze2d-umaze, hopper-medium, walker2d-medium]\nunseen_tasks: [maze2d-umaze]\n"
        "collect_tasks: [maze2d-umaze, hopper-medium, walker2d-medium]\n"
        "task:\n  hopper-medium: {family: locomotion}\n"
        "  walker2d-medium: {family: locomotion, guide: {scale: 0.01}}\n"
    )
    out = apply_profile("mine", profiles, tmp_path / "params.yaml")
    raw = yaml.safe_load(out.read_text())
    assert "family_defaults" not in raw
    # the whole entry: the profile's keys over the family's, every other key at the family model's default
    expected = deep_merge(family_defaults("locomotion"), {"guide": {"n_samples": 5, "scale": 0.01}})
    assert raw["task"]["walker2d-medium"] == expected | {"pretrain": {"steps": 300}}
    assert "guide" not in raw["task"]["maze2d-umaze"]
    params = load_params(out)
    hopper, walker, maze = (params.resolve(t) for t in ("hopper-medium", "walker2d-medium", "maze2d-umaze"))
    assert (hopper.settings.guide.n_samples, hopper.settings.guide.scale) == (5, 0.5)
    assert (walker.settings.guide.n_samples, walker.settings.guide.scale) == (5, 0.01)
    assert hopper.pretrain.steps == walker.pretrain.steps == 300
    assert maze.pretrain.steps == params.pretrain.steps != 300


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("family_defaults: {robots: {pretrain: {steps: 3}}}\n", "names unknown families \\['robots'\\]"),
        ("family_defaults: [locomotion]\n", "family_defaults must map a family name"),
        ("family_defaults: {locomotion: {family: maze2d}}\n", "must not set 'family'"),
    ],
)
def test_bad_family_defaults_are_refused_in_one_line(tmp_path: Path, text: str, message: str) -> None:
    profiles = tmp_path / "profiles"
    profiles.mkdir()
    shutil.copy2(PROFILES / "quick.yaml", profiles)
    (profiles / "mine.yaml").write_text(text)
    with pytest.raises(ConfigError, match=message) as err:
        apply_profile("mine", profiles, tmp_path / "params.yaml")
    assert len(str(err.value).splitlines()) == 1
    assert not (tmp_path / "params.yaml").exists()


@pytest.mark.parametrize(
    ("files", "message"),
    [
        ({"mine.yaml": "extends: nowhere\n"}, "extends unknown part 'nowhere'; parts: \\['a'\\]"),
        ({"mine.yaml": "extends: a\n", "parts/a.yaml": "extends: [b]\n", "parts/b.yaml": "extends: a\n"},
         "in a cycle: mine -> a -> b -> a"),
        ({"mine.yaml": "extends: {a: 1}\n"}, "extends must name a part"),
        ({"mine.yaml": "- seeds\n"}, "a profile or part must be a mapping"),
        ({"mine.yaml": "extends: ../mine\n"}, "extends must name a part"),
        ({"mine.yaml": "extends: a\n", "parts/a.yaml": "alpha: [1\n"}, "a.yaml: not valid YAML \\(line 2\\)"),
        ({"mine.yaml": "alpha: 1\n", "quick.yaml": "extends: a\n"}, "quick.yaml: the quick profile .* extends nothing"),
    ],
)  # fmt: skip
def test_bad_extends_is_refused_in_one_line(tmp_path: Path, files: dict[str, str], message: str) -> None:
    profiles = tmp_path / "profiles"
    (profiles / "parts").mkdir(parents=True)
    shutil.copy2(PROFILES / "quick.yaml", profiles)
    (profiles / "parts" / "a.yaml").write_text("alpha: 3.0\n")
    for name, text in files.items():
        (profiles / name).write_text(text)
    with pytest.raises(ConfigError, match=message) as err:
        apply_profile("mine", profiles, tmp_path / "params.yaml")
    assert len(str(err.value).splitlines()) == 1
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


def test_an_empty_or_partial_file_is_refused_naming_what_it_misses(tmp_path: Path) -> None:
    """A run never falls back on values its params file does not write (the profiles are the one source)."""
    path = tmp_path / "params.yaml"
    path.write_text("pretrain:\n  steps: 5\n")
    with pytest.raises(ConfigError, match=r"missing model, diffusion, pretrain\.batch_size, pretrain\.grad_accum"):
        load_params(path)
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    with pytest.raises(ConfigError, match=r"empty.yaml: missing model, .* and \d+ more; .*adaptdiffuser profile"):
        load_params(empty)
    full = quick()
    del full["evaluate"]["pictures"], full["evolution"]["generate"]["tasks"]
    with pytest.raises(ConfigError, match=r"missing evaluate\.pictures, evolution\.generate\.tasks;"):
        load_params(write_params_raw(tmp_path, full))
    del full["imports"], full["collect_tasks"]  # optional: no imports, collect every task
    full |= {"evaluate": quick()["evaluate"], "evolution": quick()["evolution"]}
    assert load_params(write_params_raw(tmp_path, full)) == load_params(REPO / "params.yaml")


BAD = [
    (umaze(env={"maze": "mars"}), rf"{T}.env.maze"),
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
    (umaze(env={"goal_radius": 0}), rf"{T}.env.goal_radius"),
    (umaze(env={"episode_steps": -1}), rf"{T}.env.episode_steps"),
    (umaze(env={"maze": 7}), rf"{T}.env.maze"),
    (umaze(env={"layout": ["#####", "#G..", "#####"]}), rf"{T}.env.layout"),
    ({"evaluate": {"episodes": 0}}, "evaluate.episodes"),
    (umaze(follower={"p_gain": 0.0}), rf"{T}.follower.p_gain"),
    (umaze(follower={"d_gain": -0.5}), rf"{T}.follower.d_gain"),
    (umaze(env={"tracking_p_gain": 1.0}), rf"{T}.env.tracking_p_gain"),  # the gains live in follower
    ({"planner": {"tracking_p_gain": 2.0}}, "planner.tracking_p_gain"),  # a maze key, not a generic one
    ({"evolution": {"generate": {"coin_fraction": 0.25}}}, "evolution.generate.coin_fraction"),
    (umaze(evolution={"coin_fraction": 1.5}), rf"{T}.evolution.coin_fraction"),
    ({"pretrain": {"expert_fraction": 0.0}}, "pretrain.expert_fraction"),
    ({"pretrain": {"lr_schedule": "linear"}}, "pretrain.lr_schedule"),
    ({"pretrain": {"lr_warmup": -1}}, "pretrain.lr_warmup"),
    ({"phases": {"phase1": {"previous": 1}}}, "phases.phase1.previous"),
    ({"phases": {"phase3": {}}}, "phases.phase3.previous"),
    ({"phases": {"first": {"previous": 0}}}, "phases.first"),
    ({"phases": {"phase2": {"previous": 1}, "phase4": {"previous": 0}}}, "phase1..phase3"),
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
        {"phases": {"phase1": {"previous": 0}}, **umaze(env={"layout": ["###", "#G#", "#.#", "###"]})},
        "phases.phase1.discriminate.rule: the rule 'paper'",
    ),
    # the maze sections are a task's now: at the top level they are unknown keys
    ({"env": {"maze": "umaze"}}, "env: unknown key"),
    ({"collect": {"steps": 10}}, "collect: unknown key"),
    ({"gold_coin": {"seed": 1}}, "gold_coin: unknown key"),
    # a task's overrides of the generic sections are checked as the sections are, under the task's key
    (umaze(diffusion={"horizon": 102}), rf"{T}.diffusion.horizon"),
    (umaze(diffusion={"horizonz": 128}), rf"{T}.diffusion.horizonz"),
    (umaze(pretrain={"lr": "fast"}), rf"{T}.pretrain.lr"),
    (umaze(planner={"sampler_steps": 65}), rf"{T}.planner.sampler_steps"),
    (umaze(model={"dim_mults": [1, 0]}), rf"{T}.model.dim_mults"),
    (umaze(evolution={"generate": {"tasks": 3}}), rf"{T}.evolution"),  # not a per-task section
]


@pytest.mark.parametrize(("overlay", "key"), BAD, ids=[key.replace("\\", "") for _, key in BAD])
def test_bad_values_raise_config_error_naming_the_key(tmp_path: Path, overlay: dict, key: str) -> None:
    with pytest.raises(ConfigError, match=key) as err:
        load_params(write_params(tmp_path, overlay))
    assert len(str(err.value).splitlines()) == 1


NAN, INF = float("nan"), float("inf")
SEEDS = [f"{T}.collect.seed", "pretrain.seed", "evaluate.seed", f"{T}.gold_coin.seed", "sweep.seed"]
SEEDS += ["sweep.evaluate_seed", "sweep.held_out_seed", "evaluate.held_out_seed"]
SEEDS += [f"{T}.pretrain.seed", f"{T}.evaluate.seed"]
SEEDS += ["evolution.generate.seed", "evolution.finetune.seed"]
PHASE1 = {"phases": {"phase1": {"previous": 0}}}
# values the hand-written loader used to accept (or crash on): each is a one-line ConfigError starting with its key
REJECTED = [
    ({"pretrain": {"lr": NAN}}, "pretrain.lr", "must be a finite number, got nan"),
    ({"pretrain": {"lr": INF}}, "pretrain.lr", "must be a finite number, got inf"),
    ({"pretrain": {"lr": -INF}}, "pretrain.lr", "must be a finite number, got -inf"),
    (umaze(env={"goal_radius": NAN}), f"{T}.env.goal_radius", "must be a finite number, got nan"),
    ({"alpha": INF}, "alpha", "must be a finite number, got inf"),
    ({"evolution": {"discriminate": {"max_error": NAN}}}, "evolution.discriminate.max_error", "finite"),
    *[(set_dotted({}, key, -1), key, "must be >= 0, got -1") for key in SEEDS],
    (PHASE1 | {"phases": {"phase1": {"previous": 0, "generate": {"seed": -3}}}}, "phases.phase1.generate.seed", ">= 0"),
    (PHASE1 | {"phases": {"phase1": {"previous": 0, "finetune": {"seed": -3}}}}, "phases.phase1.finetune.seed", ">= 0"),
    ({"sweep": {"heartbeat_s": 0}}, "sweep.heartbeat_s", "must be > 0, got 0"),
    ({"sweep": {"pruner_startup_trials": -1}}, "sweep.pruner_startup_trials", "must be >= 0"),
    (umaze(env={"episode_steps": 100}), f"{T}.env.episode_steps", "100 is shorter than diffusion.horizon=128"),
    ({"diffusion": {"horizon": 320}}, f"{T}.env.episode_steps", "null means the maze umaze protocol's 300 steps"),
    (
        umaze(env={"maze": "large"}) | {"diffusion": {"horizon": 1024}},
        f"{T}.env.episode_steps",
        "maze large protocol's 800 steps, shorter than diffusion.horizon=1024",
    ),
    # the task's own horizon counts, not the top-level one
    (umaze(diffusion={"horizon": 320}), f"{T}.env.episode_steps", "shorter than diffusion.horizon=320"),
    (umaze(planner={"sampler_steps": 65}), f"{T}.planner.sampler_steps", "65 exceeds diffusion.n_steps=64"),
    (umaze(diffusion={"n_steps": 2}), f"{T}.planner.sampler_steps", "4 exceeds diffusion.n_steps=2"),
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
    (umaze(env={"random_goal": "yes"}), f"{T}.env.random_goal", "must be true or false, got 'yes'"),
    (umaze(env={"random_goal": 1}), f"{T}.env.random_goal", "must be true or false, got 1"),
    (umaze(collect={"steps": 1.5}), f"{T}.collect.steps", "must be an integer, got 1.5"),
    ({"model": {"dim_mults": []}}, "model.dim_mults", "non-empty list of positive integers"),
    ({"sweep": {"trials": 0}}, "sweep.trials", "must be > 0"),
    ({"sweep": {"objective": "speed"}}, "sweep.objective", "must be one of 'gain', 'score', 'unseen', 'mix'"),
    ({"sweep": {"evaluate_seed": 1000}}, "sweep.evaluate_seed", "must not be tuned on the episodes"),
    # each training seed plays evaluate.seed + seed: ranges that meet are refused, not only equal bases
    ({"seeds": [0, 1, 2], "sweep": {"evaluate_seed": 998}}, "sweep.evaluate_seed", "plus a training seed"),
    ({"sweep": {"evaluate_seed": 7000}}, "sweep.evaluate_seed", "evaluate.held_out_seed"),
    (umaze(evaluate={"held_out_seed": 1000}), f"{T}.evaluate.held_out_seed", "held-out start states must be others"),
    # every set of start states against every other, each over the training seeds: the sweep's held-out set ...
    ({"sweep": {"held_out_seed": 1000}}, "sweep.held_out_seed", "must not be tuned on the episodes"),
    ({"seeds": [0, 1, 2], "sweep": {"held_out_seed": 6998}}, "sweep.held_out_seed", f"{T}.evaluate.held_out_seed"),
    ({"sweep": {"held_out_seed": 5000}}, "sweep.held_out_seed", "others than its evaluation's"),
    # ... and evaluate-kept's default re-tests, which the other keys must leave alone
    (umaze(evaluate={"seed": 9000}), f"{T}.evaluate.seed", "evaluate-kept's default re-tests"),
    ({"seeds": [0, 1, 2], "evaluate": {"held_out_seed": 9998}}, f"{T}.evaluate.held_out_seed", "--held-out-seed"),
    ({"seeds": [0, 3], "sweep": {"evaluate_seed": 8997}}, "sweep.evaluate_seed", "evaluate-kept --eval-seed (9000)"),
    ({"seeds": [0, 1000], "sweep": {"space": None}}, "seeds", "evaluate-kept's two default sets"),
    ({"sweep": {"task": "maze2d-large"}}, "sweep.task", "must be one of tasks"),
    ({"seeds": []}, "seeds", "needs at least one training seed"),
    ({"seeds": [0, 1, 0]}, "seeds", "lists a seed twice"),
    ({"seeds": [-2]}, "seeds[0]", "must be >= 0, got -2"),
    ({"seeds": 3}, "seeds", "must be a list"),
    ({"sweep": {"space": {"alpha": {"low": NAN, "high": 1.0}}}}, "sweep.space.alpha.low", "finite"),
    ({"sweep": {"space": {"alpha": {"lo": 1.0, "high": 2.0}}}}, "sweep.space.alpha", "unknown field 'lo'"),
    ({"sweep": {"space": {"alpha": 3}}}, "sweep.space.alpha", "must be a mapping"),
    ({"sweep": {"space": [1, 2]}}, "sweep.space", "must map params keys to ranges"),
    ({"sweep": {"storage": 5}}, "sweep.storage", "must be a string, got 5"),
    # the task lists: `tasks` names defined tasks, `unseen_tasks` exactly those with an unseen task, `evolve` one
    ({"tasks": []}, "tasks", "must list at least one task"),
    ({"tasks": None}, "tasks", "must list at least one task"),
    ({"tasks": ["maze2d-medium"]}, "tasks", "'maze2d-medium' is not a task defined under 'task'"),
    ({"tasks": [UMAZE, UMAZE]}, "tasks", "lists a task twice"),
    ({"unseen_tasks": []}, "unseen_tasks", "the tasks of 'tasks' whose family has an unseen task: ['maze2d-umaze']"),
    ({"unseen_tasks": ["maze2d-medium"]}, "unseen_tasks", "'maze2d-medium' is not a task defined under 'task'"),
    (
        {
            "task": {"maze2d-medium": {"family": "maze2d", "env": {"maze": "medium"}}},
            "unseen_tasks": [UMAZE, "maze2d-medium"],
        },
        "unseen_tasks",
        "must list exactly the tasks of 'tasks' whose family has an unseen task: ['maze2d-umaze']",
    ),
    (
        {
            "task": {"hopper-medium": {"family": "locomotion"}},
            "tasks": [UMAZE, "hopper-medium"],
            "unseen_tasks": [UMAZE, "hopper-medium"],
        },
        "unseen_tasks",
        "must list exactly the tasks of 'tasks' whose family has an unseen task: ['maze2d-umaze']",
    ),
    ({"evolve": "maze2d-medium"}, "evolve", "'maze2d-medium' must be one of tasks ['maze2d-umaze'] (or null)"),
    (
        {"task": {"maze2d-medium": {"family": "maze2d", "env": {"maze": "medium"}}}, "evolve": "maze2d-medium"},
        "evolve",
        "must be one of tasks ['maze2d-umaze']",
    ),
    ({"evolve": None}, "evolve", "is null but phases are declared"),
    (
        {
            "task": {"hopper-medium": {"family": "locomotion"}},
            "tasks": [UMAZE, "hopper-medium"],
            "evolve": "hopper-medium",
            "evolution": {"discriminate": {"tracking": False}},
        },
        "phases.phase1.discriminate.tracking",
        "locomotion segments are judged by executing them",
    ),
    (
        {
            "task": {"hopper-medium": {"family": "locomotion", "evolution": {"reset_fraction": 1.5}}},
            "tasks": [UMAZE, "hopper-medium"],
        },
        "task.hopper-medium.evolution.reset_fraction",
        "less than or equal to 1",
    ),
    # task entries: names, families, their shape
    ({"task": None}, "task", "must be a mapping of task names to their settings"),
    ({"task": {"hopper-fast": {"family": "locomotion"}}}, "task.hopper-fast", "unknown locomotion task 'hopper-fast'"),
    (
        {
            "tasks": ["hopper-medium"],
            "unseen_tasks": [],
            "evolve": None,
            "phases": {},
            "task": {"hopper-medium": {"family": "locomotion", "episode_steps": 10}},
        },
        "task.hopper-medium.episode_steps",
        "10 is shorter than diffusion.horizon=128",
    ),
    (
        {
            "tasks": ["hopper-medium"],
            "unseen_tasks": [],
            "evolve": None,
            "phases": {},
            "task": {"hopper-medium": {"family": "locomotion", "guide": {"warm_start_step": 64}}},
        },
        "task.hopper-medium.guide.warm_start_step",
        "64 is not a diffusion step (0..63, diffusion.n_steps)",
    ),
    (
        {"task": {"hopper-medium": {"family": "locomotion", "guide": {"warm_start_step": -1}}}},
        "task.hopper-medium.guide.warm_start_step",
        "greater than or equal to 0",
    ),
    ({"task": {"hopper-medium": {"family": "locomotion", "env": {}}}}, "task.hopper-medium.env", "unknown"),
    ({"task": {"Maze2D": {"family": "maze2d"}}}, "task.Maze2D", "task names are lower-case letters"),
    (
        {"task": {"maze2d-medium": {"family": "quadcopter"}}},
        "task.maze2d-medium.family",
        "must be one of ['kuka', 'locomotion', 'maze2d']",
    ),
    ({"task": {"maze2d-medium": {"env": {"maze": "medium"}}}}, "task.maze2d-medium.family", "got None"),
    ({"task": {"maze2d-medium": 5}}, "task.maze2d-medium", "must be a mapping with a 'family' key, got 5"),
    (umaze(diffusion=5), f"{T}.diffusion", "must be a mapping of diffusion keys to override, got 5"),
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


def test_every_set_of_start_states_is_checked_and_no_two_share_an_episode(tmp_path: Path) -> None:
    """The evolved task's six sets (evaluation, held out, the sweep's two, evaluate-kept's two) over five training
    seeds: disjoint seed numbers, and, since episode i of seed b plays ``episode_rng(b, i)`` (the episode a word of
    its own, not added to b), no episode of one set starts like any episode of another, however many each plays."""
    params = load_params(write_params(tmp_path, {"seeds": [0, 1, 2, 3, 4]}))
    sets = start_state_sets(UMAZE, params.task[UMAZE].evaluate, params.sweep)
    assert [s.key for s in sets] == [
        f"{T}.evaluate.seed",
        f"{T}.evaluate.held_out_seed",
        "sweep.evaluate_seed",
        "sweep.held_out_seed",
        "evaluate-kept --eval-seed",
        "evaluate-kept --held-out-seed",
    ]
    assert (sets[-2].base, sets[-1].base) == (KEPT_EVAL_SEED, KEPT_HELD_OUT_SEED)
    numbers = [start_seeds(s.base, params.seeds) for s in sets]
    assert sum(map(len, numbers)) == len(set().union(*numbers)) == 30
    firsts = [episode_rng(seed, i).random() for seed in set().union(*numbers) for i in range(200)]
    assert len(set(firsts)) == len(firsts)
    # the sets meet as soon as two bases lie closer than the spread of the training seeds
    with pytest.raises(ConfigError, match="sweep.held_out_seed: 5004 plus a training seed is sweep.evaluate_seed"):
        load_params(write_params(tmp_path, {"seeds": [0, 1, 2, 3, 4], "sweep": {"held_out_seed": 5004}}))
    load_params(write_params(tmp_path, {"seeds": [0, 1, 2, 3, 4], "sweep": {"held_out_seed": 5005}}))


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("lr: 0.001", "lr: .nan", "pretrain.lr: must be a finite number, got nan"),
        ("lr: 0.001", "lr: .inf", "pretrain.lr: must be a finite number, got inf"),
        ("lr: 0.001", "lr: 1e999", "pretrain.lr: must be a finite number, got inf"),  # YAML 1.1: a string
        ("goal_radius: 0.5", "goal_radius: .NaN", f"{T}.env.goal_radius: must be a finite number, got nan"),
        ("  seed: 0\n    gold_coin", "  seed: -1\n    gold_coin", f"{T}.collect.seed: must be >= 0, got -1"),
        ("heartbeat_s: 30", "heartbeat_s: 0", "sweep.heartbeat_s: must be > 0, got 0"),
        (
            "episode_steps: null",
            "episode_steps: 64",
            f"{T}.env.episode_steps: 64 is shorter than diffusion.horizon=128",
        ),
        ("tasks: [maze2d-umaze]", "tasks: []", "tasks: must list at least one task"),
        ("unseen_tasks: [maze2d-umaze]", "unseen_tasks: []", "unseen_tasks: must list exactly the tasks of 'tasks'"),
        ("evolve: maze2d-umaze", "evolve: null", "evolve: is null but phases are declared"),
        ("evolve: maze2d-umaze", "evolve: maze2d-large", "evolve: 'maze2d-large' must be one of tasks"),
        ("    family: maze2d", "    family: maze3d", f"{T}.family: must be one of ['kuka', 'locomotion', 'maze2d']"),
        ("phase1:\n    previous: 0", "phase1: 3", "phases.phase1: must be a mapping"),
        ("random_goal: false", "random_goal: no", None),  # YAML 1.1 reads `no` as false: accepted
    ],
)
def test_rejected_values_as_written_in_yaml(tmp_path: Path, old: str, new: str, key: str | None) -> None:
    text = (REPO / "params.yaml").read_text()
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
    task = params.resolve(UMAZE)
    with pytest.raises(ValueError, match="unknown maze"):
        dataclasses.replace(task.settings.env, maze="mars")
    with pytest.raises(ValueError, match="unknown maze"):
        EnvParams(maze="mars")
    with pytest.raises(ValueError, match="horizon"):  # replacing a section re-runs the cross-section checks
        dataclasses.replace(params, diffusion=dataclasses.replace(params.diffusion, horizon=102))
    with pytest.raises(dataclasses.FrozenInstanceError):
        params.pretrain.lr = 1.0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        task.settings.env.maze = "large"  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        task.diffusion = params.diffusion  # type: ignore[misc]
    assert dataclasses.replace(params.pretrain, steps=3).steps == 3
    assert pickle.loads(pickle.dumps(load_params(REPO / "params.yaml"))) == load_params(REPO / "params.yaml")


def test_describe_lists_the_task_and_the_stages_dvc_runs() -> None:
    params = load_params(REPO / "params.yaml")
    lines = describe(params)
    assert lines[0].startswith(f"tasks: {UMAZE}")
    assert lines[1].startswith(f"task {UMAZE}: family maze2d, horizon 128")
    task = params.resolve(UMAZE)
    assert get_family("maze2d").describe(task) == {"maze": "umaze", "episode_steps": 300}  # 300-step episodes
    stages = [line.strip().split(":")[0] for line in lines[lines.index("stages:") + 1 :]]
    assert stages == stage_names(params)
    phase0 = ("code", "collect", "reference", "pretrain", "evaluate-phase0", "evaluate-unseen-phase0")
    assert stages[:6] == [f"{s}@{UMAZE}" for s in phase0]
    phase_stages = ("generate", "discriminate", "finetune", "evaluate", "control", "evaluate-control")
    phase_stages += ("evaluate-unseen", "evaluate-unseen-control")
    assert stages[6:14] == [f"{s}@phase1" for s in phase_stages]
    assert stages[-2:] == ["summarize", "report"] and len(stages) == 6 + 8 + 2  # the default runs one phase
    dvc = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    items = {"${tasks}": params.tasks, "${unseen_tasks}": params.unseen_tasks, "${phases}": params.phase_names}
    items |= {"${task}": list(params.task)}
    items |= {"${collect_tasks}": params.collect_tasks, "${imports}": list(params.imports)}
    items |= {"${pretrain_tasks}": params.pretrain_tasks, "${pretrained}": list(params.pretrained)}
    expanded = {f"{name}@{k}" for name, spec in dvc.items() if "foreach" in spec for k in items[spec["foreach"]]} | {
        name for name, spec in dvc.items() if "foreach" not in spec
    }
    assert set(stages) == expanded


def test_describe_and_stages_of_a_phase0_only_locomotion_task() -> None:
    params = params_from_dict(
        {
            "tasks": ["hopper-medium"],
            "unseen_tasks": [],
            "evolve": None,
            "task": {"hopper-medium": {"family": "locomotion"}},
        }
    )
    stages = stage_names(params)
    assert stages == [
        *(f"{s}@hopper-medium" for s in ("code", "collect", "reference", "pretrain", "evaluate-phase0")),
        "summarize",
        "report",
    ]
    lines = describe(params)
    assert lines[0].startswith("tasks: hopper-medium") and "evolve: None, phases: 0" in lines
    assert any(line.strip().startswith("+ value function") for line in lines)


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
    assert params.diffusion.horizon == 100 and params.resolve(UMAZE).diffusion.horizon == 100


def test_valid_custom_layout_and_episode_length(tmp_path: Path) -> None:
    layout = ["######", "#..#G#", "#....#", "#.##.#", "######"]
    # the paper's reward/length thresholds exist for the three D4RL mazes only, so a custom maze selects by quantile
    overlay = umaze(env={"layout": layout, "episode_steps": 200}) | {
        "evolution": {"discriminate": {"rule": "quantile"}}
    }
    params = load_params(write_params(tmp_path, overlay))
    settings = params.resolve(UMAZE).settings
    assert settings.env.layout == layout and settings.env.episode_steps == 200
    assert settings.maze_name == "custom" and settings.episode_steps == 200


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
    # an empty mapping replaces the base one (`phases: {}` in a profile means no phases)
    assert deep_merge(base, {"a": {}}) == {"a": {}, "b": 3}
    assert deep_merge({"a": {"b": {"x": 1}, "y": 2}}, {"a": {"b": {}}}) == {"a": {"b": {}, "y": 2}}
    assert deep_merge(base, {}) == base and base == {"a": {"x": 1, "y": 2}, "b": 3}


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
    assert f"pretrain@{UMAZE}:" in result.output and "evaluate@phase1" in result.output  # what it will run


def test_cli_profile_writes_params(tmp_path: Path) -> None:
    out = tmp_path / "params.yaml"
    args = ["profile", "paper-medium", "--params", str(out), "--profiles-dir", str(PROFILES)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert load_params(out).evolved.settings.env.maze == "medium"
    result = CliRunner().invoke(app, ["profile", "nope", "--params", str(out), "--profiles-dir", str(PROFILES)])
    assert result.exit_code == 2 and "unknown profile" in result.output


def test_cli_set_validates_and_keeps_the_rest_of_the_file(tmp_path: Path) -> None:
    out = tmp_path / "params.yaml"
    out.write_text((REPO / "params.yaml").read_text())
    result = CliRunner().invoke(app, ["set", "seeds=[0, 1, 2]", "--params", str(out)])
    assert result.exit_code == 0, result.output
    assert load_params(out).seeds == (0, 1, 2) and "# Written by `adaptdiffuser profile quick`" in out.read_text()
    before = out.read_text()
    for bad, message in (("seeds=[1, 1]", "lists a seed twice"), ("evolve=nowhere", "evolve"), ("seeds", "key=value")):
        result = CliRunner().invoke(app, ["set", bad, "--params", str(out)])
        assert result.exit_code == 2 and message in result.output, result.output
    assert out.read_text() == before  # a rejected value leaves the file as it was


def apply_and_load(profile: str, tmp_path: Path) -> Params:
    return load_params(apply_profile(profile, PROFILES, tmp_path / "params.yaml"))


def test_a_locomotion_task_with_phases_describes_its_coin_stages(tmp_path: Path) -> None:
    """``check`` on a locomotion task with phases: its coin stages are named as skipped (no gold-coin task)."""
    p = apply_and_load("quick-locomotion", tmp_path)
    lines = describe(p)
    assert "  evaluate-unseen@phase1: skipped (hopper-medium has no unseen task)" in lines
    assert p.evolve == "hopper-medium" and p.phase(2).discriminate.rule == "paper"


def test_the_kuka_profiles_describe_their_data_and_phases(tmp_path: Path) -> None:
    """``check`` on the KUKA profiles: the collect line is the family's own; evolution phases on the paper profile."""
    lines = describe(apply_and_load("quick-kuka", tmp_path))
    assert "  collect@kuka-stacking: 300 scripted stacking demonstrations (seed 0)" in lines
    assert "  finetune@phase2: 3000 steps on phases [1, 2] + expert (0.5 of each batch)" in lines
    lines = describe(apply_and_load("paper-kuka", tmp_path))
    assert "  discriminate@phase1: paper thresholds, tracking error <= 1.02" in lines
    assert "  evaluate-unseen@phase2: pick-and-place, 100 episodes in each of setups [1, 2]" in lines
    assert (
        "  evaluate-unseen-control@phase2: the control, pick-and-place, 100 episodes in each of setups [1, 2]" in lines
    )


def test_science_profile_runs_both_tasks_on_three_seeds(tmp_path: Path) -> None:
    p = apply_and_load("science", tmp_path)
    assert p.tasks == ("maze2d-umaze", "hopper-medium") and p.seeds == (0, 1, 2)
    assert p.resolve("hopper-medium").family == "locomotion" and len(p.phases) == 2


def test_exponent_without_dot_is_a_number(tmp_path: Path) -> None:
    path = tmp_path / "params.yaml"
    path.write_text((REPO / "params.yaml").read_text().replace("lr: 0.001\n", "lr: 1e-3\n"))
    assert load_params(path).pretrain.lr == pytest.approx(1e-3)
    path.write_text((REPO / "params.yaml").read_text().replace("lr: 0.001\n", "lr: fast\n"))
    with pytest.raises(ConfigError, match="pretrain.lr"):
        load_params(path)


def test_task_override_is_merged_over_the_top_level_section(tmp_path: Path) -> None:
    medium = {"family": "maze2d", "env": {"maze": "medium"}, "diffusion": {"horizon": 256, "n_steps": 128}}
    overlay = {
        "tasks": [UMAZE, "maze2d-medium"],
        "unseen_tasks": [UMAZE, "maze2d-medium"],
        "collect_tasks": [UMAZE, "maze2d-medium"],
        "pretrain_tasks": [UMAZE, "maze2d-medium"],
        "task": {"maze2d-medium": medium | {"model": {"dim": 32}, "planner": {"sampler": "ddpm"}}},
    }
    params = load_params(write_params(tmp_path, overlay))
    m, u = params.resolve("maze2d-medium"), params.resolve(UMAZE)
    # the overridden keys are the task's, every other key of the section is the top level's
    assert m.diffusion == dataclasses.replace(params.diffusion, horizon=256, n_steps=128)
    assert m.model == dataclasses.replace(params.model, dim=32) and m.model.dim_mults == [1, 4, 8]
    assert m.planner == dataclasses.replace(params.planner, sampler="ddpm")
    assert (m.pretrain, m.evaluate) == (params.pretrain, params.evaluate)
    assert m.settings.env.maze == "medium" and m.settings.episode_steps == 600
    # the other task keeps the top-level sections
    assert (u.diffusion, u.model, u.planner) == (params.diffusion, params.model, params.planner)
    assert params.diffusion.horizon == 128 and params.model.dim == 16
    assert m.section("diffusion")["horizon"] == 256 and u.section("diffusion")["horizon"] == 128
    # the evolution phases sample with the evolved task's diffusion steps
    assert params.evolved == u
    steps = {"evolution": {"generate": {"sampler_steps": 100}}}
    evolved = load_params(write_params(tmp_path, overlay | steps | {"evolve": "maze2d-medium"}))
    assert evolved.evolved == m and evolved.phase(1).generate.sampler_steps == 100
    with pytest.raises(ConfigError, match=r"^phases\.phase1\.generate\.sampler_steps: .*n_steps=64 of maze2d-umaze"):
        load_params(write_params(tmp_path, overlay | steps))


def test_paper_rule_is_checked_on_the_evolved_task_only(tmp_path: Path) -> None:
    custom = {"family": "maze2d", "env": {"layout": ["######", "#..#G#", "#....#", "#.##.#", "######"]}}
    overlay = {"tasks": [UMAZE, "maze2d-custom"], "unseen_tasks": [UMAZE, "maze2d-custom"]}
    overlay["collect_tasks"] = overlay["pretrain_tasks"] = overlay["tasks"]
    overlay["task"] = {"maze2d-custom": custom}
    params = load_params(write_params(tmp_path, overlay))  # evolve: maze2d-umaze, rule paper
    assert (
        params.phase(1).discriminate.rule == "paper" and params.resolve("maze2d-custom").settings.maze_name == "custom"
    )
    with pytest.raises(ConfigError) as err:
        load_params(write_params(tmp_path, overlay | {"evolve": "maze2d-custom"}))
    message = str(err.value)
    assert message.startswith("phases.phase1.discriminate.rule: the rule 'paper'") and "maze2d-custom" in message
    assert len(message.splitlines()) == 1


def test_locomotion_task_entry_validates_and_bad_names_are_rejected() -> None:
    raw = {
        "tasks": ["hopper-medium"],
        "unseen_tasks": [],
        "evolve": None,
        "task": {"hopper-medium": {"family": "locomotion", "episode_steps": 200, "diffusion": {"horizon": 32}}},
    }
    params = params_from_dict(raw)
    assert list(params.task) == ["hopper-medium"] and params.phases == ()
    task = params.resolve("hopper-medium")
    assert task.family == "locomotion" and task.settings.episode_steps == 200
    assert task.diffusion.horizon == 32 and task.diffusion.n_steps == params.diffusion.n_steps
    assert get_family(task.family).describe(task) == {"env_id": "Hopper-v5", "dataset": "medium", "episode_steps": 200}
    with pytest.raises(ConfigError, match="evolve: is null, so no evolution phase runs"):
        _ = params.evolved
    # walker2d-medium-replay is a known robot and dataset too
    walker = raw | {"tasks": ["walker2d-medium-replay"], "task": {"walker2d-medium-replay": {"family": "locomotion"}}}
    assert params_from_dict(walker).resolve("walker2d-medium-replay").family == "locomotion"
    for bad in ("hopper-fast", "quadruped-medium"):
        entry = raw | {"tasks": [bad], "task": {bad: {"family": "locomotion"}}}
        with pytest.raises(ConfigError) as err:
            params_from_dict(entry)
        message = str(err.value)
        assert message.startswith(f"task.{bad}: unknown locomotion task {bad!r}"), message
        assert len(message.splitlines()) == 1
