"""Faults a run survives: a second writer (refused, nothing written), SIGINT / SIGTERM (a checkpoint at the episode's
end, then an exact resume), a second Ctrl-C (stops at once), a full disk during a checkpoint or a log row (the last
complete checkpoint stays, one-line error, exact resume, no torn row).

The end-to-end tests run `mcrl train` in subprocesses as a user would and compare the resumed run's eval.csv and
metrics.csv (every column but wall-clock time) with an uninterrupted run's.
"""
import csv
import errno
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from mcrl import files
from mcrl.cli import main
from mcrl.config import resolve_config
from mcrl.errors import MCRLError
from mcrl.run import checkpoint, lock, rundir, stop
from mcrl.run.rundir import LEARNING_COLUMNS
from mcrl.run.trainer import train

CLI = [sys.executable, "-m", "mcrl.cli"]
SMALL = {"hidden_sizes": "[64,64]", "mc_hidden_sizes": "[64,64]", "batch_size": 64, "buffer_size": 20000,
         "eval_episodes": 2, "learning_starts": 100}


def _sets(**extra) -> list[str]:
    out = []
    for k, v in {**SMALL, **extra}.items():
        out += ["--set", f"{k}={v}"]
    return out


def _rows(path):
    with open(path) as f:
        return [{k: r[k] for k in LEARNING_COLUMNS if k in r} for r in csv.DictReader(f)]


def _same_numbers(run, ref):
    assert (run / "done").exists()
    assert (run / "eval.csv").read_text() == (ref / "eval.csv").read_text()
    assert _rows(run / "metrics.csv") == _rows(ref / "metrics.csv")


def _snapshot(d: Path) -> dict:
    return {p: p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def _wait(cond, proc, what, timeout=300):
    deadline = time.time() + timeout
    while not cond():
        assert proc.poll() is None, f"the process ended before {what}"
        assert time.time() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def _logged_step(run: Path) -> int:
    rows = rundir.read_rows(run / rundir.METRICS)
    return int(rows[-1]["step"]) if rows else 0


class _Lines:
    """A subprocess' stream, read in a thread."""

    def __init__(self, stream):
        self.text = ""
        self._t = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._t.start()

    def _read(self, stream):
        for line in stream:
            self.text += line

    def join(self):
        self._t.join(30)


# ----------------------------------------------------------------------------- one writer per run directory
@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    small = {**SMALL, "hidden_sizes": [64, 64], "mc_hidden_sizes": [64, 64]}
    cfg = resolve_config("fetchreach-sac", {**small, "total_steps": 150, "eval_every": 0})
    return train(cfg, tmp_path_factory.mktemp("runs") / "r", progress=False)


def _hold_lock(run_dir: Path) -> subprocess.Popen:
    """Another process that holds `run_dir`'s lock (and writes nothing) until killed."""
    code = ("import sys, time; from mcrl.run.lock import acquire; acquire(sys.argv[1]); print('locked', flush=True); "
            "time.sleep(600)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(run_dir)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_a_second_writer_is_refused_and_writes_nothing(finished_run, tmp_path, capsys):
    fresh = tmp_path / "fresh"
    holders = [_hold_lock(finished_run), _hold_lock(fresh)]
    try:
        before = {d: _snapshot(d) for d in (finished_run, fresh)}
        for args in (["train", "--resume", str(finished_run), "--steps", "300"],
                     ["train", "--preset", "fetchreach-sac", "--run-dir", str(fresh), *_sets()]):
            rc = main([*args, "--no-progress"])
            err = capsys.readouterr().err.strip()
            holder = holders[0] if "--resume" in args else holders[1]
            assert rc == 2 and len(err.splitlines()) == 1, err
            assert f"is being written by pid {holder.pid}" in err and "one writer per run" in err
        assert {d: _snapshot(d) for d in (finished_run, fresh)} == before
    finally:
        for h in holders:
            h.kill()  # kill -9: the kernel drops the lock with the process
            h.wait()
    lock.acquire(finished_run).release()  # nothing stale behind


def test_a_group_with_a_run_written_elsewhere_writes_nothing(tmp_path):
    from mcrl.run.group import train_group

    cfgs = [resolve_config("fetchreach-sacmc", {"hidden_sizes": [64, 64], "mc_hidden_sizes": [64, 64], "seed": s,
                                                 "total_steps": 100}) for s in (0, 1)]
    dirs = [tmp_path / "g0", tmp_path / "g1"]
    holder = _hold_lock(dirs[1])
    try:
        with pytest.raises(MCRLError, match=f"pid {holder.pid}"):
            train_group(cfgs, dirs)
        assert not dirs[0].exists() and [p.name for p in dirs[1].iterdir()] == [rundir.LOCK]
    finally:
        holder.kill()
        holder.wait()


# ----------------------------------------------------------------------------- signals
def test_signals_ask_for_a_stop_and_a_second_one_stops_at_once():
    with stop.handle():
        signal.raise_signal(signal.SIGTERM)
        assert stop.requested() == signal.SIGTERM
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
    assert stop.requested() is None and signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert stop.exit_code() == 130
    with stop.handle(second_stops_now=False):  # a sweep's worker: its driver stops it for a second signal
        signal.raise_signal(signal.SIGINT)
        signal.raise_signal(signal.SIGINT)
        assert stop.requested() == signal.SIGINT
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)  # started with SIGINT ignored (nohup, a background job)
    try:
        with stop.handle():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, old)


SIGNAL_RUN = ["--preset", "fetchreach-sacmc", "--steps", "1500",
              *_sets(eval_every=300, log_every=100, checkpoint_every=100_000)]  # no periodic checkpoint in the run


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    run = tmp_path_factory.mktemp("signals") / "full"
    subprocess.run(CLI + ["train", *SIGNAL_RUN, "--run-dir", str(run), "--no-progress"], check=True,
                   capture_output=True)
    return run


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_saves_at_the_episode_end_and_the_resume_is_exact(uninterrupted, tmp_path, sig):
    run = tmp_path / "run"
    proc = subprocess.Popen(CLI + ["train", *SIGNAL_RUN, "--run-dir", str(run)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # progress on: a pipe gets plain lines
    err = _Lines(proc.stderr)
    _wait(lambda: _logged_step(run) >= 400, proc, "step 400")
    proc.send_signal(sig)
    proc.wait(300)
    err.join()
    assert proc.returncode == 128 + sig, err.text
    step = rundir.checkpoint_step(rundir.latest_checkpoint(run))
    assert 400 <= step < 1500 and step % 50 == 0  # FetchReach's episodes are 50 steps
    assert checkpoint.is_complete(run / "checkpoints" / rundir.checkpoint_name(step))
    assert f"stopped by {signal.Signals(sig).name}: saved at step {step:,}" in err.text
    assert f"mcrl train --resume {run}" in err.text
    assert "\r" not in err.text and 2 <= sum(line.startswith("train: ") for line in err.text.splitlines()) <= 21
    assert not (run / "done").exists()

    res = subprocess.run(CLI + ["train", "--resume", str(run), "--no-progress"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    _same_numbers(run, uninterrupted)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_second_ctrl_c_stops_at_once(tmp_path):
    run = tmp_path / "run"
    # one episode as long as the run: the first Ctrl-C waits for an episode end that does not come
    args = ["train", "--env", "Pendulum-v1", "--steps", "100000", "--run-dir", str(run), "--no-progress",
            *_sets(log_every=100, eval_every=0, checkpoint_every=100_000),
            "--set", 'env_kwargs={"max_episode_steps": 1000000}']
    proc = subprocess.Popen(CLI + args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        err = _Lines(proc.stderr)
        _wait(lambda: _logged_step(run) >= 200, proc, "step 200")
        proc.send_signal(signal.SIGINT)
        _wait(lambda: "saving a checkpoint at the episode's end" in err.text, proc, "the first Ctrl-C's notice")
        proc.send_signal(signal.SIGINT)
        proc.wait(120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err.join()
    assert proc.returncode == 130, err.text
    assert "interrupted; a run continues from its last checkpoint" in err.text
    assert not (run / "checkpoints").exists()


# ----------------------------------------------------------------------------- a full disk
DISK_RUN = {"total_steps": 600, "eval_every": 300, "log_every": 100, "checkpoint_every": 200}


def _disk_args(run):
    return ["train", "--preset", "fetchreach-sac", "--run-dir", str(run), "--no-progress",
            *_sets(**DISK_RUN)]


@pytest.fixture(scope="module")
def disk_reference(tmp_path_factory):
    run = tmp_path_factory.mktemp("disk") / "full"
    assert main(_disk_args(run)) == 0
    return run


def _enospc(path=None):
    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), *([str(path)] if path else []))


def _resume_matches(run, ref, capsys):
    capsys.readouterr()
    assert main(["train", "--resume", str(run), "--no-progress"]) == 0, capsys.readouterr().err
    _same_numbers(run, ref)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_full_disk_during_a_checkpoint_keeps_the_last_one(disk_reference, tmp_path, monkeypatch, capsys):
    run = tmp_path / "run"
    real_savez = np.savez

    def savez(file, *args, **kw):  # the disk fills up half-way through step 400's replay buffer
        real_savez(file, *args, **kw)
        p = Path(file)
        if p.name == "buffer.npz" and p.parent.name == f".tmp-{rundir.checkpoint_name(400)}":
            p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
            raise _enospc()

    monkeypatch.setattr(np, "savez", savez)
    rc = main(_disk_args(run))
    err = capsys.readouterr().err.strip()
    monkeypatch.undo()
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("mcrl: error: No space left on device") and f"{run} resumes from step 200" in err
    assert rundir.latest_checkpoint(run) == rundir.checkpoint_name(200)
    assert checkpoint.find(run) == run / "checkpoints" / rundir.checkpoint_name(200)
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["latest", rundir.checkpoint_name(200)]
    _resume_matches(run, disk_reference, capsys)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_full_disk_during_a_log_row_leaves_no_torn_row(disk_reference, tmp_path, monkeypatch, capsys):
    run = tmp_path / "run"
    real_open = open

    class Torn:  # writes the first two characters of the row, then finds the disk full
        def __init__(self, f):
            self.f = f

        def write(self, s):
            self.f.write(s[:2])
            self.f.flush()
            raise _enospc(self.f.name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    def fake_open(file, mode="r", *args, **kw):
        f = real_open(file, mode, *args, **kw)
        if Path(file).name == rundir.METRICS and mode == "a" and _logged_step(run) == 400:
            return Torn(f)  # the row of step 500, after step 400's checkpoint
        return f

    monkeypatch.setattr(files, "open", fake_open, raising=False)  # the one CSV row writer's
    rc = main(_disk_args(run))
    err = capsys.readouterr().err.strip()
    monkeypatch.undo()
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert f"({run / rundir.METRICS}, " in err and f"{run} resumes from step 400" in err
    assert (run / rundir.METRICS).read_text().endswith("\n50")  # torn
    _resume_matches(run, disk_reference, capsys)
