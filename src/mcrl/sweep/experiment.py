"""``run_sweep``: run a ``SweepPlan`` into one experiment directory ``EXP``.

In order: validate every setting (backend, counts, ``EXP`` against a sweep already in it, the backend's own
check, e.g. the Ray address, the tracking URI) while nothing is written; start the backend (`mcrl.sweep.backend`);
then lock ``EXP``, add this call to ``EXP/provenance.json`` (`mcrl.sweep.provenance`), write ``EXP/sweep.json``
(the union of the runs there and the plan's), skip finished runs and hand the others to the driver loop
(`mcrl.sweep.driver.drive`). Runs that finish are logged to MLflow in a
background thread (``tracking``), so the next runs start meanwhile. On SIGINT or SIGTERM the driver starts no more
runs and lets the running ones save at their episode ends (``SweepResult.stopped_by``).
"""
from __future__ import annotations

import json
import shlex
import sys
import time
import uuid
from pathlib import Path
from typing import Any, Callable

from mcrl.config import resolve_config
from mcrl.renames import new_names
from mcrl.errors import MCRLError
from mcrl.files import write_json
from mcrl.run import lock as locks
from mcrl.run import stop
from mcrl.run.rundir import SWEEP_JSON
import mcrl.sweep.backend as backends
import mcrl.sweep.provenance as provenance
from mcrl.sweep.driver import Driver, SweepResult, drive
from mcrl.sweep.files import RUNS, run_dir, run_status
from mcrl.sweep.plan import RunPlan, SweepPlan, jsonable, load_sweep_json, safe_name
from mcrl.sweep.worker import cpu_count, thread_env

LOCK = ".sweep.lock"  # EXP/.sweep.lock: held by the one `mcrl sweep` running on EXP


def default_exp_dir(plan: SweepPlan) -> Path:
    name = plan.preset or safe_name(plan.runs[0].config.env_id)
    return Path("experiments") / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"


def _merge_with_existing(plan: SweepPlan, exp: Path, shared: bool = False) -> tuple[dict | None, list[dict]]:
    """Check that `plan` fits the sweep already in `exp`; the runs of the merged sweep.json. `shared`: `exp` may
    hold other files before its first sweep (a sequential plan's directory, `mcrl decide`)."""
    if exp.exists() and not exp.is_dir():
        raise MCRLError(f"--exp {exp} is a file: give a directory")
    old = load_sweep_json(exp) if exp.is_dir() else None
    if old is None:
        if exp.is_dir() and not shared and any(exp.iterdir()):
            raise MCRLError(f"--exp {exp} exists and is not a sweep directory (no {SWEEP_JSON}): choose a new "
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


def merged_grid_and_set(old: dict | None, plan: SweepPlan) -> tuple[dict, dict]:
    """sweep.json's ``grid`` and ``set`` once ``plan`` joins the sweep ``old`` (None: a new directory).

    ``grid`` lists every value each key took across the merged sweeps; a ``set`` key stays fixed only where both
    fix it to the same value, otherwise it joins the grid (a side that left it unset ran the preset's default).
    The ``runs`` list stays the record of each run's own overrides."""
    def todays_names(d: dict) -> dict:  # a sweep.json from before a rename: today's names (mcrl.renames)
        return jsonable(new_names(d))

    new_grid, new_set = todays_names(plan.grid), todays_names(plan.fixed)
    if old is None:
        return new_grid, new_set
    old_grid, old_set = todays_names(old.get("grid") or {}), todays_names(old.get("set") or {})
    grid: dict[str, list] = {}

    def add(key: str, values: list) -> None:
        seen = grid.setdefault(key, [])
        for v in values:
            if all(json.dumps(v, sort_keys=True) != json.dumps(w, sort_keys=True) for w in seen):
                seen.append(v)

    for g in (old_grid, new_grid):
        for k, vals in g.items():
            add(k, list(vals))
    fixed: dict = {}
    defaults = None
    for k in list(old_set) + [k for k in new_set if k not in old_set]:
        if k in old_set and k in new_set and old_set[k] == new_set[k]:
            fixed[k] = old_set[k]
            continue
        for this_set, this_grid in ((old_set, old_grid), (new_set, new_grid)):
            if k in this_set:
                add(k, [this_set[k]])
            elif k not in this_grid:
                if defaults is None:
                    defaults = resolve_config(plan.preset, {}).to_dict()
                add(k, [jsonable(defaults.get(k))])
    return grid, fixed


def _write_sweep_json(exp: Path, doc: dict) -> None:
    """Atomically, indented for people to read, ending with a newline."""
    write_json(exp / SWEEP_JSON, doc, indent=2, default=str, newline=True)


def run_sweep(plan: SweepPlan, exp_dir: str | Path | None = None, backend: str = "local", workers: int | None = None,
              threads_per_run: int | None = None, tracking: bool = False, tracking_uri: str | None = None,
              retries: int = 0, progress: bool = True, out: Callable[[str], None] | None = None,
              shared_dir: bool = False, command: str | None = None, **options: Any) -> SweepResult:
    """Run every unfinished run of `plan` into one experiment directory; see the package docstring.

    `threads_per_run`: pin each run's process to that many cores (default: not pinned, every core, as
    `mcrl train`; docs/performance.md, "A sweep's workers and their cores"). `shared_dir`: ``exp`` may hold other
    files before the sweep's first run (`mcrl decide` runs its batches into the plan's directory, and records its
    looks itself: no provenance.json is written there). `command`: the command line provenance.json records
    (default: this process's, `sys.argv`). `options`: the backend's own (its `OPTIONS`: `address` and
    `gpus_per_run` for ray, `group_size` and `env_workers` for vmap; None: its default), checked by the backend.
    Raises MCRLError (before writing anything) on bad settings; a run that fails is reported in the
    result (`failed`) while the others go on."""
    # ---- validate everything before EXP exists
    if backend not in backends.names():
        raise MCRLError(f"--backend {backend!r}: choose {', '.join(backends.names())}")
    if not plan.runs:
        raise MCRLError("the sweep has no runs (empty grid): give at least one value per grid key")
    if workers is not None and workers < 1:
        raise MCRLError(f"--workers {workers}: give at least 1")
    if threads_per_run is not None and threads_per_run < 1:
        raise MCRLError(f"--threads-per-run {threads_per_run}: give at least 1")
    if retries < 0:
        raise MCRLError(f"--retries {retries}: give 0 or more")
    options = backends.options_for(backend, options)  # another backend's option, or a bad value: MCRLError
    cls = backends.get(backend)
    cores = cpu_count()
    n_workers = workers or cls.default_workers(cores)
    threads = threads_per_run or max(1, cores // n_workers)
    exp = (Path(exp_dir) if exp_dir is not None else default_exp_dir(plan)).absolute()
    old, entries = _merge_with_existing(plan, exp, shared_dir)
    tracker = None
    if tracking or tracking_uri:
        from mcrl.sweep.tracking import Tracker  # imports MLflow: only when tracking

        tracker = Tracker.check(tracking_uri, exp)  # probes; writes nothing
    settings = backends.Settings(exp, (old or {}).get("id") or uuid.uuid4().hex, n_workers, threads,
                                 thread_env(threads), workers is not None, threads_per_run is not None, options)
    cls.check(settings)

    # ---- start
    runner = cls(settings)  # e.g. connects to Ray
    result = SweepResult(exp)
    held = drv = log_pool = recorded = None
    log_jobs: list = []
    kill = False

    def log(run: RunPlan) -> None:
        try:
            tracker.log_run(run, run_dir(exp, run.name))
        except Exception as e:  # tracking must not cost the run; the next sweep call logs it
            drv.line(f"warning: MLflow logging of {run.name} failed ({type(e).__name__}: "
                     f"{str(e).splitlines()[0] if str(e) else ''}); re-run the sweep to log it")

    def on_finish(run: RunPlan, summary: dict) -> None:
        if tracker is not None:  # in the background: the next runs start meanwhile
            log_jobs.append(log_pool.submit(log, run))

    try:
        try:
            held = locks.acquire(exp, LOCK)
        except locks.Locked as e:
            raise MCRLError(f"another `mcrl sweep` is running on {exp} ({e.holder}): wait for it or stop it "
                            "first") from None
        if not shared_dir:  # before sweep.json: a provenance.json it cannot extend stops the sweep writing nothing
            recorded = provenance.start(exp, command if command is not None else shlex.join(sys.argv))
        grid, fixed = merged_grid_and_set(old, plan)
        doc = {"preset": plan.preset, "id": settings.sweep_id,
               "created": (old or {}).get("created") or time.strftime("%Y-%m-%dT%H:%M:%S"),
               "grid": grid, "set": fixed, "runs": entries}
        _write_sweep_json(exp, doc)
        (exp / RUNS).mkdir(exist_ok=True)
        if tracker is not None:
            tracker.open(exp, settings.sweep_id, plan.preset)
            result.tracking_uri, result.tracking_experiment = tracker.uri, tracker.experiment_name

        drv = Driver(plan.runs, exp, result, progress, out, on_finish)
        drv.line(f"experiment directory: {exp} ({len(plan.runs)} run{'s' if len(plan.runs) != 1 else ''}, "
                 f"backend {backend}, up to {runner.slots} at a time, " + (
                     f"each pinned to {threads} core(s))" if settings.pin else "not pinned to cores)"))
        others = len(entries) - len(plan.runs)
        if others > 0:
            drv.line(f"note: {SWEEP_JSON} lists {others} more run(s) than this command; "
                     f"`mcrl sweep --exp {exp}` continues all of them")
        todo = []
        for r in plan.runs:
            if run_status(run_dir(exp, r.name))[0] == "finished":
                drv.skipped(r)
            else:
                todo.append(r)

        if tracker is not None:
            from concurrent.futures import ThreadPoolExecutor

            log_pool = ThreadPoolExecutor(1, thread_name_prefix="mcrl-mlflow")
            # runs finished earlier (maybe before --tracking was given): log those missing from the store
            for name in result.skipped:
                if not tracker.is_logged(name):
                    on_finish(next(r for r in plan.runs if r.name == name), {})
        with stop.handle():  # the first SIGINT/SIGTERM: the driver lets the running runs save and stop
            drive(runner, todo, drv, retries)
            result.stopped_by = stop.requested()
        if log_pool is not None:
            if any(not j.done() for j in log_jobs):
                drv.line("logging the last run(s) to MLflow ...")
            log_pool.shutdown(wait=True)
            log_pool = None
    except KeyboardInterrupt:  # a second signal: the running runs end at once, each keeps its last checkpoint
        kill = True
        raise
    finally:
        if log_pool is not None:  # interrupted: do not wait for MLflow (the next sweep call logs what is missing)
            log_pool.shutdown(wait=False, cancel_futures=True)
        try:  # the backend's one close, before EXP is unlocked: a stop lets each running run save, a kill does not
            runner.close(kill=kill)
        finally:
            if drv is not None:
                drv.close()
            if recorded is not None:
                try:
                    provenance.end(exp, recorded)
                except (OSError, MCRLError):  # the record keeps ended: null; the sweep's own error stays the error
                    pass
            if held is not None:
                held.release()
    return result
