"""Where a sweep's runs train: one small interface, `Backend`, and the registry of backends (`--backend`).

The driver loop (`mcrl.sweep.driver.drive`) owns everything the backends share: the queue, retries of a worker
that died, forwarding a stop request, skipping runs another process writes, and progress. A backend only starts
jobs and reports what became of them:

    backend.jobs(todo) -> [[RunPlan, ...], ...]  how the runs group into jobs (one run each, or vmapped groups)
    backend.launch(job) -> where | None          start a job; where it runs ("pid 123"), or None until it starts
    backend.poll(timeout) -> [Started | Ended]   what happened since the last call, waiting up to `timeout` s
    backend.request_stop()                       every running run saves at its episode's end and stops
    backend.close(kill)                          release everything; `kill`: end the running jobs at once

`slots` says how many jobs may run at a time. A backend is built from the sweep's `Settings` after
`check(settings)` (which writes nothing) has passed. Adding one: a class with these, and one line in `_REGISTRY`.
This module imports neither jax nor ray (a local worker pins its cores before jax loads; Ray reads its auth
settings on import).
"""
from __future__ import annotations

import importlib
import itertools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol

from mcrl.sweep.plan import RunPlan

__all__ = ["Backend", "Ended", "Job", "Settings", "Started", "get", "names", "options_of"]

_ids = itertools.count()


@dataclass
class Settings:
    """What a backend is built from (`mcrl.sweep.experiment.run_sweep`'s arguments, resolved)."""

    exp: Path
    sweep_id: str
    workers: int  # jobs at a time (a backend may find more room: Ray with a cluster)
    threads: int  # each job's share of the cores (Ray: the CPUs its task asks for)
    env: dict[str, str]  # environment variables of every worker process (`mcrl.sweep.worker.thread_env`)
    workers_given: bool = False  # --workers was given (not the default)
    pin: bool = False  # pin each job's process to `threads` cores (--threads-per-run; `worker.pin_cores`)
    address: str | None = None  # ray
    gpus_per_run: float = 0.0  # ray
    group_size: int | None = None  # vmap
    env_workers: int = 0  # vmap


@dataclass
class Job:
    """Runs that train in one worker process (one, or a vmapped group), and how often they were started."""

    runs: list[RunPlan]
    attempt: int = 0
    id: int = field(default_factory=lambda: next(_ids))

    @property
    def label(self) -> str:
        return self.runs[0].name if len(self.runs) == 1 else f"group of {len(self.runs)} ({self.runs[0].name} ...)"

    def again(self) -> "Job":
        """The same runs, started once more (from their last checkpoints)."""
        return Job(self.runs, self.attempt + 1)


@dataclass
class Started:
    """A launched job began to run (`launch` could not say where)."""

    job: Job
    where: str  # e.g. "pid 123 on host-1, files shipped back"


@dataclass
class Ended:
    """A job ended: `status` is "ok" (`results`: run name -> its `done` summary), "stopped" (`results`: run name ->
    the step of the checkpoint it saved, or None), "locked" (`holder`: who writes the runs `results` names),
    "error" (`why`, `traceback`: the run itself failed) or "died" (`why`: the worker process died; retried)."""

    job: Job
    status: str
    results: dict[str, Any] = field(default_factory=dict)
    why: str = ""
    traceback: str | None = None
    holder: str = ""


class Backend(Protocol):
    name: ClassVar[str]
    slots: int  # jobs at a time

    @classmethod
    def default_workers(cls, cores: int) -> int: ...

    @classmethod
    def check(cls, settings: Settings) -> None: ...

    def jobs(self, todo: list[RunPlan]) -> list[list[RunPlan]]: ...

    def launch(self, job: Job) -> str | None: ...

    def poll(self, timeout: float) -> list[Started | Ended]: ...

    def request_stop(self) -> None: ...

    def close(self, kill: bool = False) -> None: ...


# --backend NAME -> its class, as "module:attribute" (imported when chosen: Ray's only then)
_REGISTRY: dict[str, str] = {
    "local": "mcrl.sweep.local:LocalBackend",  # a process per run
    "ray": "mcrl.sweep.ray_backend:RayBackend",  # a Ray task per run, on a cluster or a local instance
    "vmap": "mcrl.sweep.local:VmapBackend",  # a process per group of runs trained as one vmapped computation
}
# a backend-only setting -> the backend that takes it
OPTIONS = {"address": "ray", "gpus_per_run": "ray", "group_size": "vmap", "env_workers": "vmap"}


def names() -> tuple[str, ...]:
    """The values `--backend` may take."""
    return tuple(_REGISTRY)


def get(name: str) -> type:
    module, _, attr = _REGISTRY[name].partition(":")
    return getattr(importlib.import_module(module), attr)


def options_of(name: str) -> tuple[str, ...]:
    """The backend-only settings backend `name` takes (without importing it)."""
    return tuple(k for k, v in OPTIONS.items() if v == name)
