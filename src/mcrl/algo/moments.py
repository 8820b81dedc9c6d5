"""Running mean and variance of states, as `baselines`' RunningMeanStd keeps them: RND's and Disagreement's
observation normalisation (their models' untrained state)."""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["Moments", "moments_init", "moments_update", "standardise"]


class Moments(NamedTuple):
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
