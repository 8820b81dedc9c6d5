"""Grouping runs into configurations (arms) and naming them, for ``mcrl report``.

Runs are grouped by every config key that differs between them, except the keys that only name, place or save a
run (:data:`NOT_CONFIGURATION`); reference arms (runs with a ``peer.json``) never join mcrl's. An arm is named by
the user's label (``--with DIR=LABEL``), else by sweep.json's config keys when they name the arms one-to-one, else
by its algorithm ('SAC', 'SAC-MC 0.2', 'SAC+RND 0.2') when only the reward differs, else by the differing settings.
"""
from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

from mcrl.algo.intrinsic import THESIS_REWARD, about
from mcrl.analysis.runs import Run
from mcrl.config import Config
from mcrl.errors import MCRLError

# Config keys that name, place or only save a run (not what it trains or how it is evaluated): runs
# that differ only in these are seeds of one configuration.
NOT_CONFIGURATION = frozenset({"seed", "out_dir", "preset", "video_every", "keep_checkpoints", "save_buffer",
                               "checkpoint_every", "log_every"})


def run_settings(config: dict[str, Any]) -> dict[str, Any] | None:
    """The settings that define a run's configuration: its config.json completed with defaults
    (so a key left out equals its default), without :data:`NOT_CONFIGURATION`. None without config.json."""
    if not config:
        return None
    try:  # from_dict, not from_run_json: grouping needs the defaults filled in, not a judgement on the version
        full = Config.from_dict(config).to_dict()
    except (MCRLError, TypeError, ValueError):
        full = dict(config)  # a config this mcrl cannot read (other keys): compare it as written
    return {k: v for k, v in full.items() if k not in NOT_CONFIGURATION}


def _family(r: Run) -> str:
    """"" for mcrl runs; "<system> <algorithm>" for a reference arm."""
    if r.peer is None:
        return ""
    return f"{r.peer.get('system') or 'peer'} {r.peer.get('algorithm') or 'SAC'}"


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(map(_fmt, v)) + "]"
    return "null" if v is None else str(v)


def same_value(a: Any, b: Any) -> bool:
    """Equal as JSON (a tuple from Config equals a list from sweep.json; 1 equals 1.0)."""
    return json.dumps(a, sort_keys=True, default=str) == json.dumps(b, sort_keys=True, default=str) or (
        isinstance(a, (int, float)) and isinstance(b, (int, float)) and float(a) == float(b))


def _varying(settings: Sequence[dict[str, Any]]) -> list[str]:
    """Keys whose value differs between the settings (intrinsic_alpha first, then alphabetical)."""
    def value(s: dict[str, Any], k: str) -> str:
        return json.dumps(s[k], sort_keys=True, default=str) if k in s else "<unset>"

    keys = {k for s in settings for k in s}
    vary = {k for k in keys if len({value(s, k) for s in settings}) > 1}
    return sorted(vary, key=lambda k: (k != "intrinsic_alpha", k))


def _algorithm(settings: dict[str, Any]) -> str:
    """'SAC', 'SAC-MC 0.2', 'SAC+RND 0.2': the algorithm of settings that differ from others only in the reward
    (its `About.algorithm`; 'SAC+name' for a reward this process does not know)."""
    alpha, reward = float(settings.get("intrinsic_alpha") or 0.0), str(settings.get("intrinsic") or THESIS_REWARD)
    return "SAC" if alpha == 0.0 else f"{about(reward).algorithm} {alpha:g}"


def arms(runs: Sequence[Run]) -> list[tuple[str, list[Run], str | None, dict[str, Any]]]:
    """Group runs into configurations: equal settings (and, for reference arms, the same system and
    version), whatever their sweep labels say. Labels are the user's (``--with DIR=LABEL``) where given; else
    sweep.json's config keys when they name the groups one-to-one and come from one sweep (another sweep's
    "fetchpush-sacmc-0.2" may mean something else); else the differing settings, e.g.
    ``intrinsic_alpha=0.2, mc_reduction=batch``."""
    buckets: dict[tuple[str, str, str], list[Run]] = {}  # (family, settings, user label) -> runs
    settings: dict[tuple[str, str, str], dict[str, Any]] = {}
    unstarted: list[Run] = []
    for r in runs:
        s = run_settings(r.config)
        if s is None:
            unstarted.append(r)
            continue
        if r.peer is not None:
            s["version"] = r.peer.get("version")
        key = (_family(r), json.dumps(s, sort_keys=True, default=str), r.label or "")
        buckets.setdefault(key, []).append(r)
        settings[key] = s
    # Runs not started have no config.json: they join the group of their sweep's config_key, or, when
    # that label spans several groups, the one whose settings agree with the run's sweep overrides.
    for r in unstarted:
        homes = [k for k, v in buckets.items() if k[0] == _family(r) and k[2] == (r.label or "") and k in settings
                 and r.config_key is not None
                 and any(o.config_key == r.config_key and o.source == r.source for o in v)]
        if len(homes) > 1:
            homes = [k for k in homes if all(same_value(settings[k].get(o), v) for o, v in r.overrides.items()
                                             if o not in NOT_CONFIGURATION)]
        key = homes[0] if len(homes) == 1 else (_family(r), f"unstarted:{r.source}:{r.config_key or r.name}",
                                                r.label or "")
        buckets.setdefault(key, []).append(r)
    # An arm none of whose runs has started has no settings of its own; for its name take those of a started run
    # of the same sweep whose overrides have the same keys, with the arm's override values (sweep.json's overrides
    # are a run's whole difference from the sweep's preset), so a partial sweep names its arms alike.
    for key, rs in buckets.items():
        r = rs[0]
        if key in settings or not r.overrides:
            continue
        twin = next((o for k, v in buckets.items() if k in settings and k[0] == key[0] for o in v
                     if o.config and o.source == r.source and o.overrides.keys() == r.overrides.keys()), None)
        if twin is not None:
            settings[key] = run_settings({**twin.config, **{k: v for k, v in r.overrides.items()
                                                         if k not in NOT_CONFIGURATION}})

    labels: dict[tuple[str, str, str], str] = {}
    for fam in dict.fromkeys(k[0] for k in buckets):
        keys = [k for k in buckets if k[0] == fam]
        sweep_keys = [{r.config_key for r in buckets[k]} for k in keys]
        unnamed = [k for k in keys if not k[2]]
        one_to_one = (all(len(s) == 1 and None not in s for s in sweep_keys)
                      and len({next(iter(s)) for s in sweep_keys}) == len(keys)
                      and len({r.source for k in unnamed for r in buckets[k]}) <= 1)
        # An arm is told apart from the arms that share its kind of name: the unnamed from the unnamed, a user
        # label's arms from each other; a labelled arm's settings must not lengthen every unnamed arm's name.
        vary = {user: _varying([settings[k] for k in keys if k in settings and k[2] == user])
                for user in dict.fromkeys(k[2] for k in keys)}
        for k, sk in zip(keys, sweep_keys):
            parts = ", ".join(f"{v}={_fmt(settings[k].get(v))}" for v in vary[k[2]]) if k in settings else ""
            if k in settings and not fam and set(vary[k[2]]) <= {"intrinsic_alpha", "intrinsic"}:
                parts = _algorithm(settings[k])  # only the reward differs: name the algorithm
            user = k[2]
            if user:  # the user's name; the settings too when one directory holds several configurations
                several = sum(kk[2] == user for kk in keys) > 1
                labels[k] = f"{user} ({parts})" if several and parts else user
            elif fam:
                labels[k] = f"{fam} ({parts})" if parts else fam
            elif one_to_one:
                labels[k] = next(iter(sk))
            else:
                cfg = next((r.config for r in buckets[k] if r.config), {})
                labels[k] = (parts or next((c for c in sk if c), None) or cfg.get("preset") or cfg.get("env_id")
                             or buckets[k][0].name)
    seen: dict[str, int] = {}
    for k, lab in labels.items():  # labels of groups whose settings are unknown may repeat
        seen[lab] = seen.get(lab, 0) + 1
        labels[k] = lab if seen[lab] == 1 else f"{lab} #{seen[lab]}"

    out = []
    for k, rs in buckets.items():
        peer = rs[0].peer
        system = None if peer is None else f"{peer.get('system') or 'peer'} {peer.get('version') or ''}".strip()
        out.append((labels[k], sorted(rs, key=lambda r: (r.seed is None, r.seed or 0, r.name)), system,
                    settings.get(k) or {}))
    return out

