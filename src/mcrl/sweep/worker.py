"""A worker process, whichever backend started it: its thread limits, its one run, and its death with the
driver.

A worker trains one run with the same environment on every backend (``thread_env``), so a sweep gives
the same numbers locally and on Ray. The thread limits must be set before jax is imported, which is
why nothing in ``mcrl.sweep`` imports jax at import time and ``train_one`` imports the trainer late.
"""
from __future__ import annotations

import contextlib
import os
import re
import threading
import time
import traceback
from pathlib import Path
from typing import Any

from mcrl.config import Config
from mcrl.run import rundir


def cpu_count() -> int:
    """The CPUs this process may use (its affinity mask, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def thread_env(threads: int, base: dict[str, str] | None = None) -> dict[str, str]:
    """Environment variables that limit one run to `threads` threads; set before jax is imported.

    On jax 0.10.2 the XLA flags among them do not keep XLA to one core (`benchmarks/xla_threads.py`: a matmul
    loop uses both cores of a 2-core machine with them as without them); pinning the process to cores does.

    The driver's other XLA flags are kept, so a run sees the same flags on every backend."""
    base = os.environ if base is None else base
    keep = [f for f in base.get("XLA_FLAGS", "").split()
            if not re.match(r"^(--)?(xla_cpu_multi_thread_eigen|intra_op_parallelism_threads)\b", f)]
    n = str(int(threads))
    flags = " ".join(keep + ["--xla_cpu_multi_thread_eigen=false", f"intra_op_parallelism_threads={n}"])
    return {"XLA_FLAGS": flags, "OMP_NUM_THREADS": n, "MKL_NUM_THREADS": n, "OPENBLAS_NUM_THREADS": n,
            "NUMEXPR_NUM_THREADS": n, "VECLIB_MAXIMUM_THREADS": n}


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
