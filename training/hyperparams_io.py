"""rl-zoo style hyperparameter files: one block per env id, overridden by ``key=value`` items."""

from __future__ import annotations

from pathlib import Path

import yaml


def parse_value(text: str):
    """A command-line value: YAML (lists, booleans, ...), with ``1e-4`` read as a number
    (YAML 1.1 wants ``1.0e-4`` for a float and would keep ``1e-4`` a string)."""
    value = yaml.safe_load(text)
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def load_block(path: str | Path, env_id: str, overrides: list[str]) -> dict:
    """The block for ``env_id`` in the YAML file ``path``, with ``key=value`` overrides
    (values parsed by :func:`parse_value`, so ``1e-4``, ``[64, 64]`` and ``true`` keep their types)."""
    with open(path) as f:
        table = yaml.safe_load(f) or {}
    if env_id not in table:
        raise ValueError(f"hyperparams={str(path)!r}: no block for env id {env_id!r}")
    hp = dict(table[env_id])
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"hp={item!r}: expected key=value")
        hp[key] = parse_value(value)
    return hp
