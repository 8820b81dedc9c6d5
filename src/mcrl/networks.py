"""Flax modules: MLP trunks, the tanh-Gaussian actor, twin critics and diagonal-Gaussian models."""
from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax.numpy as jnp

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0  # as in stable-baselines3 and the thesis' MC models


class MLP(nn.Module):
    hidden: Sequence[int]

    @nn.compact
    def __call__(self, x):
        for h in self.hidden:
            x = nn.relu(nn.Dense(h)(x))
        return x


class GaussianHead(nn.Module):
    """MLP trunk with separate mean and log-std heads; log-std clamped to [-20, 2]."""

    hidden: Sequence[int]
    out_dim: int

    @nn.compact
    def __call__(self, x):
        h = MLP(self.hidden)(x)
        mean = nn.Dense(self.out_dim, name="mean")(h)
        log_std = jnp.clip(nn.Dense(self.out_dim, name="log_std")(h), LOG_STD_MIN, LOG_STD_MAX)
        return mean, log_std


class TwinCritic(nn.Module):
    """Two independent Q-networks evaluated as one batched computation; returns (2, batch)."""

    hidden: Sequence[int]

    @nn.compact
    def __call__(self, obs, action):
        x = jnp.concatenate([obs, action], -1)
        ensemble = nn.vmap(MLP, variable_axes={"params": 0}, split_rngs={"params": True},
                           in_axes=None, out_axes=0, axis_size=2)
        h = ensemble(self.hidden)(x)
        q = nn.vmap(nn.Dense, variable_axes={"params": 0}, split_rngs={"params": True},
                    in_axes=0, out_axes=0, axis_size=2)(1)(h)
        return q[..., 0]


class TransitionModel(nn.Module):
    """p(s' | s, a): diagonal Gaussian over the next MC state."""

    hidden: Sequence[int]
    state_dim: int

    @nn.compact
    def __call__(self, s, a):
        return GaussianHead(self.hidden, self.state_dim)(jnp.concatenate([s, a], -1))


class ActionModel(nn.Module):
    """p(s' | a): diagonal Gaussian over the next MC state from the action alone."""

    hidden: Sequence[int]
    state_dim: int

    @nn.compact
    def __call__(self, a):
        return GaussianHead(self.hidden, self.state_dim)(a)
