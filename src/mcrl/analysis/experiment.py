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
  are; ``"machines"``, run name -> machine, is summarised by ``"machine"``; ``"sweeps"``, one entry per
  ``mcrl sweep`` call, is :mod:`mcrl.sweep.provenance`'s), and that of each extra directory.

Runs are grouped into configurations and named by :mod:`mcrl.analysis.grouping`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mcrl.algo.intrinsic import THESIS_REWARD
from mcrl.analysis.grouping import arms
from mcrl.analysis.runs import Run
from mcrl.errors import MCRLError
from mcrl.renames import new_names
from mcrl.run.rundir import (CONFIG, EVAL, FINAL_EVAL, METRICS, PEER, PROVENANCE, RUNS, SWEEP_JSON, is_done,
                             read_columns, read_json)


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
    def intrinsic_alpha(self) -> float | None:
        v = self._setting("intrinsic_alpha")
        return None if v is None else float(v)

    @property
    def intrinsic_schedule(self) -> str:
        """How the intrinsic weight moves during training; `constant` where no run names one (older configs)."""
        return str(self._setting("intrinsic_schedule") or "constant")

    @property
    def intrinsic(self) -> str:
        """The intrinsic reward intrinsic_alpha mixes in; the config's default, the thesis' reward, where no run
        names one (configs older than the key)."""
        return str(self._setting("intrinsic") or THESIS_REWARD)

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


# ------------------------------------------------------------------------------------ loading


def _read_json(path: Path) -> dict[str, Any]:
    return read_json(path, strict=True)  # a damaged run or sweep.json is an error, not a silently missing run


def _read_run(rd: Path, name: str, config_key: str | None, seed: Any, overrides: dict[str, Any],
              source: Path) -> Run:
    peer = _read_json(rd / PEER) or None
    final_eval = _read_json(rd / FINAL_EVAL)
    done = is_done(rd) or (peer is not None and bool(final_eval))
    status = "finished" if done else ("partial" if rd.is_dir() else "missing")
    config = new_names(_read_json(rd / CONFIG))  # files from before a rename: today's names from here on
    if seed is None and isinstance(config.get("seed"), int):
        seed = config["seed"]
    return Run(name=name, config_key=config_key, seed=seed, dir=rd, status=status, config=config,
               overrides=new_names(overrides), eval=read_columns(rd / EVAL), metrics=read_columns(rd / METRICS),
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


def read_runs(path: Path, empty_ok: bool = False) -> list[Run]:
    """The runs of a directory: an experiment directory, a run directory, a directory of run directories, or
    one whose ``runs/`` holds them (a reference arm laid out like an experiment, without sweep.json). A directory
    that holds none is an error, or no runs with ``empty_ok`` (a registry arm whose runs have not started)."""
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
        if empty_ok:
            return []
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
    return Path(text), None  # not a directory either way: read_runs says so


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
        for r in read_runs(p):
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


def group_runs(runs: Sequence[Run]) -> list[ConfigGroup]:
    """The runs' configurations (:func:`mcrl.analysis.grouping.arms`): mcrl's SAC first, then increasing alpha
    (the order of the thesis' tables), then the reference arms."""
    groups = [ConfigGroup(*arm) for arm in arms(runs)]
    groups.sort(key=lambda g: (g.peer is not None, g.intrinsic_alpha is None, g.intrinsic_alpha or 0.0, g.key))
    return groups
