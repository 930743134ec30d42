"""What a params file will run: the tasks and the pipeline's stages, one line each (for ``adaptdiffuser check``)."""

from __future__ import annotations

from adaptdiffuser.config.params import Params
from adaptdiffuser.config.tasks import TaskParams


def stage_names(params: Params) -> list[str]:
    """The pipeline's stages in order, as ``dvc.yaml`` names them (``pretrain@hopper-medium``, ``generate@phase1``).
    Each entry of ``task`` has a ``code@<task>`` stage: the fingerprint of the code its stages run."""
    names = [f"code@{task}" for task in params.task]
    for task in params.tasks:
        data = f"import-data@{task}" if task in params.imports else f"collect@{task}"
        phase0 = f"import-model@{task}" if task in params.pretrained else f"pretrain@{task}"
        names += [data, f"reference@{task}", phase0]
        names.append(f"evaluate-phase0@{task}")
        if task in params.unseen_tasks:
            names.append(f"evaluate-unseen-phase0@{task}")
    stages = ("generate", "discriminate", "finetune", "evaluate", "control", "evaluate-control")
    stages += ("evaluate-unseen", "evaluate-unseen-control")
    for phase in params.phases:
        names += [f"{stage}@{phase.name}" for stage in stages]
    return [*names, "summarize", "report"]


def describe(params: Params) -> list[str]:
    """Lines describing the tasks and every stage that will run, with the settings that matter most."""
    p = params
    lines = [f"tasks: {', '.join(p.tasks)} (alpha {p.alpha:g}), training seeds {list(p.seeds)}"]
    for name in p.tasks:
        t = p.resolve(name)
        lines.append(
            f"task {name}: family {t.family}, horizon {t.diffusion.horizon}, {t.diffusion.n_steps} diffusion steps, "
            f"model dim {t.model.dim} x {t.model.dim_mults}"
        )
    lines += [
        f"evolve: {p.evolve}, phases: {len(p.phases)}"
        + "".join(f", {ph.name} <- phase{ph.previous}" for ph in p.phases),
        "stages:",
    ]
    lines += [f"  code@{name}: the fingerprint of the core and family {p.task[name].family}" for name in p.task]
    for name in p.tasks:
        t = p.resolve(name)
        src = p.imports.get(name)
        data = f"import-data@{name}: {src.format} data from {src.path}" if src else f"collect@{name}: {_data(t)}"
        phase0 = (
            f"  import-model@{name}: trained models from {p.pretrained[name]}"
            if name in p.pretrained
            else f"  pretrain@{name}: {t.pretrain.steps} steps, batch {t.pretrain.batch_size} x "
            f"{t.pretrain.grad_accum}, lr {t.pretrain.lr:g}"
        )
        lines += [f"  {data}", f"  reference@{name}: the score's 0 and 100, {t.evaluate.episodes} episodes", phase0]
        if hasattr(t.settings, "value"):
            lines.append(
                f"    + value function: {t.settings.value.steps} steps, discount {t.settings.value.discount:g}"
            )
        lines.append(f"  evaluate-phase0@{name}: {t.evaluate.episodes} episodes, {_planner(t)}")
        if name in p.unseen_tasks:
            lines.append(f"  evaluate-unseen-phase0@{name}: {t.settings.describe_unseen()}")
    if p.phases:
        t = p.evolved
        unseen = t.settings.describe_unseen() if t.name in p.unseen_tasks else f"skipped ({t.name} has no unseen task)"
        for phase in p.phases:
            g, d, f = phase.generate, phase.discriminate, phase.finetune
            rule = {"paper": "paper thresholds", "quantile": f"quantile {d.quantile:g}", "top_k": f"top {d.top_k}"}
            k = phase.name
            lines += [
                f"  generate@{k}: {g.tasks} {'plans' if g.recipe == 'plans' else g.recipe} from {t.name} "
                f"phase{phase.previous}, {_sampler(g.sampler, g.sampler_steps)}"
                + (f", replanning every {g.replan_every} steps" if g.recipe != "plans" else ""),
                f"  discriminate@{k}: {rule[d.rule]}"
                + (f", tracking error <= {d.max_error:g}" if d.tracking else ", no tracking (planned reward)"),
                f"  finetune@{k}: {max(1, round(f.steps_fraction * t.pretrain.steps))} steps on phases "
                f"{p.lineage(phase.index)} + expert ({f.expert_weight:g} of each batch)",
                f"  evaluate@{k}: {t.evaluate.episodes} episodes",
                f"  control@{k}: the same steps from phase{phase.previous} on expert data only (equal compute)",
                f"  evaluate-control@{k}: the control on the same episodes; gain of {k} over it",
                f"  evaluate-unseen@{k}: {unseen}",
                f"  evaluate-unseen-control@{k}: the control, {unseen}",
            ]
    return [*lines, "  summarize", "  report"]


def _data(task: TaskParams) -> str:
    """The family's own line for its collect stage (``describe_data`` of its task settings)."""
    return task.settings.describe_data()


def _planner(task: TaskParams) -> str:
    text = _sampler(task.planner.sampler, task.planner.sampler_steps)
    guide = getattr(task.settings, "guide", None)
    if guide is not None:
        text += f", {guide.n_samples} value-guided samples per step (scale {guide.scale:g})"
    return text


def _sampler(name: str, steps: int) -> str:
    return f"ddim {steps} steps" if name == "ddim" else "ddpm (full chain)"
