"""A worker process, whichever backend started it: its cores, its runs, and its death with the driver.

With ``--threads-per-run N`` a worker is pinned to N cores (``pin_cores``: ``os.sched_setaffinity``, which XLA's
thread pool respects, since XLA sizes it by the cores the process may use); without it, it may use every core,
as `mcrl train` does. It limits the thread pools of the libraries that read environment variables
(``thread_env``). Both happen the same way on every backend, so a sweep gives the same numbers locally and on
Ray, and before jax is imported, which is why nothing in ``mcrl.sweep`` imports jax at import time and
``train_one`` imports the trainer late. (XLA's own thread flags, ``--xla_cpu_multi_thread_eigen=false
intra_op_parallelism_threads=N``, do not keep XLA to N cores on jax 0.10: ``benchmarks/xla_threads.py``.)
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
import threading
import time
import traceback
from pathlib import Path
from typing import Any

from mcrl.config import Config
from mcrl.errors import MCRLError
from mcrl.run import lock, rundir, stop
from mcrl.sweep.backend import Outcome


def cpu_count() -> int:
    """The CPUs this process may use (its affinity mask, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def thread_env(threads: int, base: dict[str, str] | None = None) -> dict[str, str]:
    """Environment variables that size the OpenMP / BLAS thread pools of one run to `threads`; set before those
    libraries load. XLA's pool follows the cores the process may use (`pin_cores`). The driver's XLA_FLAGS
    (`base`: its environment) come along, so a run sees the same flags on every backend."""
    base = os.environ if base is None else base
    n = str(int(threads))
    env = {"OMP_NUM_THREADS": n, "MKL_NUM_THREADS": n, "OPENBLAS_NUM_THREADS": n, "NUMEXPR_NUM_THREADS": n,
           "VECLIB_MAXIMUM_THREADS": n}
    return {**env, "XLA_FLAGS": base["XLA_FLAGS"]} if base.get("XLA_FLAGS") else env


_CLAIMS: list = []  # this process's core claims: open files whose flock lasts until the process ends


def claims_dir() -> Path:
    """Where workers claim their cores (one lock file a core), shared by every sweep on this machine:
    $MCRL_CORE_CLAIMS, else <tmp>/mcrl-cores."""
    return Path(os.environ.get("MCRL_CORE_CLAIMS") or Path(tempfile.gettempdir()) / "mcrl-cores")


def _claim(cores: list[int]) -> bool:
    """Take an exclusive flock on each core's lock file, all or none. The kernel drops the locks when this
    process ends however it ends (kill -9 included), so a claim never outlives its worker."""
    held = []
    try:
        claims_dir().mkdir(parents=True, exist_ok=True)
        for c in cores:
            f = open(claims_dir() / f"cpu{c}.lock", "a")
            held.append(f)
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:  # taken by another worker, or no lock directory to write: no claim
        for f in held:
            f.close()
        return False
    _CLAIMS.extend(held)
    return True


def pin_cores(threads: int, slot: int) -> list[int]:
    """Bind this process to `threads` of the cores it may use: slot `slot`'s (slots 0, 1, ... take consecutive
    blocks, wrapping around when there are more slots than blocks); all of them when `threads` covers them. Call
    before jax is imported: XLA sizes its thread pool by these cores (so they also set the run's float results:
    docs/algorithm.md, "Reproducibility and resume"; which cores they are does not). Returns the cores.

    A block another worker holds (a second sweep on the same machine, whose slot 0 is also the first block) is
    passed over for the next free one, so two sweeps side by side do not share a core while another idles;
    when every block is held, the slot's own block is used."""
    try:
        mask = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux: no pinning
        return []
    if threads >= len(mask):
        return mask
    blocks = [[mask[(start + i) % len(mask)] for i in range(threads)]
              for start in ((slot + k) * threads % len(mask) for k in range(-(-len(mask) // threads)))]
    cores = next((b for b in blocks if _claim(b)), blocks[0])
    os.sched_setaffinity(0, cores)
    return cores


@contextlib.contextmanager
def patched_environ(env: dict[str, str]):
    """Set environment variables for the duration of the block, then restore them."""
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def train_one(config: dict[str, Any], run_dir: str | Path) -> dict[str, Any]:
    """Train (or resume) one run in this process; returns the `done` summary."""
    from mcrl.run import trainer  # imports jax: only after the thread limits are set
    from mcrl.video.render import record_training_video

    cfg = Config.from_dict(config)
    out = trainer.train(cfg, Path(run_dir), progress=False, resume=True, video=record_training_video)
    return rundir.read_json(Path(out) / rundir.DONE)


def train_group_runs(runs: list[dict[str, Any]], env_workers: int = 0) -> dict[str, dict[str, Any]]:
    """Train (or resume) `runs` ({name, config, run_dir}) as one vmapped group in this process; their `done`
    summaries by name."""
    from mcrl.run.group import train_group  # imports jax: only after the thread limits are set
    from mcrl.video.render import record_training_video

    dirs = train_group([Config.from_dict(r["config"]) for r in runs], [r["run_dir"] for r in runs], env_workers,
                       video=record_training_video)
    return {r["name"]: rundir.read_json(Path(d) / rundir.DONE) for r, d in zip(runs, dirs)}


def error_report(e: BaseException) -> tuple[str, str]:
    """(one line for the driver's output, the traceback for sweep-error.log) of an unexpected error."""
    return f"{type(e).__name__}: {e}".splitlines()[0], traceback.format_exc()


def outcome_of(e: BaseException, runs: dict[str, str | Path]) -> Outcome:
    """The `Outcome` of a job whose runs (name -> run directory) raised `e`, on every backend (call it in the
    `except` block: an unexpected error's traceback comes along): stopped on a signal, each run with the step of
    the checkpoint it saved; locked (a run another process writes); or an error."""
    names = {os.path.abspath(d): n for n, d in runs.items()}
    first = next(iter(runs))
    if isinstance(e, stop.Stopped):
        return Outcome("stopped", {names.get(os.path.abspath(d), first): step for d, step in e.saved})
    if isinstance(e, lock.Locked):
        return Outcome("locked", {names.get(os.path.abspath(e.directory), first): None}, holder=e.holder)
    if isinstance(e, MCRLError):
        return Outcome("error", why=str(e))
    if isinstance(e, KeyboardInterrupt):
        return Outcome("error", why="interrupted")
    why, tb = error_report(e)
    return Outcome("error", why=why, traceback=tb)


def die_with_parent() -> None:
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
