"""The local backends: one fresh process per job ('spawn' context), at most ``workers`` at a time.

A job is one run (``--backend local``, `LocalBackend`) or a group of runs trained as one vmapped computation
(``--backend vmap``, `VmapBackend`, see ``mcrl.run.group``). Each worker process starts with the limits of
``worker.thread_env`` and, with ``--threads-per-run N``, pinned to N cores of its slot (`worker.pin_cores`, so two
workers never share one), both before it imports anything else (so before jax); it writes straight into
``EXP/runs/<name>/`` (each run locked, as `mcrl train` locks it), dies with the driver, and sends its job's
`Outcome` back through a pipe (`mcrl.sweep.backend.Outcome`: "ok", "stopped", "locked" or "error"). A worker that
dies without one (killed, out of memory) ended as "died": the driver (`mcrl.sweep.driver.drive`) starts it again
from its runs' last checkpoints if retries are left.

A stop request (`request_stop`) sends SIGTERM to the running workers, which save each run at its next episode end
and report "stopped". A worker takes every signal as that one request (a terminal's Ctrl-C reaches it and its
driver alike). `close()` stops the workers still running the same way and waits for them; `close(kill=True)` (a
second signal to the driver) kills them at once, each run keeping its last periodic checkpoint.
"""
from __future__ import annotations

import contextlib
import os
import signal
from typing import Any, ClassVar

from mcrl.errors import MCRLError
from mcrl.run import lock, stop
from mcrl.sweep.backend import Ended, Job, Outcome, Settings, Started
from mcrl.sweep.files import run_dir, run_status
from mcrl.sweep.plan import RunPlan
from mcrl.sweep.worker import (die_with_parent, outcome_of, patched_environ, pin_cores, train_group_runs,
                               train_one)


def _local_worker(spec: dict[str, Any], env: dict[str, str], conn) -> None:
    """Entry point of a local worker process (spawned; jax not imported yet)."""
    os.environ.update(env)
    if spec["pin"]:
        pin_cores(spec["threads"], spec["slot"])
    die_with_parent()
    lock.describe_holder(f"a worker of `mcrl sweep --exp {spec['exp']}`")
    try:
        with stop.handle(second_stops_now=False):  # the driver kills the worker for a second signal
            if len(spec["runs"]) == 1 and not spec["group"]:
                (run,) = spec["runs"]
                summaries = {run["name"]: train_one(run["config"], run["run_dir"])}
            else:
                summaries = train_group_runs(spec["runs"], spec["env_workers"])
        conn.send(Outcome("ok", summaries))
    except BaseException as e:  # stopped, locked or failed: the driver keeps the other runs going
        conn.send(outcome_of(e, {r["name"]: r["run_dir"] for r in spec["runs"]}))
    finally:
        conn.close()


class LocalBackend:
    """A spawned process per run on this machine."""

    name: ClassVar[str] = "local"
    group: ClassVar[bool] = False
    OPTIONS: ClassVar[dict[str, Any]] = {}

    def __init__(self, settings: Settings):
        import multiprocessing as mp

        self.s = settings
        self.options = {**self.OPTIONS, **settings.options}
        self.slots = settings.workers
        self._ctx = mp.get_context("spawn")
        self._running: dict[int, tuple] = {}  # job id -> (job, process, reader, slot)

    @classmethod
    def default_workers(cls, cores: int) -> int:
        return cores

    @classmethod
    def check_options(cls, options: dict[str, Any]) -> None:
        pass

    @classmethod
    def check(cls, settings: Settings) -> None:
        pass

    def jobs(self, todo: list[RunPlan]) -> list[list[RunPlan]]:
        return [[r] for r in todo]

    def launch(self, job: Job) -> str:
        used = {slot for *_, slot in self._running.values()}
        slot = next(i for i in range(len(self._running) + 1) if i not in used)  # the cores no running job has
        s = self.s
        spec = {"runs": [{"name": r.name, "config": r.config.to_dict(), "run_dir": str(run_dir(s.exp, r.name))}
                         for r in job.runs], "group": self.group, "env_workers": self.options.get("env_workers", 0),
                "exp": str(s.exp), "sweep_id": s.sweep_id, "threads": s.threads, "pin": s.pin, "slot": slot}
        reader, writer = self._ctx.Pipe(duplex=False)
        proc = self._ctx.Process(target=_local_worker, args=(spec, s.env, writer), name=f"mcrl-{job.runs[0].name}",
                                 daemon=True)
        with patched_environ(s.env):  # the child's environment from its first instruction on
            proc.start()
        writer.close()
        self._running[job.id] = (job, proc, reader, slot)
        return f"pid {proc.pid}"

    def poll(self, timeout: float) -> list[Started | Ended]:
        from multiprocessing.connection import wait

        if not self._running:
            return []
        ready = wait([p.sentinel for _, p, _, _ in self._running.values()], timeout=timeout)
        out = []
        for job_id in [i for i, (_, p, _, _) in self._running.items() if p.sentinel in ready]:
            job, proc, reader, _ = self._running.pop(job_id)
            proc.join()
            msg = None
            with contextlib.suppress(EOFError, OSError):
                if reader.poll():
                    msg = reader.recv()
            reader.close()
            if msg is None:
                code = proc.exitcode
                why = (f"worker killed by signal {-code}" if code is not None and code < 0
                       else f"worker exited with code {code}")
                msg = Outcome("died", why=why)
            out.append(Ended(job, msg))
        return out

    def request_stop(self) -> None:
        for _, proc, _, _ in self._running.values():
            with contextlib.suppress(OSError):
                os.kill(proc.pid, signal.SIGTERM)

    def close(self, kill: bool = False) -> None:
        """Stop the running workers (SIGTERM: each run saves at its episode's end) and wait for them; with `kill`,
        or if the wait is interrupted, SIGKILL them at once."""
        from multiprocessing.connection import wait

        try:
            if not kill:
                self.request_stop()
                while alive := [p.sentinel for _, p, _, _ in self._running.values() if p.is_alive()]:
                    wait(alive, timeout=1.0)
        finally:
            for _, proc, reader, _ in self._running.values():
                if proc.is_alive():
                    proc.kill()
                proc.join()
                reader.close()
            self._running.clear()


class VmapBackend(LocalBackend):
    """Runs whose configs share shapes (``mcrl.run.group.group_key``) and resume from the same step train as one
    group per worker process; groups of at most `group_size` runs (default: the runs shared evenly among the
    workers)."""

    name: ClassVar[str] = "vmap"
    group: ClassVar[bool] = True
    # --group-size: at most N runs a group (None: shared evenly); --env-workers: environment processes a group
    OPTIONS: ClassVar[dict[str, Any]] = {"group_size": None, "env_workers": 0}

    @classmethod
    def check_options(cls, options: dict[str, Any]) -> None:
        if options["group_size"] is not None and options["group_size"] < 1:
            raise MCRLError(f"--group-size {options['group_size']}: give at least 1 run per group")
        if options["env_workers"] < 0:
            raise MCRLError(f"--env-workers {options['env_workers']}: give 0 (environments in the group's process) "
                            "or more")

    @classmethod
    def default_workers(cls, cores: int) -> int:
        # on a CPU one group per core (XLA runs one vmapped step on about one core); on a GPU one group
        import importlib.util

        cuda = any(importlib.util.find_spec(m) is not None for m in ("jax_cuda12_plugin", "jax_cuda13_plugin"))
        return 1 if cuda else cores

    def jobs(self, todo: list[RunPlan]) -> list[list[RunPlan]]:
        from mcrl.run.group import plan_groups  # imports jax: not at this module's import

        by_step: dict[int, list[RunPlan]] = {}
        for r in todo:
            by_step.setdefault(run_status(run_dir(self.s.exp, r.name))[1], []).append(r)
        size = self.options["group_size"] or max(1, -(-len(todo) // max(1, self.s.workers)))
        return [[runs[i] for i in ix] for runs in by_step.values()
                for ix in plan_groups([r.config for r in runs], size)]
