"""The intrinsic rewards beside MC: one interface, chosen by the config key `intrinsic` (docs/intrinsic.md).

`mc` is the thesis' MC reward (`mcrl.algo.mc`, its own path in `mcrl.algo.sac`, kept bit for bit as it was). The
others each live in their own module (`mcrl.algo.rnd`, `.icm`, `.disagreement`) as a frozen dataclass of
`Sizes` (state_dim, action_dim, width, init_scheme, matmul_precision), with the same small pure interface:

    models.init(key) -> (params, untrained)
        `params` are trained by Adam (`mc_lr`, one step per gradient step); `untrained` is what no gradient trains
        (RND's random target network, the running state statistics of RND and Disagreement; {} for ICM).
    models.step(params, untrained, s, a, s_next, key) -> Raw
        on a replay batch: the raw reward of every transition, the models' loss and its gradients, and `untrained`
        after this batch. The reward is computed with the parameters before their update (like MC's).
    models.reward(params, untrained, s, a, s_next) -> (B,)
        the raw reward alone, nothing updated (to look at transitions the models have not trained on).

All four see the same inputs: the MC state (`mc_state`: the observation part by default) of the sampled batch
after HER relabelling, its action and next state, every gradient step, inside the one jitted update; their raw
values go through the same percentile normaliser into [mc_reward_low, mc_reward_high] and are mixed with weight
mc_alpha (`mcrl.algo.sac.Agent.update`). `key` is used by Disagreement only (its per-member sample masks).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["Moments", "Raw", "Sizes", "moments_init", "moments_update", "standardise"]


@dataclass(frozen=True)
class Sizes:
    """What every intrinsic reward's models are built from (`mcrl.algo.sac.Agent.intrinsic_net`)."""

    state_dim: int
    action_dim: int
    width: int = 256  # hidden layers (the widest of mc_hidden_sizes)
    init_scheme: str = "torch"
    matmul_precision: str = "float32"


class Raw(NamedTuple):
    """One batch through an intrinsic reward's models (before the percentile normaliser)."""

    raw: jax.Array  # (B,) raw reward of each transition
    loss: jax.Array  # scalar: what the models minimise
    grads: Any  # of `loss` with respect to the trained parameters
    untrained: Any  # the part no gradient trains, after this batch


class Moments(NamedTuple):
    """Running mean and variance of states (per dimension), as `baselines`' RunningMeanStd keeps them."""

    count: jax.Array  # float32 () states seen
    mean: jax.Array  # (d,)
    var: jax.Array  # (d,) population variance


def moments_init(dim: int) -> Moments:
    return Moments(jnp.float32(0), jnp.zeros(dim, jnp.float32), jnp.ones(dim, jnp.float32))


def moments_update(m: Moments, x: jax.Array) -> Moments:
    """`m` with the rows of `x` (B, d) added (Chan et al.'s parallel update; the first batch sets them)."""
    n = jnp.float32(x.shape[0])
    b_mean, b_var = x.mean(0), x.var(0)
    total = m.count + n
    delta = b_mean - m.mean
    mean = m.mean + delta * (n / total)
    m2 = m.var * m.count + b_var * n + jnp.square(delta) * (m.count * n / total)
    return Moments(total, mean, m2 / total)


def standardise(m: Moments, x: jax.Array, clip: float | None = None) -> jax.Array:
    """(x - mean) / std per dimension (a constant dimension stays at 0), clipped to [-clip, clip] if given."""
    z = (x - m.mean) * jax.lax.rsqrt(jnp.maximum(m.var, 1e-8))
    return z if clip is None else jnp.clip(z, -clip, clip)

