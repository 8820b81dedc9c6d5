"""The local backend: one fresh process per job ('spawn' context), at most ``workers`` at a time.

A job is one run (``--backend local``) or a group of runs trained as one vmapped computation
(``--backend vmap``, see ``mcrl.run.group``). Each worker process starts with the thread limits of
``worker.thread_env`` in its environment (set before it imports anything, so before jax), writes straight
into ``EXP/runs/<name>/`` (each run locked, as `mcrl train` locks it), dies with the driver, and sends one
message back through a pipe: ("ok", {name: summary}, None), ("stopped", {name: step}, None) or ("error", why,
traceback). A worker that dies without a message (killed, out of memory) is retried from its runs' last
checkpoints up to ``retries`` times.

Signals: the driver's first SIGINT or SIGTERM (`mcrl.run.stop`) starts no more runs and sends SIGTERM to the
running workers, which save each run at its next episode end and report "stopped"; the driver waits for them. A
worker takes every signal as that one request (a terminal's Ctrl-C reaches it and its driver alike); a second
signal to the driver kills the workers at once, each run keeping its last checkpoint.
"""
from __future__ import annotations

import contextlib
import os
import signal
import time
from collections import deque
from pathlib import Path
from typing import Any

from mcrl.errors import MCRLError
from mcrl.run import lock, stop
from mcrl.sweep.driver import Driver
from mcrl.sweep.files import run_dir, run_status
from mcrl.sweep.plan import RunPlan
from mcrl.sweep.worker import die_with_parent, error_report, patched_environ, train_group_runs, train_one


def _local_worker(spec: dict[str, Any], env: dict[str, str], conn) -> None:
    """Entry point of a local worker process (spawned; jax not imported yet)."""
    os.environ.update(env)
    die_with_parent()
    lock.describe_holder(f"a worker of `mcrl sweep --exp {spec['exp']}`")
    try:
        with stop.handle(second_stops_now=False):  # the driver kills the worker for a second signal
            if len(spec["runs"]) == 1 and not spec["group"]:
                (run,) = spec["runs"]
                summaries = {run["name"]: train_one(run["config"], run["run_dir"])}
            else:
                summaries = train_group_runs(spec["runs"], spec["env_workers"])
        conn.send(("ok", summaries, None))
    except stop.Stopped as e:
        names = {os.path.abspath(r["run_dir"]): r["name"] for r in spec["runs"]}
        conn.send(("stopped", {names[os.path.abspath(d)]: step for d, step in e.saved}, None))
    except MCRLError as e:
        conn.send(("error", str(e), None))
    except KeyboardInterrupt:
        conn.send(("error", "interrupted", None))
    except BaseException as e:  # report it to the driver, which keeps the other runs going
        conn.send(("error", *error_report(e)))
    finally:
        conn.close()


def run_local(todo: list[RunPlan], exp: Path, sweep_id: str, workers: int, env: dict[str, str], retries: int,
              drv: Driver) -> None:
    """Run `todo` in worker processes, one run each, reporting each run's end to `drv`."""
    run_jobs([[r] for r in todo], exp, sweep_id, workers, env, retries, drv)


def run_jobs(jobs: list[list[RunPlan]], exp: Path, sweep_id: str, workers: int, env: dict[str, str], retries: int,
             drv: Driver, group: bool = False, env_workers: int = 0) -> None:
    """Run each job (its runs as one vmapped group if `group`) in a worker process, at most `workers` at a
    time, reporting each run's end to `drv`."""
    import multiprocessing as mp
    from multiprocessing.connection import wait

    ctx = mp.get_context("spawn")
    queue = deque((job, 0) for job in jobs)
    running: dict[str, tuple] = {}  # job label -> (process, conn, runs, attempt, t0)
    stopping = False
    try:
        while queue or running:
            if stop.requested() is not None and not stopping:  # first SIGINT/SIGTERM: the runs save and stop
                stopping = True
                queue.clear()
                drv.line(f"{signal.Signals(stop.requested()).name}: each running run saves a checkpoint at its "
                         "episode's end, then the sweep stops (press Ctrl-C again to stop at once)")
                for proc, *_ in running.values():
                    with contextlib.suppress(OSError):
                        os.kill(proc.pid, signal.SIGTERM)
                if not running:
                    break
            while queue and len(running) < workers:
                job, attempt = queue.popleft()
                spec = {"runs": [{"name": r.name, "config": r.config.to_dict(), "run_dir": str(run_dir(exp, r.name))}
                                 for r in job], "group": group, "env_workers": env_workers,
                        "exp": str(exp), "sweep_id": sweep_id}
                label = job[0].name if len(job) == 1 else f"group of {len(job)} ({job[0].name} ...)"
                reader, writer = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=_local_worker, args=(spec, env, writer), name=f"mcrl-{job[0].name}",
                                   daemon=True)
                with patched_environ(env):  # the child's environment from its first instruction on
                    proc.start()
                writer.close()
                running[label] = (proc, reader, job, attempt, time.monotonic())
                hows = []
                for r in job:
                    state, step = run_status(run_dir(exp, r.name))
                    drv.set_steps(r.name, step)
                    hows.append(f"resume {r.name} from step {step}" if state == "checkpoint" else f"start {r.name}")
                if len(job) == 1:
                    drv.line(f"{drv.tag()} {hows[0]} (pid {proc.pid})")
                else:
                    drv.line(f"{drv.tag()} {label.split(' (')[0]} as one computation (pid {proc.pid}): "
                             f"{'; '.join(hows)}")
            ready = wait([p.sentinel for p, *_ in running.values()], timeout=1.0)
            for label in [n for n, (p, *_rest) in running.items() if p.sentinel in ready]:
                proc, reader, job, attempt, t0 = running.pop(label)
                proc.join()
                msg = None
                with contextlib.suppress(EOFError, OSError):
                    if reader.poll():
                        msg = reader.recv()
                reader.close()
                if msg is not None and msg[0] == "ok":
                    for r in job:
                        drv.done(r, t0, msg[1][r.name])
                    continue
                if msg is not None and msg[0] == "stopped":
                    for r in job:
                        drv.stopped(r.name, msg[1].get(r.name))
                    continue
                if msg is not None:
                    for r in job:
                        drv.failed(r.name, msg[1], msg[2])
                    continue
                code = proc.exitcode
                why = (f"worker killed by signal {-code}" if code is not None and code < 0
                       else f"worker exited with code {code}")
                if attempt < retries and not stopping:
                    drv.line(f"{drv.tag()} {label}: {why}; retrying from its last checkpoint "
                             f"({attempt + 1} of {retries})")
                    queue.appendleft((job, attempt + 1))
                else:
                    for r in job:
                        drv.failed(r.name, why)
            drv.poll([r.name for _p, _c, job, *_ in running.values() for r in job])
    except KeyboardInterrupt:  # a second signal: stop the workers at once (each run keeps its last checkpoint)
        for proc, *_ in running.values():
            proc.kill()
        raise
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


def run_vmap(todo: list[RunPlan], exp: Path, sweep_id: str, workers: int, env: dict[str, str], retries: int,
             drv: Driver, group_size: int | None = None, env_workers: int = 0) -> None:
    """The vmap backend: runs whose configs share shapes (``mcrl.run.group.group_key``) and resume from the
    same step train as one group per worker process; groups of at most `group_size` runs (default: the runs
    shared evenly among the `workers` processes)."""
    from mcrl.run.group import plan_groups  # imports jax: not at this module's import

    by_step: dict[int, list[RunPlan]] = {}
    for r in todo:
        by_step.setdefault(run_status(run_dir(exp, r.name))[1], []).append(r)
    size = group_size or max(1, -(-len(todo) // max(1, workers)))
    jobs = [[runs[i] for i in ix] for runs in by_step.values()
            for ix in plan_groups([r.config for r in runs], size)]
    run_jobs(jobs, exp, sweep_id, workers, env, retries, drv, group=True, env_workers=env_workers)
