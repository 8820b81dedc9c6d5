"""The tanh log-probability correction (`squash_correction`) and the saturation diagnostics (issue 49)."""
import csv
import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mcrl.algo.sac import Agent, saturation, squash_log_det, tanh_gaussian_sample
from mcrl.config import Config, resolve_config
from mcrl.errors import MCRLError
from mcrl.replay import Batch


def test_exact_is_log_one_minus_tanh_squared_where_float64_can_tell():
    u = np.linspace(-8, 8, 321)
    want = np.log1p(-np.tanh(u) ** 2)
    got = np.asarray(squash_log_det(jnp.asarray(u, jnp.float32)[:, None], "exact"))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    # and it keeps falling where tanh rounds to 1 in float32: 2 (log 2 - |u|) asymptotically
    assert float(squash_log_det(jnp.float32([[30.0]]), "exact")[0]) == pytest.approx(2 * (math.log(2) - 30), rel=1e-5)


def test_epsilon_is_stable_baselines3s_formula_in_float32():
    # SB3's SquashedDiagGaussianDistribution.log_prob: log_prob -= sum(log(1 - actions**2 + 1e-6)), float32 actions
    u = np.array([[0.0, 0.5, -2.0, 4.0], [6.0, -9.0, 12.0, 30.0]], np.float32)
    a = np.asarray(jnp.tanh(u))  # XLA's float32 tanh (numpy's differs by an ulp, which 1 - a^2 magnifies)
    want = np.log(np.float32(1) - a * a + np.float32(1e-6)).sum(-1)
    np.testing.assert_allclose(np.asarray(squash_log_det(jnp.asarray(u), "epsilon")), want, rtol=1e-6)
    # the cap: a saturated entry costs at most log(1e-6) = -13.8 nats, where exact keeps growing
    sat = jnp.float32([[12.0]])
    assert float(squash_log_det(sat, "epsilon")[0]) == pytest.approx(math.log(1e-6), abs=0.05)
    assert float(squash_log_det(sat, "exact")[0]) < -22


def test_the_two_agree_on_unsaturated_samples_and_differ_on_saturated_ones():
    key = jax.random.PRNGKey(0)
    mean, log_std = jnp.zeros((512, 4)), jnp.zeros((512, 4))
    a1, lp_exact = tanh_gaussian_sample(mean, log_std, key, "exact")
    a2, lp_eps = tanh_gaussian_sample(mean, log_std, key, "epsilon")
    np.testing.assert_array_equal(np.asarray(a1), np.asarray(a2))  # the same sample, only log pi differs
    np.testing.assert_allclose(np.asarray(lp_exact), np.asarray(lp_eps), atol=2e-3)
    wide = jnp.full((512, 4), 2.0)  # std e^2: most entries far into the flat part of tanh
    _, lp_exact = tanh_gaussian_sample(mean, wide, key, "exact")
    _, lp_eps = tanh_gaussian_sample(mean, wide, key, "epsilon")
    assert float((lp_exact - lp_eps).mean()) > 1.0


def test_saturation_counts_entries_below_one_in_a_million():
    # 1 - tanh(u)^2 < 1e-6 from |u| > 7.6 on
    u = jnp.float32([[0.0, 7.0, 7.9, -8.5], [1.0, -2.0, 3.0, 20.0]])
    s = saturation(u)
    assert float(s["saturated_share"]) == pytest.approx(3 / 8)
    gap = np.asarray(squash_log_det(u, "epsilon") - squash_log_det(u, "exact")).mean()
    assert float(s["logp_gap"]) == pytest.approx(gap) and gap > 0


def _agent(correction):
    cfg = resolve_config("fetchpush-sac", {"squash_correction": correction, "hidden_sizes": [32, 32]})
    return Agent(obs_dim=31, act_dim=4, intrinsic_dim=25, cfg=cfg)


def _batch(seed=0, n=64):
    r = np.random.default_rng(seed)
    return Batch(r.normal(size=(n, 31)).astype(np.float32), r.uniform(-1, 1, (n, 4)).astype(np.float32),
                 -np.ones(n, np.float32), r.normal(size=(n, 31)).astype(np.float32), np.zeros(n, np.float32))


def _saturated(state):
    """`state` with an actor whose log-std head says e^2 everywhere: wide, so many samples saturate."""
    p = jax.tree.map(jnp.copy, state.pi.params)
    p["log_std"]["kernel"] = jnp.zeros_like(p["log_std"]["kernel"])
    p["log_std"]["bias"] = jnp.full_like(p["log_std"]["bias"], 2.0)
    return state._replace(pi=state.pi._replace(params=p))


def test_the_update_uses_the_configured_correction_and_reports_saturation():
    out = {}
    for c in ("exact", "epsilon"):
        agent = _agent(c)
        state = _saturated(agent.init(0))
        _, m = jax.jit(agent.update)(state, _batch())
        out[c] = {k: float(v) for k, v in m.items()}
    # the same sample in both (same keys): the diagnostics agree, the losses that use log pi do not
    assert out["exact"]["saturated_share"] == out["epsilon"]["saturated_share"] > 0.01
    assert out["exact"]["logp_gap"] == pytest.approx(out["epsilon"]["logp_gap"]) and out["exact"]["logp_gap"] > 0.5
    assert out["exact"]["critic_loss"] != out["epsilon"]["critic_loss"]  # through log pi of the next action
    assert out["exact"]["actor_loss"] != out["epsilon"]["actor_loss"]


def test_bad_correction_is_refused_with_the_choices():
    with pytest.raises(MCRLError, match="exact.*epsilon"):
        resolve_config(None, {"squash_correction": "clip"})


def test_a_run_written_before_the_key_resumes_with_exact_whatever_the_default():
    d = Config().to_dict()
    del d["squash_correction"]
    assert Config.from_run_json(d).squash_correction == "exact"
    d["squash_correction"] = "epsilon"  # written after: its own value
    assert Config.from_run_json(d).squash_correction == "epsilon"


def test_metrics_rows_carry_saturation_and_the_share_of_episodes_that_moved_the_object(tmp_path, small):
    from mcrl.run import checkpoint
    from mcrl.run.trainer import train

    # 600 uniform random steps (12 episodes): the share must match the object's displacement in the buffer
    cfg = resolve_config("fetchpush-sac", {**small, "total_steps": 600, "learning_starts": 600, "log_every": 300,
                                           "eval_every": 0, "final_eval_episodes": 1, "squash_correction": "epsilon"})
    run = train(cfg, tmp_path / "run", progress=False)
    rows = list(csv.DictReader(open(run / "metrics.csv")))
    assert [r["step"] for r in rows] == ["300", "600"]
    buf = checkpoint.load_buffer_arrays(checkpoint.find(run))
    od, gd, n = 25, 3, 600
    start = buf["obs"][:n:50, od:od + gd]  # episodes of 50 steps
    end = buf["next_obs"][49:n:50, od:od + gd]
    moved = np.linalg.norm(end - start, axis=1) > 0.01
    want = [moved[:6].mean(), moved[6:].mean()]
    assert [float(r["train_goal_moved"]) for r in rows] == pytest.approx(want)
    # no gradient step yet: no saturation figures; then a short run with updates has them
    assert rows[0]["saturated_share"] == ""
    cfg = dataclasses.replace(cfg, total_steps=300, learning_starts=100)
    rows = list(csv.DictReader(open(train(cfg, tmp_path / "run2", progress=False) / "metrics.csv")))
    assert 0 <= float(rows[-1]["saturated_share"]) <= 1 and float(rows[-1]["logp_gap"]) >= 0
