"""HER relabelling: rewards from the environment's compute_reward, goals from the same episode's future,
and relabelled transitions carry the MC reward."""
import jax
import jax.numpy as jnp
import numpy as np

from mcrl.algo import normaliser
from mcrl.config import resolve_config
from mcrl.envs import episode_seed, flatten_obs, inspect, make_env, to_env_action
from mcrl.algo.mc import transition_kl
from mcrl.replay import ReplayBuffer
from mcrl.algo.sac import Agent, Batch


def _filled_buffer(cfg, episodes=6, strategy="future"):
    env = make_env(cfg)
    spec = inspect(env, cfg)
    buf = ReplayBuffer(10_000, spec.obs_dim, spec.act_dim, her=True, observation_dim=spec.observation_dim,
                       goal_dim=spec.goal_dim, strategy=strategy, k=4, compute_reward=env.unwrapped.compute_reward)
    rng = np.random.default_rng(0)
    for ep in range(episodes):
        obs, _ = env.reset(seed=episode_seed(0, 0, ep))
        done = False
        while not done:
            a = rng.uniform(-1, 1, spec.act_dim).astype(np.float32)
            nxt, r, term, trunc, _ = env.step(to_env_action(a, env, 1.0))
            buf.add(flatten_obs(obs), a, r, flatten_obs(nxt), term, term or trunc)
            obs, done = nxt, term or trunc
    return env, spec, buf


def test_relabelled_rewards_equal_compute_reward_and_goals_come_from_the_future():
    cfg = resolve_config("fetchreach-sac")
    env, spec, buf = _filled_buffer(cfg)
    od, gd = spec.observation_dim, spec.goal_dim
    b = buf.sample(256, np.random.default_rng(1))
    rel = buf.relabelled(256)
    assert rel.sum() == round(256 * 4 / 5)
    ag_next = b.next_obs[:, od:od + gd]
    goal = b.obs[:, od + gd:]
    np.testing.assert_array_equal(goal, b.next_obs[:, od + gd:])
    expected = np.array([env.unwrapped.compute_reward(ag_next[i], goal[i], {}) for i in range(256)])
    np.testing.assert_array_equal(b.reward, expected.astype(np.float32))
    # some relabelled goals are reached (reward 0), unlike random real transitions of FetchReach
    assert (b.reward[rel] == 0).mean() > 0.15
    # each relabelled goal is the next achieved goal of this or a later step of the same episode
    T = spec.max_episode_steps
    for i in np.flatnonzero(rel)[:60]:
        slot = np.flatnonzero((buf.action[: len(buf)] == b.action[i]).all(1))[0]  # random actions are unique
        ep_start = slot - slot % T
        future_ag = buf.next_obs[slot: ep_start + T, od:od + gd]
        assert (np.abs(future_ag - goal[i]).max(1) == 0).any()


def test_final_strategy_uses_the_last_achieved_goal():
    cfg = resolve_config("fetchreach-sac", {"her_strategy": "final"})
    env, spec, buf = _filled_buffer(cfg, episodes=3, strategy="final")
    od, gd = spec.observation_dim, spec.goal_dim
    finals = buf.next_obs[np.arange(3) * 50 + 49, od:od + gd]
    b = buf.sample(128, np.random.default_rng(2))
    goals = b.obs[buf.relabelled(128), od + gd:]
    assert all((np.abs(finals - g).max(1) == 0).any() for g in goals)


def test_relabelled_transitions_carry_the_mc_reward():
    # with mc_state=full the MC models see the (relabelled) goal, so relabelling changes their input
    cfg = resolve_config("fetchreach-sacmc", {"mc_state": "full", "hidden_sizes": [32], "mc_hidden_sizes": [32],
                                              "mc_history": 4})
    env, spec, buf = _filled_buffer(cfg)
    agent = Agent(spec.obs_dim, spec.act_dim, spec.intrinsic_dim, cfg)
    state = agent.init(0)
    b = buf.sample(256, np.random.default_rng(3))
    batch = Batch(*(jnp.asarray(x) for x in b))
    r_mc, kl, norm, bounds, *_ = jax.jit(agent.intrinsic_reward)(state, batch)
    out = agent.intrinsic_net.models.forward(state.intrinsic.params, batch.obs, batch.action)  # mc_dim == obs_dim here
    direct_kl = np.asarray(transition_kl(out))
    np.testing.assert_allclose(np.asarray(kl), direct_kl, rtol=1e-5)
    lo, hi = normaliser.bounds(normaliser.push(state.norm, jnp.asarray(direct_kl)), 0.0, 94.0)
    expected = np.asarray(normaliser.scale(jnp.asarray(direct_kl), lo, hi, -1.0, 0.0))
    rel = buf.relabelled(256)
    np.testing.assert_allclose(np.asarray(r_mc)[rel], expected[rel], rtol=1e-5, atol=1e-6)
    assert np.ptp(np.asarray(r_mc)[rel]) > 0  # a real per-transition signal, not a constant
    # the goal matters: un-relabelled copies of the same transitions give different KL
    orig = batch._replace(obs=batch.obs.at[:, -3:].set(batch.obs[0, -3:] + 0.5))
    kl_orig = np.asarray(jax.jit(agent.intrinsic_reward)(state, orig)[1])
    assert not np.allclose(kl_orig[rel], direct_kl[rel])


def test_end_episode_closes_a_partial_episode_so_the_next_one_starts_fresh():
    buf = ReplayBuffer(100, 4, 1, her=True, observation_dim=2, goal_dim=1, compute_reward=lambda a, g, i: -(a != g))
    for t in range(3):
        buf.add(np.zeros(4), np.zeros(1), 0.0, np.zeros(4), False, False)
    assert not buf.can_sample()  # a running episode is not sampled
    buf.end_episode()
    assert buf.can_sample() and list(buf.ep_last[:3]) == [2, 2, 2]
    buf.add(np.zeros(4), np.zeros(1), 0.0, np.zeros(4), False, True)
    assert buf.ep_first[3] == 3 and buf.ep_last[3] == 3


def test_floor_rounding_relabels_as_many_rows_as_stable_baselines3():
    # SB3's HerReplayBuffer relabels int(her_ratio * B) rows: 204 of 256 at k=4, where round() gives 205
    from mcrl.config import Config
    from mcrl.run.policy import build

    counts = {}
    for rounding in ("nearest", "floor"):
        cfg = resolve_config("fetchreach-sac", {"her_rounding": rounding, "buffer_size": 1000})
        env, _, _, buf = build(cfg)
        env.close()
        counts[rounding] = [int(buf.relabelled(b).sum()) for b in (256, 64, 5)]
    assert counts == {"nearest": [205, 51, 4], "floor": [204, 51, 4]}
    # a run written before the key existed resumes with the count it was trained with
    d = Config().to_dict()
    del d["her_rounding"]
    assert Config.from_run_json(d).her_rounding == "nearest"
