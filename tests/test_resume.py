"""A run killed with SIGKILL and resumed ends with the same numbers as an uninterrupted run."""
import csv
import signal
import subprocess
import sys
import time

import pytest

from mcrl.run.rundir import LEARNING_COLUMNS


def _args(small):
    sets = {**small, "total_steps": 900, "eval_every": 300, "log_every": 100, "checkpoint_every": 200}
    out = []
    for k, v in sets.items():
        out += ["--set", f"{k}={v}"]
    return ["--preset", "fetchreach-sacmc", *out, "--no-progress"]


def _cli(*args):
    return [sys.executable, "-m", "mcrl.cli", *args]


def _rows(path):
    with open(path) as f:
        return [{k: r[k] for k in LEARNING_COLUMNS if k in r} for r in csv.DictReader(f)]


@pytest.mark.slow
def test_kill_and_resume_matches_uninterrupted_run(tmp_path, small):
    full, killed = tmp_path / "full", tmp_path / "killed"
    subprocess.run(_cli("train", *_args(small), "--run-dir", str(full)), check=True, capture_output=True)

    proc = subprocess.Popen(_cli("train", *_args(small), "--run-dir", str(killed)), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while not (killed / "checkpoints" / "latest").exists():  # killed right after the first checkpoint
        assert proc.poll() is None and time.time() < deadline
        time.sleep(0.05)
    time.sleep(1.0)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (killed / "done").exists()

    res = subprocess.run(_cli("train", "--resume", str(killed), "--no-progress"), capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert (killed / "done").exists()
    assert (killed / "eval.csv").read_text() == (full / "eval.csv").read_text()
    assert _rows(killed / "metrics.csv") == _rows(full / "metrics.csv")
    assert len(_rows(full / "metrics.csv")) == 9


def test_leftover_temporary_checkpoint_from_a_killed_save_is_ignored(tmp_path, small):
    from mcrl.run import checkpoint
    from mcrl.config import resolve_config
    from mcrl.run.policy import load_policy
    from mcrl.run.trainer import train

    cfg = resolve_config("fetchreach-sac", {**small, "total_steps": 150, "eval_every": 0})
    run = train(cfg, tmp_path / "r", progress=False)
    good = checkpoint.find(run)
    # a save killed half-way leaves only a temporary directory with a truncated file behind
    tmp = run / "checkpoints" / ".tmp-step_000000200"
    tmp.mkdir()
    (tmp / "state.npz").write_bytes(b"PK\x03\x04trunc")
    assert checkpoint.find(run) == good
    load_policy(run)  # still loads
