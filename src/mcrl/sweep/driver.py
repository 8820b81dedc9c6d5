"""The sweep's driver, one for every backend: the loop that runs the jobs (`drive`), what it prints, and the
result it returns.

`drive` owns the queue (at most `backend.slots` jobs at a time), retries of a job whose worker died (from its
runs' last checkpoints), the stop request (the first SIGINT/SIGTERM: no more jobs, the running runs save and
stop; a second one: killed at once), runs that another process writes (reported as "locked by pid N", never
started), and progress. The backend (`mcrl.sweep.backend.Backend`) only launches jobs and reports their ends.

One line per run event (``[3/8] start NAME (pid ...)``, ``finished``, ``FAILED``, ``stopped``, ``skip``,
``locked``) and an overall progress bar over all runs' steps (``mcrl.progress``: a plain line every few percent in
a pipe or a file); the bar follows running runs through their metrics.csv. Each run's end fills the
``SweepResult``.
"""
from __future__ import annotations

import math
import signal
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from mcrl.progress import Progress, duration
from mcrl.run import lock, stop
from mcrl.sweep.backend import Backend, Ended, Job, Started
from mcrl.sweep.files import last_logged_step, run_dir, run_status
from mcrl.sweep.plan import RunPlan

ERROR_LOG = "sweep-error.log"  # EXP/runs/<name>/sweep-error.log: the traceback of a run that failed


@dataclass
class SweepResult:
    exp_dir: Path
    finished: list[str] = field(default_factory=list)  # finished in this call
    skipped: list[str] = field(default_factory=list)  # already finished before
    failed: dict[str, str] = field(default_factory=dict)
    stopped: dict[str, int | None] = field(default_factory=dict)  # stopped by a signal: its checkpoint's step
    locked: dict[str, str] = field(default_factory=dict)  # written by another process: who ("pid 123 (...)")
    stopped_by: int | None = None  # the signal that stopped this sweep call (SIGINT, SIGTERM)
    tracking_uri: str | None = None
    tracking_experiment: str | None = None

    @property
    def ok(self) -> bool:
        return not self.failed


class Driver:
    """Progress output and the result of one sweep call. `on_finish(run, summary)` is called for each
    run that finishes in this call (MLflow logging)."""

    def __init__(self, runs: list[RunPlan], exp: Path, result: SweepResult, progress: bool,
                 out: Callable[[str], None] | None, on_finish: Callable[[RunPlan, dict], None] | None = None):
        self.runs = {r.name: r for r in runs}
        self.exp = exp
        self.result = result
        self.on_finish = on_finish
        self.total_runs = len(runs)
        self.finished = 0
        self.steps: dict[str, int] = {}
        self._out = out
        self.bar = Progress(sum(r.config.total_steps for r in runs), "sweep", file=sys.stderr) if progress else None
        self._last_poll = 0.0

    # ---- output
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
            self.bar.postfix(f"runs {self.finished}/{self.total_runs}")
            self.bar.set(sum(min(s, self.runs[n].config.total_steps) for n, s in self.steps.items()))

    def poll(self, running: list[str]) -> None:
        """Read the progress of running runs from their metrics.csv (at most once a second)."""
        if self.bar is None or time.monotonic() - self._last_poll < 1.0:
            return
        self._last_poll = time.monotonic()
        for name in running:
            self.steps[name] = max(self.steps.get(name, 0), last_logged_step(run_dir(self.exp, name)))
        self._refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

    # ---- a run's end
    def skipped(self, run: RunPlan) -> None:
        """`run` was finished before this call."""
        self.finished += 1
        self.set_steps(run.name, run.config.total_steps)
        self.result.skipped.append(run.name)
        self.line(f"{self.tag()} skip {run.name}: already finished")

    def done(self, run: RunPlan, t0: float, summary: dict) -> None:
        """`run` finished (started at monotonic time `t0`) with the `done` summary `summary`."""
        self.finished += 1
        self.set_steps(run.name, run.config.total_steps)
        self.line(f"{self.tag()} finished {run.name} in {duration(time.monotonic() - t0)}: "
                  f"{summary_text(summary)}")
        self.result.finished.append(run.name)
        if self.on_finish is not None:
            self.on_finish(run, summary)

    def stopped(self, name: str, step: int | None) -> None:
        """Run `name` stopped on a signal after saving a checkpoint at `step` (None: it had not started)."""
        self.result.stopped[name] = step
        where = f"at step {step:,}, checkpoint saved" if step is not None else "before it started"
        self.line(f"{self.tag()} stopped {name} {where}")

    def locked(self, name: str, holder: str) -> None:
        """Run `name` is written by another process (`holder`): not started, not failed."""
        self.result.locked[name] = holder
        self.line(f"{self.tag()} locked {name}: locked by {holder}; not started (run the sweep again once it ends)")

    def failed(self, name: str, why: str, traceback: str | None = None) -> None:
        """Run `name` failed; its traceback (if any) goes to its sweep-error.log. The other runs go on."""
        if traceback:
            log = run_dir(self.exp, name) / ERROR_LOG
            log.parent.mkdir(parents=True, exist_ok=True)
            log.write_text(traceback)
            why += f" (traceback in {log})"
        self.result.failed[name] = why
        self.line(f"{self.tag()} FAILED {name}: {why}")


def summary_text(summary: dict) -> str:
    sr, ret = summary.get("success_rate"), summary.get("mean_return")
    sr_s = "n/a" if sr is None else f"{sr:.2f}"
    ret_s = "n/a" if ret is None or not math.isfinite(ret) else f"{ret:.2f}"
    return f"success {sr_s}, return {ret_s}"


# ------------------------------------------------------------------------------------------------ the loop
def drive(backend: Backend, todo: list[RunPlan], drv: Driver, retries: int) -> None:
    """Train `todo` on `backend`, reporting each run's end to `drv` (see the module's docstring). The caller owns
    the backend and closes it once (`run_sweep`: with kill=True when a second signal ends this loop)."""
    queue = deque(Job(runs) for runs in backend.jobs(todo))
    running: dict[int, tuple[Job, float]] = {}  # job id -> (job, monotonic start)
    stopping = False
    while queue or running:
        if stop.requested() is not None and not stopping:  # first SIGINT/SIGTERM: the runs save and stop
            stopping = True
            queue.clear()
            drv.line(f"{signal.Signals(stop.requested()).name}: each running run saves a checkpoint at its "
                     "episode's end, then the sweep stops (press Ctrl-C again to stop at once)")
            backend.request_stop()
            if not running:
                break
        while queue and len(running) < backend.slots:
            job = _without_locked(queue.popleft(), drv)
            if job is not None:
                running[job.id] = (job, time.monotonic())
                _launched(job, backend.launch(job), drv)
        for event in backend.poll(1.0):
            if event.job.id not in running:
                continue
            if isinstance(event, Started):
                _started(event.job, event.where, drv)
                continue
            job, t0 = running.pop(event.job.id)
            retry = _ended(event, t0, drv, retries if not stopping else 0)
            if retry is not None:
                queue.appendleft(retry)
        drv.poll([r.name for job, _ in running.values() for r in job.runs])


def _without_locked(job: Job, drv: Driver) -> Job | None:
    """`job` without the runs another process writes (each reported), None if none is left."""
    free = []
    for r in job.runs:
        try:
            lock.check_free(run_dir(drv.exp, r.name))
            free.append(r)
        except lock.Locked as e:
            drv.locked(r.name, e.holder)
    return None if not free else job if len(free) == len(job.runs) else Job(free, job.attempt, job.id)


def _how(r: RunPlan, drv: Driver) -> str:
    state, step = run_status(run_dir(drv.exp, r.name))
    drv.set_steps(r.name, step)
    return f"resume {r.name} from step {step}" if state == "checkpoint" else f"start {r.name}"


def _launched(job: Job, where: str | None, drv: Driver) -> None:
    if where is None:  # it says where when it starts (`_started`)
        for r in job.runs:
            state, step = run_status(run_dir(drv.exp, r.name))
            drv.set_steps(r.name, step)
            drv.line(f"{drv.tag()} queued {r.name}" + (f" (resumes from step {step})" if state == "checkpoint" else ""))
    elif len(job.runs) == 1:
        drv.line(f"{drv.tag()} {_how(job.runs[0], drv)} ({where})")
    else:
        drv.line(f"{drv.tag()} group of {len(job.runs)} as one computation ({where}): "
                 f"{'; '.join(_how(r, drv) for r in job.runs)}")


def _started(job: Job, where: str, drv: Driver) -> None:
    for r in job.runs:
        drv.line(f"{drv.tag()} start {r.name} ({where})")


def _ended(e: Ended, t0: float, drv: Driver, retries: int) -> Job | None:
    """Report the end of a job (its `Outcome`); the job to start again if its worker died and retries are left."""
    runs, o = e.job.runs, e.outcome
    if o.status == "ok":
        for r in runs:
            drv.done(r, t0, o.results[r.name])
    elif o.status == "stopped":
        for r in runs:
            drv.stopped(r.name, o.results.get(r.name))
    elif o.status == "locked":
        for r in runs:
            if r.name in o.results:
                drv.locked(r.name, o.holder)
            else:  # a group that could not start for one locked run: the others go back to the queue
                drv.line(f"{drv.tag()} {r.name}: not started (its group had a locked run)")
        rest = [r for r in runs if r.name not in o.results]
        return Job(rest, e.job.attempt) if rest else None
    elif o.status == "died" and e.job.attempt < retries:
        drv.line(f"{drv.tag()} {e.job.label}: {o.why}; retrying from its last checkpoint "
                 f"({e.job.attempt + 1} of {retries})")
        return e.job.again()
    else:
        for r in runs:
            drv.failed(r.name, o.why, o.traceback)
    return None
