"""The driver's bookkeeping, shared by both backends: what it prints, and the result it returns.

One line per run event (``[3/8] start NAME (pid ...)``, ``finished``, ``FAILED``, ``stopped``, ``skip``) and
an overall progress bar over all runs' steps (``mcrl.progress``: a plain line every few percent in a pipe or a
file); the bar follows running runs through their metrics.csv. The backends report each run's end here
(``finished`` / ``failed`` / ``stopped``), which fills the ``SweepResult``.
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from mcrl.progress import Progress, duration
from mcrl.sweep.files import last_logged_step, run_dir
from mcrl.sweep.plan import RunPlan

ERROR_LOG = "sweep-error.log"  # EXP/runs/<name>/sweep-error.log: the traceback of a run that failed


@dataclass
class SweepResult:
    exp_dir: Path
    finished: list[str] = field(default_factory=list)  # finished in this call
    skipped: list[str] = field(default_factory=list)  # already finished before
    failed: dict[str, str] = field(default_factory=dict)
    stopped: dict[str, int | None] = field(default_factory=dict)  # stopped by a signal: its checkpoint's step
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
