"""Planning a sweep: a grid, command-line arguments, a YAML file or a recorded ``sweep.json`` -> runs.

A ``SweepPlan`` is a list of ``RunPlan``s, each a named, resolved ``Config``. Every grid point is
validated with ``resolve_config`` and every environment is made once (``preflight``), so a bad sweep
fails here, before anything is written. This module also owns the format of ``EXP/sweep.json``
(``RunPlan.entry`` writes its lines, ``load_sweep_json`` reads it; ``mcrl report`` reads it too).
"""
from __future__ import annotations

import itertools
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from mcrl.config import Config, resolve_config
from mcrl.renames import new_names, old_name
from mcrl.errors import MCRLError
from mcrl.run.rundir import SWEEP_JSON
from mcrl.run.rundir import label_value as _fmt  # run names and labels write values as `mcrl train`'s names do

SWEEP_FILE_KEYS = ("preset", "grid", "set", "seeds")
# Short names in configuration labels and run names (`a0.2-s3`, `alpha=0.2`). A renamed key keeps the name it had
# in them (`mcrl.renames.old_name`), so a sweep given again into a committed experiment names its runs as before
# and resumes them.
_LABEL = {"intrinsic_alpha": "alpha"}
_NAME_PREFIX = {"intrinsic_alpha": "a"}


@dataclass
class RunPlan:
    name: str
    config_key: str
    seed: int
    overrides: dict[str, Any]
    config: Config

    def entry(self) -> dict[str, Any]:
        """This run's line in sweep.json."""
        return {"name": self.name, "config_key": self.config_key, "seed": self.seed,
                "overrides": jsonable(self.overrides)}


@dataclass
class SweepPlan:
    preset: str | None
    grid: dict[str, list]
    fixed: dict[str, Any]
    runs: list[RunPlan]
    source: str = "args"  # args | file | experiment


def jsonable(x: Any) -> Any:
    """`x` as it reads back from JSON (tuples become lists, anything else its str)."""
    return json.loads(json.dumps(x, default=str))


def safe_name(s: str) -> str:
    """`s` usable as a directory name."""
    return re.sub(r"[^A-Za-z0-9._=+-]", "_", s)


def parse_alphas(text: str) -> list[float]:
    items = [t.strip() for t in str(text).split(",") if t.strip()]
    if not items:
        raise MCRLError(f"--alphas {text!r} gives an empty grid: list weights, e.g. --alphas 0,0.2,0.4")
    try:
        return [float(t) for t in items]
    except ValueError:
        raise MCRLError(f"--alphas {text!r}: give comma-separated numbers in [0, 1], e.g. 0,0.2,0.4") from None


def parse_seeds(value: Any) -> list[int]:
    """``6`` -> seeds 0..5; ``"0,3,7"`` or ``[0, 3, 7]`` -> those seeds."""
    bad = MCRLError(f"seeds {value!r}: give a count (6 = seeds 0..5) or a comma-separated list of seeds (0,3,7)")
    if isinstance(value, bool):
        raise bad
    if isinstance(value, int):
        if value < 1:
            raise MCRLError(f"seeds {value}: the count must be at least 1 (an empty grid runs nothing)")
        return list(range(value))
    if isinstance(value, (list, tuple)):
        items = list(value)
    else:
        text = str(value).strip()
        if "," not in text:
            try:
                return parse_seeds(int(text))
            except ValueError:
                raise bad from None
        items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise MCRLError(f"seeds {value!r} is empty: an empty grid runs nothing")
    try:
        seeds = [int(t) for t in items]
    except (TypeError, ValueError):
        raise bad from None
    if any(s < 0 for s in seeds) or any(isinstance(t, float) and not float(t).is_integer() for t in items):
        raise bad
    if len(set(seeds)) != len(seeds):
        raise MCRLError(f"seeds {value!r} repeat a seed: list each seed once")
    return seeds


def build_plan(preset: str | None, grid: dict[str, list], fixed: dict[str, Any] | None = None,
               source: str = "args") -> SweepPlan:
    """Expand the grid (seeds outermost, so a partial sweep has every configuration's first seeds) and
    validate every point with ``resolve_config``. Old key names (`mcrl.renames`) are read as today's."""
    if not isinstance(grid, dict) or not grid:
        raise MCRLError("the sweep's grid is empty: give at least one key with a list of values, e.g. "
                        "grid: {intrinsic_alpha: [0, 0.2]} or --alphas 0,0.2")
    grid, fixed = new_names(grid), new_names(dict(fixed or {}))
    for k, vals in grid.items():
        if not isinstance(vals, list) or not vals:
            raise MCRLError(f"grid key {k!r} has {vals!r}: give a non-empty list of values, e.g. {k}: [a, b] "
                            "(a list-valued key such as hidden_sizes takes a list of lists)")
    both = sorted(set(grid) & set(fixed))
    if both:
        raise MCRLError(f"key(s) {both} are both in the grid and fixed (set / --set): keep each key in one place")
    if "preset" in grid or "preset" in fixed:
        raise MCRLError("`preset` is not a grid or set key: give one preset per sweep (one experiment directory)")
    resolve_config(preset, fixed)  # unknown keys / bad values in the fixed part: one message, not one per point

    seed_vals = grid.get("seed")
    if seed_vals is not None:
        seed_vals = parse_seeds(seed_vals)
    keys = [k for k in grid if k != "seed"]
    combos = list(itertools.product(*(grid[k] for k in keys)))
    runs: list[RunPlan] = []
    seen_cfg: dict[str, str] = {}
    for seed_i in range(len(seed_vals) if seed_vals is not None else 1):
        for combo in combos:
            point = dict(zip(keys, combo))
            if seed_vals is not None:
                point["seed"] = seed_vals[seed_i]
            overrides = {**fixed, **point}
            label = ", ".join(f"{k}={v!r}" for k, v in point.items()) or "(no grid keys)"
            try:
                cfg = resolve_config(preset, overrides)
            except MCRLError as e:
                raise MCRLError(f"grid point {label}: {e}") from None
            key_parts = [f"{_LABEL.get(k, old_name(k))}={_fmt(getattr(cfg, k))}" for k in keys]
            config_key = ",".join(key_parts) or (preset or cfg.env_id)
            name_parts = [f"{_NAME_PREFIX[k]}{_fmt(getattr(cfg, k))}" if k in _NAME_PREFIX
                          else f"{_LABEL.get(k, old_name(k))}={_fmt(getattr(cfg, k))}" for k in keys]
            name = safe_name("-".join(name_parts + [f"s{cfg.seed}"]))
            ident = cfg.to_json()
            if ident in seen_cfg:
                raise MCRLError(f"grid point {label} gives the same config as {seen_cfg[ident]}: "
                                "remove the repeated value")
            seen_cfg[ident] = label
            runs.append(RunPlan(name, config_key, int(cfg.seed), overrides, cfg))
    names = [r.name for r in runs]
    if len(set(names)) != len(names):  # distinct configs whose labels collapse to one name
        for i, r in enumerate(runs):
            r.name = f"{r.name}-{i}"
    preflight(runs)
    return SweepPlan(preset, {k: list(v) for k, v in grid.items()}, fixed, runs, source)


def preflight(runs: list[RunPlan]) -> None:
    """What train() would reject only after starting: unknown or unsuitable environments."""
    from mcrl.envs import inspect, make_env  # makes environments: imported only when a plan is built

    checked = set()
    for r in runs:
        cfg = r.config
        ident = json.dumps([cfg.env_id, cfg.env_kwargs, cfg.her, cfg.intrinsic_state], sort_keys=True, default=str)
        if ident in checked:
            continue
        checked.add(ident)
        env = make_env(cfg)
        try:
            inspect(env, cfg)
        finally:
            env.close()


def plan_from_args(preset: str | None, alphas: str | None = None, seeds: Any = None,
                   fixed: dict[str, Any] | None = None) -> SweepPlan:
    """``mcrl sweep --preset P --alphas 0,0.2 --seeds N``: a grid over intrinsic_alpha and seeds."""
    grid: dict[str, list] = {}
    if alphas is not None:
        grid["intrinsic_alpha"] = parse_alphas(alphas)
    if seeds is not None:
        grid["seed"] = parse_seeds(seeds)
    if not grid:
        raise MCRLError("the sweep's grid is empty: give --alphas 0,0.2,... and/or --seeds N (or --file sweep.yaml)")
    return build_plan(preset, grid, fixed, source="args")


def plan_from_file(path: str | Path, extra_fixed: dict[str, Any] | None = None) -> SweepPlan:
    """A YAML sweep file: ``preset: NAME``, ``grid: {key: [values]}``, optional ``set: {key: value}``
    (fixed overrides) and ``seeds: N | [list]`` (shorthand for ``grid: {seed: ...}``)."""
    p = Path(path)
    if not p.is_file():
        raise MCRLError(f"sweep file {path} not found: give a YAML file with preset, grid and optional set")
    try:
        doc = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        where = getattr(e, "problem_mark", None)
        at = f" at line {where.line + 1}" if where is not None else ""
        raise MCRLError(f"sweep file {path} is not valid YAML{at}: fix its syntax") from None
    if not isinstance(doc, dict):
        raise MCRLError(f"sweep file {path} must be a YAML mapping with keys preset, grid, set "
                        f"(e.g. grid: {{intrinsic_alpha: [0, 0.2], seed: [0, 1]}})")
    unknown = sorted(set(doc) - set(SWEEP_FILE_KEYS))
    if unknown:
        raise MCRLError(f"sweep file {path}: unknown top-level key(s) {unknown}: use {', '.join(SWEEP_FILE_KEYS)} "
                        "(config keys go under grid or set)")
    grid = doc.get("grid") or {}
    fixed = doc.get("set") or {}
    if not isinstance(grid, dict) or not isinstance(fixed, dict):
        raise MCRLError(f"sweep file {path}: grid and set must be mappings of config keys, "
                        "e.g. grid: {intrinsic_alpha: [0, 0.2]} and set: {total_steps: 10000}")
    grid = dict(grid)
    if doc.get("seeds") is not None:
        if "seed" in grid:
            raise MCRLError(f"sweep file {path} gives both seeds and grid.seed: keep one")
        grid["seed"] = parse_seeds(doc["seeds"])
    preset = doc.get("preset")
    if preset is not None and not isinstance(preset, str):
        raise MCRLError(f"sweep file {path}: preset must be a preset name (`mcrl presets`)")
    fixed = {**fixed, **(extra_fixed or {})}  # command-line --set / --steps win over the file's set
    try:
        return build_plan(preset, grid, fixed, source="file")
    except MCRLError as e:
        raise MCRLError(f"sweep file {path}: {e}") from None


def plan_from_experiment(exp_dir: str | Path) -> SweepPlan:
    """The sweep recorded in ``EXP/sweep.json``: continue all of its runs."""
    d = Path(exp_dir)
    sweep = load_sweep_json(d)
    if sweep is None:
        raise MCRLError(f"{d} holds no {SWEEP_JSON}: to continue a sweep pass the directory `mcrl sweep` wrote; "
                        "to start one give --preset with --alphas/--seeds, or --file sweep.yaml")
    preset = sweep.get("preset") or None
    runs = []
    for e in sweep.get("runs") or []:
        try:
            cfg = resolve_config(preset, dict(e.get("overrides") or {}))
        except MCRLError as err:
            raise MCRLError(f"{d / SWEEP_JSON}: run {e.get('name')}: {err}") from None
        runs.append(RunPlan(str(e["name"]), str(e.get("config_key") or e["name"]), int(cfg.seed),
                            dict(e.get("overrides") or {}), cfg))
    if not runs:
        raise MCRLError(f"{d / SWEEP_JSON} lists no runs: start a new sweep with --preset/--alphas or --file")
    preflight(runs)
    return SweepPlan(preset, dict(sweep.get("grid") or {}), dict(sweep.get("set") or {}), runs, "experiment")


def load_sweep_json(d: Path) -> dict | None:
    """``d/sweep.json``, or None when there is none; MCRLError when it is not a sweep file."""
    path = d / SWEEP_JSON
    if not path.is_file():
        return None
    try:
        obj = json.loads(path.read_text())
    except ValueError as e:
        raise MCRLError(f"{path} is not valid JSON ({e}): fix or delete it") from None
    if not isinstance(obj, dict) or not isinstance(obj.get("runs", []), list):
        raise MCRLError(f"{path} is not a sweep file (expected {{'preset', 'runs': [...]}}): use another --exp")
    return obj
