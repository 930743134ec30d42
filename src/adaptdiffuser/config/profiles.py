"""Profiles: the config classes' defaults overlaid with ``profiles/quick.yaml`` and ``profiles/<name>.yaml``,
written as ``params.yaml`` with every value resolved (:func:`apply_profile`).

A profile may start from shared parts with ``extends: <part>`` or ``extends: [<part>, ...]``: files under
``profiles/parts/`` (named without ``.yaml``, e.g. ``two-phases``), overlaid in order before the profile's own keys;
a part may extend other parts. So a block several profiles share (two evolution phases, Diffuser's training recipe,
a task's entry) is written once.

A profile or part may also write ``family_defaults: {<family>: {...}}``: settings every task entry of that family
starts from (the entry's own keys win), so tasks sharing a scale are written once and differ only where they differ.
It is expanded into the task entries when the profile is written: ``params.yaml`` holds every task's whole entry, and
a task's stages still depend on that entry only."""

from __future__ import annotations

from pathlib import Path

import yaml

from adaptdiffuser.config.defaults import complete
from adaptdiffuser.config.errors import ConfigError
from adaptdiffuser.config.family_settings import family_names
from adaptdiffuser.config.loader import load_params, params_from_dict, read_yaml_mapping
from adaptdiffuser.config.merge import deep_merge
from adaptdiffuser.config.tiny import shrink
from adaptdiffuser.io import atomic_path

#: the folder of ``profiles/`` holding the parts profiles extend (not profiles themselves)
PARTS_DIR = "parts"
NOT_A_MAPPING = "a profile or part must be a mapping of params keys"
#: the profile key whose per-family settings are expanded into task entries (:func:`expand_family_defaults`)
FAMILY_DEFAULTS = "family_defaults"
#: the profile every profile starts from
BASE_PROFILE = "quick"


def apply_profile(
    profile: str, profiles_dir: str | Path = "profiles", params_path: str | Path = "params.yaml", tiny: bool = False
) -> Path:
    """Write ``params.yaml`` as ``profiles/<profile>.yaml`` resolved; validate first. With ``tiny``, the profile at
    tiny scale (:mod:`adaptdiffuser.config.tiny`).

    Every default is stated once: by the config classes (the generic sections in
    :mod:`adaptdiffuser.config.sections`, each family's task model in its ``params.py``). A profile is an overlay
    over them: the quick profile (``profiles/quick.yaml``, the base of every profile, stating only where it differs
    from the classes), then the parts the profile extends (:func:`profile_layers`), then the profile's own keys;
    ``family_defaults`` are expanded into the task entries (:func:`expand_family_defaults`). The classes hold the
    defaults, rather than a base profile holding every value, because the code and the tests build sections from
    them (``PretrainParams(steps=10)``) and then mean the same values the profiles do. The file written holds every
    value resolved (:func:`adaptdiffuser.config.defaults.complete`): a run uses only what it writes, and DVC
    tracks each key a stage depends on."""

    profiles_dir = Path(profiles_dir)
    base_path = profiles_dir / f"{BASE_PROFILE}.yaml"
    overlay_path = profiles_dir / f"{profile}.yaml"
    if "/" in profile or "\\" in profile or not overlay_path.exists():
        known = sorted(p.stem for p in profiles_dir.glob("*.yaml"))
        raise ConfigError(f"unknown profile {profile!r}; known profiles: {known}")
    base = read_yaml_mapping(base_path, NOT_A_MAPPING)
    if "extends" in base:
        raise ConfigError(f"{base_path}: the quick profile is the base of every profile and extends nothing")
    layers = [] if profile == BASE_PROFILE else profile_layers(overlay_path, profiles_dir / PARTS_DIR)
    merged = base
    for _, overlay in layers:
        merged = deep_merge(merged, overlay)
    merged = complete(expand_family_defaults(merged, overlay_path))
    if tiny:
        merged = shrink(merged, params_from_dict(merged))
    how = " at tiny scale (--tiny; its scores mean nothing)" if tiny else ""
    files = "".join(f" + profiles/{path.relative_to(profiles_dir).as_posix()}" for path, _ in layers)
    header = (
        f"# Written by `adaptdiffuser profile {profile}{' --tiny' if tiny else ''}`: the defaults of the config "
        f"classes + profiles/{BASE_PROFILE}.yaml{files}{how}.\n"
        "# Every value is resolved here; change the profiles (or `adaptdiffuser set key=value`), not the defaults.\n"
    )
    params_path = Path(params_path)
    with atomic_path(params_path) as tmp:
        tmp.write_text(header + yaml.dump(merged, Dumper=_ParamsDumper, sort_keys=False))
        load_params(tmp)
    return params_path


class _ParamsDumper(yaml.SafeDumper):
    """YAML as a params file reads best: a list of plain values on one line (``seeds: [0, 1, 2]``)."""


def _represent_list(dumper: yaml.SafeDumper, value: list) -> yaml.Node:
    flow = all(isinstance(item, str | int | float | bool) or item is None for item in value)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", value, flow_style=flow)


_ParamsDumper.add_representer(list, _represent_list)


def profile_layers(path: Path, parts_dir: Path, chain: tuple[Path, ...] = ()) -> list[tuple[Path, dict]]:
    """The files a profile or part overlays on the quick profile, in order, each with its keys (``extends``
    removed): the parts it extends, each preceded by its own parts, then itself; a part reached twice is
    overlaid once, where first reached. ``chain`` holds the files extending this one, to refuse a cycle."""
    if path in chain:
        raise ConfigError(f"profile parts extend each other in a cycle: {' -> '.join(p.stem for p in (*chain, path))}")
    raw = read_yaml_mapping(path, NOT_A_MAPPING)
    extends = raw.pop("extends", [])
    names = [extends] if isinstance(extends, str) else extends
    if not isinstance(names, list) or not all(isinstance(n, str) and n and not {"/", "\\"} & set(n) for n in names):
        raise ConfigError(f"{path}: extends must name a part of {parts_dir} or list them, got {extends!r}")
    layers: list[tuple[Path, dict]] = []
    for name in names:
        part = parts_dir / f"{name}.yaml"
        if not part.is_file():
            known = sorted(p.stem for p in parts_dir.glob("*.yaml"))
            raise ConfigError(f"{path}: extends unknown part {name!r}; parts: {known}")
        seen = {file for file, _ in layers}
        layers += [layer for layer in profile_layers(part, parts_dir, (*chain, path)) if layer[0] not in seen]
    return [*layers, (path, raw)]


def expand_family_defaults(raw: dict, path: Path) -> dict:
    """``raw`` without its ``family_defaults`` key, each task entry of a family it names merged over that family's
    defaults (the entry's keys win; ``family`` stays first). ``path`` names the profile in errors."""
    defaults = raw.get(FAMILY_DEFAULTS)
    if defaults is None:
        return raw
    if not isinstance(defaults, dict) or not all(isinstance(v, dict) for v in defaults.values()):
        raise ConfigError(f"{path}: {FAMILY_DEFAULTS} must map a family name to that family's task settings")
    unknown = sorted(set(defaults) - set(family_names()))
    if unknown:
        raise ConfigError(f"{path}: {FAMILY_DEFAULTS} names unknown families {unknown}; families: {family_names()}")
    if any("family" in settings for settings in defaults.values()):
        raise ConfigError(f"{path}: {FAMILY_DEFAULTS}.<family> must not set 'family' (it is the key above it)")
    expanded = {key: value for key, value in raw.items() if key != FAMILY_DEFAULTS}
    tasks = raw.get("task")
    if isinstance(tasks, dict):
        expanded["task"] = {
            name: _with_defaults(entry, defaults) if isinstance(entry, dict) else entry for name, entry in tasks.items()
        }
    return expanded


def _with_defaults(entry: dict, defaults: dict) -> dict:
    family = entry.get("family")
    if family not in defaults:
        return entry
    return {"family": family, **deep_merge(defaults[family], entry)}
