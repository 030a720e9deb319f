"""rl-zoo style hyperparameter files: one block per env id, overridden by ``key=value`` items."""

from __future__ import annotations

from pathlib import Path

import yaml


def load_block(path: str | Path, env_id: str, overrides: list[str]) -> dict:
    """The block for ``env_id`` in the YAML file ``path``, with ``key=value`` overrides
    (values parsed as YAML, so ``1e-4``, ``[64, 64]`` and ``true`` keep their types)."""
    with open(path) as f:
        table = yaml.safe_load(f) or {}
    if env_id not in table:
        raise ValueError(f"hyperparams={str(path)!r}: no block for env id {env_id!r}")
    hp = dict(table[env_id])
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"hp={item!r}: expected key=value")
        hp[key] = yaml.safe_load(value)
    return hp
