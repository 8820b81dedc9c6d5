"""``mcrl sweep``: many runs of one experiment (a grid over config keys and seeds) in one directory.

An experiment directory ``EXP`` holds ``sweep.json`` (the runs: name, config_key, seed, overrides;
the format ``mcrl report`` reads) and one run directory per run, ``EXP/runs/<name>/`` (see
docs/run-directory.md). Running the same sweep again on the same ``EXP`` skips finished runs
(``done`` exists) and resumes unfinished ones from their newest checkpoint, so killing the sweep or
one of its workers loses at most each run's work since its last checkpoint.

Backends:

- ``local``: one fresh process per run ('spawn' context), at most ``workers`` at a time, each
  limited to ``threads_per_run`` threads (XLA, OpenMP, MKL, OpenBLAS) before jax is imported.
- ``ray``: one Ray task per run on an existing cluster (``address``) or on a local Ray instance
  started on demand; each task declares ``num_cpus=threads_per_run`` (and ``num_gpus``) and runs
  with the same thread settings as the local backend, so a sweep gives the same numbers on both.
  A worker that cannot see ``EXP`` (no shared filesystem) trains in a temporary directory and
  sends the run's files back: its checkpoints as they are written, everything at the end.

Everything is validated (sweep file, every grid point with ``resolve_config``, environments, the
Ray address, the tracking URI) before ``EXP`` is created: a bad sweep writes nothing.

Python API: ``plan_from_args`` / ``plan_from_file`` / ``plan_from_experiment`` build a
``SweepPlan``; ``run_sweep`` runs it. This module imports neither jax nor ray at import time (the
local workers must set their thread limits before jax is imported).
"""
from __future__ import annotations

import contextlib
import itertools
import json
import math
import os
import re
import shutil
import socket
import sys
import tempfile
import threading
import time
import traceback
import uuid
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import yaml

from mcrl.config import Config, resolve_config
from mcrl.errors import MCRLError
from mcrl.tracking import patched_environ

SWEEP_FILE_KEYS = ("preset", "grid", "set", "seeds")
# Short names in configuration labels and run names.
_LABEL = {"mc_alpha": "alpha"}
_NAME_PREFIX = {"mc_alpha": "a"}
# Debugging / testing knob (read on the driver): "auto" (default) = a Ray worker writes into EXP when it can
# see it; "always" = every Ray run trains in a temporary directory and ships its files back; or a
# comma-separated list of run names that ship.
SHIP_ENV = "MCRL_SWEEP_SHIP_FILES"


# ------------------------------------------------------------------------------------- planning


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
                "overrides": _jsonable(self.overrides)}


@dataclass
class SweepPlan:
    preset: str | None
    grid: dict[str, list]
    fixed: dict[str, Any]
    runs: list[RunPlan]
    source: str = "args"  # args | file | experiment


def _jsonable(x: Any) -> Any:
    return json.loads(json.dumps(x, default=str))


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (list, tuple)):
        return "x".join(_fmt(x) for x in v)
    if v is None:
        return "null"
    if isinstance(v, dict):
        return json.dumps(v, sort_keys=True, separators=(",", ":"))
    return str(v)


def _safe(s: str) -> str:
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
    validate every point with ``resolve_config``."""
    fixed = dict(fixed or {})
    if not isinstance(grid, dict) or not grid:
        raise MCRLError("the sweep's grid is empty: give at least one key with a list of values, e.g. "
                        "grid: {mc_alpha: [0, 0.2]} or --alphas 0,0.2")
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
            key_parts = [f"{_LABEL.get(k, k)}={_fmt(getattr(cfg, k))}" for k in keys]
            config_key = ",".join(key_parts) or (preset or cfg.env_id)
            name_parts = [f"{_NAME_PREFIX[k]}{_fmt(getattr(cfg, k))}" if k in _NAME_PREFIX
                          else f"{k}={_fmt(getattr(cfg, k))}" for k in keys]
            name = _safe("-".join(name_parts + [f"s{cfg.seed}"]))
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
    _preflight(runs)
    return SweepPlan(preset, {k: list(v) for k, v in grid.items()}, fixed, runs, source)


def _preflight(runs: list[RunPlan]) -> None:
    """What train() would reject only after starting: unknown or unsuitable environments."""
    from mcrl.envs import inspect, make_env

    checked = set()
    for r in runs:
        cfg = r.config
        ident = json.dumps([cfg.env_id, cfg.env_kwargs, cfg.her, cfg.mc_state], sort_keys=True, default=str)
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
    grid: dict[str, list] = {}
    if alphas is not None:
        grid["mc_alpha"] = parse_alphas(alphas)
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
                        f"(e.g. grid: {{mc_alpha: [0, 0.2], seed: [0, 1]}})")
    unknown = sorted(set(doc) - set(SWEEP_FILE_KEYS))
    if unknown:
        raise MCRLError(f"sweep file {path}: unknown top-level key(s) {unknown}: use {', '.join(SWEEP_FILE_KEYS)} "
                        "(config keys go under grid or set)")
    grid = doc.get("grid") or {}
    fixed = doc.get("set") or {}
    if not isinstance(grid, dict) or not isinstance(fixed, dict):
        raise MCRLError(f"sweep file {path}: grid and set must be mappings of config keys, "
                        "e.g. grid: {mc_alpha: [0, 0.2]} and set: {total_steps: 10000}")
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
    sweep = _load_sweep_json(d)
    if sweep is None:
        raise MCRLError(f"{d} holds no sweep.json: to continue a sweep pass the directory `mcrl sweep` wrote; "
                        "to start one give --preset with --alphas/--seeds, or --file sweep.yaml")
    preset = sweep.get("preset") or None
    runs = []
    for e in sweep.get("runs") or []:
        try:
            cfg = resolve_config(preset, dict(e.get("overrides") or {}))
        except MCRLError as err:
            raise MCRLError(f"{d / 'sweep.json'}: run {e.get('name')}: {err}") from None
        runs.append(RunPlan(str(e["name"]), str(e.get("config_key") or e["name"]), int(cfg.seed),
                            dict(e.get("overrides") or {}), cfg))
    if not runs:
        raise MCRLError(f"{d / 'sweep.json'} lists no runs: start a new sweep with --preset/--alphas or --file")
    _preflight(runs)
    return SweepPlan(preset, dict(sweep.get("grid") or {}), dict(sweep.get("set") or {}), runs, "experiment")


def _load_sweep_json(d: Path) -> dict | None:
    path = d / "sweep.json"
    if not path.is_file():
        return None
    try:
        obj = json.loads(path.read_text())
    except ValueError as e:
        raise MCRLError(f"{path} is not valid JSON ({e}): fix or delete it") from None
    if not isinstance(obj, dict) or not isinstance(obj.get("runs", []), list):
        raise MCRLError(f"{path} is not a sweep file (expected {{'preset', 'runs': [...]}}): use another --exp")
    return obj


# ------------------------------------------------------------------------------ run directories


def run_status(run_dir: Path) -> tuple[str, int]:
    """("finished" | "checkpoint" | "new", newest step known)."""
    if (run_dir / "done").exists():
        try:
            return "finished", int(json.loads((run_dir / "done").read_text()).get("step", 0))
        except (ValueError, OSError, AttributeError):
            return "finished", 0
    latest = run_dir / "checkpoints" / "latest"
    if latest.is_file():
        m = re.search(r"(\d+)", latest.read_text())
        return "checkpoint", int(m.group(1)) if m else 0
    return "new", 0


def _last_logged_step(run_dir: Path) -> int:
    """The step of the last complete row of metrics.csv (0 if none); reads only the file's tail."""
    path = run_dir / "metrics.csv"
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - 4096))
            tail = f.read().decode("utf-8", "replace")
    except OSError:
        return 0
    lines = tail.split("\n")[:-1]  # complete lines only
    for line in reversed(lines):
        head = line.split(",", 1)[0]
        try:
            return int(float(head))
        except ValueError:
            continue
    return 0


def _complete_lines(data: bytes) -> bytes:
    """A CSV that may be appended to right now: up to its last newline."""
    i = data.rfind(b"\n")
    return data[: i + 1] if i >= 0 else b""


def collect_run_files(run_dir: Path, final: bool) -> dict[str, bytes]:
    """The run's files to send to the driver: every file outside checkpoints/ (CSVs cut to complete
    rows unless `final`), plus the newest checkpoint and the `latest` pointer; `done` only if `final`."""
    files: dict[str, bytes] = {}
    for p in sorted(run_dir.rglob("*")):
        rel = p.relative_to(run_dir)
        if not p.is_file() or rel.parts[0] == "checkpoints" or p.name.startswith("."):
            continue
        if rel.as_posix() == "done" and not final:
            continue
        data = p.read_bytes()
        files[rel.as_posix()] = data if final or p.suffix != ".csv" else _complete_lines(data)
    latest = run_dir / "checkpoints" / "latest"
    if latest.is_file():
        name = latest.read_text().strip()
        ck = run_dir / "checkpoints" / name
        for p in sorted(ck.iterdir()):
            if p.is_file():
                files[f"checkpoints/{name}/{p.name}"] = p.read_bytes()
        files["checkpoints/latest"] = (name + "\n").encode()
    return files


def write_run_files(run_dir: Path, files: dict[str, bytes], keep: int) -> None:
    """Write files sent by a worker into `run_dir` the way the trainer would: the checkpoint directory
    complete before `latest` names it, each file replaced atomically, `done` last."""
    run_dir.mkdir(parents=True, exist_ok=True)
    ck_root = run_dir / "checkpoints"
    ck_name = files.get("checkpoints/latest", b"").decode().strip()
    if ck_name:
        if not re.fullmatch(r"step_\d+", ck_name):
            raise MCRLError(f"a worker sent a checkpoint named {ck_name!r}: not a checkpoint directory")
        final = ck_root / ck_name
        if not final.is_dir():
            tmp = ck_root / f".tmp-{ck_name}"
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            for rel, data in files.items():
                if rel.startswith(f"checkpoints/{ck_name}/"):
                    (tmp / rel.rsplit("/", 1)[1]).write_bytes(data)
            os.rename(tmp, final)
    for rel, data in files.items():
        if rel.startswith("checkpoints/") or rel == "done":
            continue
        target = run_dir / rel
        if ".." in Path(rel).parts or Path(rel).is_absolute():
            raise MCRLError(f"a worker sent a file outside its run directory ({rel!r})")
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f".{target.name}.part")
        tmp.write_bytes(data)
        os.replace(tmp, target)
    if ck_name:
        tmp = ck_root / ".latest.tmp"
        tmp.write_text(ck_name)
        os.replace(tmp, ck_root / "latest")
        for old in sorted(ck_root.glob("step_*"))[:-max(1, keep)]:
            shutil.rmtree(old, ignore_errors=True)
    if "done" in files:
        (run_dir / "done").write_bytes(files["done"])


# ----------------------------------------------------------------------- the worker side (both)


def cpu_count() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def thread_env(threads: int, base: dict[str, str] | None = None) -> dict[str, str]:
    """Environment variables that limit one run to `threads` threads; set before jax is imported.

    The driver's other XLA flags are kept, so a run sees the same flags on every backend."""
    base = os.environ if base is None else base
    keep = [f for f in base.get("XLA_FLAGS", "").split()
            if not re.match(r"^(--)?(xla_cpu_multi_thread_eigen|intra_op_parallelism_threads)\b", f)]
    n = str(int(threads))
    flags = " ".join(keep + ["--xla_cpu_multi_thread_eigen=false", f"intra_op_parallelism_threads={n}"])
    return {"XLA_FLAGS": flags, "OMP_NUM_THREADS": n, "MKL_NUM_THREADS": n, "OPENBLAS_NUM_THREADS": n,
            "NUMEXPR_NUM_THREADS": n, "VECLIB_MAXIMUM_THREADS": n}


def _train_one(config: dict[str, Any], run_dir: str | Path) -> dict[str, Any]:
    """Train (or resume) one run in this process; returns the `done` summary."""
    from mcrl import trainer

    cfg = Config.from_dict(config)
    out = trainer.train(cfg, Path(run_dir), progress=False, resume=True)
    done = Path(out) / "done"
    return json.loads(done.read_text()) if done.exists() else {}


def _die_with_parent() -> None:
    """Linux: this process gets SIGKILL when its parent (the sweep driver) dies, so a killed sweep leaves
    no orphaned run writing into EXP behind it."""
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except Exception:  # not Linux: fall back to polling below
        pass
    parent = os.getppid()

    def watch():
        while True:
            time.sleep(1.0)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def _local_worker(spec: dict[str, Any], env: dict[str, str], conn) -> None:
    """Entry point of a local worker process (spawned; jax not imported yet)."""
    os.environ.update(env)
    _die_with_parent()
    try:
        summary = _train_one(spec["config"], spec["run_dir"])
        conn.send(("ok", summary, None))
    except MCRLError as e:
        conn.send(("error", str(e), None))
    except KeyboardInterrupt:
        conn.send(("error", "interrupted", None))
    except BaseException as e:  # report it to the driver, which keeps the other runs going
        conn.send(("error", f"{type(e).__name__}: {e}".splitlines()[0], traceback.format_exc()))
    finally:
        conn.close()


class _Inbox:
    """Ray actor: messages from the tasks to the driver (run started, checkpoint files)."""

    def __init__(self):
        self.msgs: list = []

    def push(self, msg) -> bool:
        self.msgs.append(msg)
        return True

    def drain(self) -> list:
        out, self.msgs = self.msgs, []
        return out


def _sees_experiment(spec: dict[str, Any]) -> bool:
    try:
        d = json.loads((Path(spec["exp"]) / "sweep.json").read_text())
        return d.get("id") == spec["sweep_id"] and os.access(spec["exp"], os.W_OK)
    except (OSError, ValueError):
        return False


def _ray_task(spec: dict[str, Any], inbox, seed_box: list, force_ship: bool) -> dict[str, Any]:
    """One run as a Ray task (runs in a fresh worker whose thread env vars came with the task)."""
    import ray

    shared = not force_ship and _sees_experiment(spec)
    ray.get(inbox.push.remote(("start", spec["name"], os.getpid(), socket.gethostname(), shared)))
    try:
        if shared:
            return {"summary": _train_one(spec["config"], spec["run_dir"])}
        tmp = Path(tempfile.mkdtemp(prefix="mcrl-sweep-"))
        run_dir = tmp / spec["name"]
        try:
            seed = ray.get(seed_box[0]) if seed_box else None
            if seed:
                write_run_files(run_dir, seed, keep=int(spec["config"]["keep_checkpoints"]))
            stop = threading.Event()

            def ship_checkpoints():  # send every new checkpoint (and the CSVs up to it) to the driver
                sent = None
                while not stop.wait(1.0):
                    try:
                        latest = (run_dir / "checkpoints" / "latest").read_text().strip()
                        if latest != sent:
                            files = collect_run_files(run_dir, final=False)
                            ray.get(inbox.push.remote(("files", spec["name"], files)))
                            sent = latest
                    except (OSError, FileNotFoundError):
                        continue  # no checkpoint yet, or one being replaced: next time

            watcher = threading.Thread(target=ship_checkpoints, daemon=True)
            watcher.start()
            try:
                summary = _train_one(spec["config"], run_dir)
            finally:
                stop.set()
                watcher.join()
            return {"summary": summary, "files": collect_run_files(run_dir, final=True)}
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    except MCRLError as e:
        return {"error": str(e)}
    except Exception as e:
        return {"error": f"{type(e).__name__}: {e}".splitlines()[0], "traceback": traceback.format_exc()}


# ------------------------------------------------------------------------------------ backends


def _probe_tcp(host: str, port: int, timeout: float = 3.0) -> str | None:
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return None
    except OSError as e:
        return f"{type(e).__name__}: {e.strerror or e}"


def check_ray_address(address: str) -> None:
    """Fail fast when the GCS port of `address` (host:port or ray://host:port) does not answer."""
    if address == "auto":
        return
    m = re.fullmatch(r"(?:ray://)?\[?([^\]]+?)\]?:(\d+)", address.strip())
    if not m:
        raise MCRLError(f"--address {address!r}: give HOST:PORT of the Ray head's GCS (e.g. 10.0.0.5:6379), "
                        "ray://HOST:PORT for Ray Client, or auto")
    err = _probe_tcp(m.group(1), int(m.group(2)))
    if err:
        raise MCRLError(f"Ray cluster at {address} does not answer ({err}): start it with `ray start --head` "
                        "or fix --address; leave --address out to start a local Ray instance")


class _Driver:
    """Progress output: one line per run event, and an overall tqdm bar over all runs' steps."""

    def __init__(self, runs: list[RunPlan], exp: Path, progress: bool, out: Callable[[str], None] | None):
        self.runs = {r.name: r for r in runs}
        self.exp = exp
        self.total_runs = len(runs)
        self.finished = 0
        self.steps: dict[str, int] = {}
        self._out = out
        self.bar = None
        if progress:
            from tqdm import tqdm

            total = sum(r.config.total_steps for r in runs)
            self.bar = tqdm(total=total, unit="step", desc="sweep", dynamic_ncols=True, mininterval=1.0,
                            smoothing=0.05, file=sys.stderr)
        self._last_poll = 0.0

    def line(self, msg: str) -> None:
        if self._out is not None:
            self._out(msg)
        elif self.bar is not None:
            self.bar.write(msg, file=sys.stdout)
            sys.stdout.flush()
        else:
            print(msg, flush=True)

    def tag(self) -> str:
        return f"[{self.finished}/{self.total_runs}]"

    def set_steps(self, name: str, step: int) -> None:
        self.steps[name] = max(self.steps.get(name, 0), step)
        self._refresh()

    def _refresh(self) -> None:
        if self.bar is not None:
            self.bar.n = sum(min(s, self.runs[n].config.total_steps) for n, s in self.steps.items())
            self.bar.set_postfix_str(f"runs {self.finished}/{self.total_runs}", refresh=False)
            self.bar.refresh()

    def poll(self, running: list[str]) -> None:
        """Read the progress of running runs from their metrics.csv (at most once a second)."""
        if self.bar is None or time.monotonic() - self._last_poll < 1.0:
            return
        self._last_poll = time.monotonic()
        for name in running:
            self.steps[name] = max(self.steps.get(name, 0), _last_logged_step(self.exp / "runs" / name))
        self._refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _duration(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}h{s % 3600 // 60:02d}m{s % 60:02d}s" if s >= 3600 else (
        f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s")


def _summary_text(summary: dict) -> str:
    sr, ret = summary.get("success_rate"), summary.get("mean_return")
    sr_s = "n/a" if sr is None else f"{sr:.2f}"
    ret_s = "n/a" if ret is None or not math.isfinite(ret) else f"{ret:.2f}"
    return f"success {sr_s}, return {ret_s}"


@dataclass
class SweepResult:
    exp_dir: Path
    finished: list[str] = field(default_factory=list)  # finished in this call
    skipped: list[str] = field(default_factory=list)  # already finished before
    failed: dict[str, str] = field(default_factory=dict)
    tracking_uri: str | None = None
    tracking_experiment: str | None = None

    @property
    def ok(self) -> bool:
        return not self.failed


def _run_local(todo: list[RunPlan], exp: Path, sweep_id: str, workers: int, env: dict[str, str], retries: int,
               drv: _Driver, on_finish: Callable[[RunPlan, dict], None], result: SweepResult) -> None:
    import multiprocessing as mp
    from multiprocessing.connection import wait

    ctx = mp.get_context("spawn")
    queue = deque((r, 0) for r in todo)
    running: dict[str, tuple] = {}  # name -> (process, conn, run, attempt, t0)
    try:
        while queue or running:
            while queue and len(running) < workers:
                run, attempt = queue.popleft()
                run_dir = exp / "runs" / run.name
                state, step = run_status(run_dir)
                spec = {"name": run.name, "config": run.config.to_dict(), "run_dir": str(run_dir),
                        "exp": str(exp), "sweep_id": sweep_id}
                reader, writer = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=_local_worker, args=(spec, env, writer), name=f"mcrl-{run.name}",
                                   daemon=True)
                with patched_environ(env):  # the child's environment from its first instruction on
                    proc.start()
                writer.close()
                running[run.name] = (proc, reader, run, attempt, time.monotonic())
                how = f"resume {run.name} from step {step}" if state == "checkpoint" else f"start {run.name}"
                drv.set_steps(run.name, step)
                drv.line(f"{drv.tag()} {how} (pid {proc.pid})")
            ready = wait([p.sentinel for p, *_ in running.values()], timeout=1.0)
            for name in [n for n, (p, *_rest) in running.items() if p.sentinel in ready]:
                proc, reader, run, attempt, t0 = running.pop(name)
                proc.join()
                msg = None
                with contextlib.suppress(EOFError, OSError):
                    if reader.poll():
                        msg = reader.recv()
                reader.close()
                if msg is not None and msg[0] == "ok":
                    drv.finished += 1
                    drv.set_steps(name, run.config.total_steps)
                    drv.line(f"{drv.tag()} finished {name} in {_duration(time.monotonic() - t0)}: "
                             f"{_summary_text(msg[1])}")
                    result.finished.append(name)
                    on_finish(run, msg[1])
                    continue
                if msg is not None:
                    why = msg[1]
                    if msg[2]:
                        log = exp / "runs" / name / "sweep-error.log"
                        log.parent.mkdir(parents=True, exist_ok=True)
                        log.write_text(msg[2])
                        why += f" (traceback in {log})"
                    _failed(drv, result, name, why)
                    continue
                code = proc.exitcode
                why = (f"worker killed by signal {-code}" if code is not None and code < 0
                       else f"worker exited with code {code}")
                if attempt < retries:
                    drv.line(f"{drv.tag()} {name}: {why}; retrying from its last checkpoint "
                             f"({attempt + 1} of {retries})")
                    queue.appendleft((run, attempt + 1))
                else:
                    _failed(drv, result, name, why)
            drv.poll(list(running))
    finally:
        for proc, *_ in running.values():  # interrupted: stop the runs (each keeps its checkpoints)
            if proc.is_alive():
                proc.terminate()
        for proc, reader, *_ in running.values():
            proc.join(10)
            if proc.is_alive():
                proc.kill()
                proc.join()
            reader.close()


def _failed(drv: _Driver, result: SweepResult, name: str, why: str) -> None:
    result.failed[name] = why
    drv.line(f"{drv.tag()} FAILED {name}: {why}")


def _ray_auth_env(address: str | None) -> None:
    """Ray >= 2.59: `ray start --head` enables token authentication when a token exists, but
    ray.init(address=...) sends the token only with RAY_AUTH_MODE=token, which Ray reads when it is
    imported (a cluster without authentication accepts a client that sends one)."""
    address = address or os.environ.get("RAY_ADDRESS")
    if address and address != "auto" and "RAY_AUTH_MODE" not in os.environ and "ray" not in sys.modules and (
            os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
            or (Path.home() / ".ray" / "auth_token").is_file()):
        os.environ["RAY_AUTH_MODE"] = "token"


def _import_ray():
    try:
        import ray
    except ImportError:
        raise MCRLError("--backend ray needs Ray: pip install 'mcrl[sweep]' (or 'ray[default]')") from None
    return ray


def _start_ray(address: str | None, cpus: int):
    """Connect to `address`, or start a local Ray instance with `cpus` CPUs. Returns (ray, started_local)."""
    import logging

    ray = _import_ray()
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address:
        check_ray_address(address)
    try:
        if address:
            ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
        else:
            # address="local": a new instance even when `ray start` left one (or its stale address file) behind
            ray.init(address="local", num_cpus=cpus, include_dashboard=False, log_to_driver=False,
                     logging_level=logging.WARNING)
    except (ConnectionError, TimeoutError, RuntimeError, ValueError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        where = f"the Ray cluster at {address}" if address else "a local Ray instance"
        raise MCRLError(f"cannot connect to {where} ({type(e).__name__}: {first}): start the cluster with "
                        "`ray start --head` or fix --address (a cluster with token authentication also needs "
                        "its token: RAY_AUTH_TOKEN or ~/.ray/auth_token)") from None
    return ray, not address


def _run_ray(ray, todo: list[RunPlan], exp: Path, sweep_id: str, limit: int, threads: int, gpus: float,
             env: dict[str, str], retries: int, local_instance: bool, drv: _Driver,
             on_finish: Callable[[RunPlan, dict], None], result: SweepResult) -> None:
    ship_knob = os.environ.get(SHIP_ENV, "auto").strip() or "auto"
    ship_names = None if ship_knob in ("auto", "always") else {s.strip() for s in ship_knob.split(",")}

    def forced(name: str) -> bool:
        return ship_knob == "always" or (ship_names is not None and name in ship_names)

    inbox = ray.remote(num_cpus=0)(_Inbox).remote()
    # max_calls=1: a fresh worker process per run (its thread settings from the first instruction on, and
    # its memory returned when the run ends)
    task = ray.remote(max_calls=1)(_ray_task).options(num_cpus=threads, num_gpus=gpus or 0, max_retries=retries,
                                                      runtime_env={"env_vars": env})
    queue = deque(todo)
    inflight: dict[Any, tuple] = {}  # ref -> (run, t0, seed ref)
    by_name: dict[str, RunPlan] = {r.name: r for r in todo}
    try:
        while queue or inflight:
            while queue and len(inflight) < limit:
                run = queue.popleft()
                run_dir = exp / "runs" / run.name
                state, step = run_status(run_dir)
                seed_box = []
                if state == "checkpoint" and (forced(run.name) or not local_instance):
                    seed_box = [ray.put(collect_run_files(run_dir, final=False))]  # fetched only if needed
                spec = {"name": run.name, "config": run.config.to_dict(), "run_dir": str(run_dir),
                        "exp": str(exp), "sweep_id": sweep_id}
                ref = task.remote(spec, inbox, seed_box, forced(run.name))
                inflight[ref] = (run, time.monotonic(), seed_box)
                drv.set_steps(run.name, step)
                how = f" (resumes from step {step})" if state == "checkpoint" else ""
                drv.line(f"{drv.tag()} queued {run.name}{how}")
            ready, _ = ray.wait(list(inflight), num_returns=len(inflight), timeout=1.0)
            for msg in ray.get(inbox.drain.remote()):  # after wait: a finished task's messages are all in
                if msg[0] == "start":
                    _, name, pid, host, shared = msg
                    drv.line(f"{drv.tag()} start {name} (pid {pid} on {host}"
                             f"{'' if shared else ', files shipped back'})")
                elif msg[0] == "files":
                    _, name, files = msg
                    write_run_files(exp / "runs" / name, files, by_name[name].config.keep_checkpoints)
                    drv.set_steps(name, run_status(exp / "runs" / name)[1])
            for ref in ready:
                run, t0, _seed = inflight.pop(ref)
                try:
                    out = ray.get(ref)
                except Exception as e:  # the worker died (killed, out of memory, node lost) after its retries
                    first = str(e).strip().splitlines()[0] if str(e).strip() else ""
                    _failed(drv, result, run.name, f"{type(e).__name__}: {first}"[:300])
                    continue
                if "error" in out:
                    why = out["error"]
                    if out.get("traceback"):
                        log = exp / "runs" / run.name / "sweep-error.log"
                        log.parent.mkdir(parents=True, exist_ok=True)
                        log.write_text(out["traceback"])
                        why += f" (traceback in {log})"
                    _failed(drv, result, run.name, why)
                    continue
                if "files" in out:
                    write_run_files(exp / "runs" / run.name, out["files"], run.config.keep_checkpoints)
                drv.finished += 1
                drv.set_steps(run.name, run.config.total_steps)
                drv.line(f"{drv.tag()} finished {run.name} in {_duration(time.monotonic() - t0)}: "
                         f"{_summary_text(out['summary'])}")
                result.finished.append(run.name)
                on_finish(run, out["summary"])
            drv.poll([r.name for r, *_ in inflight.values()])
    finally:
        for ref in inflight:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)
        with contextlib.suppress(Exception):
            ray.kill(inbox)


# ------------------------------------------------------------------------------------ the sweep


def default_exp_dir(plan: SweepPlan) -> Path:
    name = plan.preset or _safe(plan.runs[0].config.env_id)
    return Path("experiments") / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"


def _merge_with_existing(plan: SweepPlan, exp: Path) -> tuple[dict | None, list[dict]]:
    """Check that `plan` fits the sweep already in `exp`; the runs of the merged sweep.json."""
    if exp.exists() and not exp.is_dir():
        raise MCRLError(f"--exp {exp} is a file: give a directory")
    old = _load_sweep_json(exp) if exp.is_dir() else None
    if old is None:
        if exp.is_dir() and any(exp.iterdir()):
            raise MCRLError(f"--exp {exp} exists and is not a sweep directory (no sweep.json): choose a new "
                            "directory or an empty one")
        return None, [r.entry() for r in plan.runs]
    if (old.get("preset") or None) != plan.preset:
        raise MCRLError(f"{exp} holds a sweep of preset {old.get('preset')!r}, not {plan.preset!r}: "
                        "choose a new --exp for a different preset")
    entries = list(old.get("runs") or [])
    by_name = {str(e.get("name")): e for e in entries}
    for r in plan.runs:
        e = by_name.get(r.name)
        if e is None:
            entries.append(r.entry())
            continue
        try:
            old_cfg = resolve_config(plan.preset, dict(e.get("overrides") or {})).to_dict()
        except MCRLError:
            old_cfg = None
        if old_cfg != r.config.to_dict():
            new = r.config.to_dict()
            diff = sorted(k for k in new if old_cfg is None or old_cfg.get(k) != new[k])
            raise MCRLError(f"{exp} already has a run {r.name} with a different config (differs in {diff}): "
                            "re-run the sweep with its original settings, or choose a new --exp")
    return old, entries


def _write_json_atomic(path: Path, obj: Any) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=str) + "\n")
    os.replace(tmp, path)


def _lock(exp: Path):
    import fcntl

    f = open(exp / ".sweep.lock", "a+")
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.close()
        raise MCRLError(f"another `mcrl sweep` is running on {exp}: wait for it or stop it first") from None
    f.seek(0)
    f.truncate()
    f.write(f"{os.getpid()}\n")
    f.flush()
    return f


def run_sweep(plan: SweepPlan, exp_dir: str | Path | None = None, backend: str = "local", workers: int | None = None,
              threads_per_run: int | None = None, address: str | None = None, gpus_per_run: float = 0.0,
              tracking: bool = False, tracking_uri: str | None = None, retries: int = 0, progress: bool = True,
              out: Callable[[str], None] | None = None) -> SweepResult:
    """Run every unfinished run of `plan` into one experiment directory; see the module docstring.

    Raises MCRLError (before writing anything) on bad settings; a run that fails is reported in the
    result (`failed`) while the others go on."""
    # ---- validate everything before EXP exists
    if backend not in ("local", "ray"):
        raise MCRLError(f"--backend {backend!r}: choose local or ray")
    if not plan.runs:
        raise MCRLError("the sweep has no runs (empty grid): give at least one value per grid key")
    cores = cpu_count()
    if workers is not None and workers < 1:
        raise MCRLError(f"--workers {workers}: give at least 1")
    if threads_per_run is not None and threads_per_run < 1:
        raise MCRLError(f"--threads-per-run {threads_per_run}: give at least 1")
    if retries < 0:
        raise MCRLError(f"--retries {retries}: give 0 or more")
    if gpus_per_run and gpus_per_run < 0:
        raise MCRLError(f"--gpus-per-run {gpus_per_run}: give 0 or more")
    if backend == "local" and (address or gpus_per_run):
        raise MCRLError("--address and --gpus-per-run are for --backend ray: add --backend ray or drop them")
    n_workers = workers or cores
    threads = threads_per_run or max(1, cores // n_workers)
    exp = Path(exp_dir) if exp_dir is not None else default_exp_dir(plan)
    exp = exp.absolute()
    old, entries = _merge_with_existing(plan, exp)
    tracker = None
    if tracking or tracking_uri:
        from mcrl import tracking as tracking_mod

        tracker = tracking_mod.Tracker.check(tracking_uri, exp)  # probes; writes nothing
    env = thread_env(threads)
    ray = None
    local_instance = False
    if backend == "ray":
        if address:
            check_ray_address(address)
        _ray_auth_env(address)
        _import_ray()

    # ---- start
    if backend == "ray":
        ray, local_instance = _start_ray(address, n_workers * threads)
    result = SweepResult(exp)
    lock = None
    drv = None
    log_pool = None
    try:
        exp.mkdir(parents=True, exist_ok=True)
        lock = _lock(exp)
        sweep_id = (old or {}).get("id") or uuid.uuid4().hex
        doc = {"preset": plan.preset, "id": sweep_id,
               "created": (old or {}).get("created") or time.strftime("%Y-%m-%dT%H:%M:%S"),
               "grid": _jsonable((old or {}).get("grid") or plan.grid),
               "set": _jsonable((old or {}).get("set") or plan.fixed), "runs": entries}
        _write_json_atomic(exp / "sweep.json", doc)
        (exp / "runs").mkdir(exist_ok=True)
        if tracker is not None:
            tracker.open(exp, sweep_id, plan.preset)
            result.tracking_uri, result.tracking_experiment = tracker.uri, tracker.experiment_name

        drv = _Driver(plan.runs, exp, progress, out)
        drv.line(f"experiment directory: {exp} ({len(plan.runs)} run{'s' if len(plan.runs) != 1 else ''}, "
                 f"backend {backend}, "
                 f"{'up to ' + str(n_workers) + ' at a time, ' if backend == 'local' or workers else ''}"
                 f"{threads} thread(s) per run)")
        others = len(entries) - len(plan.runs)
        if others > 0:
            drv.line(f"note: sweep.json lists {others} more run(s) than this command; "
                     f"`mcrl sweep --exp {exp}` continues all of them")
        todo = []
        for r in plan.runs:
            state, step = run_status(exp / "runs" / r.name)
            if state == "finished":
                drv.finished += 1
                drv.set_steps(r.name, r.config.total_steps)
                result.skipped.append(r.name)
                drv.line(f"{drv.tag()} skip {r.name}: already finished")
            else:
                todo.append(r)

        def log(run: RunPlan) -> None:
            try:
                tracker.log_run(run, exp / "runs" / run.name)
            except Exception as e:  # tracking must not cost the run; the next sweep call logs it
                drv.line(f"warning: MLflow logging of {run.name} failed ({type(e).__name__}: "
                         f"{str(e).splitlines()[0] if str(e) else ''}); re-run the sweep to log it")

        def on_finish(run: RunPlan, summary: dict) -> None:
            if tracker is not None:  # in the background: the next runs start meanwhile
                log_jobs.append(log_pool.submit(log, run))

        log_jobs: list = []
        if tracker is not None:
            from concurrent.futures import ThreadPoolExecutor

            log_pool = ThreadPoolExecutor(1, thread_name_prefix="mcrl-mlflow")
            # runs finished earlier (maybe before --tracking was given): log those missing from the store
            for name in result.skipped:
                if not tracker.is_logged(name):
                    on_finish(next(r for r in plan.runs if r.name == name), {})
        if backend == "local":
            _run_local(todo, exp, sweep_id, n_workers, env, retries, drv, on_finish, result)
        else:
            if workers:
                limit = workers
            else:
                cpus = float(ray.cluster_resources().get("CPU", n_workers * threads))
                limit = max(1, int(cpus // threads))
            _run_ray(ray, todo, exp, sweep_id, limit, threads, gpus_per_run, env, retries, local_instance, drv,
                     on_finish, result)
        if log_pool is not None:
            if any(not j.done() for j in log_jobs):
                drv.line("logging the last run(s) to MLflow ...")
            log_pool.shutdown(wait=True)
            log_pool = None
    finally:
        if log_pool is not None:  # interrupted: do not wait for MLflow (the next sweep call logs what is missing)
            log_pool.shutdown(wait=False, cancel_futures=True)
        if drv is not None:
            drv.close()
        if lock is not None:
            lock.close()
        if ray is not None:
            with contextlib.suppress(Exception):
                ray.shutdown()
    return result
