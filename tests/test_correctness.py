"""Fixes from the outside review (issue 8): each test here failed before its fix."""
import json
import shutil

import jax
import numpy as np
import pytest

from mcrl.run import checkpoint
from mcrl.config import Config, resolve_config
from mcrl.envs import goal_terminated_fn, inspect, make_env
from mcrl.run.rundir import read_rows as read_csv
from mcrl.replay import ReplayBuffer
from mcrl.algo.sac import Batch
from mcrl.run.policy import build as _build, load_policy
from mcrl.run.trainer import train


@pytest.mark.slow
def test_box_observation_env_trains_through_evaluation(tmp_path, small):
    # Pendulum has no success flag: evaluation rows carry a return and an empty success rate.
    cfg = resolve_config(None, {**small, "env_id": "Pendulum-v1", "her": False, "mc_alpha": 0.2,
                                "mc_reward_low": -1.0, "mc_reward_high": 0.0, "total_steps": 600,
                                "eval_every": 200, "log_every": 200, "eval_episodes": 1,
                                "final_eval_episodes": 2})
    run = train(cfg, tmp_path / "pendulum", progress=False)
    ev = read_csv(run / "eval.csv")
    assert [r["step"] for r in ev] == [200, 400, 600]
    assert all(r["success_rate"] is None and r["mean_return"] < 0 for r in ev)
    assert [r["episodes"] for r in ev] == [1, 1, 2]
    final = json.loads((run / "final_eval.json").read_text())
    assert final["success_rate"] is None and final["episodes"] == 2 and final["step"] == 600
    rows = read_csv(run / "metrics.csv")
    assert rows[-1]["eval_mean_return"] == pytest.approx(final["mean_return"])
    assert rows[-1]["mean_raw_kl"] is not None


def test_final_evaluation_uses_final_eval_episodes(tmp_path, small):
    cfg = resolve_config("fetchreach-sac", {**small, "total_steps": 150, "eval_every": 100, "log_every": 50,
                                            "eval_episodes": 1, "final_eval_episodes": 3})
    run = train(cfg, tmp_path / "r", progress=False)
    ev = read_csv(run / "eval.csv")
    assert [(r["step"], r["episodes"]) for r in ev] == [(100, 1), (150, 3)]
    final = json.loads((run / "final_eval.json").read_text())
    assert final["episodes"] == 3 and final["success_rate"] in (0.0, 1 / 3, 2 / 3, 1.0)


def test_thesis_presets_evaluate_100_episodes_at_the_end():
    for name in ("fetchpush-sac", "fetchpush-sacmc-0.2", "antmaze-sac", "antmaze-sacmc"):
        assert resolve_config(name).n_final_eval_episodes == 100
    assert resolve_config(None, {"eval_episodes": 7}).n_final_eval_episodes == 7


def test_default_normaliser_history_holds_every_value_of_the_run(small):
    cfg = resolve_config("fetchreach-sacmc", small)
    assert cfg.intrinsic_history is None
    env, spec, agent, buffer = _build(cfg)
    env.close()
    state = agent.init(0)
    assert state.norm.ring.shape == (0,)  # no window
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(cfg.batch_size, spec.obs_dim)).astype(np.float32)
    batch = Batch(obs, rng.uniform(-1, 1, (cfg.batch_size, spec.act_dim)).astype(np.float32),
                  -np.ones(cfg.batch_size, np.float32), obs + 0.1, np.zeros(cfg.batch_size, np.float32))
    update = jax.jit(agent.update)
    for _ in range(30):
        state, _ = update(state, batch)
    assert int(state.norm.count) == 30 * cfg.batch_size


@pytest.mark.parametrize("reduction,per_step", [("transition", 64), ("batch", 1)])
def test_a_window_is_counted_in_gradient_steps(small, reduction, per_step):
    cfg = resolve_config("fetchreach-sacmc", {**small, "mc_history": 5, "mc_reduction": reduction})
    assert cfg.intrinsic_history_values == 5 * per_step
    env, spec, agent, _ = _build(cfg)
    env.close()
    assert agent.init(0).norm.ring.shape == (5 * per_step,)


def test_antmaze_presets_use_the_thesis_ant():
    for name in ("antmaze-sac", "antmaze-sacmc", "antmaze-sacmc-p94"):
        cfg = resolve_config(name)
        assert cfg.action_scale == 0.4
        env = make_env(cfg)
        spec = inspect(env, cfg)
        env.close()
        assert spec.observation_dim == 27 and spec.intrinsic_dim == 27  # no contact forces
        assert spec.act_dim == 8


def test_her_recomputes_terminated_for_environments_that_end_on_success():
    env = make_env(resolve_config(None, {"env_id": "PointMaze_UMaze-v3", "env_kwargs": {"continuing_task": False}}))
    term_fn = goal_terminated_fn(env)
    space = env.observation_space
    od, gd = space["observation"].shape[0], space["desired_goal"].shape[0]
    buf = ReplayBuffer(1000, od + 2 * gd, 2, her=True, observation_dim=od, goal_dim=gd, strategy="future", k=4,
                       compute_reward=env.unwrapped.compute_reward, compute_terminated=term_fn)
    rng = np.random.default_rng(0)
    for ep in range(4):
        obs, _ = env.reset(seed=ep)
        for t in range(30):  # the ball rarely reaches the goal: no stored transition is terminal
            a = rng.uniform(-1, 1, 2).astype(np.float32)
            nxt, r, term, trunc, _ = env.step(a)
            f = lambda o: np.concatenate([o["observation"], o["achieved_goal"], o["desired_goal"]])
            buf.add(f(obs), a, r, f(nxt), term, term or trunc or t == 29)
            obs = nxt
    assert buf.terminated[:len(buf)].sum() == 0
    b = buf.sample(512, rng)
    rel = buf.relabelled(512)
    achieved, goal = b.next_obs[:, od:od + gd], b.next_obs[:, od + gd:]
    reached = np.linalg.norm(achieved - goal, axis=1) <= 0.45
    assert reached[rel].any()  # `future` picks the transition's own achieved goal often enough
    np.testing.assert_array_equal(b.terminated[rel], reached[rel].astype(np.float32))
    np.testing.assert_array_equal(b.terminated[~rel], 0.0)
    env.close()


def test_fetch_relabelling_never_terminates():
    cfg = resolve_config("fetchreach-sac")
    env, spec, agent, buf = _build(cfg)
    obs, _ = env.reset(seed=0)
    from mcrl.envs import flatten_obs
    for t in range(100):
        a = np.zeros(spec.act_dim, np.float32)
        nxt, r, term, trunc, _ = env.step(a)
        buf.add(flatten_obs(obs), a, r, flatten_obs(nxt), term, term or trunc)
        obs = nxt if not (term or trunc) else env.reset(seed=t)[0]
    env.close()
    assert buf.sample(256, np.random.default_rng(0)).terminated.sum() == 0


def test_find_falls_back_when_latest_dangles(tmp_path, small):
    cfg = resolve_config("fetchreach-sacmc", {**small, "total_steps": 300, "checkpoint_every": 100,
                                              "keep_checkpoints": 3, "eval_every": 0, "log_every": 100})
    run = train(cfg, tmp_path / "r", progress=False)
    root = run / "checkpoints"
    newest = checkpoint.find(run)
    # a kill between moving the re-saved step aside and renaming the new one in: `latest` names nothing
    shutil.rmtree(newest)
    older = sorted(p for p in root.glob("step_*"))[-1]
    assert checkpoint.find(run) == older
    (root / "latest").unlink()
    assert checkpoint.find(run) == older
    (older / "meta.json").unlink()  # incomplete: skipped too
    assert checkpoint.find(run) != older and checkpoint.is_complete(checkpoint.find(run))
    load_policy(run)  # and the fallback loads


def test_resaving_a_step_keeps_a_usable_checkpoint(tmp_path):
    state = {"w": np.arange(3.0)}
    checkpoint.save(tmp_path, 5, state, {"a": 1}, None, keep=2)
    checkpoint.save(tmp_path, 5, {"w": np.arange(3.0) + 1}, {"a": 2}, None, keep=2)
    ck = checkpoint.find(tmp_path)
    assert checkpoint.load_meta(ck)["a"] == 2
    assert not list((tmp_path / "checkpoints").glob(".old-*")) and not list((tmp_path / "checkpoints").glob(".tmp-*"))


def test_run_dirs_written_by_mcrl_0_1_are_refused_with_the_migration_named(tmp_path):
    from mcrl.errors import MCRLError
    from mcrl.run.rundir import read_config

    from mcrl.renames import old_name

    old = {**{old_name(k): v for k, v in Config().to_dict().items()}, "mc_history": 400_000, "batch_size": 256}
    del old["init"], old["final_eval_episodes"]
    (tmp_path / "config.json").write_text(json.dumps(old))
    with pytest.raises(MCRLError, match="scripts/migrate_checkpoint.py"):
        read_config(tmp_path)
