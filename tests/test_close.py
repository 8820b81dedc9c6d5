"""A backend's `close` means the same on every backend: a stop (`close()`) lets each running run save a checkpoint
at its episode's end and waits for it; a kill (`close(kill=True)`) ends the runs at once, each keeping no checkpoint
beyond its last periodic one. A short FetchReach run a backend (local and Ray), started, stopped or killed through
the backend itself, as `run_sweep`, its one owner, closes it. About 1 minute a test on 2 busy cores, Ray's start-up
included."""
import json
import time

import pytest

from mcrl.run import checkpoint, rundir
from mcrl.sweep.backend import Ended, Job, Settings
from mcrl.sweep.files import run_dir
from mcrl.sweep.plan import plan_from_args
from mcrl.sweep.worker import thread_env

EPISODE = 50  # FetchReach's episode length: a stop's checkpoint lands on a multiple of it
STEPS_BEFORE = 100  # the steps each run has logged before the test stops or kills it
NEVER = 10**6  # checkpoint_every that makes no periodic checkpoint in these runs
SMALL = {"hidden_sizes": [64, 64], "batch_size": 64, "buffer_size": 20_000, "learning_starts": 100, "log_every": 50,
         "eval_every": 10**6, "eval_episodes": 2, "total_steps": 100_000}


def _runs(n: int, checkpoint_every: int):
    return plan_from_args("fetchreach-sac", None, n, {**SMALL, "checkpoint_every": checkpoint_every}).runs


def _backend(cls, exp, workers: int):
    exp.mkdir(parents=True, exist_ok=True)
    (exp / rundir.SWEEP_JSON).write_text(json.dumps({"id": "close-test"}))  # a Ray task sees EXP: writes into it
    return cls(Settings(exp, "close-test", workers, 1, thread_env(1), workers_given=True))


def _logged(run) -> int:
    rows = rundir.read_rows(run / rundir.METRICS)
    return int(rows[-1]["step"]) if rows else 0


def _steps(run) -> list[int]:
    root = rundir.checkpoint_root(run)
    return sorted(rundir.checkpoint_step(p.name) for p in root.glob("step_*")) if root.is_dir() else []


def _wait(backend, until, what: str, started: list[str] | None = None, timeout: float = 420) -> None:
    """Poll `backend` until `until()`, adding the `where` of each job that starts to `started`. A job that ends
    first fails the test."""
    t0 = time.monotonic()
    while not until():
        for event in backend.poll(0.5):
            if isinstance(event, Ended):
                pytest.fail(f"{event.job.label} ended before {what}: {event.outcome}")
            if started is not None:
                started.append(event.where)
        assert time.monotonic() - t0 < timeout, f"no {what} after {timeout} s"


def _launch(backend, runs) -> None:
    for run in runs:
        backend.launch(Job([run]))


def _stopped_at_an_episode_end(run, logged: int = STEPS_BEFORE) -> None:
    """The run saved exactly one checkpoint, at the stop: at an episode's end, at or past the steps it had
    `logged` before the stop."""
    (step,) = _steps(run)
    assert step >= max(logged, EPISODE) and step % EPISODE == 0, step
    assert checkpoint.find(run).name == rundir.checkpoint_name(step)
    assert not rundir.is_done(run)


def _killed_after_periodic(run) -> None:
    """Only periodic checkpoints (every 100 steps) are left: none was saved at the kill."""
    steps = _steps(run)
    assert steps and all(s % 100 == 0 for s in steps) and steps[-1] <= _logged(run), steps
    assert checkpoint.find(run).name == rundir.checkpoint_name(steps[-1])
    assert not rundir.is_done(run)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_local_close_stops_with_a_checkpoint_and_a_kill_leaves_none(tmp_path):
    from mcrl.sweep.local import LocalBackend

    exp = tmp_path / "stop"
    (run,) = _runs(1, NEVER)
    backend = _backend(LocalBackend, exp, 1)
    try:
        _launch(backend, [run])
        _wait(backend, lambda: _logged(run_dir(exp, run.name)) >= STEPS_BEFORE, f"step {STEPS_BEFORE}")
    finally:
        backend.close()
    _stopped_at_an_episode_end(run_dir(exp, run.name))

    exp = tmp_path / "kill"
    (run,) = _runs(1, 100)
    backend = _backend(LocalBackend, exp, 1)
    try:
        _launch(backend, [run])
        _wait(backend, lambda: _steps(run_dir(exp, run.name)), "a periodic checkpoint")
    finally:
        backend.close(kill=True)
    _killed_after_periodic(run_dir(exp, run.name))


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_ray_close_stops_with_a_checkpoint_and_a_kill_leaves_none(tmp_path, monkeypatch):
    """As the local backend: a run that writes into EXP, and one that trains in a temporary directory and ships its
    files back (the stop's checkpoint comes back through `close`)."""
    pytest.importorskip("ray")
    from mcrl.sweep.ray_backend import SHIP_ENV, RayBackend

    exp = tmp_path / "stop"
    runs = _runs(2, NEVER)
    shared, shipped = (run_dir(exp, r.name) for r in runs)
    monkeypatch.setenv(SHIP_ENV, runs[1].name)
    backend = _backend(RayBackend, exp, 2)
    started: list[str] = []
    try:
        _launch(backend, runs)
        _wait(backend, lambda: len(started) == 2 and _logged(shared) >= STEPS_BEFORE,
              f"both runs started and step {STEPS_BEFORE}", started)
    finally:
        backend.close()
    assert sum("files shipped back" in w for w in started) == 1, started
    _stopped_at_an_episode_end(shared)
    _stopped_at_an_episode_end(shipped, logged=0)  # written into EXP by close (it may have started later)
    assert _logged(shipped) > 0

    monkeypatch.delenv(SHIP_ENV)
    exp = tmp_path / "kill"
    (run,) = _runs(1, 100)
    backend = _backend(RayBackend, exp, 1)
    try:
        _launch(backend, [run])
        _wait(backend, lambda: _steps(run_dir(exp, run.name)), "a periodic checkpoint")
    finally:
        backend.close(kill=True)
    _killed_after_periodic(run_dir(exp, run.name))
