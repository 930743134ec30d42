"""Profiles: ``profiles/quick.yaml`` overlaid with ``profiles/<name>.yaml``, written as ``params.yaml``."""

from __future__ import annotations

from pathlib import Path

import yaml

from adaptdiffuser.config.errors import ConfigError
from adaptdiffuser.config.loader import load_params, params_from_dict
from adaptdiffuser.config.merge import deep_merge
from adaptdiffuser.config.tiny import shrink
from adaptdiffuser.io import atomic_path


def apply_profile(
    profile: str, profiles_dir: str | Path = "profiles", params_path: str | Path = "params.yaml", tiny: bool = False
) -> Path:
    """Write ``params.yaml`` as the quick profile overlaid with ``profiles/<profile>.yaml``; validate first. With
    ``tiny``, the profile at tiny scale (:mod:`adaptdiffuser.config.tiny`)."""

    profiles_dir = Path(profiles_dir)
    base_path = profiles_dir / "quick.yaml"
    overlay_path = profiles_dir / f"{profile}.yaml"
    if not overlay_path.exists():
        known = sorted(p.stem for p in profiles_dir.glob("*.yaml"))
        raise ConfigError(f"unknown profile {profile!r}; known profiles: {known}")
    base_text = base_path.read_text()
    base = yaml.safe_load(base_text) or {}
    merged = deep_merge(base, yaml.safe_load(overlay_path.read_text()) or {})
    if tiny:
        merged = shrink(merged, params_from_dict(merged))
    if merged == base:  # the quick profile itself: keep its comments
        text = base_text
    else:
        how = " at tiny scale (--tiny; its scores mean nothing)" if tiny else ""
        header = (
            f"# Written by `adaptdiffuser profile {profile}{' --tiny' if tiny else ''}`: profiles/quick.yaml + "
            f"profiles/{profile}.yaml{how}\n"
        )
        text = header + yaml.safe_dump(merged, sort_keys=False)
    params_path = Path(params_path)
    with atomic_path(params_path) as tmp:
        tmp.write_text(text)
        load_params(tmp)
    return params_path
