"""The step before issue 66's losses refactor, a frozen reference: never edit.

`reference_update(agent, state, batch, hyper, mix)` is a verbatim copy of the body of `mcrl.algo.sac.Agent.update`
at commit 5e30b6e (`self` renamed `agent`; `agent._adam` copied here as `_adam`, so that the reference does not move
if the agent's helper does). tests/test_losses.py checks that today's `Agent.update`, which composes the functions
of `mcrl.algo.losses`, gives these numbers bit for bit."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from mcrl.algo.sac import (Batch, Hyper, IntrinsicModels, Learned, Mix, TrainState, gaussian_sample, saturation,
                           squash_log_det, tanh_gaussian_sample)

__all__ = ["reference_update"]


def _adam(agent, learned: Learned, grads, lr: float) -> Learned:
    upd, opt = optax.adam(lr).update(grads, learned.opt, learned.params)
    return Learned(optax.apply_updates(learned.params, upd), opt)


def reference_update(agent, state: TrainState, batch: Batch, hyper: Hyper | None = None,
                     mix: Mix | None = None) -> tuple[TrainState, dict]:
    """One gradient step: the new state, and the step's metrics by name (`mcrl.algo.metrics`: those of the
    run's intrinsic reward, the normalised reward and the normaliser's bounds only with intrinsic models).
    The reward mix's weights: `mix` if given, else `hyper`'s intrinsic_alpha, else the config's."""
    cfg = agent.cfg
    h = Hyper.of(cfg) if hyper is None else hyper
    key, k_pi, k_next = jax.random.split(state.key, 3)
    m: dict[str, jax.Array] = {}

    reward = batch.reward
    intrinsic, norm = state.intrinsic, state.norm
    if cfg.use_intrinsic_models:
        step = agent.intrinsic_reward(state, batch)
        m.update(step.metrics)
        if mix is not None:  # the weights as data: exactly r_ext where alpha is 0 (a schedule's end, SAC runs)
            reward = jnp.where(mix.intrinsic > 0, mix.ext * batch.reward + mix.intrinsic * step.reward, reward)
        elif hyper is not None:  # alpha as data: exactly r_ext where it is 0 (a SAC run of a vmapped group)
            reward = jnp.where(h.intrinsic_alpha > 0,
                               (1.0 - h.intrinsic_alpha) * batch.reward + h.intrinsic_alpha * step.reward, reward)
        elif cfg.intrinsic_alpha > 0:
            reward = (1.0 - cfg.intrinsic_alpha) * batch.reward + cfg.intrinsic_alpha * step.reward
        learned = _adam(agent, Learned(intrinsic.params, intrinsic.opt), step.grads, h.intrinsic_lr)
        intrinsic = IntrinsicModels(learned.params, learned.opt, step.untrained)
        norm = step.norm
        m.update(mean_intrinsic_reward=step.reward.mean(), intrinsic_bound_low=step.bounds[0],
                 intrinsic_bound_high=step.bounds[1])

    ent_coef = jnp.exp(state.ent.params)

    # critics
    mean_n, log_std_n = agent.actor_net.apply({"params": state.pi.params}, batch.next_obs)
    a_next, logp_next = tanh_gaussian_sample(mean_n, log_std_n, k_next, cfg.squash_correction)
    q_next = agent.critic_net.apply({"params": state.q_target}, batch.next_obs, a_next).min(0)
    target = reward + (1.0 - batch.terminated) * h.gamma * (q_next - ent_coef * logp_next)
    target = jax.lax.stop_gradient(target)

    def critic_loss_fn(params):
        q = agent.critic_net.apply({"params": params}, batch.obs, batch.action)
        return 0.5 * jnp.square(q - target[None]).mean(-1).sum(), q.mean()

    (critic_loss, q_mean), g = jax.value_and_grad(critic_loss_fn, has_aux=True)(state.q.params)
    q = _adam(agent, state.q, g, h.learning_rate)

    # actor (against the updated critics, as stable-baselines3 does)
    def actor_loss_fn(params):
        mean, log_std = agent.actor_net.apply({"params": params}, batch.obs)
        u, logp = gaussian_sample(mean, log_std, k_pi)
        logp = logp - squash_log_det(u, cfg.squash_correction)
        q_pi = agent.critic_net.apply({"params": q.params}, batch.obs, jnp.tanh(u)).min(0)
        return (ent_coef * logp - q_pi).mean(), (logp, u)

    (actor_loss, (logp, u_pi)), g = jax.value_and_grad(actor_loss_fn, has_aux=True)(state.pi.params)
    pi = _adam(agent, state.pi, g, h.learning_rate)

    # entropy coefficient, from the same (pre-update) policy sample
    ent_target = jax.lax.stop_gradient(logp + agent.target_entropy)
    ent_loss, g = jax.value_and_grad(lambda le: -(le * ent_target).mean())(state.ent.params)
    ent = _adam(agent, state.ent, g, h.learning_rate)

    q_target = optax.incremental_update(q.params, state.q_target, h.tau)

    m.update(actor_loss=actor_loss, critic_loss=critic_loss, ent_coef=ent_coef, ent_coef_loss=ent_loss,
             q_mean=q_mean, mean_ext_reward=batch.reward.mean(), mean_total_reward=reward.mean(),
             **saturation(jax.lax.stop_gradient(u_pi)))
    return TrainState(pi=pi, q=q, q_target=q_target, ent=ent, intrinsic=intrinsic, norm=norm, key=key,
                      grad_steps=state.grad_steps + 1), m
