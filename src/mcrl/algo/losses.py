"""SAC's losses as pure functions of arrays, which `mcrl.algo.sac.Agent.update` composes into its one jitted step.

    reward_mix(r_ext, r_int, w_ext, w_int)                 (1 - alpha) r_ext + alpha r_int, exactly r_ext at alpha 0
    critic_target(reward, terminated, gamma, q_next, ent_coef, logp_next)   the clipped double-Q soft target
    critic_loss(q, target)                                 the twin critics' squared error against the target
    actor_loss(ent_coef, logp, q_pi)                       E[alpha log pi(a|s) - min Q(s, a)], a ~ pi
    entropy_loss(log_ent_coef, logp, target_entropy)       stable-baselines3's loss of log alpha

The networks are not here: the step applies the actor and the critics and hands their outputs (Q-values,
log-probabilities) to these functions, so each is checked alone on numbers written by hand (tests/test_losses.py).
The conventions are stable-baselines3's (sac.py, `SAC.train`), which mcrl's SAC matches number for number
(tests/test_sb3_golden.py).

The intrinsic reward's models have their losses with their own models, as pure functions of parameters and arrays
behind one entry point, `IntrinsicReward.step(params, untrained, s, a, s_next, key)` (`mcrl.algo.intrinsic`), which
returns the gradients of the models' loss with the raw reward: MC's is `mcrl.algo.mc.MCModels.loss` (the two
models' NLL), RND's, ICM's and Disagreement's are in their `step` (`mcrl.algo.rnd`, `icm`, `disagreement`).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["actor_loss", "critic_loss", "critic_target", "entropy_loss", "reward_mix"]


def reward_mix(r_ext, r_int, w_ext, w_int):
    """The reward the critics learn: w_ext * r_ext + w_int * r_int, with w_int = alpha and w_ext = 1 - alpha as the
    caller computed it (`sac.Mix`: which rounding of 1 - alpha keeps each learner's numbers), and exactly r_ext where
    w_int is 0, whatever r_int is: a SAC run (alpha 0, or a schedule's end) learns the extrinsic reward alone, and
    a vmapped group's SAC run its own SAC numbers. The weights are scalars or, inside jax.vmap, per run."""
    return jnp.where(w_int > 0, w_ext * r_ext + w_int * r_int, r_ext)


def critic_target(reward, terminated, gamma, q_next, ent_coef, logp_next):
    """The soft Bellman target of each transition, y = r + (1 - terminated) gamma (min_i Q'_i(s', a') - alpha log
    pi(a'|s')), a' ~ pi(.|s'): `q_next` is the smaller of the two target critics' values (clipped double-Q, against
    the overestimation of a max over noisy estimates), `logp_next` the log-probability of a' (the soft part: the
    next state's entropy is worth its value). Only a termination cuts the bootstrap (a time limit is no
    termination). No gradient flows through the target: the critics regress on it."""
    return jax.lax.stop_gradient(reward + (1.0 - terminated) * gamma * (q_next - ent_coef * logp_next))


def critic_loss(q, target):
    """0.5 * the mean squared error of each critic against the target, summed over the critics: `q` (n_critics, B),
    `target` (B,). The sum (not the mean) over critics is stable-baselines3's, so each critic's gradient is its
    own MSE's, whatever the number of critics."""
    return 0.5 * jnp.square(q - target[None]).mean(-1).sum()


def actor_loss(ent_coef, logp, q_pi):
    """The policy's loss, mean over the batch of alpha log pi(a|s) - min_i Q_i(s, a) for a reparameterised a ~ pi:
    `logp` (B,) and `q_pi` (B,) (the smaller critic's value: the same pessimism as the target) are functions of
    the actor's parameters through the sample. Minimising it raises Q and the entropy, at the price alpha."""
    return (ent_coef * logp - q_pi).mean()


def entropy_loss(log_ent_coef, logp, target_entropy):
    """The loss of log alpha, -mean(log alpha * (log pi(a|s) + target_entropy)) as stable-baselines3 writes it, with
    the policy's log-probabilities `logp` (B,) taken as data. Its gradient, -mean(logp + target_entropy), is
    negative when the entropy -logp is below the target, so gradient descent raises alpha then (and lowers it when
    the policy is more random than the target asks). Optimising log alpha keeps alpha positive."""
    return -(log_ent_coef * jax.lax.stop_gradient(logp + target_entropy)).mean()
