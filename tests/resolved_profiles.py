"""The fully resolved params of every profile and of the committed ``params.yaml``, as the pinning fixture holds
them (``tests/data/resolved_profiles.json``, checked by ``tests/test_resolved_profiles.py``).

Each profile is written with ``adaptdiffuser profile`` and loaded; its resolved :class:`Params` (every task with its
family's settings and the generic sections merged in, every phase with the evolution defaults merged in) is
flattened to dotted keys, each value written as JSON (so ``1`` and ``1.0`` differ). The tiny variant of each
profile (``--tiny``) is pinned by the digest of the same map.

Rerun after a change that is meant to change a resolved value: ``python tests/resolved_profiles.py``.
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from adaptdiffuser.config import Params, apply_profile, load_params
from adaptdiffuser.config.defaults import plain

REPO = Path(__file__).resolve().parents[1]
PROFILES = REPO / "profiles"
FIXTURE = REPO / "tests" / "data" / "resolved_profiles.json"


def flatten(tree: Any, prefix: str = "") -> dict[str, str]:
    """Dotted key -> the JSON text of its value, for every leaf of ``tree`` (lists are leaves)."""
    if isinstance(tree, dict) and tree:
        out: dict[str, str] = {}
        for key, value in tree.items():
            out |= flatten(value, f"{prefix}.{key}" if prefix else key)
        return out
    return {prefix: json.dumps(tree, sort_keys=True)}


def resolved(params: Params) -> dict[str, str]:
    """Every resolved value of ``params``, flattened (:func:`flatten`); a task's entry as written is left out: only
    what it resolves to counts."""
    tree = plain(params)
    for task in tree["task"].values():
        task.pop("entry")
    return flatten(tree)


def digest(values: dict[str, str]) -> str:
    return hashlib.sha256(json.dumps(values, sort_keys=True).encode()).hexdigest()


def resolve_profile(name: str, tiny: bool = False) -> dict[str, str]:
    """The resolved values of profile ``name`` as ``adaptdiffuser profile name`` writes it."""
    with tempfile.TemporaryDirectory() as tmp:
        return resolved(load_params(apply_profile(name, PROFILES, Path(tmp) / "params.yaml", tiny=tiny)))


def current() -> dict[str, Any]:
    """The fixture's content as the code resolves the profiles now."""
    names = sorted(path.stem for path in PROFILES.glob("*.yaml"))
    return {
        "params.yaml": resolved(load_params(REPO / "params.yaml")),
        "profiles": {name: resolve_profile(name) for name in names},
        "tiny_digests": {name: digest(resolve_profile(name, tiny=True)) for name in names},
    }


def main() -> int:
    FIXTURE.parent.mkdir(exist_ok=True)
    FIXTURE.write_text(json.dumps(current(), indent=1, sort_keys=True) + "\n")
    print(f"wrote {FIXTURE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
