"""One SAC gradient step, side by side: mcrl's ``Agent.update`` against stable-baselines3's ``SAC.train``.

Given identical weights (mcrl's, copied into SB3's torch modules), the identical replay batch (a random-action
rollout of the preset's environment, HER-relabelled; or, with ``--checkpoint``, a trained run's weights and a
batch of its buffer) and identical Gaussian noise (mcrl's, handed to SB3's ``Normal.rsample``), both take
``--steps`` gradient steps; losses, gradients and parameters are compared per group, in three modes: ``as-is``,
``sb3-exact`` (SB3 given mcrl's exact tanh correction) and ``mcrl-eps`` (mcrl given SB3's epsilon correction, in
this process only), on the batch and on a saturating variant (the actor's mean-head bias set to
+-``--sat-mean``). Run from the repository root (needs ``pip install -e ".[bench]"``; one thread each side)::

    python studies/sb3-parity/parity_step.py [--preset fetchpush-sac] [--seed 0] [--steps 3] [--sat-mean 7]
                                             [--set key=value ...] [--checkpoint RUN_DIR[/checkpoints/step_N]]
                                             [--json out.json]

Exit status 1 if ``sb3-exact`` or ``mcrl-eps`` disagree beyond the tolerances below. The method in full and the
results: docs/studies/sb3-parity.md, "One gradient step, side by side".
"""
from __future__ import annotations

import _common

_common.one_thread()  # one thread on each side, before jax / torch load (the machine is shared)

import argparse  # noqa: E402
import contextlib  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

MODES = ("as-is", "sb3-exact", "mcrl-eps")
#: Tolerances of the pass/fail check (modes sb3-exact and mcrl-eps). float32 round-off of a 256-sample
#: mean through three 256-wide layers is ~1e-7..1e-6 relative; these leave an order of magnitude of room.
# Losses after step 1 also carry Adam's bias-correction arithmetic: optax computes 1 - b2**t in float32
# (b2 = 0.99900001), torch in float64, so mcrl's first step is 6.4e-6 (relative) longer; the entropy
# coefficient loss of step 2, proportional to log alpha, shows exactly that.
TOL_LOSS_REL = 5e-5  # |a - b| / max(|a|, |b|) of every loss at every step ...
TOL_LOSS_ABS = 1e-6  # ... unless |a - b| is below this (an actor loss near 0 is a cancellation of larger terms)
TOL_GRAD_REL = 1e-4  # ||g_mcrl - g_sb3|| / ||g_mcrl|| per parameter group after step 1
# ||(p_mcrl - p0) - (p_sb3 - p0)|| / ||p_mcrl - p0|| per group after the last step. Looser: after step 1 the
# round-off in the parameters moves u by ~1e-7, which flips the float32 rounding of tanh(u) ~ 1 for a few
# saturated samples, and SB3's epsilon formula turns one such ulp (1.2e-7 in 1 - tanh^2 against epsilon 1e-6)
# into an O(10%) change of that sample's log-probability and gradient (1.4e-3 measured at --sat-mean 9).
TOL_UPDATE_REL = 1e-2
SB3_EPSILON = 1e-6  # SquashedDiagGaussianDistribution's default


# ------------------------------------------------------------------------------------------ batch


def collect_batch(cfg, env, spec, batch_size: int, seed: int) -> dict[str, np.ndarray]:
    """A replay batch like mcrl's: random-action rollout, HER-future relabelling, rewards from the env."""
    from mcrl.envs import episode_seed, flatten_obs, to_env_action

    rng = np.random.default_rng(seed)
    episodes, n = [], 0
    while n < 2 * batch_size:  # enough episodes to draw the batch from
        obs, _ = env.reset(seed=episode_seed(seed, 7, len(episodes)))
        ep = {k: [] for k in ("obs", "action", "reward", "next_obs", "terminated", "ag_next", "dict_obs")}
        while True:
            a = rng.uniform(-1, 1, spec.act_dim).astype(np.float32)
            nxt, r, term, trunc, _ = env.step(to_env_action(a, env, cfg.action_scale))
            ep["obs"].append(flatten_obs(obs))
            ep["action"].append(a)
            ep["reward"].append(np.float32(r))
            ep["next_obs"].append(flatten_obs(nxt))
            ep["terminated"].append(np.float32(term))
            if spec.goal_env:
                ep["ag_next"].append(np.asarray(nxt["achieved_goal"], np.float32))
            obs = nxt
            if term or trunc:
                break
        episodes.append({k: np.asarray(v) for k, v in ep.items() if v})
        n += len(ep["obs"])

    ep_idx = rng.integers(len(episodes), size=batch_size)
    cols = {k: [] for k in ("obs", "action", "reward", "next_obs", "terminated")}
    n_her = round(batch_size * cfg.her_k / (cfg.her_k + 1)) if spec.goal_env else 0
    g0 = spec.observation_dim + spec.goal_dim  # desired_goal's slice in the flat observation
    for j, e in enumerate(ep_idx):
        ep = episodes[e]
        t = int(rng.integers(len(ep["obs"])))
        o, nx = ep["obs"][t].copy(), ep["next_obs"][t].copy()
        r, term = ep["reward"][t], ep["terminated"][t]
        if j < n_her:  # mcrl relabels the first round(B k/(k+1)) with a future achieved goal
            goal = ep["ag_next"][int(rng.integers(t, len(ep["obs"])))]
            o[g0:], nx[g0:] = goal, goal
            r = np.float32(env.unwrapped.compute_reward(ep["ag_next"][t], goal, {}))
            term = np.float32(0.0)  # Fetch never terminates
        for k, v in zip(cols, (o, ep["action"][t], r, nx, term)):
            cols[k].append(v)
    return {k: np.asarray(v, np.float32) for k, v in cols.items()}


# ------------------------------------------------------------------------------------------ weights


def checkpoint_batch(cfg, agent, ckpt: Path, seed: int):
    """(batch, train state, label) from a checkpoint: the trained networks and a HER batch of its replay buffer."""
    from mcrl.run import checkpoint as ckpt_io
    from mcrl.run.policy import build, restore

    env, _, _, buffer = build(cfg)
    env.close()
    state, meta = restore(cfg, agent, ckpt)
    arrays = ckpt_io.load_buffer_arrays(ckpt) if meta.get("has_buffer") else None
    if arrays is None:
        raise SystemExit(f"error: {ckpt} has no replay buffer (save_buffer=false): no batch to compare on")
    buffer.load_arrays(arrays)
    b = buffer.sample(cfg.batch_size, np.random.default_rng(seed))
    batch = {k: np.asarray(v, np.float32) for k, v in b._asdict().items()}
    # the trained parameters with fresh optimiser states, as SB3's side starts with fresh Adam moments
    fresh = agent.init(seed)
    state = fresh._replace(pi=fresh.pi._replace(params=state.pi.params), q=fresh.q._replace(params=state.q.params),
                           q_target=state.q_target, ent=fresh.ent._replace(params=state.ent.params))
    return batch, state, f"trained (step {meta['step']})"


def _layout(n_hidden: int):
    """(flax path, torch module prefix) of every Dense/Linear layer; critic prefixes take '{}' = qf0/qf1."""
    actor = [(("MLP_0", f"Dense_{i}"), f"latent_pi.{2 * i}") for i in range(n_hidden)]
    actor += [(("mean",), "mu"), (("log_std",), "log_std")]
    critic = [(("VmapMLP_0", f"Dense_{i}"), f"{{}}.{2 * i}") for i in range(n_hidden)]
    critic += [(("VmapDense_0",), f"{{}}.{2 * n_hidden}")]
    return actor, critic


def _get(tree, path):
    for p in path:
        tree = tree[p]
    return tree


def tree_to_torch(tree, module, layout, stacked: bool) -> None:
    """Copy a flax parameter tree into a torch module (flax kernel (in, out) -> torch weight (out, in))."""
    import torch

    named = dict(module.named_parameters())
    with torch.no_grad():
        for path, prefix in layout:
            layer = _get(tree, path)
            k, b = np.asarray(layer["kernel"]), np.asarray(layer["bias"])
            for c in (range(k.shape[0]) if stacked else [None]):
                name = prefix.format(f"qf{c}") if stacked else prefix
                kc, bc = (k[c], b[c]) if stacked else (k, b)
                named[name + ".weight"].copy_(torch.from_numpy(np.array(kc.T, order="C")))
                named[name + ".bias"].copy_(torch.from_numpy(np.array(bc)))


def torch_to_tree(module, layout, stacked: bool, value=None) -> dict:
    """The flax-shaped numpy tree of a torch module's parameters (or of `value(param)`, e.g. Adam's moment)."""
    value = value or (lambda p: p)
    named = dict(module.named_parameters())
    tree: dict = {}
    for path, prefix in layout:
        def arr(name):
            return value(named[name]).detach().cpu().numpy().astype(np.float32)
        if stacked:
            qs = [prefix.format(f"qf{c}") for c in range(2)]
            k = np.stack([arr(q + ".weight").T for q in qs])
            b = np.stack([arr(q + ".bias") for q in qs])
        else:
            k, b = arr(prefix + ".weight").T, arr(prefix + ".bias")
        node = tree
        for p in path[:-1]:
            node = node.setdefault(p, {})
        node[path[-1]] = {"bias": b, "kernel": k}
    return tree


# ------------------------------------------------------------------------------------------ SB3


class FixedBatch:
    """Stands in for SB3's replay buffer: every `sample()` returns the same batch."""

    def __init__(self, batch: dict[str, np.ndarray]):
        import torch
        from stable_baselines3.common.type_aliases import ReplayBufferSamples

        t = {k: torch.from_numpy(v.copy()) for k, v in batch.items()}
        self.samples = ReplayBufferSamples(observations=t["obs"], actions=t["action"],
                                           next_observations=t["next_obs"], dones=t["terminated"][:, None],
                                           rewards=t["reward"][:, None])
        self.calls = 0

    def sample(self, batch_size, env=None):
        assert batch_size == self.samples.observations.shape[0]
        self.calls += 1
        return self.samples


def make_sb3(cfg, obs_dim: int, act_dim: int, seed: int):
    import gymnasium as gym
    from stable_baselines3 import SAC
    from stable_baselines3.common.logger import Logger

    class FlatEnv(gym.Env):
        """Only for SB3's model construction: the spaces matter, the dynamics are never used."""
        observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        action_space = gym.spaces.Box(-1.0, 1.0, (act_dim,), np.float32)

        def reset(self, *, seed=None, options=None):
            return np.zeros(obs_dim, np.float32), {}

        def step(self, action):
            return np.zeros(obs_dim, np.float32), 0.0, False, False, {}

    model = SAC("MlpPolicy", FlatEnv(), learning_rate=cfg.learning_rate, buffer_size=10, learning_starts=0,
                batch_size=cfg.batch_size, tau=cfg.tau, gamma=cfg.gamma, train_freq=1, gradient_steps=1,
                ent_coef=f"auto_{cfg.ent_coef_init}",
                target_entropy="auto" if cfg.target_entropy is None else float(cfg.target_entropy),
                policy_kwargs=dict(net_arch=list(cfg.hidden_sizes)), seed=seed, device="cpu", verbose=0)
    model.set_logger(Logger(folder=None, output_formats=[]))
    # optax.adam's defaults; SB3's SAC passes no optimizer_kwargs, so torch's defaults apply. Checked, not assumed.
    for opt in (model.actor.optimizer, model.critic.optimizer, model.ent_coef_optimizer):
        g = opt.param_groups[0]
        assert g["betas"] == (0.9, 0.999) and g["eps"] == 1e-8 and g["weight_decay"] == 0 and not g["amsgrad"], g
        assert g["lr"] == cfg.learning_rate
    return model


def load_into_sb3(model, state, layout) -> None:
    import torch

    actor_l, critic_l = layout
    tree_to_torch(state.pi.params, model.actor, actor_l, stacked=False)
    tree_to_torch(state.q.params, model.critic, critic_l, stacked=True)
    tree_to_torch(state.q_target, model.critic_target, critic_l, stacked=True)
    with torch.no_grad():
        model.log_ent_coef.copy_(torch.tensor([float(state.ent.params)]))


def sb3_snapshot(model, layout) -> dict:
    """Parameters and Adam first moments of the SB3 model in mcrl's tree layout."""
    actor_l, critic_l = layout

    def m1(opt):
        return lambda p: opt.state[p]["exp_avg"] if p in opt.state else p * 0

    return {
        "params": {"actor": torch_to_tree(model.actor, actor_l, False),
                   "critic": torch_to_tree(model.critic, critic_l, True),
                   "critic_target": torch_to_tree(model.critic_target, critic_l, True),
                   "log_ent_coef": np.float32(model.log_ent_coef.detach().numpy()[0])},
        "adam_m": {"actor": torch_to_tree(model.actor, actor_l, False, m1(model.actor.optimizer)),
                   "critic": torch_to_tree(model.critic, critic_l, True, m1(model.critic.optimizer)),
                   "log_ent_coef": np.float32(model.ent_coef_optimizer.state[model.log_ent_coef]["exp_avg"][0])
                   if model.log_ent_coef in model.ent_coef_optimizer.state else np.float32(0)},
    }


def mcrl_snapshot(state) -> dict:
    import jax

    m = lambda learned: jax.device_get(learned.opt[0].mu)  # noqa: E731  (optax.adam = (ScaleByAdam, scale))
    return {"params": {"actor": jax.device_get(state.pi.params), "critic": jax.device_get(state.q.params),
                       "critic_target": jax.device_get(state.q_target),
                       "log_ent_coef": np.float32(state.ent.params)},
            "adam_m": {"actor": m(state.pi), "critic": m(state.q), "log_ent_coef": np.float32(m(state.ent))}}


@contextlib.contextmanager
def fixed_normal_noise():
    """SB3's Normal.rsample returns loc + eps * scale with eps popped from `queue` (torch's own formula)."""
    import torch
    from torch.distributions import Normal

    queue: list = []
    orig = Normal.rsample

    def rsample(self, sample_shape=torch.Size()):
        if not queue:
            raise AssertionError("SB3 drew more Gaussian samples than mcrl did")
        eps = queue.pop(0)
        assert tuple(eps.shape) == tuple(self._extended_shape(sample_shape)), (eps.shape, self.loc.shape)
        return self.loc + eps * self.scale

    Normal.rsample = rsample
    try:
        yield queue
    finally:
        Normal.rsample = orig


@contextlib.contextmanager
def sb3_exact_log_prob(enabled: bool):
    """Mode sb3-exact: SB3's squash correction replaced by mcrl's exact 2 (log 2 - u - softplus(-2u))."""
    import torch.nn.functional as F
    from stable_baselines3.common.distributions import (DiagGaussianDistribution,
                                                        SquashedDiagGaussianDistribution as Squashed)

    if not enabled:
        yield
        return
    orig = Squashed.log_prob

    def log_prob(self, actions, gaussian_actions=None):
        assert gaussian_actions is not None  # SAC.train always passes the pre-squash sample
        u = gaussian_actions
        lp = DiagGaussianDistribution.log_prob(self, u)
        return lp - (2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))).sum(dim=1)

    Squashed.log_prob = log_prob
    try:
        yield
    finally:
        Squashed.log_prob = orig


def _rounded_tanh():
    """float32 tanh computed as torch computes it near saturation (XLA's is not; see mcrl_eps_log_prob).

    Value: for |u| > 2, 1 - 2 / (exp(2|u|) + 1); the small term is accurate to ~1e-7 relative, so the one
    rounding of the subtraction gives the correctly rounded float32 value (as torch's tanh, 1 ulp, does).
    Below 2 the epsilon formula is well conditioned and XLA's tanh is used. Derivative: torch's tanh_backward,
    1 - y*y from the float32 output y (0 once y rounds to 1), where JAX uses (1 + y)(1 - y).
    """
    import jax
    import jax.numpy as jnp

    @jax.custom_jvp
    def rounded_tanh(u):
        au = jnp.abs(u)
        return jnp.where(au > 2.0, jnp.sign(u) * (1.0 - 2.0 / (jnp.exp(2.0 * au) + 1.0)), jnp.tanh(u))

    @rounded_tanh.defjvp
    def _jvp(primals, tangents):
        y = rounded_tanh(primals[0])
        return y, tangents[0] * (1.0 - jax.lax.optimization_barrier(y * y))

    return rounded_tanh


@contextlib.contextmanager
def mcrl_eps_log_prob(enabled: bool):
    """Mode mcrl-eps: mcrl's sampler with SB3's log(1 - tanh(u)^2 + 1e-6) correction, in this process only.

    SB3's formula resolves 1 - tanh(u)^2 only in steps of ~1.2e-7 (float32 spacing below 1) against its 1e-6
    epsilon, so near saturation it depends on the last bits of tanh(u). XLA's float32 tanh is a rational
    approximation (up to 4 ulp off) that returns exactly +-1 from |u| ~ 7.9, torch's (1 ulp) from 9.0: with
    jnp.tanh the formula differs from SB3's by up to ~0.4 per dimension for 6 < |u| < 9. So the tanh here is
    computed as torch's is (`_rounded_tanh`, its derivative too), for the action as well. For the same reason
    the sum 1 - a^2 + 1e-6 must be evaluated in torch's order: XLA's simplifier otherwise reassociates it into
    (1 + 1e-6) - a^2 with 1 + 1e-6 rounded to float32 (1.00000095, an effective epsilon of 9.5e-7).
    """
    import jax
    import jax.numpy as jnp

    import mcrl.algo.sac as sac

    if not enabled:
        yield
        return
    orig = sac.tanh_gaussian_sample
    rounded_tanh = _rounded_tanh()

    def tanh_gaussian_sample(mean, log_std, key):
        u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
        logp = (-0.5 * jnp.square((u - mean) * jnp.exp(-log_std)) - log_std - 0.5 * jnp.log(2 * jnp.pi)).sum(-1)
        a = rounded_tanh(u)
        # the barrier keeps XLA from folding (1 - a^2) + 1e-6 into 1.00000095 - a^2 (float32 1 + 1e-6)
        return a, logp - jnp.log(jax.lax.optimization_barrier(1.0 - jnp.square(a)) + SB3_EPSILON).sum(-1)

    sac.tanh_gaussian_sample = tanh_gaussian_sample
    try:
        yield
    finally:
        sac.tanh_gaussian_sample = orig


# ------------------------------------------------------------------------------------------ one comparison


def host_noise(key, steps: int, shape):
    """mcrl's noise, reproduced on the host: per step key, k_pi, k_next = split(key, 3)."""
    import jax

    out = []
    for _ in range(steps):
        key, k_pi, k_next = jax.random.split(key, 3)
        out.append((np.asarray(jax.random.normal(k_pi, shape)), np.asarray(jax.random.normal(k_next, shape))))
    return out


def _rel(a, b) -> float:
    a, b = float(a), float(b)
    d = max(abs(a), abs(b))
    return 0.0 if d == 0 else abs(a - b) / d


def _flat(tree) -> np.ndarray:
    import jax

    return np.concatenate([np.asarray(x, np.float64).ravel() for x in jax.tree.leaves(tree)])


def compare(agent, state0, batch_np, layout, mode: str, steps: int, seed: int) -> dict:
    import jax
    import torch

    from mcrl.algo.sac import Batch

    cfg = agent.cfg
    B, A = batch_np["action"].shape
    noise = host_noise(state0.key, steps, (B, A))
    batch = Batch(**{k: jax.numpy.asarray(v) for k, v in batch_np.items()})

    # mcrl: a fresh jit per mode, so the (possibly patched) module-level sampler is traced anew
    m_loss, m_snaps = [], []
    with mcrl_eps_log_prob(mode == "mcrl-eps"):
        update = jax.jit(lambda s, b: agent.update(s, b))
        state = state0
        for _ in range(steps):
            state, metrics = update(state, batch)
            m_loss.append({k: float(v) for k, v in metrics.items()})
            m_snaps.append(mcrl_snapshot(state))

    # SB3: same weights, same batch, same noise
    model = make_sb3(cfg, agent.obs_dim, agent.act_dim, seed)
    load_into_sb3(model, state0, layout)
    model.replay_buffer = FixedBatch(batch_np)
    order: list[str] = []
    for name, opt in (("ent_coef", model.ent_coef_optimizer), ("critic", model.critic.optimizer),
                      ("actor", model.actor.optimizer)):
        opt.step = (lambda f, n: (lambda *a, **k: (order.append(n), f(*a, **k))[1]))(opt.step, name)
    s_loss, s_snaps = [], []
    with fixed_normal_noise() as queue, sb3_exact_log_prob(mode == "sb3-exact"):
        for eps_pi, eps_next in noise:
            queue[:] = [torch.tensor(eps_pi), torch.tensor(eps_next)]  # SB3 order: current, next
            model.train(gradient_steps=1, batch_size=B)
            assert not queue, "SB3 drew fewer Gaussian samples than mcrl did"
            v = model.logger.name_to_value
            s_loss.append({k: float(v[f"train/{k}"]) for k in ("critic_loss", "actor_loss", "ent_coef_loss",
                                                                 "ent_coef")})
            s_snaps.append(sb3_snapshot(model, layout))
    assert model.replay_buffer.calls == steps

    p0 = mcrl_snapshot(state0)["params"]
    res: dict = {"mode": mode, "steps": steps, "sb3_optimizer_order": order[:3]}
    losses = {}
    for k in ("critic_loss", "actor_loss", "ent_coef_loss", "ent_coef"):
        losses[k] = {"mcrl": m_loss[0][k], "sb3": s_loss[0][k], "rel": _rel(m_loss[0][k], s_loss[0][k]),
                     "max_rel_all_steps": max(_rel(m[k], s[k]) for m, s in zip(m_loss, s_loss)),
                     "max_abs_all_steps": max(abs(m[k] - s[k]) for m, s in zip(m_loss, s_loss))}
    res["losses_step1"] = losses
    # Adam's first moment after step 1 is (1 - beta1) * gradient on both sides
    g = {}
    for grp in ("actor", "critic", "log_ent_coef"):
        gm, gs = _flat(m_snaps[0]["adam_m"][grp]) / 0.1, _flat(s_snaps[0]["adam_m"][grp]) / 0.1
        g[grp] = {"rel_l2": float(np.linalg.norm(gm - gs) / max(np.linalg.norm(gm), 1e-30)),
                  "max_abs": float(np.abs(gm - gs).max()), "norm_mcrl": float(np.linalg.norm(gm))}
    res["grads_step1"] = g
    # the policy's mean log-probability, from the entropy coefficient's gradient -(mean logp + target)
    tgt = agent.target_entropy
    res["mean_logp_step1"] = {side: float(-float(snap[0]["adam_m"]["log_ent_coef"]) / 0.1 - tgt)
                              for side, snap in (("mcrl", m_snaps), ("sb3", s_snaps))}
    for tag, i in (("step1", 0), ("last", steps - 1)):
        out = {}
        for grp in ("actor", "critic", "critic_target", "log_ent_coef"):
            pm, ps, pb = (_flat(x["params"][grp]) for x in (m_snaps[i], s_snaps[i], {"params": p0}))
            du = np.linalg.norm((pm - pb) - (ps - pb)) / max(np.linalg.norm(pm - pb), 1e-30)
            out[grp] = {"max_abs": float(np.abs(pm - ps).max()), "update_rel_l2": float(du)}
        res[f"params_{tag}"] = out
    # what SB3's actor loss would have been had it used the coefficient after its own (first) update
    a0, a1 = math.exp(float(p0["log_ent_coef"])), math.exp(float(s_snaps[0]["params"]["log_ent_coef"]))
    shift = abs((a1 - a0) * res["mean_logp_step1"]["sb3"])
    res["post_update_coef_shift_rel"] = shift / abs(s_loss[0]["actor_loss"])
    return res


def forward_check(agent, state, model, obs_dim, act_dim, seed) -> dict:
    import torch

    rng = np.random.default_rng(seed + 1)
    obs = rng.normal(size=(512, obs_dim)).astype(np.float32)
    act = rng.uniform(-1, 1, (512, act_dim)).astype(np.float32)
    mean, log_std = (np.asarray(x) for x in agent.actor_net.apply({"params": state.pi.params}, obs))
    q = np.asarray(agent.critic_net.apply({"params": state.q.params}, obs, act))
    qt = np.asarray(agent.critic_net.apply({"params": state.q_target}, obs, act))
    with torch.no_grad():
        to, ta = torch.from_numpy(obs), torch.from_numpy(act)
        smean, slog_std, _ = model.actor.get_action_dist_params(to)
        sq = np.stack([x.numpy()[:, 0] for x in model.critic(to, ta)])
        sqt = np.stack([x.numpy()[:, 0] for x in model.critic_target(to, ta)])
    # relative to the outputs' scale: a trained critic's Q values are O(10), float32 round-off grows with them
    scaled = lambda a, b: float(np.abs(a - b).max() / max(1.0, np.abs(a).max()))  # noqa: E731
    return {"actor_mean": scaled(mean, smean.numpy()), "actor_log_std": scaled(log_std, slog_std.numpy()),
            "critics": scaled(q, sq), "target_critics": scaled(qt, sqt)}


def saturation_stats(agent, state, batch_np, eps) -> dict:
    """How saturated the policy sample of step 1 is, and the two tanh corrections on it (float32)."""
    import jax
    import jax.numpy as jnp

    import torch

    mean, log_std = agent.actor_net.apply({"params": state.pi.params}, batch_np["obs"])
    u = mean + jnp.exp(log_std) * eps
    exact = (2.0 * (jnp.log(2.0) - u - jnp.logaddexp(0.0, -2.0 * u))).sum(-1)
    t_torch = torch.tanh(torch.from_numpy(np.array(u)))
    sb3 = torch.log(1.0 - t_torch ** 2 + SB3_EPSILON).sum(1).numpy()
    # SB3's formula written naively in JAX (XLA's tanh, reassociated epsilon): what a port would compute
    sb3_xla = jax.jit(lambda x: jnp.log(1.0 - jnp.square(jnp.tanh(x)) + SB3_EPSILON).sum(-1))(u)
    au = np.abs(np.asarray(u))
    return {"abs_u_p10_p50_p90": [float(x) for x in np.percentile(au, [10, 50, 90])],
            "frac_tanh_is_1": float(np.mean(np.abs(t_torch.numpy()) == 1.0)),
            "frac_1m_tanh2_below_eps": float(np.mean(1.0 - np.square(np.tanh(au.astype(np.float64))) < 1e-6)),
            "mean_log_jacobian_exact": float(exact.mean()), "mean_log_jacobian_sb3": float(sb3.mean()),
            "mean_log_jacobian_sb3_formula_xla_tanh": float(sb3_xla.mean())}


# ------------------------------------------------------------------------------------------ report


def _fmt(x: float) -> str:
    return "0" if x == 0 else f"{x:.1e}" if abs(x) < 1e-2 or abs(x) >= 1e4 else f"{x:.4g}"


def tables(results: list[dict]) -> str:
    lines = ["| batch | mode | critic loss mcrl / SB3 (rel) | actor loss mcrl / SB3 (rel) "
             "| mean log pi mcrl / SB3 | loss max rel, all steps | grad rel L2: actor / critic / log alpha |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in results:
        L, G = r["losses_step1"], r["grads_step1"]
        worst = max(v["max_rel_all_steps"] for v in L.values())
        lines.append(
            f"| {r['batch']} | {r['mode']} | {L['critic_loss']['mcrl']:.6g} / {L['critic_loss']['sb3']:.6g} "
            f"({_fmt(L['critic_loss']['rel'])}) | {L['actor_loss']['mcrl']:.6g} / {L['actor_loss']['sb3']:.6g} "
            f"({_fmt(L['actor_loss']['rel'])}) | {r['mean_logp_step1']['mcrl']:.4f} / "
            f"{r['mean_logp_step1']['sb3']:.4f} | {_fmt(worst)} | {_fmt(G['actor']['rel_l2'])} / "
            f"{_fmt(G['critic']['rel_l2'])} / {_fmt(G['log_ent_coef']['rel_l2'])} |")
    lines += ["", "| batch | mode | params after step 1, max abs diff: actor / critic / target / log alpha "
              f"| update rel L2 after step {results[0]['steps']}: actor / critic / target / log alpha |",
              "| --- | --- | --- | --- |"]
    for r in results:
        p1, pl = r["params_step1"], r["params_last"]
        grp = ("actor", "critic", "critic_target", "log_ent_coef")
        lines.append(f"| {r['batch']} | {r['mode']} | " + " / ".join(_fmt(p1[g]["max_abs"]) for g in grp)
                     + " | " + " / ".join(_fmt(pl[g]["update_rel_l2"]) for g in grp) + " |")
    return "\n".join(lines)


def failures(r: dict) -> list[str]:
    bad = []
    for k, v in r["losses_step1"].items():
        if v["max_rel_all_steps"] > TOL_LOSS_REL and v["max_abs_all_steps"] > TOL_LOSS_ABS:
            bad.append(f"{k} rel {v['max_rel_all_steps']:.2e}, abs {v['max_abs_all_steps']:.2e}")
    for k, v in r["grads_step1"].items():
        if v["rel_l2"] > TOL_GRAD_REL:
            bad.append(f"grad {k} rel {v['rel_l2']:.2e}")
    for k, v in r["params_last"].items():
        if v["update_rel_l2"] > TOL_UPDATE_REL:
            bad.append(f"update {k} rel {v['update_rel_l2']:.2e}")
    return bad


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="fetchpush-sac")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=3, help="gradient steps per comparison (the first is the "
                    "one-step check; later ones exercise Adam's bias correction and the Polyak average)")
    ap.add_argument("--sat-mean", type=float, default=7.0, help="|mean-head bias| of the saturating batch")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="mcrl config override")
    ap.add_argument("--json", type=Path, help="write every number to this file")
    ap.add_argument("--checkpoint", type=Path, metavar="RUN_DIR[/checkpoints/step_N]",
                    help="compare on a trained policy instead of a fresh one: the run's actor, critics and "
                    "entropy coefficient from this checkpoint (newest if a run directory), and a batch from its "
                    "replay buffer (the run's own config; --preset and --set are ignored)")
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(1)
    import jax
    import jax.numpy as jnp
    import stable_baselines3

    from mcrl.algo.sac import Agent
    from mcrl.config import parse_set, resolve_config
    from mcrl.envs import inspect, make_env

    t0 = time.time()
    if args.checkpoint is not None:
        from mcrl.run import checkpoint as ckpt_io
        from mcrl.run import rundir

        ckpt_dir = Path(args.checkpoint)
        run_dir = ckpt_dir.parent.parent if ckpt_dir.parent.name == "checkpoints" else ckpt_dir
        ckpt = ckpt_dir if ckpt_dir != run_dir else ckpt_io.find(run_dir)
        cfg = rundir.read_config(run_dir)
        args.preset, args.seed = cfg.preset or cfg.env_id, cfg.seed
    else:
        cfg = resolve_config(args.preset, {**parse_set(args.set), "seed": args.seed})
    if cfg.use_intrinsic_models:
        print(f"error: {args.preset} trains intrinsic models; stable-baselines3 has none (use a SAC preset)",
              file=sys.stderr)
        return 2
    env = make_env(cfg)
    spec = inspect(env, cfg)
    agent = Agent(spec.obs_dim, spec.act_dim, spec.intrinsic_dim, cfg)
    state0 = agent.init(args.seed)
    layout = _layout(len(cfg.hidden_sizes))
    if args.checkpoint is not None:
        batch, state0, first = checkpoint_batch(cfg, agent, ckpt, args.seed)
    else:
        batch, first = collect_batch(cfg, env, spec, cfg.batch_size, args.seed), "rollout"
    env.close()

    # the saturating variant: same batch, actor mean-head bias set to +-sat_mean (random signs)
    signs = np.where(np.random.default_rng(args.seed + 2).random(spec.act_dim) < 0.5, -1.0, 1.0)
    actor_sat = jax.tree.map(jnp.copy, state0.pi.params)
    actor_sat["mean"]["bias"] = jnp.asarray(signs * args.sat_mean, jnp.float32)
    state_sat = state0._replace(pi=state0.pi._replace(params=actor_sat))

    model = make_sb3(cfg, spec.obs_dim, spec.act_dim, args.seed)
    load_into_sb3(model, state0, layout)
    fwd = forward_check(agent, state0, model, spec.obs_dim, spec.act_dim, args.seed)
    eps_pi = host_noise(state0.key, 1, batch["action"].shape)[0][0]
    # the host noise must be what the jitted update draws (threefry is bit-exact, checked anyway)
    k_pi = jax.jit(lambda k: jax.random.split(k, 3)[1])(state0.key)
    assert np.array_equal(eps_pi, np.asarray(jax.jit(lambda k: jax.random.normal(k, eps_pi.shape))(k_pi)))

    print(f"mcrl vs stable-baselines3 {stable_baselines3.__version__} (torch {torch.__version__}, jax "
          f"{jax.__version__}), preset {args.preset}, seed {args.seed}, batch {cfg.batch_size}, "
          f"obs {spec.obs_dim}, act {spec.act_dim}, hidden {list(cfg.hidden_sizes)}")
    source = "from the run's replay buffer" if args.checkpoint else "from random-action episodes"
    print(f"batch: {len(batch['reward'])} transitions {source}, reward 0 (goal reached) for "
          f"{np.mean(batch['reward'] == 0):.0%}, terminated for {np.mean(batch['terminated'] > 0):.0%}")
    print("forward outputs after copying the weights, max abs diff / max(1, max |output|): "
          + ", ".join(f"{k} {v:.1e}" for k, v in fwd.items()))
    batches = {first: (state0, batch), f"saturating (mean bias +-{args.sat_mean:g})": (state_sat, batch)}
    sat = {}
    for name, (st, b) in batches.items():
        sat[name] = saturation_stats(agent, st, b, eps_pi)
        s = sat[name]
        print(f"{name}: |u| p10/p50/p90 {'/'.join(f'{x:.2f}' for x in s['abs_u_p10_p50_p90'])}, float32 tanh(u) = "
              f"+-1 for {s['frac_tanh_is_1']:.1%}, 1 - tanh^2 < 1e-6 for {s['frac_1m_tanh2_below_eps']:.1%}; mean "
              f"sum log(1 - tanh^2): exact {s['mean_log_jacobian_exact']:.3f}, "
              f"SB3 {s['mean_log_jacobian_sb3']:.3f} "
              f"(SB3's formula jitted in JAX: {s['mean_log_jacobian_sb3_formula_xla_tanh']:.3f})")

    results = []
    for name, (st, b) in batches.items():
        for mode in MODES:
            r = compare(agent, st, b, layout, mode, args.steps, args.seed)
            r["batch"] = name
            results.append(r)
    print()
    print(tables(results))
    order = results[0]["sb3_optimizer_order"]
    checked = [r for r in results if r["mode"] != "as-is"]
    shift = min(r["post_update_coef_shift_rel"] for r in checked)
    agree = max(r["losses_step1"]["actor_loss"]["rel"] for r in checked)
    print(f"\nSB3 optimiser order per step: {' -> '.join(order)}; mcrl's (source): critic -> actor -> ent_coef. "
          f"Both use the pre-update coefficient: had SB3 used the one after its own update, its actor loss would "
          f"differ by >= {shift:.1e} (relative); measured agreement {agree:.1e}.")
    bad = {f"{r['batch']} / {r['mode']}": failures(r) for r in results if r["mode"] != "as-is"}
    bad = {k: v for k, v in bad.items() if v}
    if fwd and max(fwd.values()) > 1e-5:
        bad["forward"] = [f"forward outputs differ by {max(fwd.values()):.1e}"]
    verdict = ("PASS: with the same tanh correction the two updates agree to float32 round-off; the tanh "
               "log-probability is the only difference" if not bad else f"FAIL: {bad}")
    print(f"\n{verdict}  ({time.time() - t0:.0f} s)")
    if args.json:
        _common.write_json(args.json, {"preset": args.preset, "seed": args.seed, "steps": args.steps,
                                       "sb3": stable_baselines3.__version__, "torch": torch.__version__,
                                       "jax": jax.__version__, "forward_max_abs_diff": fwd, "saturation": sat,
                                       "results": results, "pass": not bad, "failures": bad})
    return 0 if not bad else 1


if __name__ == "__main__":
    sys.exit(main())
