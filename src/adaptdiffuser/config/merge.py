"""Merging nested mappings (profiles over the quick profile, overrides over defaults)."""

from __future__ import annotations


def deep_merge(base: dict, overlay: dict) -> dict:
    """``base`` with ``overlay`` merged in, recursively for nested mappings; an empty mapping in ``overlay``
    replaces the base one (``phases: {}`` in a profile means no phases)."""
    merged = dict(base)
    for key, value in overlay.items():
        if isinstance(value, dict) and value and isinstance(merged.get(key), dict):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged
