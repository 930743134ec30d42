"""What a params file will run: the task and the pipeline's stages, one line each (for ``adaptdiffuser check``)."""

from __future__ import annotations

from adaptdiffuser.config.params import Params


def stage_names(params: Params) -> list[str]:
    """The pipeline's stages in order, as ``dvc.yaml`` names them (``generate@phase1``, ...)."""
    names = ["collect", "reference", "pretrain", "evaluate-phase0", "evaluate-coin-phase0"]
    for phase in params.phases:
        names += [f"{stage}@{phase.name}" for stage in ("generate", "discriminate", "finetune", "evaluate")]
        names.append(f"evaluate-coin@{phase.name}")
    return [*names, "summarize", "report"]


def describe(params: Params) -> list[str]:
    """Lines describing the task and every stage that will run, with the settings that matter most."""
    p = params
    layout = "custom layout" if p.env.layout is not None else f"maze {p.env.maze}"
    lines = [
        f"task: {p.task} ({layout}, {p.episode_steps}-step episodes, horizon {p.diffusion.horizon}, "
        f"{p.diffusion.n_steps} diffusion steps, alpha {p.alpha:g})",
        f"phases: {len(p.phases)}" + "".join(f", {ph.name} <- phase{ph.previous}" for ph in p.phases),
        "stages:",
        f"  collect: {p.collect.steps} expert steps (seed {p.collect.seed})",
        f"  reference: random and expert returns, {p.evaluate.episodes} episodes each",
        f"  pretrain: {p.pretrain.steps} steps, batch {p.pretrain.batch_size} x {p.pretrain.grad_accum}, "
        f"lr {p.pretrain.lr:g}",
        f"  evaluate-phase0: {p.evaluate.episodes} episodes, {_sampler(p.planner.sampler, p.planner.sampler_steps)}",
        f"  evaluate-coin-phase0: {p.gold_coin.cases_per_kind} gold-coin cases per kind",
    ]
    for phase in p.phases:
        g, d, f = phase.generate, phase.discriminate, phase.finetune
        rule = {"paper": "paper thresholds", "quantile": f"quantile {d.quantile:g}", "top_k": f"top {d.top_k}"}
        k = phase.name
        lines += [
            f"  generate@{k}: {g.tasks} plans from phase{phase.previous}, {_sampler(g.sampler, g.sampler_steps)}, "
            f"coin fraction {g.coin_fraction:g}",
            f"  discriminate@{k}: {rule[d.rule]}"
            + (f", tracking error <= {d.max_error:g}" if d.tracking else ", no tracking (planned reward)"),
            f"  finetune@{k}: {max(1, round(f.steps_fraction * p.pretrain.steps))} steps on phases "
            f"{p.lineage(phase.index)} + expert ({f.expert_weight:g} of each batch)",
            f"  evaluate@{k}: {p.evaluate.episodes} episodes",
            f"  evaluate-coin@{k}: {p.gold_coin.cases_per_kind} gold-coin cases per kind",
        ]
    return [*lines, "  summarize", "  report"]


def _sampler(name: str, steps: int) -> str:
    return f"ddim {steps} steps" if name == "ddim" else "ddpm (full chain)"
