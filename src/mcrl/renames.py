"""The names mcrl used before, and the one place that reads them as today's.

Issue 52 renamed the keys that serve every intrinsic reward but were named after MC (`mc_alpha` became
`intrinsic_alpha`, ...). mcrl writes only today's names. Files written before (config.json, a checkpoint's
meta.json and state.npz, sweep.json, metrics.csv, claims registries, users' sweep files and ``--set``) may hold
the old ones: every reader passes what it read through `new_names` (a checkpoint's array paths through
`new_path`) at the file boundary, so nothing past it, and nothing else in mcrl, knows an old name.
"""
from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from mcrl.errors import MCRLError

# old name -> today's: config keys, then metrics.csv columns (the one mapping; `new_names` applies it)
OLD_NAMES: dict[str, str] = {
    "mc_alpha": "intrinsic_alpha", "mc_models": "intrinsic_models", "mc_lr": "intrinsic_lr",
    "mc_hidden_sizes": "intrinsic_hidden_sizes", "mc_state": "intrinsic_state", "mc_history": "intrinsic_history",
    "mc_reward_low": "intrinsic_reward_low", "mc_reward_high": "intrinsic_reward_high",
    "mean_mc_reward": "mean_intrinsic_reward", "mc_bound_low": "intrinsic_bound_low",
    "mc_bound_high": "intrinsic_bound_high",
}
# A checkpoint's state.npz keys each array by its pytree path: the models' field of TrainState was `mc_models`
# (now `intrinsic`); the metric sums are keyed by metrics.csv's column names (`OLD_NAMES`).
_OLD_FIELDS = {"mc_models": "intrinsic"}

# The value a config key had in effect before it existed: a config.json written then, read as it was trained
# (`trained_config`), whatever the key's default is now.
TRAINED_BEFORE_KEY: dict[str, Any] = {"squash_correction": "exact", "her_rounding": "nearest"}


def new_names(d: Mapping[str, Any]) -> dict[str, Any]:
    """`d` with every old name replaced by today's, in the order given (a grid's run names follow it). Both names
    with different values is an error: which one was meant?"""
    for old, new in OLD_NAMES.items():
        if old in d and new in d and json.dumps(d[new], default=str) != json.dumps(d[old], default=str):
            raise MCRLError(f"keys {old}={d[old]!r} and {new}={d[new]!r} disagree: {old} is the old name of "
                            f"{new}; give only {new}")
    return {OLD_NAMES.get(k, k): v for k, v in d.items()}


def trained_config(d: Mapping[str, Any]) -> dict[str, Any]:
    """A run's config.json (or a checkpoint's copy of it) in today's names, a key it predates at the value it was
    trained with."""
    return {**TRAINED_BEFORE_KEY, **new_names(d)}


def new_path(key: str) -> str:
    """A state.npz key in today's names: `.mc_models.params[...]` -> `.intrinsic.params[...]`,
    `.metric_sums['mean_mc_reward']` -> `.metric_sums['mean_intrinsic_reward']`."""
    for old, new in _OLD_FIELDS.items():
        if key.startswith(f".{old}."):
            return f".{new}." + key[len(old) + 2:]
    head, sep, rest = key.partition("['")
    if sep and rest.endswith("']") and rest[:-2] in OLD_NAMES:
        return f"{head}['{OLD_NAMES[rest[:-2]]}']"
    return key


def old_name(new: str) -> str:
    """The name a renamed key had (itself if it has none): sweep run names and labels keep it, so a sweep given
    again into an experiment committed before the rename names its runs as then and resumes them."""
    return next((o for o, n in OLD_NAMES.items() if n == new), new)
