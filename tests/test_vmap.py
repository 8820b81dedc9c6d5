"""The vmap backend: a group of runs trained as one vmapped computation (mcrl.run.group, `--backend vmap`).

Small networks and few steps: the group machinery does not depend on the sizes."""
import os
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

from mcrl.config import resolve_config
from mcrl.run.group import group_key, plan_groups, train_group
from mcrl.run.policy import load_policy
from mcrl.run.rundir import read_json, read_rows
from mcrl.run.trainer import train

SMALL = dict(hidden_sizes=[64, 64], mc_hidden_sizes=[64, 64], batch_size=64, buffer_size=5000, mc_history=2000,
             log_every=10, checkpoint_every=100_000)


def _leaves(run_dir):
    _, _, state = load_policy(run_dir)
    return jax.tree_util.tree_flatten_with_path(state)[0]


def _assert_same_state(a_dir, b_dir, rtol):
    a, b = _leaves(a_dir), _leaves(b_dir)
    assert [jax.tree_util.keystr(p) for p, _ in a] == [jax.tree_util.keystr(p) for p, _ in b]
    for (path, x), (_, y) in zip(a, b):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if ".norm.c" in jax.tree_util.keystr(path):  # histogram counts: a value near a bin edge may change bin
            assert x.sum() == y.sum()
            continue
        scale = max(float(np.abs(y).max(initial=0.0)), 1e-3)
        assert np.abs(x - y).max(initial=0.0) <= rtol * scale, jax.tree_util.keystr(path)


def test_plan_groups_by_shape():
    a = [resolve_config("fetchpush-sac", {"seed": s}) for s in range(3)]
    b = [resolve_config("fetchpush-sacmc-0.2", {"seed": s}) for s in range(3)]
    c = [resolve_config("fetchpush-sacmc-0.2", {"seed": 0, "hidden_sizes": [128, 128]})]
    d = [resolve_config("fetchpush-sacmc-0.2", {"seed": 0, "matmul_precision": "bfloat16"})]
    assert group_key(a[0]) == group_key(b[1])  # alpha and seed are per-run data
    assert plan_groups(a + b + c + d) == [[0, 1, 2, 3, 4, 5], [6], [7]]
    assert plan_groups(a + b, max_size=4) == [[0, 1, 2, 3], [4, 5]]


@pytest.mark.slow
def test_group_matches_runs_trained_alone(tmp_path):
    """A SAC run (carrying ballast MC models in the group) and two SAC-MC runs with different alphas: after 30
    gradient steps each run's whole state and its log rows match the same run trained alone, to float tolerance,
    and the SAC run's files are a SAC run's (no MC models, no MC metrics)."""
    over = dict(SMALL, total_steps=130, learning_starts=100, eval_every=65, eval_episodes=2)
    cfgs = [resolve_config("fetchreach-sac", {**over, "seed": 0}),
            resolve_config("fetchreach-sacmc", {**over, "seed": 1}),
            resolve_config("fetchreach-sacmc", {**over, "seed": 2, "mc_alpha": 0.6})]
    group_dirs = train_group(cfgs, [tmp_path / f"g{i}" for i in range(3)])
    for i, cfg in enumerate(cfgs):
        alone = train(cfg, tmp_path / f"alone{i}", progress=False)
        assert read_json(group_dirs[i] / "config.json") == read_json(alone / "config.json")
        _assert_same_state(group_dirs[i], alone, rtol=1e-5)
        g_rows, a_rows = read_rows(group_dirs[i] / "metrics.csv"), read_rows(alone / "metrics.csv")
        assert [r["step"] for r in g_rows] == [r["step"] for r in a_rows] and len(g_rows) == 13
        for g, a in zip(g_rows, a_rows):
            for k in ("q_mean", "critic_loss", "actor_loss", "ent_coef", "mean_total_reward", "mean_intrinsic_reward",
                      "train_return"):
                assert (g[k] is None) == (a[k] is None), k
                if g[k] is not None:
                    assert g[k] == pytest.approx(a[k], rel=1e-4, abs=1e-5), (k, g["step"])
        assert read_rows(group_dirs[i] / "eval.csv") == read_rows(alone / "eval.csv")
    _, _, sac_state = load_policy(group_dirs[0])
    assert sac_state.intrinsic is None and sac_state.norm is None
    assert read_rows(group_dirs[0] / "metrics.csv")[-1]["mean_raw_kl"] is None
    assert read_rows(group_dirs[1] / "metrics.csv")[-1]["mean_raw_kl"] > 0


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["rnd", "icm", "disagreement"])
def test_group_with_another_intrinsic_reward_matches_runs_alone(tmp_path, kind):
    """A SAC run (carrying the reward's models as ballast) and a run with RND, ICM or Disagreement at weight 0.4:
    each run's whole state (the models' trained and untrained parts included) and its log rows match the run
    trained alone; the SAC run's files are a SAC run's."""
    over = dict(SMALL, total_steps=130, learning_starts=100, eval_every=65, eval_episodes=2, intrinsic=kind)
    cfgs = [resolve_config("fetchreach-sac", {**over, "seed": 0}),
            resolve_config("fetchreach-sac", {**over, "seed": 1, "mc_alpha": 0.4})]
    group_dirs = train_group(cfgs, [tmp_path / f"g{i}" for i in range(2)])
    for i, cfg in enumerate(cfgs):
        alone = train(cfg, tmp_path / f"alone{i}", progress=False)
        # 1e-4, not 1e-5: Adam turns the round-off of a vmapped matmul in a near-zero gradient into a step of
        # its own size (measured: ICM's inverse-model output kernel, 3.7e-5 of its largest entry after 30 steps)
        _assert_same_state(group_dirs[i], alone, rtol=1e-4)
        g_rows, a_rows = read_rows(group_dirs[i] / "metrics.csv"), read_rows(alone / "metrics.csv")
        assert [r["step"] for r in g_rows] == [r["step"] for r in a_rows] and len(g_rows) == 13
        for g, a in zip(g_rows, a_rows):
            for k in ("q_mean", "critic_loss", "mean_total_reward", "mean_intrinsic_reward", "intrinsic_loss",
                      "mean_raw_intrinsic"):
                assert (g[k] is None) == (a[k] is None), k
                if g[k] is not None:
                    assert g[k] == pytest.approx(a[k], rel=1e-4, abs=1e-5), (k, g["step"])
        assert read_rows(group_dirs[i] / "eval.csv") == read_rows(alone / "eval.csv")
    _, _, sac_state = load_policy(group_dirs[0])
    _, _, own_state = load_policy(group_dirs[1])
    assert sac_state.intrinsic is None and sac_state.norm is None and own_state.intrinsic is not None
    assert read_rows(group_dirs[0] / "metrics.csv")[-1]["mean_raw_intrinsic"] is None
    assert read_rows(group_dirs[1] / "metrics.csv")[-1]["mean_raw_intrinsic"] > 0


def _sweep_cmd(exp):
    return [sys.executable, "-m", "mcrl.cli", "sweep", "--preset", "fetchreach-sacmc", "--alphas", "0,0.2",
            "--seeds", "1", "--steps", "400", "--backend", "vmap", "--workers", "1", "--exp", str(exp), "--no-progress",
            "--set", "hidden_sizes=[64,64]", "--set", "mc_hidden_sizes=[64,64]", "--set", "batch_size=64",
            "--set", "buffer_size=5000", "--set", "mc_history=2000", "--set", "checkpoint_every=100",
            "--set", "eval_every=200", "--set", "log_every=50"]


@pytest.mark.slow
def test_vmap_sweep_resumes_after_kill9(tmp_path):
    """kill -9 the group's sweep after its first checkpoints; the same command resumes both runs from them and
    ends with the numbers of an uninterrupted group."""
    exp = tmp_path / "exp"
    env = {**os.environ, "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}
    proc = subprocess.Popen(_sweep_cmd(exp), env=env, start_new_session=True, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    latest = [exp / "runs" / n / "checkpoints" / "latest" for n in ("a0-s0", "a0.2-s0")]
    deadline = time.monotonic() + 300
    while not all(p.exists() for p in latest):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[0] if proc.poll() else "slow"
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)  # the driver and its group worker
    proc.wait()
    assert not (exp / "runs" / "a0-s0" / "done").exists()
    out = subprocess.run(_sweep_cmd(exp), env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "group of 2 as one computation" in out.stdout, out.stdout
    assert "resume a0-s0 from step" in out.stdout and "resume a0.2-s0 from step" in out.stdout
    _assert_matches_uninterrupted_group(exp, tmp_path)


@pytest.mark.slow
def test_vmap_sweep_ctrl_c_saves_the_group_and_resumes_exactly(tmp_path):
    """Ctrl-C in a terminal (SIGINT to the driver and its group worker alike): the group saves both runs at their
    episode's end and the sweep exits 130; the same command resumes them to an uninterrupted group's numbers."""
    exp = tmp_path / "exp"
    env = {**os.environ, "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}
    proc = subprocess.Popen(_sweep_cmd(exp), env=env, start_new_session=True, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    metrics = [exp / "runs" / n / "metrics.csv" for n in ("a0-s0", "a0.2-s0")]
    deadline = time.monotonic() + 300
    while not all(p.exists() and len(read_rows(p)) >= 2 for p in metrics):  # both past step 100
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[0] if proc.poll() else "slow"
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGINT)
    text = proc.communicate(timeout=300)[0]
    assert proc.returncode == 130, text
    for name in ("a0-s0", "a0.2-s0"):
        run = exp / "runs" / name
        assert not (run / "done").exists(), text
        step = int((run / "checkpoints" / "latest").read_text().strip().split("_")[1])
        assert step >= 100 and step % 50 == 0 and f"stopped {name} at step {step:,}" in text, text
    out = subprocess.run(_sweep_cmd(exp), env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    _assert_matches_uninterrupted_group(exp, tmp_path)


def _assert_matches_uninterrupted_group(exp, tmp_path):
    from mcrl.sweep.plan import load_sweep_json

    ref_cfgs = [resolve_config("fetchreach-sacmc", e["overrides"]) for e in load_sweep_json(exp)["runs"]]
    ref = train_group(ref_cfgs, [tmp_path / "ref" / e["name"] for e in load_sweep_json(exp)["runs"]])
    for d in ref:
        got = exp / "runs" / d.name
        assert read_rows(got / "eval.csv") == read_rows(d / "eval.csv")
        for g, r in zip(read_rows(got / "metrics.csv"), read_rows(d / "metrics.csv"), strict=True):
            assert g["step"] == r["step"] and (g["q_mean"] is None) == (r["q_mean"] is None)
            if r["q_mean"] is not None:
                assert g["q_mean"] == pytest.approx(r["q_mean"], rel=1e-6, abs=1e-7)
        _assert_same_state(got, d, rtol=1e-6)


def test_env_pool_workers_step_like_in_process():
    from mcrl.run.envpool import EnvPool

    cfgs = [resolve_config("fetchreach-sac", {"seed": s}) for s in range(3)]
    local, remote = EnvPool(cfgs, 0), EnvPool(cfgs, 2)
    try:
        assert remote.workers == 2
        for i in range(3):
            np.testing.assert_array_equal(local.reset(i, 100 + i), remote.reset(i, 100 + i))
        rng = np.random.default_rng(0)
        for _ in range(5):
            a = rng.uniform(-1, 1, (3, 4)).astype(np.float32)
            x, y = local.step(a), remote.step(a)
            for u, v in zip(x.next_obs, y.next_obs):
                np.testing.assert_array_equal(u, v)
            np.testing.assert_array_equal(x.reward, y.reward)
            assert x.success == y.success
    finally:
        local.close()
        remote.close()


@pytest.mark.parametrize("args, msg", [
    (["--backend", "vmap", "--group-size", "0"], "--group-size 0"),
    (["--env-workers", "2"], "--backend vmap"),
])
def test_vmap_bad_options(tmp_path, args, msg):
    out = subprocess.run([sys.executable, "-m", "mcrl.cli", "sweep", "--preset", "fetchreach-sac", "--seeds", "1",
                          "--exp", str(tmp_path / "exp"), *args], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and msg in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert not (tmp_path / "exp").exists()


def test_vmap_backend_shares_runs_among_workers(tmp_path):
    """On a CPU the default is one group per worker (XLA runs a vmapped step on about one core); runs that
    resume from different steps never share a group."""
    from mcrl.sweep.backend import Settings
    from mcrl.sweep.local import VmapBackend
    from mcrl.sweep.plan import plan_from_args

    plan = plan_from_args("fetchreach-sacmc", alphas="0,0.2", seeds=3)

    def jobs(workers, group_size=None):
        backend = VmapBackend(Settings(tmp_path, "id", workers, 1, {}, options={"group_size": group_size}))
        return [[r.name for r in j] for j in backend.jobs(plan.runs)]

    seen = [jobs(2), jobs(1, group_size=4)]
    ck = tmp_path / "runs" / "a0.2-s1" / "checkpoints"
    (ck / "step_100").mkdir(parents=True)
    (ck / "latest").write_text("step_100\n")
    seen.append(jobs(1))
    assert seen[0] == [["a0-s0", "a0.2-s0", "a0-s1"], ["a0.2-s1", "a0-s2", "a0.2-s2"]]
    assert seen[1] == [["a0-s0", "a0.2-s0", "a0-s1", "a0.2-s1"], ["a0-s2", "a0.2-s2"]]
    assert seen[2] == [["a0-s0", "a0.2-s0", "a0-s1", "a0-s2", "a0.2-s2"], ["a0.2-s1"]]
