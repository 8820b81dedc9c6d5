"""The run directory: the one place that knows its file names, and how each file is read and written.

One reader and one writer per format (the idea of stable-baselines3's `monitor.py` / `save_util.py`). Importing
this module does not import JAX, so analysis, sweeps and tracking can read runs cheaply. The layout is
documented in docs/run-directory.md:

    RUN_DIR/config.json       the resolved Config                  read_config / write_json_atomic
    RUN_DIR/metrics.csv       one row per log interval             read_rows / read_columns
    RUN_DIR/eval.csv          one row per evaluation               read_rows / read_columns
    RUN_DIR/final_eval.json   the evaluation at the end            read_json
    RUN_DIR/done              the final summary, written last      read_json / is_done
    RUN_DIR/peer.json         reference runs made by another system (optional)
    RUN_DIR/checkpoints/step_<N>/ and checkpoints/latest           latest_checkpoint / write_latest
    RUN_DIR/videos/
    RUN_DIR/.lock             held by the one process writing the run   mcrl.run.lock

An experiment directory (``mcrl sweep``) holds ``EXP/sweep.json`` (its runs) and ``EXP/runs/<name>/``.
"""
from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

import mcrl.files as files
from mcrl.algo.metrics import BOUNDS, UPDATE_METRICS
from mcrl.config import PRESETS, Config, resolve_config
from mcrl.errors import MCRLError
from mcrl.renames import new_names

CONFIG = "config.json"
METRICS = "metrics.csv"
EVAL = "eval.csv"
FINAL_EVAL = "final_eval.json"
DONE = "done"
PEER = "peer.json"
CHECKPOINTS = "checkpoints"
LATEST = "latest"
VIDEOS = "videos"
LOCK = ".lock"  # flock-ed by the run's one writer (mcrl.run.lock)
SWEEP_JSON = "sweep.json"  # EXP/sweep.json: the runs of a sweep
RUNS = "runs"              # EXP/runs/<name>/: its run directories
PROVENANCE = "provenance.json"  # EXP/provenance.json: who ran the experiment, how (mcrl.sweep.provenance)
SMALL_FILES = (CONFIG, METRICS, EVAL, FINAL_EVAL, PEER, DONE)  # what an experiment commits of a finished run

# metrics.csv: the loop's columns around the gradient step's metrics (mcrl.algo.metrics); intrinsic_alpha is the
# weight in force, as the run's schedule gives it (mcrl.algo.schedule; empty in runs before issue 67)
METRIC_COLUMNS = ("step", "time_s", "steps_per_s", "episodes", "train_return", "train_success_rate",
                  "train_goal_moved", "eval_success_rate", "eval_mean_return", "intrinsic_alpha", *UPDATE_METRICS,
                  *BOUNDS)
EVAL_COLUMNS = ("step", "success_rate", "mean_return", "episodes")
TIMING_COLUMNS = ("time_s", "steps_per_s")  # wall-clock: the only columns that differ between identical runs
LEARNING_COLUMNS = tuple(c for c in METRIC_COLUMNS if c not in TIMING_COLUMNS)


def metric_columns(own: tuple[str, ...] = ()) -> tuple[str, ...]:
    """metrics.csv's columns of a run whose reward reports `own` (`mcrl.algo.intrinsic.About.metrics`):
    `METRIC_COLUMNS`, the layout of every built-in reward's runs, then the names of `own` it lacks, in their order
    (as `mcrl.algo.metrics.update_metrics` sums them)."""
    return (*METRIC_COLUMNS, *(k for k in own if k not in METRIC_COLUMNS))


# ----------------------------------------------------------------------------- JSON
def read_json(path: str | Path, strict: bool = False) -> dict[str, Any]:
    """A JSON object, or {} when the file is missing, unreadable or not an object (a run still being written).

    With `strict`, a file that exists but is not valid JSON is an error: a report must not quietly leave out a
    damaged run."""
    try:
        obj = json.loads(Path(path).read_text())
    except OSError:
        return {}
    except ValueError as e:
        if strict:
            raise MCRLError(f"{path} is not valid JSON ({e}): fix or delete it and re-run that step") from None
        return {}
    return obj if isinstance(obj, dict) else {}


# how the run's JSON files are laid out (`mcrl.files.write_json`'s options): config.json for people to read, the
# others (final_eval.json, done) on one line
JSON_LAYOUT = {CONFIG: {"indent": 2, "sort_keys": True}}


def write_json_atomic(path: str | Path, obj: dict[str, Any]) -> None:
    """Write one of the run's JSON files in its layout (`JSON_LAYOUT`) with the one atomic writer: a reader sees
    the old file or the new one, never half of one."""
    files.write_json(path, obj, **JSON_LAYOUT.get(Path(path).name, {}))


def read_config(run_dir: str | Path) -> Config:
    """The run's typed config (see Config.from_run_json)."""
    path = Path(run_dir) / CONFIG
    if not path.is_file():
        raise MCRLError(f"{run_dir} is not a run directory (no {CONFIG}): give the directory `mcrl train` printed")
    try:
        d = json.loads(path.read_text())
    except ValueError as e:
        raise MCRLError(f"{path} is not valid JSON ({e}): the run directory is damaged") from None
    try:
        return Config.from_run_json(d)
    except MCRLError as e:
        raise MCRLError(f"{path}: {e}") from None


def is_done(run_dir: str | Path) -> bool:
    return (Path(run_dir) / DONE).is_file()


def read_summary(run_dir: str | Path) -> dict[str, Any]:
    """The final summary `done` holds ({} while the run is unfinished)."""
    return read_json(Path(run_dir) / DONE)


# ----------------------------------------------------------------------------- CSV
def read_rows(path: str | Path) -> list[dict[str, float | None]]:
    """Rows of a run's CSV as dicts of floats (None for empty cells), columns in today's names
    (`mcrl.renames`); [] for a missing file."""
    p = Path(path)
    if not p.is_file():
        return []
    with p.open(newline="") as f:
        return [new_names({k: files.number(v) for k, v in r.items() if k is not None}) for r in csv.DictReader(f)]


def read_columns(path: str | Path) -> dict[str, np.ndarray]:
    """Columns of a run's CSV as float arrays, NaN for empty cells, in today's names (`mcrl.renames`); {} for a
    missing or empty file."""
    rows = read_rows(path)
    p = Path(path)
    if not rows:
        if not p.is_file():
            return {}
        with p.open(newline="") as f:
            header = next(csv.reader(f), None)
        return new_names({h.strip(): np.zeros(0) for h in header}) if header else {}
    return {k.strip(): np.array([math.nan if r.get(k) is None else r[k] for r in rows], dtype=float)
            for k in rows[0]}


def _whole_rows(path: Path) -> list[dict[str, str]]:
    """The rows of a CSV this package wrote, without a last row that a crash or a full disk cut short (no line
    end, or too few cells)."""
    with open(path, newline="") as f:
        text = f.read()
    lines = list(csv.reader(io.StringIO(text[: text.rfind("\n") + 1])))
    header = lines[0] if lines else []
    return [dict(zip(header, cells)) for cells in lines[1:] if len(cells) == len(header)]


def truncate_rows(path: Path, columns: tuple[str, ...], max_step: int) -> None:
    """Keep the header and the whole rows with step <= max_step (a resumed run writes the later rows again), in
    `columns` (a column the file has and `columns` lacks, e.g. a metric its reward no longer reports, is left
    out); the file is replaced atomically, so a failure here leaves it as it was."""
    if not path.exists():
        return
    rows = [new_names(r)  # a run from before a rename: today's names
            for r in _whole_rows(path) if (step := files.number(r.get("step"))) is not None and step <= max_step]
    files.write_csv(path, columns, [{k: v for k, v in r.items() if k in columns} for r in rows])


def start_csv(path: Path, columns: tuple[str, ...]) -> None:
    """A new CSV of the run holding its header (atomically)."""
    files.write_csv(path, columns)


def append_row(path: Path, columns: tuple[str, ...], row: dict[str, Any]) -> None:
    """One row of the run's CSV, appended and fsynced (`mcrl.files.append_row`)."""
    files.append_row(path, columns, row)


def video_path(run_dir: str | Path, kind: str, step: int, fmt: str) -> Path:
    """RUN_DIR/videos/<kind>_step<N>.<fmt>: `policy` from `mcrl render`, `eval` from --video-every."""
    return Path(run_dir) / VIDEOS / f"{kind}_step{step}.{fmt}"


# ----------------------------------------------------------------------------- checkpoints
def checkpoint_root(run_dir: str | Path) -> Path:
    return Path(run_dir) / CHECKPOINTS


def checkpoint_name(step: int) -> str:
    return f"step_{step:09d}"


def checkpoint_step(name: str) -> int | None:
    """The step of a checkpoint directory's name (`checkpoint_name`'s inverse); None for any other name."""
    digits = name[len("step_"):]
    return int(digits) if name.startswith("step_") and digits.isascii() and digits.isdigit() else None


def latest_checkpoint(run_dir: str | Path) -> str | None:
    """The name the `latest` pointer holds, or None (the pointer may dangle: see checkpoint.find)."""
    p = checkpoint_root(run_dir) / LATEST
    try:
        return p.read_text().strip() or None
    except OSError:
        return None


def write_latest(run_dir: str | Path, name: str) -> None:
    """Point `latest` at checkpoint `name`, atomically."""
    files.write_atomic(checkpoint_root(run_dir) / LATEST, name)


# ----------------------------------------------------------------------------- names
# Keys that say how a run is recorded and how long it runs, not what it learns: left out of its default name.
UNNAMED = ("seed", "out_dir", "preset", "total_steps", "eval_every", "eval_episodes", "final_eval_episodes",
           "log_every", "checkpoint_every", "keep_checkpoints", "save_buffer", "video_every")
NAME_SETTINGS_MAX = 100  # characters of settings in a default name; those beyond are counted ("+2"), not named


def label_value(v: Any) -> str:
    """A setting's value as run names and configuration labels write it: 0.2, true, 64x64, null."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (list, tuple)):
        return "x".join(label_value(x) for x in v)
    if v is None:
        return "null"
    if isinstance(v, dict):
        return json.dumps(v, sort_keys=True, separators=(",", ":"))
    return str(v)


def run_name(cfg: Config) -> str:
    """A run's default name before its seed and start time: its preset, then every setting that differs from the
    preset, the weight as a sweep names it (`mcrl train --preset fetchreach-sac --set intrinsic=rnd --set
    intrinsic_alpha=0.2`: 'fetchreach-sac-intrinsic=rnd-a0.2'). Without a preset: the environment and the weight,
    then the settings that differ from the defaults. A run trained as the preset has just the preset's name."""
    if cfg.preset in PRESETS:
        name, base = cfg.preset, resolve_config(cfg.preset)
    else:
        name = f"{cfg.env_id}-a{label_value(cfg.intrinsic_alpha)}"
        base = Config(env_id=cfg.env_id, intrinsic_alpha=cfg.intrinsic_alpha)
    parts = [f"a{label_value(v)}" if f.name == "intrinsic_alpha" else f"{f.name}={label_value(v)}"
             for f in dataclasses.fields(Config)
             if f.name not in UNNAMED and (v := getattr(cfg, f.name)) != getattr(base, f.name)]
    shown: list[str] = []
    for part in parts:
        if len("-".join([*shown, part])) > NAME_SETTINGS_MAX:
            break
        shown.append(part)
    if len(shown) < len(parts):
        shown.append(f"+{len(parts) - len(shown)}")
    return re.sub(r"[^A-Za-z0-9._=+-]", "_", "-".join([name, *shown]))  # a directory name, as sweeps make them
