"""A run killed with SIGKILL and resumed ends with the same numbers as an uninterrupted run."""
import csv
import signal
import subprocess
import sys
import time

import pytest

from mcrl.run.rundir import LEARNING_COLUMNS, METRICS, read_rows


def kill_past_first_checkpoint(proc: subprocess.Popen, run_dir, checkpoint_every: int) -> None:
    """SIGKILL a training process once it has checkpointed and logged a row past its first checkpoint (work the kill
    throws away), not after a fixed sleep: on a fast CPU a small run finished within a second of its checkpoint."""
    deadline = time.time() + 300
    while not ((run_dir / "checkpoints" / "latest").exists()
               and any((r.get("step") or 0) > checkpoint_every for r in read_rows(run_dir / METRICS))):
        assert proc.poll() is None and time.time() < deadline
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()


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
    kill_past_first_checkpoint(proc, killed, 200)
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


def test_a_run_from_before_the_renames_resumes_exactly(tmp_path, small):
    """A run directory as mcrl wrote it before issue 52's renames (config keys mc_alpha, mc_hidden_sizes, ...;
    state.npz keys `.mc_models.*` and `.metric_sums['mean_mc_reward']`; metrics.csv columns `mean_mc_reward`,
    `mc_bound_low`, `mc_bound_high`), killed after its step-200 checkpoint, resumes to the numbers of the
    uninterrupted run, and its metrics.csv then has today's column names."""
    import json
    import shutil

    import numpy as np

    from mcrl.config import resolve_config
    from mcrl.run import rundir
    from mcrl.run.rundir import read_rows
    from mcrl.run.trainer import resume, train

    # the names mcrl wrote before the renames, written out here (not taken from mcrl.renames: the test checks it)
    old_keys = {"intrinsic_alpha": "mc_alpha", "intrinsic_models": "mc_models", "intrinsic_lr": "mc_lr",
                "intrinsic_hidden_sizes": "mc_hidden_sizes", "intrinsic_state": "mc_state",
                "intrinsic_history": "mc_history", "intrinsic_reward_low": "mc_reward_low",
                "intrinsic_reward_high": "mc_reward_high"}
    old_columns = {"mean_intrinsic_reward": "mean_mc_reward", "intrinsic_bound_low": "mc_bound_low",
                   "intrinsic_bound_high": "mc_bound_high"}
    old_paths = ((".intrinsic.", ".mc_models."),
                 (".metric_sums['mean_intrinsic_reward']", ".metric_sums['mean_mc_reward']"))
    cfg = resolve_config("fetchreach-sacmc", {**small, "total_steps": 300, "eval_every": 150, "log_every": 50,
                                              "checkpoint_every": 100, "keep_checkpoints": 5})
    full = train(cfg, tmp_path / "full", progress=False)
    # today's files hold only today's names
    written = json.loads((full / "config.json").read_text())
    meta = json.loads((full / "checkpoints" / rundir.checkpoint_name(300) / "meta.json").read_text())
    header = (full / "metrics.csv").read_text().split("\n")[0].split(",")
    assert written["intrinsic_alpha"] == 0.2 and meta["config"] == written
    assert not set(old_keys.values()) & (set(written) | set(meta["config"])) and not set(old_columns.values()) & set(header)
    assert set(old_columns) <= set(header)

    old = tmp_path / "old"
    shutil.copytree(full, old)
    shutil.rmtree(old / "checkpoints" / rundir.checkpoint_name(300))
    rundir.write_latest(old, rundir.checkpoint_name(200))
    for name in (rundir.DONE, rundir.FINAL_EVAL):
        (old / name).unlink()
    # ... written by the code before the renames
    (old / "config.json").write_text(json.dumps({old_keys.get(k, k): v for k, v in written.items()}))
    for ck in (old / "checkpoints").glob("step_*"):
        with np.load(ck / "state.npz") as f:
            arrays = {k: f[k] for k in f.files}
        for new, o in old_paths:
            arrays = {(o + k[len(new):] if k.startswith(new) else k): v for k, v in arrays.items()}
        assert any(k.startswith(".mc_models.params") for k in arrays)
        assert ".metric_sums['mean_mc_reward']" in arrays
        np.savez(ck / "state.npz", **arrays)
    header, *lines = (old / "metrics.csv").read_text().split("\n")
    header = ",".join(old_columns.get(c, c) for c in header.split(","))
    (old / "metrics.csv").write_text("\n".join([header, *lines]))
    assert "mean_mc_reward" not in read_rows(old / "metrics.csv")[-1]  # read under today's name only
    assert read_rows(old / "metrics.csv")[-1]["mean_intrinsic_reward"] is not None

    resume(old, progress=False)
    assert (old / "eval.csv").read_text() == (full / "eval.csv").read_text()
    assert _rows(old / "metrics.csv") == _rows(full / "metrics.csv") and len(_rows(full / "metrics.csv")) == 6
    assert (old / "metrics.csv").read_text().split("\n")[0] == (full / "metrics.csv").read_text().split("\n")[0]
