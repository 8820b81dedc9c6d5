"""Where a sweep's runs train: one small interface, `Backend`, and the registry of backends (`--backend`).

The driver loop (`mcrl.sweep.driver.drive`) owns everything the backends share: the queue, retries of a worker
that died, forwarding a stop request, skipping runs another process writes, and progress. A backend only starts
jobs and reports what became of them:

    backend.jobs(todo) -> [[RunPlan, ...], ...]  how the runs group into jobs (one run each, or vmapped groups)
    backend.launch(job) -> where | None          start a job; where it runs ("pid 123"), or None until it starts
    backend.poll(timeout) -> [Started | Ended]   what happened since the last call, waiting up to `timeout` s
    backend.request_stop()                       every running run saves at its episode's end and stops
    backend.close(kill)                          the end: with `kill` False (a stop) every running run saves at
                                                 its episode's end and is waited for; with `kill` True the running
                                                 jobs end at once (each run keeps its last periodic checkpoint);
                                                 then everything is released. Its one caller is `run_sweep`, once

`slots` says how many jobs may run at a time. A job's end is an `Ended` holding its worker's `Outcome`, the one
encoding of a job's end on every backend. A backend's own options (`--address`, `--group-size`) are its `OPTIONS`
(name -> default): `options_for` refuses another backend's with a one-line error naming the fix and hands the
given ones to the backend's `check_options`. A backend is built from the sweep's `Settings` (its options in
`Settings.options`) after `check(settings)` (which writes nothing) has passed. Adding one: a class with these,
and one line in `_REGISTRY`; adding an option: an `OPTIONS` entry checked in `check_options`, and its flag in
`mcrl.cli`. This module imports neither jax nor ray (a local worker pins its cores before jax loads; Ray reads
its auth settings on import).
"""
from __future__ import annotations

import importlib
import itertools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol

from mcrl.errors import MCRLError
from mcrl.sweep.plan import RunPlan

__all__ = ["Backend", "Ended", "Job", "Outcome", "Settings", "Started", "get", "given_options", "names",
           "option_names", "options_for"]

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
    options: dict[str, Any] = field(default_factory=dict)  # the backend's own options (`options_for`)


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


@dataclass(frozen=True)
class Outcome:
    """How a job ended, the same on every backend (what a local worker sends through its pipe, what a Ray task
    returns): `status` is "ok" (`results`: run name -> its `done` summary), "stopped" (`results`: run name -> the
    step of the checkpoint it saved, or None), "locked" (`holder`: who writes the runs `results` names), "error"
    (`why`, `traceback`: the run itself failed) or "died" (`why`: the worker process died, as its backend saw;
    retried). `mcrl.sweep.worker.outcome_of` makes a worker's from what its runs raised."""

    status: str
    results: dict[str, Any] = field(default_factory=dict)
    why: str = ""
    traceback: str | None = None
    holder: str = ""


@dataclass
class Ended:
    """A job ended, with its `outcome`."""

    job: Job
    outcome: Outcome


class Backend(Protocol):
    name: ClassVar[str]
    OPTIONS: ClassVar[dict[str, Any]]  # its own options and their defaults (`options_for`)
    slots: int  # jobs at a time

    @classmethod
    def default_workers(cls, cores: int) -> int: ...

    @classmethod
    def check_options(cls, options: dict[str, Any]) -> None: ...  # its own options' values; MCRLError naming the fix

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


def names() -> tuple[str, ...]:
    """The values `--backend` may take."""
    return tuple(_REGISTRY)


def get(name: str) -> type:
    module, _, attr = _REGISTRY[name].partition(":")
    return getattr(importlib.import_module(module), attr)


def option_names() -> tuple[str, ...]:
    """Every backend's own options (imports each backend's module, which imports neither jax nor ray)."""
    return tuple(dict.fromkeys(o for n in names() for o in get(n).OPTIONS))


def given_options(args: Any) -> dict[str, Any]:
    """The backends' options among the attributes of `args` (`mcrl sweep`'s and `mcrl decide`'s parsed flags)."""
    return {k: getattr(args, k) for k in option_names() if hasattr(args, k)}


def options_for(name: str, given: dict[str, Any]) -> dict[str, Any]:
    """Backend `name`'s options: its `OPTIONS` with the `given` values (None: not given), checked by its
    `check_options`. Another backend's option given (not None, not its default) is a one-line error naming the
    fix; a name no backend takes, a TypeError."""
    cls = get(name)
    for option, value in given.items():
        if option in cls.OPTIONS:
            continue
        owner = next((n for n in names() if option in get(n).OPTIONS), None)
        if owner is None:
            raise TypeError(f"no sweep backend takes the option {option!r} (they take {', '.join(option_names())})")
        if value is not None and value != get(owner).OPTIONS[option]:
            flag = "--" + option.replace("_", "-")
            raise MCRLError(f"{flag} is for --backend {owner}: add --backend {owner} or drop it")
    options = {**cls.OPTIONS, **{k: v for k, v in given.items() if k in cls.OPTIONS and v is not None}}
    cls.check_options(options)
    return options
