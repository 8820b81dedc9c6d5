"""Loading an experiment directory for ``mcrl report``: its runs, and their grouping into configurations.

Reads ``EXP/sweep.json`` and ``EXP/runs/<name>/`` (docs/run-directory.md). Besides each run's
``config.json``, ``eval.csv``, ``metrics.csv`` and ``done`` it reads:

- ``final_eval.json`` ``{"step", "success_rate" (or null), "mean_return", "episodes"}``: the evaluation at
  the end of training; a run's final numbers come from it, else from the last row of ``eval.csv``.
- ``peer.json`` ``{"system": "stable-baselines3", "version": "2.9.2"}`` (optional ``"algorithm"``, default
  ``"SAC"``): the run was trained by another system at the settings of its ``config.json``. Such runs are
  reference arms, grouped by system and never with mcrl runs. Besides the runs sweep.json lists, directories
  under ``EXP/runs/`` with a ``peer.json`` are read, and runs from other places can be added (``extra_runs``,
  ``mcrl report --with DIR``). A peer run without ``done`` counts as finished once it has ``final_eval.json``.
- ``EXP/provenance.json`` ``{"commit", "machine", "command", "rerun_one_seed"}`` (more keys are shown as they
  are; ``"machines"``, run name -> machine, is summarised by ``"machine"``), and that of each extra directory.

Runs are grouped into configurations by every config key that differs between them, except the keys that
only name, place or save a run (:data:`NOT_CONFIGURATION`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mcrl.analysis.plots import has_data
from mcrl.config import Config
from mcrl.errors import MCRLError
from mcrl.run.rundir import (CONFIG, EVAL, FINAL_EVAL, METRICS, PEER, RUNS, SWEEP_JSON, is_done, read_columns,
                             read_json)

PROVENANCE = "provenance.json"  # EXP/provenance.json, written by whoever ran the experiment

# Config keys that name, place or only save a run (not what it trains or how it is evaluated): runs
# that differ only in these are seeds of one configuration.
NOT_CONFIGURATION = frozenset({"seed", "out_dir", "preset", "video_every", "keep_checkpoints", "save_buffer",
                               "checkpoint_every", "log_every"})


# ------------------------------------------------------------------------------------ loading


def _number(v: Any) -> float | None:
    """A JSON number as float; None for null, strings, booleans and non-finite values."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        return None
    return float(v)


@dataclass
class Run:
    """One run (of the sweep, or a reference arm) and what it has written so far."""

    name: str
    config_key: str | None  # sweep.json's label of its configuration; None for runs from elsewhere
    seed: int | None
    dir: Path
    status: Literal["finished", "partial", "missing"]
    config: dict[str, Any] = field(default_factory=dict)
    overrides: dict[str, Any] = field(default_factory=dict)
    eval: dict[str, np.ndarray] = field(default_factory=dict)
    metrics: dict[str, np.ndarray] = field(default_factory=dict)
    final_eval: dict[str, Any] = field(default_factory=dict)  # final_eval.json; {} when absent
    peer: dict[str, Any] | None = None  # peer.json of a run trained by another system
    source: Path | None = None  # the experiment or directory it was read from
    label: str | None = None  # the user's name for its arm (`mcrl report --with DIR=LABEL`)

    @property
    def has_eval(self) -> bool:
        return has_data(self.eval, "step") and has_data(self.eval, "success_rate")

    @property
    def _final_from_json(self) -> bool:
        return _number(self.final_eval.get("mean_return")) is not None

    @property
    def final(self) -> tuple[float, float] | None:
        """(success rate, mean return) of the final evaluation, for finished runs only.

        From final_eval.json when the run wrote one (its many-episode evaluation), else from the last
        row of eval.csv.
        """
        if self.status != "finished":
            return None
        if self._final_from_json:
            s = _number(self.final_eval.get("success_rate"))
            return (math.nan if s is None else s), float(self.final_eval["mean_return"])
        if not self.has_eval:
            return None
        ret = self.eval.get("mean_return", np.array([math.nan]))
        return float(self.eval["success_rate"][-1]), float(ret[-1])

    @property
    def final_source(self) -> tuple[str, int | None] | None:
        """Where :attr:`final` comes from: ("final_eval.json" | "eval.csv", episodes if known)."""
        if self.final is None:
            return None
        if self._final_from_json:
            n = _number(self.final_eval.get("episodes"))
        else:
            eps = self.eval.get("episodes")
            n = float(eps[-1]) if eps is not None and eps.size and np.isfinite(eps[-1]) else None
        return ("final_eval.json" if self._final_from_json else "eval.csv"), (None if n is None else int(n))

    @property
    def last_step(self) -> float | None:
        steps = [c["step"][np.isfinite(c["step"])] for c in (self.eval, self.metrics) if "step" in c]
        steps = [s for s in steps if s.size]
        return float(max(s.max() for s in steps)) if steps else None

    @property
    def total_steps(self) -> int | None:
        v = self.config.get("total_steps", self.overrides.get("total_steps"))
        return int(v) if v is not None else None


@dataclass
class ConfigGroup:
    """The runs of one configuration (the same settings, different seeds)."""

    key: str  # its label in the report
    runs: list[Run]
    peer: str | None = None  # "stable-baselines3 2.9.2" for a reference arm trained by another system
    settings: dict[str, Any] = field(default_factory=dict)  # as grouped (an arm not started: its started twin's)

    def _setting(self, key: str) -> Any:
        """The first value of ``key`` that its runs' config.json or sweep overrides give, else its settings'."""
        return next((src[key] for r in self.runs for src in (r.config, r.overrides) if src.get(key) is not None),
                    self.settings.get(key))

    @property
    def mc_alpha(self) -> float | None:
        v = self._setting("mc_alpha")
        return None if v is None else float(v)

    @property
    def intrinsic(self) -> str:
        """The intrinsic reward mc_alpha mixes in; "mc" where no run names one (configs older than the key)."""
        return str(self._setting("intrinsic") or "mc")

    @property
    def total_steps(self) -> int | None:
        """The budget its runs were configured with (the first one known; an arm not started: its settings')."""
        return next((r.total_steps for r in self.runs if r.total_steps is not None), self.settings.get("total_steps"))

    @property
    def finished(self) -> list[Run]:
        return [r for r in self.runs if r.final is not None]

    def finals(self) -> tuple[np.ndarray, np.ndarray]:
        """Final eval success rates and returns of the finished runs, in seed order."""
        f = [r.final for r in self.finished]
        return np.array([s for s, _ in f], dtype=float), np.array([m for _, m in f], dtype=float)


@dataclass
class Experiment:
    """An experiment directory: its runs, and the configurations they form."""

    dir: Path
    preset: str
    runs: list[Run]
    configs: list[ConfigGroup]
    provenance: dict[str, Any] = field(default_factory=dict)  # EXP/provenance.json
    extra_sources: list[Path] = field(default_factory=list)  # the extra_runs paths read
    extra_provenance: dict[Path, dict[str, Any]] = field(default_factory=dict)  # of those that have one


def _read_json(path: Path) -> dict[str, Any]:
    return read_json(path, strict=True)  # a damaged run or sweep.json is an error, not a silently missing run


def _read_run(rd: Path, name: str, config_key: str | None, seed: Any, overrides: dict[str, Any],
              source: Path) -> Run:
    peer = _read_json(rd / PEER) or None
    final_eval = _read_json(rd / FINAL_EVAL)
    done = is_done(rd) or (peer is not None and bool(final_eval))
    status = "finished" if done else ("partial" if rd.is_dir() else "missing")
    config = _read_json(rd / CONFIG)
    if seed is None and isinstance(config.get("seed"), int):
        seed = config["seed"]
    return Run(name=name, config_key=config_key, seed=seed, dir=rd, status=status, config=config,
               overrides=overrides, eval=read_columns(rd / EVAL), metrics=read_columns(rd / METRICS),
               final_eval=final_eval, peer=peer, source=source)


def _is_run_dir(d: Path) -> bool:
    return d.is_dir() and any((d / f).is_file() for f in (CONFIG, EVAL, PEER))


def _sweep_runs(d: Path, prefix: str = "") -> tuple[dict[str, Any], list[Run]]:
    """sweep.json of experiment ``d`` and its runs: those it lists, then unlisted peer runs under runs/."""
    sweep = _read_json(d / SWEEP_JSON)
    entries = sweep.get("runs") or []
    if not entries:
        raise MCRLError(f"{d / 'sweep.json'} lists no runs: re-create the experiment with `mcrl sweep`")
    runs = [_read_run(d / RUNS / str(e["name"]), prefix + str(e["name"]), str(e.get("config_key") or e["name"]),
                      e.get("seed"), dict(e.get("overrides") or {}), d) for e in entries]
    listed = {str(e["name"]) for e in entries}
    if (d / RUNS).is_dir():
        for rd in sorted((d / RUNS).iterdir()):
            if rd.name not in listed and (rd / PEER).is_file():
                runs.append(_read_run(rd, prefix + rd.name, None, None, {}, d))
    return sweep, runs


def _extra_runs(path: Path) -> list[Run]:
    """The runs of an extra path: an experiment directory, a run directory, a directory of run directories, or
    one whose ``runs/`` holds them (a reference arm laid out like an experiment, without sweep.json)."""
    if not path.is_dir():
        raise MCRLError(f"--with {path}: no such directory: give an experiment directory, a run directory "
                        "or a directory of run directories")
    if (path / SWEEP_JSON).is_file():
        return _sweep_runs(path, prefix=f"{path.name}/")[1]
    if _is_run_dir(path):
        return [_read_run(path, path.name, None, None, {}, path.parent)]
    def run_dirs(d: Path) -> list[Path]:
        return [x for x in sorted(d.iterdir()) if _is_run_dir(x)] if d.is_dir() else []
    # its run directories, or those of its runs/ (an experiment's layout without sweep.json, e.g. a reference arm)
    subdirs = run_dirs(path) or run_dirs(path / RUNS)
    if not subdirs:
        raise MCRLError(f"--with {path} holds no run (no sweep.json, and no config.json, eval.csv or peer.json in "
                        f"it, its subdirectories or its {RUNS}/): give an experiment or run directory")
    return [_read_run(d, f"{path.name}/{d.name}", None, None, {}, path) for d in subdirs]


def split_label(arg: str | Path) -> tuple[Path, str | None]:
    """``DIR`` or ``DIR=LABEL`` (``mcrl report --with``) -> (DIR, LABEL or None). A directory whose name holds
    "=" is taken whole; otherwise the first "=" after which the text before it names a directory splits it."""
    text = str(arg)
    if Path(text).is_dir() or "=" not in text:
        return Path(text), None
    for i, ch in enumerate(text):
        if ch == "=" and Path(text[:i]).is_dir():
            label = text[i + 1:].strip()
            if not label:
                raise MCRLError(f"--with {text}: the label after '=' is empty: give --with DIR=LABEL or just DIR")
            return Path(text[:i]), label
    return Path(text), None  # not a directory either way: _extra_runs says so


def load_experiment(experiment_dir: str | Path, extra_runs: Sequence[str | Path] = ()) -> Experiment:
    """Read sweep.json, every run directory it lists, and the runs of ``extra_runs`` (experiment
    directories, run directories, or directories of run directories, each optionally ``DIR=LABEL`` to name
    its arm); raise MCRLError when there is nothing to report."""
    d = Path(experiment_dir)
    if not d.is_dir():
        raise MCRLError(f"experiment directory {d} does not exist: pass the directory `mcrl sweep` wrote "
                        "(the one holding sweep.json)")
    if not (d / SWEEP_JSON).is_file():
        raise MCRLError(f"{d} has no sweep.json: pass the experiment directory `mcrl sweep` wrote "
                        "(for a single run use `mcrl plot RUN_DIR`)")
    sweep, runs = _sweep_runs(d)
    labelled = [split_label(p) for p in extra_runs]
    extra = [p for p, _ in labelled]
    seen = {r.dir.resolve() for r in runs}
    for p, label in labelled:
        for r in _extra_runs(p):
            if r.dir.resolve() not in seen:  # a run given twice (e.g. --with EXP itself) counts once
                seen.add(r.dir.resolve())
                r.label = label
                runs.append(r)
    if not any(r.has_eval or r.final is not None for r in runs):
        started = sum(r.status != "missing" for r in runs)
        raise MCRLError(f"no run in {d} has written an evaluation yet ({started} of {len(runs)} runs started): "
                        "wait for the first evaluation (eval.csv), then run `mcrl report` again")
    preset = str(sweep.get("preset") or next((r.config["preset"] for r in runs if r.config.get("preset")), ""))
    extra_prov = {p: prov for p in extra if p.resolve() != d.resolve() and (prov := _read_json(p / PROVENANCE))}
    return Experiment(d, preset, runs, group_runs(runs), _read_json(d / PROVENANCE), extra, extra_prov)


# ------------------------------------------------------------------------------------ grouping


def _settings(config: dict[str, Any]) -> dict[str, Any] | None:
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


def _same(a: Any, b: Any) -> bool:
    """Equal as JSON (a tuple from Config equals a list from sweep.json; 1 equals 1.0)."""
    return json.dumps(a, sort_keys=True, default=str) == json.dumps(b, sort_keys=True, default=str) or (
        isinstance(a, (int, float)) and isinstance(b, (int, float)) and float(a) == float(b))


def _varying(settings: Sequence[dict[str, Any]]) -> list[str]:
    """Keys whose value differs between the settings (mc_alpha first, then alphabetical)."""
    def value(s: dict[str, Any], k: str) -> str:
        return json.dumps(s[k], sort_keys=True, default=str) if k in s else "<unset>"

    keys = {k for s in settings for k in s}
    vary = {k for k in keys if len({value(s, k) for s in settings}) > 1}
    return sorted(vary, key=lambda k: (k != "mc_alpha", k))


def _algorithm(settings: dict[str, Any]) -> str:
    """'SAC', 'SAC-MC 0.2', 'SAC+RND 0.2': the algorithm of settings that differ from others only in the reward."""
    alpha, reward = float(settings.get("mc_alpha") or 0.0), str(settings.get("intrinsic") or "mc")
    name = {"mc": "-MC", "rnd": "+RND", "icm": "+ICM"}.get(reward, f"+{reward.capitalize()}")
    return "SAC" if alpha == 0.0 else f"SAC{name} {alpha:g}"


def group_runs(runs: Sequence[Run]) -> list[ConfigGroup]:
    """Group runs into configurations: equal settings (and, for reference arms, the same system and
    version), whatever their sweep labels say. Labels are the user's (``--with DIR=LABEL``) where given; else
    sweep.json's config keys when they name the groups one-to-one and come from one sweep (another sweep's
    "fetchpush-sacmc-0.2" may mean something else); else the differing settings, e.g.
    ``mc_alpha=0.2, mc_reduction=batch``."""
    buckets: dict[tuple[str, str, str], list[Run]] = {}  # (family, settings, user label) -> runs
    settings: dict[tuple[str, str, str], dict[str, Any]] = {}
    unstarted: list[Run] = []
    for r in runs:
        s = _settings(r.config)
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
            homes = [k for k in homes if all(_same(settings[k].get(o), v) for o, v in r.overrides.items()
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
            settings[key] = _settings({**twin.config, **{k: v for k, v in r.overrides.items()
                                                         if k not in NOT_CONFIGURATION}})

    labels: dict[tuple[str, str, str], str] = {}
    for fam in dict.fromkeys(k[0] for k in buckets):
        keys = [k for k in buckets if k[0] == fam]
        sweep_keys = [{r.config_key for r in buckets[k]} for k in keys]
        unnamed = [k for k in keys if not k[2]]
        one_to_one = (all(len(s) == 1 and None not in s for s in sweep_keys)
                      and len({next(iter(s)) for s in sweep_keys}) == len(keys)
                      and len({r.source for k in unnamed for r in buckets[k]}) <= 1)
        vary = _varying([settings[k] for k in keys if k in settings])
        for k, sk in zip(keys, sweep_keys):
            parts = ", ".join(f"{v}={_fmt(settings[k].get(v))}" for v in vary) if k in settings else ""
            if k in settings and not fam and set(vary) <= {"mc_alpha", "intrinsic"}:
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

    groups = []
    for k, rs in buckets.items():
        peer = rs[0].peer
        system = None if peer is None else f"{peer.get('system') or 'peer'} {peer.get('version') or ''}".strip()
        groups.append(ConfigGroup(labels[k], sorted(rs, key=lambda r: (r.seed is None, r.seed or 0, r.name)), system,
                                  settings.get(k) or {}))
    # mcrl's SAC first, then increasing alpha (the order of the thesis' tables), then the reference arms.
    groups.sort(key=lambda g: (g.peer is not None, g.mc_alpha is None, g.mc_alpha or 0.0, g.key))
    return groups

