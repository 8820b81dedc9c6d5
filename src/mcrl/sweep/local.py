"""The local backend: one fresh process per run ('spawn' context), at most ``workers`` at a time.

Each worker process starts with the thread limits of ``worker.thread_env`` in its environment (set
before it imports anything, so before jax), writes straight into ``EXP/runs/<name>/``, dies with the
driver, and sends one message back through a pipe: ("ok", summary, None) or ("error", why, traceback).
A worker that dies without a message (killed, out of memory) is retried from its last checkpoint up to
``retries`` times.
"""
from __future__ import annotations

import contextlib
import os
import time
from collections import deque
from pathlib import Path
from typing import Any

from mcrl.errors import MCRLError
from mcrl.sweep.driver import Driver
from mcrl.sweep.files import run_dir, run_status
from mcrl.sweep.plan import RunPlan
from mcrl.sweep.worker import die_with_parent, error_report, patched_environ, train_one


def _local_worker(spec: dict[str, Any], env: dict[str, str], conn) -> None:
    """Entry point of a local worker process (spawned; jax not imported yet)."""
    os.environ.update(env)
    die_with_parent()
    try:
        summary = train_one(spec["config"], spec["run_dir"])
        conn.send(("ok", summary, None))
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
    """Run `todo` in worker processes, reporting each run's end to `drv`."""
    import multiprocessing as mp
    from multiprocessing.connection import wait

    ctx = mp.get_context("spawn")
    queue = deque((r, 0) for r in todo)
    running: dict[str, tuple] = {}  # name -> (process, conn, run, attempt, t0)
    try:
        while queue or running:
            while queue and len(running) < workers:
                run, attempt = queue.popleft()
                rdir = run_dir(exp, run.name)
                state, step = run_status(rdir)
                spec = {"name": run.name, "config": run.config.to_dict(), "run_dir": str(rdir),
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
                    drv.done(run, t0, msg[1])
                    continue
                if msg is not None:
                    drv.failed(name, msg[1], msg[2])
                    continue
                code = proc.exitcode
                why = (f"worker killed by signal {-code}" if code is not None and code < 0
                       else f"worker exited with code {code}")
                if attempt < retries:
                    drv.line(f"{drv.tag()} {name}: {why}; retrying from its last checkpoint "
                             f"({attempt + 1} of {retries})")
                    queue.appendleft((run, attempt + 1))
                else:
                    drv.failed(name, why)
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
