"""The measurement's child processes (`child.py`) under a time budget, and what the parent learns without jax.

A child runs in its own process session so that its environment workers go with it. At its deadline it gets
SIGTERM (mcrl's own stop: every run saves at its episode's end and the loop ends), and `GRACE_S` later SIGKILL
to the whole session, so a phase never outlives its budget by more than the grace; what its runs logged until
then stays in their metrics.csv.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
GRACE_S = 15.0  # from SIGTERM to SIGKILL: a FetchPush episode ends within 50 steps, an AntMaze one may not


class Child:
    """`child.py` with its jobs, started at once; `poll()` enforces the deadline, `result()` reads its info."""

    def __init__(self, name: str, jobs: list[dict], work: Path, budget_s: float, env: dict[str, str] | None = None,
                 grace_s: float = GRACE_S):
        self.name, self.work, self.t0, self.grace_s = name, work, time.monotonic(), grace_s
        self.deadline = self.t0 + max(budget_s - grace_s, 1.0)
        self.info_path, self.log_path = work / f"{name}.info.json", work / f"{name}.log"
        spec = work / f"{name}.spec.json"
        spec.write_text(json.dumps({"info": str(self.info_path), "jobs": jobs}))
        self._log = self.log_path.open("wb")
        self.proc = subprocess.Popen([sys.executable, str(HERE / "child.py"), str(spec)], stdout=self._log,
                                     stderr=subprocess.STDOUT, start_new_session=True,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})})
        self.termed_at: float | None = None
        self.killed = False
        self.cpu_s: float | None = None  # user + system seconds of the child and its environment workers

    def info(self) -> dict:
        try:
            return json.loads(self.info_path.read_text())
        except (OSError, ValueError):
            return {}

    def _reap(self, block: bool) -> bool:
        """Wait for the child (os.wait4, for its CPU time); True once it has ended."""
        if self.proc.returncode is not None:
            return True
        pid, status, usage = os.wait4(self.proc.pid, 0 if block else os.WNOHANG)
        if pid == 0:
            return False
        self.proc.returncode = os.waitstatus_to_exitcode(status)
        self.cpu_s = round(usage.ru_utime + usage.ru_stime, 2)
        return True

    def poll(self) -> bool:
        """True once the child has ended; stops it at its deadline (SIGTERM, then SIGKILL after the grace)."""
        if self._reap(block=False):
            return True
        now = time.monotonic()
        if self.termed_at is None and now >= self.deadline:
            self.termed_at = now
            self._signal(signal.SIGTERM, group=False)  # the child alone: its env workers must not die first
        elif self.termed_at is not None and now >= self.termed_at + self.grace_s:
            self.killed = True
            self._signal(signal.SIGKILL, group=True)
            return self._reap(block=True)
        return False

    def _signal(self, sig: int, group: bool) -> None:
        try:
            os.killpg(self.proc.pid, sig) if group else self.proc.send_signal(sig)
        except ProcessLookupError:
            pass

    def stop_now(self) -> None:
        self._signal(signal.SIGKILL, group=True)
        self._reap(block=True)

    def result(self) -> dict:
        """What the phase record keeps of this child: exit, budget stop, wall time, its info, the log's tail."""
        self._signal(signal.SIGKILL, group=True)  # leftover env workers of a child that ended
        self._log.close()
        log = self.log_path.read_bytes()[-3000:].decode(errors="replace")
        return {"rc": self.proc.returncode, "stopped_by_budget": self.termed_at is not None, "killed": self.killed,
                "wall_s": round(time.monotonic() - self.t0, 2), "cpu_s": self.cpu_s, "info": self.info(),
                "log_tail": log}


def wait_all(children: list[Child], abort=None) -> None:
    """Poll until every child has ended; `abort(child)` -> True stops all of them at once."""
    while True:
        done = [c.poll() for c in children]
        if abort is not None and any(abort(c) for c in children):
            for c in children:
                c.stop_now()
            return
        if all(done):
            return
        time.sleep(0.2)


def _run(cmd: list[str], cwd: Path | None = None) -> str | None:
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=20, cwd=cwd)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def machine() -> dict:
    """GPU (nvidia-smi), CPU, memory and Python of this machine, read without importing jax."""
    out: dict = {"python": sys.version.split()[0], "executable": sys.executable, "cores": len(os.sched_getaffinity(0))}
    gpus = _run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"])
    if gpus:
        name, driver, mem = (x.strip() for x in gpus.splitlines()[0].split(","))
        out.update(gpu=name, driver=driver, gpu_memory=mem, gpus=len(gpus.splitlines()))
    head = _run(["nvidia-smi"]) or ""
    m = re.search(r"CUDA Version:\s*([\d.]+)", head)
    out["cuda_driver_api"] = m.group(1) if m else None
    try:
        info = Path("/proc/cpuinfo").read_text()
        out["cpu"] = re.search(r"model name\s*:\s*(.*)", info).group(1)
        out["memory_gib"] = round(int(re.search(r"MemTotal:\s*(\d+)", Path("/proc/meminfo").read_text()).group(1))
                                  / 2**20, 1)
    except (OSError, AttributeError):
        pass
    return out


def source() -> dict:
    """Which mcrl this is: the git commit where .git came along, the one `run.sh fetch-wheels` recorded, and a
    digest of src/mcrl's Python files (recomputable from any checkout: `source()` there)."""
    files = sorted((REPO / "src" / "mcrl").rglob("*.py"))
    h = hashlib.sha256()
    for f in files:
        h.update(str(f.relative_to(REPO)).encode() + b"\0" + f.read_bytes())
    recorded = HERE / "wheels" / "commit.txt"
    return {"git_head": _run(["git", "rev-parse", "HEAD"], REPO),
            "recorded": recorded.read_text().strip() if recorded.is_file() else None,
            "src_sha256": h.hexdigest(), "src_files": len(files)}
