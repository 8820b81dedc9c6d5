"""Chaos: a sweep of 8 short FetchReach runs whose workers are killed with SIGKILL again and again ends, once run
again, with exactly the files of the same sweep run uninterrupted: the same eval.csv, final evaluation and learning
columns of metrics.csv for every run, no row or run twice, no run reported failed. Once on the local backend, once
on Ray.

Tiny networks and 150 steps a run (three 50-step episodes, a checkpoint at every episode end), so a run is mostly
process start and compilation; the killer strikes every 2.5 s, 5 times.
"""
import json
import os
import random
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from mcrl.run.rundir import LEARNING_COLUMNS, read_rows

SETS = {"hidden_sizes": "[16]", "intrinsic_hidden_sizes": "[16]", "batch_size": 16, "buffer_size": 1000,
        "learning_starts": 50, "eval_every": 100, "eval_episodes": 1, "log_every": 50, "checkpoint_every": 50}
CLI = [sys.executable, "-c", "import sys; from mcrl.cli import main; sys.exit(main())"]
NAMES = [f"a{a}-s{s}" for s in range(4) for a in ("0", "0.2")]  # 8 runs, seeds outermost
KILLS, EVERY = 5, 2.5


def _args(exp, *extra):
    sets = [x for k, v in SETS.items() for x in ("--set", f"{k}={v}")]
    return ["sweep", "--preset", "fetchreach-sacmc", "--alphas", "0,0.2", "--seeds", "4", "--steps", "150", *sets,
            "--exp", str(exp), "--workers", "2", "--no-progress", *extra]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The same 8 runs, swept without interruption."""
    exp = tmp_path_factory.mktemp("chaos") / "reference"
    res = subprocess.run(CLI + _args(exp), capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stdout + res.stderr
    return exp


class _Lines:
    """A subprocess' stdout, collected in a thread."""

    def __init__(self, proc):
        self.lines: list[str] = []
        threading.Thread(target=lambda: self.lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()

    def text(self) -> str:
        return "".join(self.lines)


def _alive_worker(pid: int, driver: int, ray: bool) -> bool:
    """`pid` is a running worker of this sweep (not a zombie, not a reused pid)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False
    if re.search(r"^State:\s+Z", status, re.M):
        return False
    parent = int(re.search(r"^PPid:\s+(\d+)", status, re.M).group(1))
    return b"ray" in cmdline if ray else parent == driver


def _chaos(exp, extra=(), ray=False, timeout=900):
    """Run the sweep with `extra` arguments, killing a random running worker every EVERY s, KILLS times; returns
    the sweep's output and the pids killed."""
    started = re.compile(r"(?:start|resume) \S+(?: from step \d+)? \(pid (\d+)")
    proc = subprocess.Popen(CLI + _args(exp, "--retries", "20", *extra), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    out, rng, killed = _Lines(proc), random.Random(0), []
    deadline = time.time() + timeout
    try:
        while proc.poll() is None and time.time() < deadline:
            time.sleep(EVERY)
            if len(killed) < KILLS:
                live = sorted({int(p) for p in started.findall(out.text())} - set(killed))
                live = [p for p in live if _alive_worker(p, proc.pid, ray)]
                if live:
                    victim = rng.choice(live)
                    os.kill(victim, signal.SIGKILL)
                    killed.append(victim)
        proc.wait(max(1.0, deadline - time.time()))
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    time.sleep(0.5)  # the reader thread's last lines
    assert proc.returncode == 0, out.text()
    return out.text(), killed


def _learning(path):
    return [{k: r.get(k) for k in LEARNING_COLUMNS} for r in read_rows(path)]


def _same_as_reference(exp, reference, first, killed):
    assert len(killed) >= 3, (killed, first)  # several workers were killed mid-sweep ...
    assert "worker killed by signal 9" in first or "WorkerCrashedError" in first, first
    assert "retrying from its last checkpoint" in first and "FAILED" not in first, first  # ... and retried
    res = subprocess.run(CLI + _args(exp), capture_output=True, text=True, timeout=600)  # the sweep again
    assert res.returncode == 0 and "FAILED" not in res.stdout, res.stdout + res.stderr
    assert res.stdout.count("already finished") + len(re.findall(r"\] finished ", res.stdout)) == len(NAMES)
    sweep = json.loads((exp / "sweep.json").read_text())
    assert [r["name"] for r in sweep["runs"]] == NAMES  # no run twice
    for name in NAMES:
        run, ref = exp / "runs" / name, reference / "runs" / name
        assert (run / "done").is_file(), name
        assert (run / "eval.csv").read_text() == (ref / "eval.csv").read_text(), name
        assert (run / "final_eval.json").read_text() == (ref / "final_eval.json").read_text(), name
        rows = _learning(run / "metrics.csv")
        assert rows == _learning(ref / "metrics.csv"), name  # every row once, with the same numbers
        assert [r["step"] for r in rows] == [50.0, 100.0, 150.0]
        assert not list((run / "checkpoints").glob(".*-step_*")), name  # no half-written checkpoint left


@pytest.mark.slow
@pytest.mark.timeout(1500)
def test_local_sweep_survives_repeated_kill_9(reference, tmp_path):
    exp = tmp_path / "chaos"
    first, killed = _chaos(exp)
    _same_as_reference(exp, reference, first, killed)


@pytest.mark.slow
@pytest.mark.timeout(2000)
def test_ray_sweep_survives_repeated_kill_9(reference, tmp_path):
    pytest.importorskip("ray")
    exp = tmp_path / "chaos-ray"
    first, killed = _chaos(exp, ("--backend", "ray"), ray=True)
    _same_as_reference(exp, reference, first, killed)
