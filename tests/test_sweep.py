"""`mcrl sweep`: local and Ray backends give the same runs, a killed sweep resumes, MLflow tracking,
bad input, run files shipped from a worker.

Tiny runs (300 steps, small networks); the sweeps run through the CLI in subprocesses, as a user
would run them. The whole file takes about 2 minutes on 2 cores.
"""
import csv
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

from mcrl.cli import main
from mcrl.run.rundir import LEARNING_COLUMNS

TINY = {"hidden_sizes": "[64,64]", "mc_hidden_sizes": "[64,64]", "batch_size": 64, "buffer_size": 20000,
        "eval_every": 150, "eval_episodes": 2, "log_every": 100, "learning_starts": 100,
        "checkpoint_every": 100}
STEPS = 300
CLI = [sys.executable, "-c", "import sys; from mcrl.cli import main; sys.exit(main())"]


def _sets():
    out = []
    for k, v in TINY.items():
        out += ["--set", f"{k}={v}"]
    return out


def _sweep_args(exp, alphas="0,0.2", seeds="2", *extra):
    return ["sweep", "--preset", "fetchreach-sacmc", "--alphas", alphas, "--seeds", seeds, "--steps", str(STEPS),
            *_sets(), "--exp", str(exp), "--no-progress", *extra]


def _run_cli(args, env=None, timeout=400):
    res = subprocess.run(CLI + args, capture_output=True, text=True, timeout=timeout,
                         env={**os.environ, **(env or {})})
    return res


def _learning_rows(path):
    with open(path) as f:
        return [{k: r[k] for k in LEARNING_COLUMNS} for r in csv.DictReader(f)]


def _same_run(a, b):
    assert (a / "done").exists() and (b / "done").exists()
    assert (a / "eval.csv").read_text() == (b / "eval.csv").read_text()
    assert _learning_rows(a / "metrics.csv") == _learning_rows(b / "metrics.csv")


@pytest.fixture(scope="module")
def local_exp(tmp_path_factory):
    """2 alphas x 2 seeds on the local backend, tracked in MLflow (the reference for the other tests)."""
    exp = tmp_path_factory.mktemp("sweeps") / "local"
    res = _run_cli(_sweep_args(exp, "0,0.2", "2", "--backend", "local", "--workers", "2", "--tracking"))
    assert res.returncode == 0, res.stdout + res.stderr
    return exp, res.stdout


RUN_NAMES = ["a0-s0", "a0.2-s0", "a0-s1", "a0.2-s1"]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_local_sweep_writes_the_experiment_directory(local_exp):
    exp, out = local_exp
    sweep = json.loads((exp / "sweep.json").read_text())
    assert sweep["preset"] == "fetchreach-sacmc" and sweep["grid"] == {"intrinsic_alpha": [0.0, 0.2], "seed": [0, 1]}
    assert [r["name"] for r in sweep["runs"]] == RUN_NAMES  # seeds outermost
    assert [(r["config_key"], r["seed"]) for r in sweep["runs"]] == [
        ("alpha=0", 0), ("alpha=0.2", 0), ("alpha=0", 1), ("alpha=0.2", 1)]
    assert sweep["runs"][1]["overrides"]["intrinsic_alpha"] == 0.2
    for name in RUN_NAMES:
        run = exp / "runs" / name
        assert (run / "done").exists()
        cfg = json.loads((run / "config.json").read_text())
        assert cfg["total_steps"] == STEPS and cfg["seed"] == int(name[-1])
        assert cfg["intrinsic_alpha"] == (0.2 if name.startswith("a0.2") else 0.0)
        assert re.search(rf"start {re.escape(name)} \(pid \d+\)", out)
        assert re.search(rf"finished {re.escape(name)} in", out)
    from mcrl.analysis.report import load_experiment

    loaded = load_experiment(exp)  # the format `mcrl report` reads
    assert [g.key for g in loaded.configs] == ["alpha=0", "alpha=0.2"]
    assert all(r.status == "finished" for r in loaded.runs)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_mlflow_holds_every_run_and_rerun_skips_finished_runs(local_exp):
    import mlflow
    from mlflow import MlflowClient

    exp, out = local_exp
    uri = f"sqlite:///{exp / 'mlflow.db'}"
    assert f"mlflow ui --backend-store-uri {uri}" in out
    client = MlflowClient(tracking_uri=uri)
    mlflow.set_tracking_uri(uri)
    try:
        df = mlflow.search_runs(experiment_names=[exp.name])
    finally:
        mlflow.set_tracking_uri(None)
    assert sorted(df["tags.mlflow.runName"]) == sorted(RUN_NAMES)
    assert set(df["status"]) == {"FINISHED"}
    for _, row in df.iterrows():
        name = row["tags.mlflow.runName"]
        cfg = json.loads((exp / "runs" / name / "config.json").read_text())
        assert float(row["params.intrinsic_alpha"]) == cfg["intrinsic_alpha"] and int(row["params.seed"]) == cfg["seed"]
        assert row["params.hidden_sizes"] == "[64, 64]" and row["params.config_key"].startswith("alpha=")
        with open(exp / "runs" / name / "eval.csv") as f:
            evals = list(csv.DictReader(f))
        hist = client.get_metric_history(row["run_id"], "eval/success_rate")
        assert [(m.step, m.value) for m in hist] == [(int(e["step"]), float(e["success_rate"])) for e in evals]
        loss = client.get_metric_history(row["run_id"], "critic_loss")
        assert [m.step for m in loss] == [200, 300]
        arts = {a.path for a in client.list_artifacts(row["run_id"])}
        assert {"curves.png", "config.json", "metrics.csv", "eval.csv"} <= arts
    assert (exp / "mlartifacts").is_dir()

    # `mcrl sweep --exp EXP` alone continues the recorded sweep: everything is finished, nothing logged twice
    before = {p: p.stat().st_mtime_ns for p in exp.glob("runs/*/*.csv")}
    res = _run_cli(["sweep", "--exp", str(exp), "--no-progress", "--tracking"])
    assert res.returncode == 0, res.stderr
    assert res.stdout.count("already finished") == 4
    assert {p: p.stat().st_mtime_ns for p in exp.glob("runs/*/*.csv")} == before
    assert len(client.search_runs([df["experiment_id"][0]])) == 4


class _Lines:
    """Collects a subprocess' stdout lines in a thread."""

    def __init__(self, proc):
        self.lines: list[str] = []
        self._t = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._t.start()

    def _read(self, proc):
        for line in proc.stdout:
            self.lines.append(line)

    def text(self):
        return "".join(self.lines)


def _wait_for(cond, proc, what, timeout=240):
    deadline = time.time() + timeout
    while not cond():
        assert proc.poll() is None, f"sweep ended before {what}"
        assert time.time() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_killed_worker_and_killed_sweep_resume_to_the_same_numbers(local_exp, tmp_path):
    ref, _ = local_exp
    exp = tmp_path / "killed"
    args = _sweep_args(exp, "0.2", "2", "--workers", "2")  # runs a0.2-s0 and a0.2-s1, as in the reference
    proc = subprocess.Popen(CLI + args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    out = _Lines(proc)
    try:
        # 1. SIGKILL one worker after its run's first checkpoint: the driver reports it and goes on
        _wait_for(lambda: list(exp.glob("runs/*/checkpoints/latest")), proc, "a first checkpoint")
        victim = exp.glob("runs/*/checkpoints/latest").__next__().parent.parent.name
        start_line = re.compile(rf"start {re.escape(victim)} \(pid (\d+)\)")
        _wait_for(lambda: start_line.search(out.text()), proc, "the victim's start line")
        pid = int(start_line.search(out.text()).group(1))
        os.kill(pid, signal.SIGKILL)
        _wait_for(lambda: f"FAILED {victim}" in out.text(), proc, "the driver to report the killed worker")
        assert not (exp / "runs" / victim / "done").exists()
        # 2. SIGKILL the whole sweep (driver and the other worker) while the other run is still going
        other = next(n for n in ("a0.2-s0", "a0.2-s1") if n != victim)
        if not (exp / "runs" / other / "done").exists():
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert f"worker killed by signal {int(signal.SIGKILL)}" in out.text()
    time.sleep(1.0)  # the killed driver's workers die with it (no one else writes into EXP)

    res = _run_cli(args)  # the same command again
    assert res.returncode == 0, res.stdout + res.stderr
    assert re.search(rf"resume {re.escape(victim)} from step \d+", res.stdout), res.stdout
    for name in ("a0.2-s0", "a0.2-s1"):
        _same_run(ref / "runs" / name, exp / "runs" / name)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_sigterm_saves_the_runs_of_a_sweep_and_the_rerun_is_exact(local_exp, tmp_path):
    """SIGTERM to the driver alone (what `timeout`, a scheduler or `docker stop` send): it starts no more runs, each
    running run saves at its episode's end, the sweep exits 143; the same command resumes them exactly."""
    ref, _ = local_exp
    exp = tmp_path / "stopped"
    args = _sweep_args(exp, "0.2", "2", "--workers", "2")
    proc = subprocess.Popen(CLI + args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    out = _Lines(proc)
    try:
        _wait_for(lambda: all(_logged(exp / "runs" / n) >= 100 for n in ("a0.2-s0", "a0.2-s1")), proc,
                  "both runs past step 100", timeout=600)
        proc.send_signal(signal.SIGTERM)
        proc.wait(300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 143, out.text()
    stopped = [n for n in ("a0.2-s0", "a0.2-s1") if not (exp / "runs" / n / "done").exists()]
    assert stopped, out.text()  # (a run may finish before the signal reaches it, not both)
    for name in stopped:
        run = exp / "runs" / name
        step = int((run / "checkpoints" / "latest").read_text().strip().split("_")[1])
        assert f"stopped {name} at step {step:,}, checkpoint saved" in out.text(), out.text()
    assert "`mcrl sweep --exp" in out.text() and "resumes them exactly" in out.text()

    res = _run_cli(args)
    assert res.returncode == 0, res.stdout + res.stderr
    for name in ("a0.2-s0", "a0.2-s1"):
        _same_run(ref / "runs" / name, exp / "runs" / name)


def _logged(run) -> int:
    try:
        lines = (run / "metrics.csv").read_text().strip().splitlines()
    except OSError:
        return 0
    return int(float(lines[-1].split(",")[0])) if len(lines) > 1 else 0


@pytest.mark.slow
@pytest.mark.timeout(1200)  # two Ray start-ups and 2 + 1 runs: ~4 min on a quiet 2-core machine
def test_ray_backend_ships_files_and_resumes_a_killed_worker(local_exp, tmp_path):
    """The Ray backend gives the local backend's runs: a0.2-s1 pretends its worker cannot see EXP (it trains in a
    temporary directory and ships its files back); a0.2-s0's worker is killed with -9 after its first checkpoint,
    the driver reports that run failed and finishes the other, and the same command again resumes the killed run
    from its checkpoint. Both end with the uninterrupted local sweep's numbers and sweep.json entries."""
    ref, _ = local_exp
    exp = tmp_path / "ray"
    args = _sweep_args(exp, "0.2", "2", "--backend", "ray", "--workers", "2")  # a0.2-s0 and a0.2-s1, as in ref
    victim, shipped = "a0.2-s0", "a0.2-s1"  # the shipped run writes nothing under EXP before it ends
    proc = subprocess.Popen(CLI + args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True, env={**os.environ, "MCRL_SWEEP_SHIP_FILES": shipped})
    out = _Lines(proc)
    try:
        _wait_for(lambda: (exp / "runs" / victim / "checkpoints" / "latest").exists(), proc, "a first checkpoint",
                  timeout=600)
        start_line = re.compile(rf"start {re.escape(victim)} \(pid (\d+) on ")
        _wait_for(lambda: start_line.search(out.text()), proc, "the victim's start line")
        os.kill(int(start_line.search(out.text()).group(1)), signal.SIGKILL)  # the Ray worker process
        proc.wait(600)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text = out.text()
    assert proc.returncode == 1 and f"FAILED {victim}" in text, text
    assert not (exp / "runs" / victim / "done").exists()
    assert f"start {shipped} (pid" in text and "files shipped back" in text, text
    assert (exp / "runs" / shipped / "checkpoints" / "latest").read_text().strip() == f"step_{STEPS:09d}"
    assert list((exp / "runs" / shipped).glob("events.out.tfevents.*"))

    res = _run_cli(args, timeout=600)  # the same command again
    assert res.returncode == 0, res.stdout + res.stderr
    assert re.search(rf"queued {re.escape(victim)} \(resumes from step [1-9]\d*\)", res.stdout), res.stdout
    names = [victim, shipped]
    for name in names:
        _same_run(ref / "runs" / name, exp / "runs" / name)
    runs = [json.loads((d / "sweep.json").read_text())["runs"] for d in (ref, exp)]
    assert [r for r in runs[0] if r["name"] in names] == runs[1]


def _closed_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _write(tmp_path, text):
    p = tmp_path / "sweep.yaml"
    p.write_text(text)
    return str(p)


BAD_FILES = [
    ("preset: fetchreach-sacmc\ngrid: {mc_alpha: [0, 0.2], no_such_key: [1]}\n", "unknown config key"),
    ("preset: fetchreach-sacmc\ngrid: {mc_alpha: [0, 0.2]}\nset: {bogus: 3}\n", "unknown config key"),
    ("preset: fetchreach-sacmc\ngrid: {mc_alpha: [0, 1.5]}\n", "outside [0, 1]"),
    ("preset: fetchreach-sacmc\ngrid: {}\n", "grid is empty"),
    ("preset: fetchreach-sacmc\n", "grid is empty"),
    ("preset: fetchreach-sacmc\ngrid: {mc_alpha: []}\n", "non-empty list"),
    ("preset: fetchreach-sacmc\ngrids: {mc_alpha: [0]}\n", "unknown top-level key"),
    ("preset: no-such-preset\ngrid: {mc_alpha: [0]}\n", "unknown preset"),
    ("preset: fetchreach-sacmc\ngrid: {env_id: [NoSuchEnv-v9]}\n", "unknown environment"),
    ("preset: fetchreach-sacmc\ngrid: {mc_alpha: [0.2, 0.2]}\n", "same config"),
    ("preset: fetchreach-sacmc\ngrid: {mc_alpha: [0, 0.2}\n", "not valid YAML"),
    ("- just\n- a list\n", "YAML mapping"),
]


@pytest.mark.parametrize("text,needle", BAD_FILES)
def test_bad_sweep_file(text, needle, tmp_path, capsys):
    path = _write(tmp_path, text)
    exp = tmp_path / "exp"
    rc = main(["sweep", "--file", path, "--exp", str(exp), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert needle in err and len(err.splitlines()) == 1, err
    assert not exp.exists()


@pytest.mark.parametrize("extra,needle", [
    (["--alphas", ""], "empty grid"),
    (["--alphas", "0,abc"], "comma-separated numbers"),
    (["--alphas", "0,0.2", "--seeds", "0"], "at least 1"),
    (["--alphas", "0,0.2", "--set", "nope=1"], "unknown config key"),
    (["--alphas", "0,0.2", "--backend", "ray", "--address", "127.0.0.1:{port}"], "does not answer"),
    (["--alphas", "0,0.2", "--backend", "ray", "--address", "not-an-address"], "HOST:PORT"),
    (["--alphas", "0,0.2", "--tracking-uri", "http://127.0.0.1:{port}"], "cannot be reached"),
    (["--alphas", "0,0.2", "--tracking", "--tracking-uri", "sqlite:////no/such/dir/mlflow.db"], "does not exist"),
    (["--alphas", "0,0.2", "--address", "127.0.0.1:6379"], "--backend ray"),
    (["--alphas", "0,0.2", "--workers", "0"], "--workers"),
])
def test_bad_sweep_arguments(extra, needle, tmp_path, capsys):
    port = _closed_port()
    exp = tmp_path / "exp"
    args = ["sweep", "--preset", "fetchreach-sacmc", "--exp", str(exp), "--no-progress"]
    rc = main(args + [a.format(port=port) for a in extra])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert needle in err and len(err.splitlines()) == 1, err
    assert not exp.exists()


def test_missing_sweep_file_and_foreign_directory(tmp_path, capsys):
    rc = main(["sweep", "--file", str(tmp_path / "nope.yaml"), "--exp", str(tmp_path / "exp")])
    assert rc == 2 and "not found" in capsys.readouterr().err
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    rc = main(["sweep", "--preset", "fetchreach-sacmc", "--alphas", "0", "--exp", str(other), "--no-progress"])
    assert rc == 2 and "not a sweep directory" in capsys.readouterr().err
    assert sorted(p.name for p in other.iterdir()) == ["notes.txt"]
    assert not (tmp_path / "exp").exists()


@pytest.mark.slow
def test_rerun_with_a_different_config_is_refused(local_exp, capsys):
    exp, _ = local_exp
    before = (exp / "sweep.json").read_text()
    rc = main(_sweep_args(exp, "0,0.2", "2")[:-3] + ["--steps", "600", "--exp", str(exp), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "different config" in err and len(err.splitlines()) == 1, err
    assert (exp / "sweep.json").read_text() == before


def test_grid_file_plan_names_and_keys(tmp_path):
    from mcrl.sweep import plan_from_file

    path = _write(tmp_path, "preset: fetchreach-sacmc\n"
                            "grid: {mc_alpha: [0, 0.2], batch_size: [64, 128], seed: [3, 5]}\n"
                            "set: {total_steps: 300, hidden_sizes: [64, 64]}\n")
    plan = plan_from_file(path)
    assert len(plan.runs) == 8
    first = plan.runs[0]
    assert (first.name, first.config_key, first.seed) == ("a0-batch_size=64-s3", "alpha=0,batch_size=64", 3)
    assert first.config.hidden_sizes == (64, 64) and first.config.total_steps == 300
    assert [r.seed for r in plan.runs] == [3, 3, 3, 3, 5, 5, 5, 5]
    assert len({r.name for r in plan.runs}) == 8


def test_a_second_sweep_into_the_directory_merges_its_grid_and_set(tmp_path):
    """sweep.json's grid and set describe every run once a later sweep adds runs (issue 29's ICM phase after RND
    and Disagreement): grid values join, a set key that differs between the sweeps becomes a grid key."""
    from mcrl.config import resolve_config
    from mcrl.sweep import plan_from_file
    from mcrl.sweep.experiment import merged_grid_and_set
    from mcrl.sweep.plan import SweepPlan

    first = plan_from_file(_write(tmp_path, "preset: fetchreach-sacmc\ngrid: {intrinsic: [rnd, disagreement]}\n"
                                            "seeds: 2\nset: {total_steps: 300, batch_size: 64}\n"))
    old = {"grid": merged_grid_and_set(None, first)[0], "set": merged_grid_and_set(None, first)[1]}
    assert old == {"grid": {"intrinsic": ["rnd", "disagreement"], "seed": [0, 1]},
                   "set": {"total_steps": 300, "batch_size": 64}}
    second = plan_from_file(_write(tmp_path, "preset: fetchreach-sacmc\ngrid: {intrinsic: [icm, rnd]}\n"
                                             "seeds: 3\nset: {total_steps: 300, hidden_sizes: [64, 64]}\n"))
    grid, fixed = merged_grid_and_set(old, second)
    default = resolve_config("fetchreach-sacmc", {})  # the first sweep left hidden_sizes, the second batch_size
    assert grid == {"intrinsic": ["rnd", "disagreement", "icm"], "seed": [0, 1, 2],
                    "batch_size": [64, default.batch_size], "hidden_sizes": [list(default.hidden_sizes), [64, 64]]}
    assert fixed == {"total_steps": 300}
    # continuing the directory as it is (`mcrl sweep --exp EXP`) changes nothing
    assert merged_grid_and_set({"grid": grid, "set": fixed}, SweepPlan("fetchreach-sacmc", grid, fixed, [], "x")) == (
        grid, fixed)


def test_mlflow_receives_the_runs_videos(local_exp, tmp_path):
    import shutil

    from mlflow import MlflowClient

    from mcrl.config import Config
    from mcrl.sweep import RunPlan
    from mcrl.sweep.tracking import Tracker

    exp, _ = local_exp
    run_dir = tmp_path / "exp" / "runs" / "v"
    shutil.copytree(exp / "runs" / RUN_NAMES[0], run_dir)
    (run_dir / "videos").mkdir()
    (run_dir / "videos" / "eval_step300.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(64))
    tracker = Tracker.check(None, tmp_path / "exp")
    tracker.open(tmp_path / "exp", "sweep-id", "fetchreach-sacmc")
    cfg = Config.from_dict(json.loads((run_dir / "config.json").read_text()))
    rid = tracker.log_run(RunPlan("v", "alpha=0.2", cfg.seed, {}, cfg), run_dir)
    client = MlflowClient(tracking_uri=tracker.uri)
    assert [a.path for a in client.list_artifacts(rid, "videos")] == ["videos/eval_step300.mp4"]


def test_run_files_ship_between_worker_and_driver(tmp_path):
    """What a Ray worker without EXP sends (collect_run_files) the driver writes back as the trainer would."""
    from mcrl.run import rundir
    from mcrl.sweep.files import collect_run_files, run_status, write_run_files

    src = tmp_path / "worker" / "r"
    for step in (100, 200):
        ck = rundir.checkpoint_root(src) / rundir.checkpoint_name(step)
        ck.mkdir(parents=True)
        (ck / "meta.json").write_text(json.dumps({"step": step}))
    rundir.write_latest(src, rundir.checkpoint_name(200))
    (src / rundir.CONFIG).write_text("{}")
    (src / rundir.METRICS).write_text("step,x\n100,1\n200,2\n3")  # a row being written: not shipped yet
    files = collect_run_files(src, final=False)
    assert sorted(files) == ["checkpoints/latest", f"checkpoints/{rundir.checkpoint_name(200)}/meta.json",
                             rundir.CONFIG, rundir.METRICS]

    dst = tmp_path / "exp" / "runs" / "r"
    write_run_files(dst, files, keep=1)
    assert rundir.latest_checkpoint(dst) == rundir.checkpoint_name(200)
    assert (dst / rundir.METRICS).read_text() == "step,x\n100,1\n200,2\n"
    assert run_status(dst) == ("checkpoint", 200)
    rundir.write_json_atomic(src / rundir.DONE, {"step": 300})
    write_run_files(dst, collect_run_files(src, final=True), keep=1)
    assert run_status(dst) == ("finished", 300)
    assert (dst / rundir.METRICS).read_text() == (src / rundir.METRICS).read_text()  # at the end: all of it


def test_importing_the_sweep_package_imports_neither_jax_nor_ray():
    """A local worker sets its thread limits before jax is imported; Ray reads its auth settings on import."""
    code = ("import sys, mcrl.sweep, mcrl.sweep.tracking; "
            "print(sorted(m for m in ('jax', 'ray', 'mlflow', 'matplotlib') if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "[]", res.stdout + res.stderr


def test_a_run_another_process_writes_is_reported_locked_not_failed(tmp_path, capsys):
    """The driver checks each run's lock before it starts it: a run written elsewhere (here: locked by this
    process, as `mcrl train --resume` would hold it) is reported "locked by pid N", not started and not failed."""
    from mcrl.run import lock
    from mcrl.sweep import plan_from_args

    exp = tmp_path / "exp"
    args = ["sweep", "--preset", "fetchreach-sacmc", "--alphas", "0.2", "--seeds", "1", "--steps", "100",
            "--exp", str(exp), "--no-progress"]
    (run,) = plan_from_args("fetchreach-sacmc", "0.2", 1, {"total_steps": 100}).runs
    (exp / "runs").mkdir(parents=True)  # the sweep's directory as an earlier call left it
    (exp / "sweep.json").write_text(json.dumps({"preset": "fetchreach-sacmc", "id": "x", "runs": [run.entry()]}))
    with lock.acquire(exp / "runs" / run.name):
        rc = main(args)
    out, err = capsys.readouterr()
    assert rc == 1, out + err
    assert re.search(rf"locked a0.2-s0: locked by pid {os.getpid()} ", out), out
    assert "FAILED" not in out and "failed" not in err and "locked by another process (a0.2-s0)" in err
    assert not (exp / "runs" / "a0.2-s0" / "config.json").exists()  # never started


def test_backend_choices_come_from_the_registry():
    from mcrl.cli import build_parser
    from mcrl.sweep import backend

    sweep = next(a for a in build_parser()._subparsers._group_actions[0].choices["sweep"]._actions
                 if a.dest == "backend")
    assert tuple(sweep.choices) == backend.names() == ("local", "ray", "vmap")


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two cores to pass one over")
def test_a_second_sweeps_worker_passes_over_a_core_another_worker_holds(tmp_path):
    """Two sweeps side by side both start their first worker in slot 0: the second one's goes to the next free
    core, not onto the first one's; with every core held it keeps its slot's core; a held core is free again when
    its worker dies."""
    mask = sorted(os.sched_getaffinity(0))
    env = {**os.environ, "MCRL_CORE_CLAIMS": str(tmp_path / "claims")}
    code = "import os, sys; from mcrl.sweep.worker import pin_cores; print(pin_cores(1, 0)); sys.stdout.flush(); "
    holder = [subprocess.Popen([sys.executable, "-c", code + "sys.stdin.read()"], stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, text=True, env=env) for _ in mask]
    try:
        held = [json.loads(h.stdout.readline()) for h in holder]
        assert sorted(c for cores in held for c in cores) == mask  # each takes its own core, though all are slot 0

        def pinned() -> list[int]:
            return json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                                             check=True).stdout)

        assert pinned() == mask[:1]  # all held: the slot's own core
        holder[-1].kill()
        holder[-1].wait()
        assert pinned() == held[-1]  # its claim died with it
    finally:
        for h in holder:
            h.kill()
            h.wait()


def test_threads_per_run_pins_each_worker_to_its_slots_cores(tmp_path, monkeypatch):
    """`--threads-per-run N` binds each worker to N cores of its slot before jax loads (XLA sizes its pool by the
    cores a process may use); without it a worker keeps every core."""
    from mcrl.sweep.backend import Job, Settings
    from mcrl.sweep.local import LocalBackend
    from mcrl.sweep.plan import plan_from_args

    mask = sorted(os.sched_getaffinity(0))
    code = ("import os, sys; from mcrl.sweep.worker import pin_cores; pin_cores(int(sys.argv[1]), int(sys.argv[2])); "
            "print(sorted(os.sched_getaffinity(0)), 'jax' in sys.modules)")
    for threads, slot, expected in ((1, 0, mask[:1]), (1, 1, [mask[1 % len(mask)]]), (1, len(mask), mask[:1]),
                                    (len(mask), 3, mask)):
        out = subprocess.run([sys.executable, "-c", code, str(threads), str(slot)], capture_output=True, text=True,
                             check=True, env={**os.environ, "MCRL_CORE_CLAIMS": str(tmp_path / "claims")}
                             ).stdout.split(maxsplit=len(expected))
        assert out[-1].strip() == "False" and json.loads(" ".join(out[:-1])) == expected

    specs = []

    class Spawned:  # records what a worker would be started with
        def __init__(self, target, args, **kw):
            specs.append(args[0])
            self.pid = 100 + len(specs)

        def start(self):
            pass

    runs = plan_from_args("fetchreach-sacmc", "0,0.2", 1, {"total_steps": 100}).runs
    for pin in (True, False):
        backend = LocalBackend(Settings(tmp_path, "id", 2, 1, {}, pin=pin))
        monkeypatch.setattr(backend._ctx, "Process", Spawned)
        assert all(re.fullmatch(r"pid \d+", backend.launch(Job([r]))) for r in runs)
        assert [(s["pin"], s["threads"], s["slot"]) for s in specs[-2:]] == [(pin, 1, 0), (pin, 1, 1)]
        backend._running.clear()
