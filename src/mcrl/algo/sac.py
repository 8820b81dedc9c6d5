"""SAC-MC: one gradient step as a pure function, jitted once.

`Agent.update(state, batch) -> state` does, in one compiled call and in this order:
  1. MC models' forward pass on the batch -> their NLL losses and the per-transition KL (one pass);
  2. the KL values go into the percentile normaliser, then are mapped into the MC reward range;
  3. reward = (1 - mc_alpha) * r_ext + mc_alpha * r_mc (exactly r_ext when mc_alpha == 0);
  4. critics (clipped double-Q target, polyak targets), actor, entropy coefficient — in the order of
     stable-baselines3 (entropy coefficient read before its own update);
  5. the MC models' Adam step (so the reward used step t's models before their update, like the thesis).
Metrics are summed on the device and read by the host only at log intervals.

`update(state, batch, hyper)` with a `Hyper` takes mc_alpha, gamma, tau and the learning rates as data
instead of compile-time constants: `jax.vmap` of it trains a grid of runs as one computation
(`mcrl.run.group`), compiled once for every alpha. Without `hyper` they are the config's constants.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from mcrl.algo import normaliser
from mcrl.config import Config
from mcrl.algo.mc import MCModels, transition_kl
from mcrl.algo.networks import GaussianHead, TwinCritic

from mcrl.algo.metrics import MC_METRICS, UPDATE_METRICS as METRICS


class Learned(NamedTuple):
    """Parameters and their optimiser state, kept together (flax's TrainState without the methods)."""

    params: Any
    opt: Any


class TrainState(NamedTuple):
    pi: Learned  # the actor
    q: Learned  # the twin critics
    q_target: Any  # polyak-averaged critic parameters
    ent: Learned  # log of the entropy coefficient
    mc_models: Learned | None  # transition and action-only models; None without MC models
    norm: Any  # normaliser.NormaliserState, None without MC models
    key: jax.Array
    grad_steps: jax.Array
    metric_sums: dict  # name -> float32 sum since the last read
    metric_count: jax.Array
    bounds: jax.Array  # (2,) last normaliser bounds

    # the parameters alone, as acting, evaluation and videos need them
    @property
    def actor(self):
        return self.pi.params

    @property
    def critic(self):
        return self.q.params

    @property
    def mc(self):
        return None if self.mc_models is None else self.mc_models.params


class Hyper(NamedTuple):
    """A run's scalar hyperparameters as data (per-run values of a vmapped group)."""

    mc_alpha: Any
    gamma: Any
    tau: Any
    learning_rate: Any
    mc_lr: Any

    @classmethod
    def of(cls, cfg: Config) -> "Hyper":
        return cls(cfg.mc_alpha, cfg.gamma, cfg.tau, cfg.learning_rate, cfg.mc_lr)


class Batch(NamedTuple):
    obs: jax.Array  # (B, obs_dim): observation | achieved_goal | desired_goal for goal envs
    action: jax.Array  # (B, act_dim) in [-1, 1]
    reward: jax.Array  # (B,) extrinsic (HER-recomputed) reward
    next_obs: jax.Array
    terminated: jax.Array  # (B,) 1.0 only for true terminations, never for time-limit truncations


def tanh_gaussian_sample(mean, log_std, key):
    """Reparameterised tanh-squashed Gaussian sample and its log-probability."""
    u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
    logp = (-0.5 * jnp.square((u - mean) * jnp.exp(-log_std)) - log_std - 0.5 * jnp.log(2 * jnp.pi)).sum(-1)
    # log(1 - tanh(u)^2) in a numerically stable form
    logp -= (2.0 * (jnp.log(2.0) - u - jax.nn.softplus(-2.0 * u))).sum(-1)
    return jnp.tanh(u), logp


@dataclass(frozen=True)
class Agent:
    """The static description of the learner (sizes, hyperparameters); all state lives in TrainState."""

    obs_dim: int
    act_dim: int
    mc_dim: int  # first mc_dim entries of obs are the MC state
    cfg: Config

    @property
    def actor_net(self):
        return GaussianHead(self.cfg.hidden_sizes, self.act_dim, self.cfg.init, self.cfg.matmul_precision)

    @property
    def critic_net(self):
        return TwinCritic(self.cfg.hidden_sizes, self.cfg.init, self.cfg.matmul_precision)

    @property
    def mc_models(self) -> MCModels:
        return MCModels(state_dim=self.mc_dim, hidden=self.cfg.mc_hidden_sizes, init_scheme=self.cfg.init,
                        matmul_precision=self.cfg.matmul_precision)

    @property
    def target_entropy(self) -> float:
        return -float(self.act_dim) if self.cfg.target_entropy is None else float(self.cfg.target_entropy)

    def _opt(self, lr):
        return optax.adam(lr)

    def init(self, seed: int) -> TrainState:
        # The SAC keys do not depend on whether MC models exist, so mc_alpha=0 reproduces SAC exactly.
        k_actor, k_critic, k_mc, k_state = jax.random.split(jax.random.PRNGKey(seed), 4)
        obs, act = jnp.zeros((1, self.obs_dim)), jnp.zeros((1, self.act_dim))
        actor = self.actor_net.init(k_actor, obs)["params"]
        critic = self.critic_net.init(k_critic, obs, act)["params"]
        log_ent = jnp.log(jnp.float32(self.cfg.ent_coef_init))
        mc_models = norm = None
        if self.cfg.use_mc_models:
            mc = self.mc_models.init(k_mc, self.act_dim)
            mc_models = Learned(mc, self._opt(self.cfg.mc_lr).init(mc))
            norm = normaliser.init(self.cfg.mc_history_values)
        lr = self.cfg.learning_rate
        return TrainState(pi=Learned(actor, self._opt(lr).init(actor)), q=Learned(critic, self._opt(lr).init(critic)),
                          q_target=jax.tree.map(jnp.copy, critic), ent=Learned(log_ent, self._opt(lr).init(log_ent)),
                          mc_models=mc_models, norm=norm, key=k_state,
                          grad_steps=jnp.int32(0), metric_sums={m: jnp.float32(0) for m in METRICS},
                          metric_count=jnp.int32(0), bounds=jnp.zeros(2, jnp.float32))

    # ------------------------------------------------------------------ acting
    def act(self, actor_params, obs, key):
        mean, log_std = self.actor_net.apply({"params": actor_params}, obs)
        return tanh_gaussian_sample(mean, log_std, key)[0]

    def act_deterministic(self, actor_params, obs):
        return jnp.tanh(self.actor_net.apply({"params": actor_params}, obs)[0])

    # ------------------------------------------------------------------ the MC reward
    def mc_reward(self, state: TrainState, batch: Batch):
        """MC losses/grads, raw KL, updated normaliser and the scaled MC reward of every transition."""
        cfg = self.cfg
        s, s_next = batch.obs[:, : self.mc_dim], batch.next_obs[:, : self.mc_dim]
        (_, (out, lt, la)), grads = jax.value_and_grad(self.mc_models.loss, has_aux=True)(
            state.mc, s, batch.action, s_next)
        kl = transition_kl(out)
        if cfg.mc_reduction == "batch":  # the thesis' code: one batch-mean value for every transition
            kl = jnp.broadcast_to(kl.mean(), kl.shape)
            norm = normaliser.push(state.norm, kl[:1])  # one history value per step, as its code appended
        else:
            norm = normaliser.push(state.norm, kl)
        r_mc, (lo, hi) = normaliser.mc_reward(norm, kl, cfg.min_percentile, cfg.max_percentile, cfg.mc_reward_low,
                                              cfg.mc_reward_high)
        return r_mc, kl, norm, jnp.stack([lo, hi]), grads, lt, la

    # ------------------------------------------------------------------ one gradient step
    def _adam(self, learned: Learned, grads, lr: float) -> Learned:
        upd, opt = self._opt(lr).update(grads, learned.opt, learned.params)
        return Learned(optax.apply_updates(learned.params, upd), opt)

    def update(self, state: TrainState, batch: Batch, hyper: Hyper | None = None) -> TrainState:
        cfg = self.cfg
        h = Hyper.of(cfg) if hyper is None else hyper
        key, k_pi, k_next = jax.random.split(state.key, 3)
        m: dict[str, jax.Array] = {}

        reward = batch.reward
        mc_models, norm, bounds = state.mc_models, state.norm, state.bounds
        if cfg.use_mc_models:
            r_mc, kl, norm, bounds, mc_grads, lt, la = self.mc_reward(state, batch)
            if hyper is not None:  # alpha as data: exactly r_ext where it is 0 (a SAC run of a vmapped group)
                reward = jnp.where(h.mc_alpha > 0, (1.0 - h.mc_alpha) * batch.reward + h.mc_alpha * r_mc, reward)
            elif cfg.mc_alpha > 0:
                reward = (1.0 - cfg.mc_alpha) * batch.reward + cfg.mc_alpha * r_mc
            mc_models = self._adam(state.mc_models, mc_grads, h.mc_lr)
            m.update(transition_model_loss=lt, action_model_loss=la, mean_mc_reward=r_mc.mean(),
                     mean_raw_kl=kl.mean())

        ent_coef = jnp.exp(state.ent.params)

        # critics
        mean_n, log_std_n = self.actor_net.apply({"params": state.actor}, batch.next_obs)
        a_next, logp_next = tanh_gaussian_sample(mean_n, log_std_n, k_next)
        q_next = self.critic_net.apply({"params": state.q_target}, batch.next_obs, a_next).min(0)
        target = reward + (1.0 - batch.terminated) * h.gamma * (q_next - ent_coef * logp_next)
        target = jax.lax.stop_gradient(target)

        def critic_loss_fn(params):
            q = self.critic_net.apply({"params": params}, batch.obs, batch.action)
            return 0.5 * jnp.square(q - target[None]).mean(-1).sum(), q.mean()

        (critic_loss, q_mean), g = jax.value_and_grad(critic_loss_fn, has_aux=True)(state.critic)
        q = self._adam(state.q, g, h.learning_rate)

        # actor (against the updated critics, as stable-baselines3 does)
        def actor_loss_fn(params):
            mean, log_std = self.actor_net.apply({"params": params}, batch.obs)
            a_pi, logp = tanh_gaussian_sample(mean, log_std, k_pi)
            q_pi = self.critic_net.apply({"params": q.params}, batch.obs, a_pi).min(0)
            return (ent_coef * logp - q_pi).mean(), logp

        (actor_loss, logp), g = jax.value_and_grad(actor_loss_fn, has_aux=True)(state.actor)
        pi = self._adam(state.pi, g, h.learning_rate)

        # entropy coefficient, from the same (pre-update) policy sample
        ent_target = jax.lax.stop_gradient(logp + self.target_entropy)
        ent_loss, g = jax.value_and_grad(lambda le: -(le * ent_target).mean())(state.ent.params)
        ent = self._adam(state.ent, g, h.learning_rate)

        q_target = optax.incremental_update(q.params, state.q_target, h.tau)

        m.update(actor_loss=actor_loss, critic_loss=critic_loss, ent_coef=ent_coef, ent_coef_loss=ent_loss,
                 q_mean=q_mean, mean_ext_reward=batch.reward.mean(), mean_total_reward=reward.mean())
        sums = {k: state.metric_sums[k] + m.get(k, 0.0) for k in METRICS}
        return TrainState(pi=pi, q=q, q_target=q_target, ent=ent, mc_models=mc_models, norm=norm, key=key,
                          grad_steps=state.grad_steps + 1, metric_sums=sums, metric_count=state.metric_count + 1,
                          bounds=bounds)

    def read_metrics(self, state: TrainState) -> tuple[dict[str, float], TrainState]:
        """Means since the last read (host side), and the state with the sums reset."""
        n = int(state.metric_count)
        if n == 0:
            return {}, state
        out = metric_means(jax.device_get(state.metric_sums), n, jax.device_get(state.bounds),
                           self.cfg.use_mc_models)
        reset = {k: jnp.float32(0) for k in METRICS}
        return out, state._replace(metric_sums=reset, metric_count=jnp.int32(0))


def metric_means(sums: dict, count: int, bounds, with_mc: bool) -> dict[str, float]:
    """The log row's means from the device sums of `count` gradient steps (MC metrics only `with_mc`)."""
    out = {k: float(v) / count for k, v in sums.items() if with_mc or k not in MC_METRICS}
    if with_mc:
        out["mc_bound_low"], out["mc_bound_high"] = float(bounds[0]), float(bounds[1])
    return out
