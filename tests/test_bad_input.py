"""Every bad input: one line naming the problem and the fix, exit code 2, nothing written."""
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from mcrl.cli import main
from mcrl.config import resolve_config
from mcrl.run.trainer import train


def _run(args, tmp_path, capsys):
    before = set(tmp_path.rglob("*"))
    rc = main(args)
    err = capsys.readouterr().err.strip()
    after = set(tmp_path.rglob("*"))
    return rc, err, after - before


@pytest.mark.parametrize("args,needle", [
    (["train", "--preset", "fetchpush-sacmc-0.3"], "unknown preset"),
    (["train", "--env", "NoSuchEnv-v9"], "unknown environment"),
    (["train", "--set", "mc_alpha=1.2"], "outside [0, 1]"),
    (["train", "--set", "mc_alpha=-0.1"], "outside [0, 1]"),
    (["train", "--set", "min_percentile=94", "--set", "max_percentile=90"], "min_percentile"),
    (["train", "--set", "max_percentile=101"], "outside [0, 100]"),
    (["train", "--env", "Pendulum-v1", "--set", "her=true"], "her=true"),
    (["train", "--env", "CartPole-v1", "--set", "her=false"], "Box action space"),
    (["train", "--set", "no_such_key=1"], "unknown config key"),
    (["train", "--set", "batch_size=abc"], "expected int"),
    (["train", "--set", "mc_alpha=0.2", "--set", "mc_models=false"], "needs the intrinsic reward's models"),
    (["train", "--set", "intrinsic_alpha=0.2", "--set", "mc_alpha=0.4"], "disagree"),
    (["train", "--set", "intrinsic=nope"], "choose one of mc, rnd, icm, disagreement"),
    (["train", "--set", "init=xavier"], "init="),
    (["train", "--set", "mc_history=0"], "intrinsic_history=0"),
])
def test_bad_training_input(args, needle, tmp_path, capsys):
    rc, err, new = _run(args + ["--out-dir", str(tmp_path / "runs")], tmp_path, capsys)
    assert rc == 2
    assert needle in err and len(err.splitlines()) == 1, err
    assert not new


@pytest.fixture
def finished_run(tmp_path_factory, small):
    cfg = resolve_config("fetchreach-sac", {**small, "total_steps": 150, "eval_every": 0})
    return train(cfg, tmp_path_factory.mktemp("runs") / "r", progress=False)


def test_corrupt_checkpoint(finished_run, tmp_path, capsys):
    run = tmp_path / "copy"
    shutil.copytree(finished_run, run)
    ck = run / "checkpoints" / (run / "checkpoints" / "latest").read_text().strip()
    data = (ck / "state.npz").read_bytes()
    (ck / "state.npz").write_bytes(data[: len(data) // 2])
    for args in (["eval", str(run)], ["train", "--resume", str(run), "--steps", "300"]):
        rc, err, _ = _run(args, tmp_path, capsys)
        assert rc == 2 and "corrupt" in err and len(err.splitlines()) == 1, err


def test_mismatched_checkpoint(finished_run, tmp_path, capsys):
    run = tmp_path / "copy"
    shutil.copytree(finished_run, run)
    cfg = json.loads((run / "config.json").read_text())
    cfg["hidden_sizes"] = [32, 32]
    (run / "config.json").write_text(json.dumps(cfg))
    before = (run / "metrics.csv").read_text()
    rc, err, _ = _run(["train", "--resume", str(run), "--steps", "300"], tmp_path, capsys)
    assert rc == 2 and "shape" in err and len(err.splitlines()) == 1, err
    assert (run / "metrics.csv").read_text() == before  # nothing rewritten


def test_not_a_run_directory_and_no_checkpoint(tmp_path, capsys):
    rc, err, _ = _run(["eval", str(tmp_path)], tmp_path, capsys)
    assert rc == 2 and "not a run directory" in err
    (tmp_path / "config.json").write_text(json.dumps({"env_id": "FetchReach-v4"}))
    rc, err, _ = _run(["eval", str(tmp_path)], tmp_path, capsys)
    assert rc == 2 and "no checkpoint" in err


@pytest.mark.parametrize("arrays,needle", [
    ({"states": np.zeros((50, 3)), "actions": np.zeros((50, 2))}, "lacks array"),
    ({"states": np.zeros((50, 3)), "actions": np.zeros((50, 2)), "next_states": np.zeros((50, 4))}, "disagree"),
    ({"states": np.zeros((50, 3)), "actions": np.zeros((49, 2)), "next_states": np.zeros((50, 3))}, "disagree"),
    ({"states": np.zeros(50), "actions": np.zeros((50, 2)), "next_states": np.zeros(50)}, "2-d"),
])
def test_bad_measure_data(arrays, needle, tmp_path, capsys):
    path = tmp_path / "d.npz"
    np.savez(path, **arrays)
    rc, err, new = _run(["measure", str(path), "--out", str(tmp_path / "kl.npy")], tmp_path, capsys)
    assert rc == 2 and needle in err and len(err.splitlines()) == 1, err
    assert not new


def test_measure_unreadable_file(tmp_path, capsys):
    path = tmp_path / "d.npz"
    path.write_bytes(b"not a zip")
    rc, err, _ = _run(["measure", str(path)], tmp_path, capsys)
    assert rc == 2 and "cannot read" in err


def test_console_script_exit_code():
    res = subprocess.run([sys.executable, "-m", "mcrl.cli", "train", "--set", "mc_alpha=2"], capture_output=True,
                         text=True)
    assert res.returncode == 2 and res.stderr.strip().startswith("mcrl: error: intrinsic_alpha=2.0")


def test_training_into_an_existing_run_directory_is_refused(finished_run, capsys):
    before = (finished_run / "metrics.csv").read_text()
    rc = main(["train", "--run-dir", str(finished_run), "--steps", "100"])
    assert rc == 2 and "already holds a run" in capsys.readouterr().err
    assert (finished_run / "metrics.csv").read_text() == before
