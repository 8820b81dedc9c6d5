"""SAC with an intrinsic reward (SAC-MC by default): one gradient step as a pure function, jitted once.

`Agent.update(state, batch) -> (state, metrics)` does, in one compiled call and in this order:
  1. the intrinsic reward's models on the batch -> the gradients of their loss and the raw reward of each
     transition, in one pass (`intrinsic`: MC, the thesis' reward, by default; any of `mcrl.algo.intrinsic`'s
     registry, all through the one interface `IntrinsicReward`);
  2. the raw values go into the percentile normaliser, then are mapped into the reward range;
  3. reward = (1 - intrinsic_alpha) * r_ext + intrinsic_alpha * r_int (exactly r_ext when the weight is 0);
  4. critics (clipped double-Q target, polyak targets), actor, entropy coefficient — in the order of
     stable-baselines3 (entropy coefficient read before its own update);
  5. the intrinsic models' Adam step (so the reward used step t's models before their update, like the thesis).
The losses and the reward mix are pure functions of arrays in `mcrl.algo.losses` (each checked alone by hand);
`update` applies the networks, hands their outputs to those functions and takes the gradients and Adam steps.
`state` holds only what learns (parameters, optimiser states, targets, the normaliser's history, the key);
`metrics` are the step's numbers by name, which the training loop adds up on the device in the same compiled
call (`mcrl.algo.diagnostics`) and reads only at log intervals.

`update(state, batch, hyper)` with a `Hyper` takes intrinsic_alpha, gamma, tau and the learning rates as data
instead of compile-time constants: `jax.vmap` of it trains a grid of runs as one computation
(`mcrl.run.group`), compiled once for every alpha. Without `hyper` they are the config's constants.
`update(state, batch, hyper, mix)` takes the reward mix's weights as data too (`Mix`): the training loop passes the
weight its schedule gives each step (`mcrl.algo.schedule`), so a changing alpha compiles nothing.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from mcrl.algo import intrinsic as intrinsic_rewards
from mcrl.algo import losses, normaliser
from mcrl.algo.intrinsic import IntrinsicReward
from mcrl.algo.networks import GaussianHead, TwinCritic
from mcrl.config import Config
from mcrl.replay import Batch

__all__ = ["Agent", "Batch", "Hyper", "IntrinsicModels", "IntrinsicStep", "Learned", "Mix", "SQUASH_CORRECTIONS",
           "TrainState", "saturation", "squash_log_det", "tanh_gaussian_sample"]

INTRINSIC_KEY = 0x1A7  # folded into the step's key for the intrinsic reward's own randomness


class Learned(NamedTuple):
    """Parameters and their optimiser state, kept together (flax's TrainState without the methods)."""

    params: Any
    opt: Any


class IntrinsicModels(NamedTuple):
    """The models of the run's intrinsic reward, whichever it is (`mcrl.algo.intrinsic`)."""

    params: Any  # trained by Adam at intrinsic_lr
    opt: Any
    untrained: Any  # what no gradient trains (RND's target network, running state statistics); {} for MC, ICM


class TrainState(NamedTuple):
    """What learns. A checkpoint's state.npz keys each leaf by its path: `.pi.params['MLP_0']...`, `.pi.opt[0]...`,
    `.intrinsic.params[...]` (`.mc_models.params[...]` in checkpoints from before issue 52, read as these)."""

    pi: Learned  # the actor
    q: Learned  # the twin critics
    q_target: Any  # polyak-averaged critic parameters
    ent: Learned  # log of the entropy coefficient
    intrinsic: IntrinsicModels | None  # the intrinsic reward's models; None without them (plain SAC)
    norm: Any  # normaliser.NormaliserState of the raw intrinsic rewards, None without intrinsic models
    key: jax.Array
    grad_steps: jax.Array


class Hyper(NamedTuple):
    """A run's scalar hyperparameters as data (per-run values of a vmapped group)."""

    intrinsic_alpha: Any
    gamma: Any
    tau: Any
    learning_rate: Any
    intrinsic_lr: Any

    @classmethod
    def of(cls, cfg: Config) -> "Hyper":
        return cls(cfg.intrinsic_alpha, cfg.gamma, cfg.tau, cfg.learning_rate, cfg.intrinsic_lr)


class Mix(NamedTuple):
    """The reward mix's weights as data of the step: `ext` = 1 - alpha on the extrinsic reward, `intrinsic` = alpha
    on the intrinsic one (scalars for a run, (N,) for a vmapped group). 1 - alpha is computed on the host, each
    learner the way its step computed it when alpha was fixed, so that `constant` keeps every number bit for bit."""

    ext: Any
    intrinsic: Any

    @classmethod
    def of(cls, alpha: float) -> "Mix":
        """A run's: 1 - alpha in float64, then float32, as the constant folding of `(1.0 - alpha) * r` gave it."""
        return cls(np.float32(1.0 - alpha), np.float32(alpha))

    @classmethod
    def of_float32(cls, alphas) -> "Mix":
        """A vmapped group's: 1 - alpha in float32, as its step computed it from the float32 alphas in `Hyper`
        (it differs from `of` in the last bit for some alphas, e.g. 0.058)."""
        a = np.asarray(alphas, np.float32)
        return cls(np.float32(1.0) - a, a)


class IntrinsicStep(NamedTuple):
    """The intrinsic part of one gradient step (`Agent.intrinsic_reward`)."""

    reward: jax.Array  # (B,) normalised reward of each transition, in [intrinsic_reward_low, intrinsic_reward_high]
    raw: jax.Array  # (B,) raw reward before the normaliser (MC: KL in nats)
    norm: Any  # the normaliser's history with this step's values pushed
    bounds: jax.Array  # (2,) the history's percentile bounds the reward was scaled with
    grads: Any  # of the models' loss
    untrained: Any  # the models' untrained part after this batch
    metrics: dict  # the reward's own metrics (its `metrics` names)


SQUASH_CORRECTIONS = ("exact", "epsilon")
SATURATED = 1e-6  # an action entry with 1 - tanh(u)^2 below this is saturated: `epsilon` caps its correction


def squash_log_det(u, correction: str = "exact"):
    """log |d tanh(u) / du| = log(1 - tanh(u)^2), summed over the last axis, as `correction` computes it:
    "exact" in a numerically stable form (unbounded as |u| grows); "epsilon" as stable-baselines3 and the
    thesis' (CleanRL-style) code do, log(1 - a^2 + 1e-6) of the float32 action a = tanh(u), which is never below
    log(1e-6) = -13.8 nats per entry, so saturated (bang-bang) actions cost less entropy."""
    if correction == "exact":
        return (2.0 * (jnp.log(2.0) - u - jax.nn.softplus(-2.0 * u))).sum(-1)
    if correction == "epsilon":
        a = jnp.tanh(u)
        return jnp.log(1.0 - jnp.square(a) + 1e-6).sum(-1)
    raise ValueError(f"unknown squash_correction {correction!r}: choose one of {SQUASH_CORRECTIONS}")


def gaussian_sample(mean, log_std, key):
    """Reparameterised Gaussian sample u (before the tanh) and its log-density, summed over the last axis."""
    u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
    logp = (-0.5 * jnp.square((u - mean) * jnp.exp(-log_std)) - log_std - 0.5 * jnp.log(2 * jnp.pi)).sum(-1)
    return u, logp


def tanh_gaussian_sample(mean, log_std, key, correction: str = "exact"):
    """Reparameterised tanh-squashed Gaussian sample and its log-probability (`squash_log_det`'s correction)."""
    u, logp = gaussian_sample(mean, log_std, key)
    return jnp.tanh(u), logp - squash_log_det(u, correction)


def saturation(u) -> dict[str, jax.Array]:
    """Diagnostics of the squash on pre-tanh samples u: the share of entries with 1 - tanh(u)^2 < 1e-6, and the
    mean (over samples) of exact minus epsilon log-probability (>= 0: how much `epsilon` lowers log pi)."""
    log_det = squash_log_det(u[..., None], "exact")  # per entry
    return {"saturated_share": (log_det < jnp.log(SATURATED)).mean(),
            "logp_gap": (squash_log_det(u, "epsilon") - squash_log_det(u, "exact")).mean()}


@dataclass(frozen=True)
class Agent:
    """The static description of the learner (sizes, hyperparameters); all state lives in TrainState."""

    obs_dim: int
    act_dim: int
    intrinsic_dim: int  # first intrinsic_dim entries of obs are the state the intrinsic reward sees
    cfg: Config

    @property
    def actor_net(self):
        return GaussianHead(self.cfg.hidden_sizes, self.act_dim, self.cfg.init, self.cfg.matmul_precision)

    @property
    def critic_net(self):
        return TwinCritic(self.cfg.hidden_sizes, self.cfg.init, self.cfg.matmul_precision)

    @property
    def intrinsic_net(self) -> IntrinsicReward:
        """The models of the config's `intrinsic` reward on the intrinsic state (whether this run trains them or
        not: see `use_intrinsic_models`)."""
        return intrinsic_rewards.get(self.cfg.intrinsic).from_config(self.cfg, self.intrinsic_dim, self.act_dim)

    @property
    def about(self) -> intrinsic_rewards.About:
        """What mcrl knows of the config's `intrinsic` reward: its title, metrics, raw value (`About`)."""
        return intrinsic_rewards.about(self.cfg.intrinsic)

    @property
    def own_metrics(self) -> tuple[str, ...] | None:
        """The metrics its intrinsic reward reports; None without intrinsic models (`mcrl.algo.metrics.reported`)."""
        return self.about.metrics if self.cfg.use_intrinsic_models else None

    @property
    def target_entropy(self) -> float:
        return -float(self.act_dim) if self.cfg.target_entropy is None else float(self.cfg.target_entropy)

    def _opt(self, lr):
        return optax.adam(lr)

    def init(self, seed: int) -> TrainState:
        # The SAC keys do not depend on whether intrinsic models exist, so intrinsic_alpha=0 reproduces SAC exactly.
        k_actor, k_critic, k_intrinsic, k_state = jax.random.split(jax.random.PRNGKey(seed), 4)
        obs, act = jnp.zeros((1, self.obs_dim)), jnp.zeros((1, self.act_dim))
        actor = self.actor_net.init(k_actor, obs)["params"]
        critic = self.critic_net.init(k_critic, obs, act)["params"]
        log_ent = jnp.log(jnp.float32(self.cfg.ent_coef_init))
        intrinsic = norm = None
        if self.cfg.use_intrinsic_models:
            params, untrained = self.intrinsic_net.init(k_intrinsic)
            intrinsic = IntrinsicModels(params, self._opt(self.cfg.intrinsic_lr).init(params), untrained)
            norm = normaliser.init(self.cfg.intrinsic_history_values)
        lr = self.cfg.learning_rate
        return TrainState(pi=Learned(actor, self._opt(lr).init(actor)), q=Learned(critic, self._opt(lr).init(critic)),
                          q_target=jax.tree.map(jnp.copy, critic), ent=Learned(log_ent, self._opt(lr).init(log_ent)),
                          intrinsic=intrinsic, norm=norm, key=k_state, grad_steps=jnp.int32(0))

    # ------------------------------------------------------------------ acting
    def act(self, actor_params, obs, key):
        mean, log_std = self.actor_net.apply({"params": actor_params}, obs)
        return jnp.tanh(gaussian_sample(mean, log_std, key)[0])

    def act_deterministic(self, actor_params, obs):
        return jnp.tanh(self.actor_net.apply({"params": actor_params}, obs)[0])

    # ------------------------------------------------------------------ the intrinsic reward
    def intrinsic_reward(self, state: TrainState, batch: Batch) -> IntrinsicStep:
        """The intrinsic reward's models on the batch: raw reward, gradients, untrained part, metrics, and the
        normalised reward of every transition (the normaliser's history pushed)."""
        s, s_next = batch.obs[:, : self.intrinsic_dim], batch.next_obs[:, : self.intrinsic_dim]
        models = state.intrinsic
        # a key of its own (Disagreement's masks), so that SAC's keys are the same with or without these models
        out = self.intrinsic_net.step(models.params, models.untrained, s, batch.action, s_next,
                                      jax.random.fold_in(state.key, INTRINSIC_KEY))
        history = out.raw if out.history is None else out.history
        reward, norm, bounds = self._scaled(state.norm, out.raw, history)
        return IntrinsicStep(reward, out.raw, norm, bounds, out.grads, out.untrained, out.metrics)

    def _scaled(self, norm, raw, history_values):
        """The percentile normaliser, shared by every intrinsic reward: `history_values` pushed into its history,
        then `raw` scaled into [intrinsic_reward_low, intrinsic_reward_high]. (reward, new history, (2,) bounds)."""
        cfg = self.cfg
        norm = normaliser.push(norm, history_values)
        reward, (lo, hi) = normaliser.reward(norm, raw, cfg.min_percentile, cfg.max_percentile,
                                             cfg.intrinsic_reward_low, cfg.intrinsic_reward_high)
        return reward, norm, jnp.stack([lo, hi])

    # ------------------------------------------------------------------ one gradient step
    def _adam(self, learned: Learned, grads, lr: float) -> Learned:
        upd, opt = self._opt(lr).update(grads, learned.opt, learned.params)
        return Learned(optax.apply_updates(learned.params, upd), opt)

    def update(self, state: TrainState, batch: Batch, hyper: Hyper | None = None,
               mix: Mix | None = None) -> tuple[TrainState, dict]:
        """One gradient step: the new state, and the step's metrics by name (`mcrl.algo.metrics`: those of the
        run's intrinsic reward, the normalised reward and the normaliser's bounds only with intrinsic models).
        The reward mix's weights: `mix` if given, else `hyper`'s intrinsic_alpha, else the config's."""
        cfg = self.cfg
        h = Hyper.of(cfg) if hyper is None else hyper
        key, k_pi, k_next = jax.random.split(state.key, 3)
        m: dict[str, jax.Array] = {}

        reward = batch.reward
        intrinsic, norm = state.intrinsic, state.norm
        if cfg.use_intrinsic_models:
            step = self.intrinsic_reward(state, batch)
            m.update(step.metrics)
            # Without `mix`, its weights from `hyper`'s alpha (the config's without `hyper`), 1 - alpha computed here:
            # in float64 on the host for the config's float (as `Mix.of`), in float32 in the step for a float32
            # `Hyper` (as `Mix.of_float32`), so every learner keeps the numbers of its step before issue 66.
            w = Mix(1.0 - h.intrinsic_alpha, h.intrinsic_alpha) if mix is None else mix
            reward = losses.reward_mix(batch.reward, step.reward, w.ext, w.intrinsic)
            learned = self._adam(Learned(intrinsic.params, intrinsic.opt), step.grads, h.intrinsic_lr)
            intrinsic = IntrinsicModels(learned.params, learned.opt, step.untrained)
            norm = step.norm
            m.update(mean_intrinsic_reward=step.reward.mean(), intrinsic_bound_low=step.bounds[0],
                     intrinsic_bound_high=step.bounds[1])

        ent_coef = jnp.exp(state.ent.params)

        # critics
        mean_n, log_std_n = self.actor_net.apply({"params": state.pi.params}, batch.next_obs)
        a_next, logp_next = tanh_gaussian_sample(mean_n, log_std_n, k_next, cfg.squash_correction)
        q_next = self.critic_net.apply({"params": state.q_target}, batch.next_obs, a_next).min(0)
        target = losses.critic_target(reward, batch.terminated, h.gamma, q_next, ent_coef, logp_next)

        def critic_loss_fn(params):
            q = self.critic_net.apply({"params": params}, batch.obs, batch.action)
            return losses.critic_loss(q, target), q.mean()

        (critic_loss, q_mean), g = jax.value_and_grad(critic_loss_fn, has_aux=True)(state.q.params)
        q = self._adam(state.q, g, h.learning_rate)

        # actor (against the updated critics, as stable-baselines3 does)
        def actor_loss_fn(params):
            mean, log_std = self.actor_net.apply({"params": params}, batch.obs)
            u, logp = gaussian_sample(mean, log_std, k_pi)
            logp = logp - squash_log_det(u, cfg.squash_correction)
            q_pi = self.critic_net.apply({"params": q.params}, batch.obs, jnp.tanh(u)).min(0)
            return losses.actor_loss(ent_coef, logp, q_pi), (logp, u)

        (actor_loss, (logp, u_pi)), g = jax.value_and_grad(actor_loss_fn, has_aux=True)(state.pi.params)
        pi = self._adam(state.pi, g, h.learning_rate)

        # entropy coefficient, from the same (pre-update) policy sample
        ent_loss, g = jax.value_and_grad(losses.entropy_loss)(state.ent.params, logp, self.target_entropy)
        ent = self._adam(state.ent, g, h.learning_rate)

        q_target = optax.incremental_update(q.params, state.q_target, h.tau)

        m.update(actor_loss=actor_loss, critic_loss=critic_loss, ent_coef=ent_coef, ent_coef_loss=ent_loss,
                 q_mean=q_mean, mean_ext_reward=batch.reward.mean(), mean_total_reward=reward.mean(),
                 **saturation(jax.lax.stop_gradient(u_pi)))
        return TrainState(pi=pi, q=q, q_target=q_target, ent=ent, intrinsic=intrinsic, norm=norm, key=key,
                          grad_steps=state.grad_steps + 1), m
