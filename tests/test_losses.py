"""SAC's losses as functions (issue 66, item 3): each function of `mcrl.algo.losses` alone on numbers worked out by
hand from its formula, then `Agent.update`, which composes them, against the step before the refactor
(tests/reference_update.py) bit for bit: every parameter, optimiser state and metric over five steps for SAC, SAC-MC
and a vmapped group with `Hyper` and `Mix`, and a whole FetchReach SAC-MC run's learning columns and final state."""
import jax
import numpy as np
import pytest

from mcrl.algo import losses
from mcrl.algo.sac import Agent, Batch, Hyper, Mix
from mcrl.config import resolve_config
from mcrl.run import rundir
from mcrl.run.learner import Learner
from mcrl.run.policy import load_policy
from mcrl.run.trainer import train, train_runs
from tests.reference_update import reference_update
from tests.test_schedule import TINY, _batches, _same

F = np.float32


def _f(*x):
    return np.asarray(x, np.float32)


# ----------------------------------------------------------------------------- each loss by hand
def test_the_critic_target_is_the_clipped_double_q_soft_target():
    """Two transitions, the second terminated. The twin target critics say (2, 5) and (4, 3): min (2, 3).
    y0 = 1 + 0.5 (2 - 0.5 * (-1)) = 2.25; y1 = -1 (terminated: no bootstrap, whatever Q' and log pi say)."""
    q_next = _f([2.0, 4.0], [5.0, 3.0]).min(0)
    y = losses.critic_target(_f(1.0, -1.0), _f(0.0, 1.0), 0.5, q_next, F(0.5), _f(-1.0, 4.0))
    np.testing.assert_array_equal(y, _f(2.25, -1.0))
    # the critics regress on it: no gradient flows into Q' or log pi
    g = jax.grad(lambda q, lp: losses.critic_target(_f(1.0, -1.0), _f(0.0, 0.0), 0.5, q, F(0.5), lp).sum(),
                 argnums=(0, 1))(q_next, _f(-1.0, 4.0))
    assert not any(np.any(x) for x in g)


def test_the_critic_loss_and_its_gradient():
    """q (2 critics, 2 transitions) = [[1, 2], [3, 0]] against y = (1.5, 1): errors (-0.5, 1) and (1.5, -1), MSEs
    0.625 and 1.625, loss 0.5 * (0.625 + 1.625) = 1.125 (summed over critics); dL/dq = (q - y) / B."""
    q, y = _f([1.0, 2.0], [3.0, 0.0]), _f(1.5, 1.0)
    loss, g = jax.value_and_grad(losses.critic_loss)(q, y)
    assert loss == 1.125
    np.testing.assert_array_equal(g, _f([-0.25, 0.5], [0.75, -0.5]))
    # through a tiny critic q_i(x) = w_i x on x = (1, 2), w = (1, 0.5), y = (0, 1): q = [[1, 2], [0.5, 1]],
    # loss 0.5 (1 + 0.125) = 0.5625, dL/dw_i = mean_b (q_ib - y_b) x_b = (1 + 2) / 2 and (0.5 + 0) / 2
    x, y = _f(1.0, 2.0), _f(0.0, 1.0)
    loss, g = jax.value_and_grad(lambda w: losses.critic_loss(w[:, None] * x[None], y))(_f(1.0, 0.5))
    assert loss == 0.5625
    np.testing.assert_array_equal(g, _f(1.5, 0.25))


def test_the_actor_loss():
    """alpha 0.5, log pi = (-1, 2), min Q = (3, 1): mean(-0.5 - 3, 1 - 1) = -1.75; it falls as Q rises (-1/B per
    unit) and rises with log pi (alpha/B per nat)."""
    loss, (g_logp, g_q) = jax.value_and_grad(losses.actor_loss, argnums=(1, 2))(F(0.5), _f(-1.0, 2.0), _f(3.0, 1.0))
    assert loss == -1.75
    np.testing.assert_array_equal(g_logp, _f(0.25, 0.25))
    np.testing.assert_array_equal(g_q, _f(-0.5, -0.5))


@pytest.mark.parametrize("logp,value,grad", [((2.0, 4.0), -0.5, -2.0), ((-1.0, -3.0), 0.75, 3.0)])
def test_the_entropy_loss_raises_alpha_when_the_entropy_is_below_target(logp, value, grad):
    """stable-baselines3: ent_coef_loss = -(log_ent_coef * (log_prob + target_entropy).detach()).mean(). Target
    entropy -1, log alpha 0.25. log pi = (2, 4): entropy -3 below the target, logp + target = (1, 3), loss
    -0.25 * 2 = -0.5, gradient -mean = -2 < 0: gradient descent raises log alpha. log pi = (-1, -3): entropy 2
    above it, logp + target = (-2, -4), loss 0.75, gradient 3 > 0: log alpha falls."""
    le, lp = F(0.25), _f(*logp)
    loss, g = jax.value_and_grad(losses.entropy_loss)(le, lp, -1.0)
    assert loss == value and g == grad
    assert not np.any(jax.grad(losses.entropy_loss, argnums=1)(le, lp, -1.0))  # the policy is data here


def test_the_reward_mix_is_r_ext_at_alpha_0_r_int_at_1_and_the_mix_between():
    r_ext = _f(-1.0, -0.0, 0.0, -1.0)  # -0.0: what a Fetch reward of a success is (-(d > eps) as float32)
    r_int = _f(3e38, 7.5, -123.25, -3e38)  # any finite values
    at0 = losses.reward_mix(r_ext, r_int, *Mix.of(0.0))
    assert np.asarray(at0).tobytes() == r_ext.tobytes()  # bit for bit, -0.0 included
    assert (F(1.0) * r_ext + F(0.0) * r_int).tobytes() != r_ext.tobytes()  # the formula alone: -0 + 0 = +0
    np.testing.assert_array_equal(losses.reward_mix(r_ext, r_int, *Mix.of(1.0)), r_int)
    # 0.75 (-1, 0) + 0.25 (-0.5, 1) = (-0.875, 0.25)
    np.testing.assert_array_equal(losses.reward_mix(_f(-1.0, 0.0), _f(-0.5, 1.0), *Mix.of(0.25)), _f(-0.875, 0.25))
    # per run in a vmapped group: the run at alpha 0 keeps its r_ext, the other mixes
    group = jax.vmap(losses.reward_mix)(np.stack([r_ext[:2]] * 2), _f([-0.5, 1.0], [-0.5, 1.0]),
                                        *Mix.of_float32([0.0, 0.5]))
    assert np.asarray(group[0]).tobytes() == r_ext[:2].tobytes()
    np.testing.assert_array_equal(group[1], _f(-0.75, 0.5))


# ----------------------------------------------------------------------------- the composed step, bit for bit
CONFIGS = {"sac": {"intrinsic_alpha": 0.0},
           "sac-with-models": {"intrinsic_alpha": 0.0, "intrinsic_models": True},
           "sacmc-0.2": {"intrinsic_alpha": 0.2},
           "sacmc-0.058": {"intrinsic_alpha": 0.058}}  # float32 1 - alpha differs from float64's rounded here


def _steps(fn, state, batches, *args):
    out = []
    for batch in batches:
        state, m = fn(state, batch, *args)
        out.append(m)
    return state, out


@pytest.mark.parametrize("name", list(CONFIGS))
def test_the_step_is_the_step_before_the_refactor_bit_for_bit(name):
    """Five jitted steps of `Agent.update` and of the frozen reference from the same state and batches: the same
    state (parameters, optimiser states, targets, normaliser, key) and metrics, leaf for leaf, with the weights
    a constant of the step, `Hyper` as data, `Mix` as data; and in a vmapped group of two runs with `Hyper` (alphas
    0 and the config's: the group's SAC run keeps r_ext) and with `Mix`."""
    cfg = resolve_config("fetchreach-sac", {**TINY, **CONFIGS[name]})
    agent = Agent(10, 4, 6, cfg)
    batches = _batches(agent, 5)
    alpha = cfg.intrinsic_alpha
    for args in ((), (Hyper.of(cfg),), (None, Mix.of(alpha))):
        now = _steps(jax.jit(lambda s, b, *a: agent.update(s, b, *a)), agent.init(0), batches, *args)
        before = _steps(jax.jit(lambda s, b, *a: reference_update(agent, s, b, *a)), agent.init(0), batches, *args)
        assert _same(now, before), (name, args)
    states = jax.tree.map(lambda *x: np.stack(x), agent.init(0), agent.init(1))
    stacked = [Batch(*(np.stack(x) for x in zip(*pair))) for pair in zip(batches, _batches(agent, 5, seed=1))]
    alphas = [0.0, alpha]
    hyper = Hyper(*(np.full(2, v, np.float32) for v in Hyper.of(cfg)))._replace(intrinsic_alpha=_f(*alphas))
    for args in ((hyper,), (hyper, Mix.of_float32(alphas))):
        now = _steps(jax.jit(jax.vmap(lambda s, b, *a: agent.update(s, b, *a))), states, stacked, *args)
        before = _steps(jax.jit(jax.vmap(lambda s, b, *a: reference_update(agent, s, b, *a))), states, stacked, *args)
        assert _same(now, before), (name, "group", len(args))
    m = now[1][-1]  # the group's run at alpha 0 learns r_ext; the other its mix, where it has one
    assert m["mean_total_reward"][0] == m["mean_ext_reward"][0]
    assert (m["mean_total_reward"][1] != m["mean_ext_reward"][1]) == (cfg.use_intrinsic_models and alpha > 0)


class _ReferenceLearner(Learner):
    """A run's learner whose compiled step is the frozen reference, with the weight as data like today's."""

    def __init__(self, agent, state, diag):
        super().__init__(agent, state, diag)
        from mcrl.algo import diagnostics

        def step(s, d, b, w):
            s, metrics = reference_update(agent, s, b, mix=w)
            return s, diagnostics.add(d, metrics)

        self._step = jax.jit(step, donate_argnums=(0, 1))


@pytest.mark.slow
def test_a_sacmc_run_is_the_run_before_the_refactor_bit_for_bit(tmp_path):
    """A short fixed-seed FetchReach SAC-MC run (acting, HER, evaluation, log rows) writes the learning columns,
    evaluations and final state of the same run whose step is the frozen reference."""
    cfg = resolve_config("fetchreach-sacmc", {**TINY, "total_steps": 300, "eval_every": 150, "log_every": 50})
    now = train(cfg, tmp_path / "now", progress=False)
    (before,) = train_runs([cfg], [tmp_path / "before"], False,
                           lambda ms, ss, ds: _ReferenceLearner(ms[0].agent, ss[0], ds[0]))
    cols = rundir.LEARNING_COLUMNS
    rows = [[{c: r[c] for c in cols} for r in rundir.read_rows(d / rundir.METRICS)] for d in (now, before)]
    assert rows[0] == rows[1] and len(rows[0]) == 6 and rows[0][-1]["mean_intrinsic_reward"] is not None
    assert (now / rundir.EVAL).read_text() == (before / rundir.EVAL).read_text()
    assert _same(load_policy(now)[2], load_policy(before)[2])
