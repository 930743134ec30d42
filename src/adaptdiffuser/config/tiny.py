"""Any profile at a tiny scale: the same tasks, phases, models (width, depth, horizon), samplers and code paths, with
training steps, diffusion steps, episodes, datasets and generated batches shrunk so that the whole pipeline runs in
about a minute on a CPU (``adaptdiffuser profile NAME --tiny``). It finds a profile's configuration and shape errors
before a long run does; its scores mean nothing.

The generic sections are shrunk here; each family shrinks its own keys (``tiny`` of its task params model, given the
resolved task). Compiling is turned off (minutes per stage; ``tests/test_compiled.py`` runs the compiled path), and
the first training seed and the first evolution phase are kept: later seeds and phases run the same stages with the
same settings on other inputs (the smoke pipeline runs two phases, ``tests/test_training_seeds.py`` several
seeds)."""

from __future__ import annotations

from typing import Any

from adaptdiffuser.config.merge import deep_merge
from adaptdiffuser.config.params import Params
from adaptdiffuser.config.tasks import TaskParams

#: the most diffusion steps a tiny run keeps, and the most steps of its planner and generation samplers
TINY_DIFFUSION_STEPS = 4
TINY_SAMPLER_STEPS = 4
TINY_PRETRAIN = {"steps": 2, "ema_start": 1, "ema_every": 1, "log_every": 1, "checkpoint_every": 2, "lr_warmup": 0}
TINY_EVALUATE = {"episodes": 1, "batch_size": 1, "pictures": 1}
TINY_GENERATE = {"tasks": 4, "batch_size": 4}


def _generic_sections(sections: Params | TaskParams) -> dict[str, Any]:
    """The generic sections (top-level or one task's) at tiny scale: diffusion and sampler steps capped, not
    raised; one held-out episode where the profile plays any."""
    return {
        "diffusion": {"n_steps": min(sections.diffusion.n_steps, TINY_DIFFUSION_STEPS)},
        "planner": {"sampler_steps": min(sections.planner.sampler_steps, TINY_SAMPLER_STEPS)},
        "pretrain": TINY_PRETRAIN,
        "evaluate": TINY_EVALUATE | {"held_out_episodes": min(sections.evaluate.held_out_episodes, 1)},
    }


def tiny_overlay(params: Params, raw: dict[str, Any]) -> dict[str, Any]:
    """What to merge over ``raw`` (the params file as written, validated as ``params``) to run it at tiny scale;
    its ``phases`` replace the file's."""
    overlay: dict[str, Any] = {
        "compile": {"training": False, "sampling": False},
        "seeds": list(params.seeds[:1]),
        **_generic_sections(params),
        "evolution": {"generate": _tiny_generate(params.evolution.generate.sampler_steps)},
    }
    if params.phases:  # the first phase, its own generation settings shrunk too
        first = params.phases[0]
        raw_first = dict((raw.get("phases") or {}).get(first.name) or {})
        generate = deep_merge(dict(raw_first.get("generate") or {}), _tiny_generate(first.generate.sampler_steps))
        overlay["phases"] = {first.name: raw_first | {"generate": generate}}
    for name in raw.get("task") or {}:
        task = params.resolve(name)
        own = task.settings.tiny(task) if hasattr(task.settings, "tiny") else {}
        overlay.setdefault("task", {})[name] = deep_merge(_generic_sections(task), own)
    return overlay


def _tiny_generate(sampler_steps: int) -> dict[str, Any]:
    return TINY_GENERATE | {"sampler_steps": min(sampler_steps, TINY_SAMPLER_STEPS)}


def shrink(raw: dict[str, Any], params: Params) -> dict[str, Any]:
    """``raw`` (a params file's content, validated as ``params``) at tiny scale."""
    overlay = tiny_overlay(params, raw)
    tiny = deep_merge(raw, overlay)
    if "phases" in overlay:  # the first phase replaces the list, it is not merged into it
        tiny["phases"] = overlay["phases"]
    return tiny
