"""Flax modules: MLP trunks, the tanh-Gaussian actor, twin critics and diagonal-Gaussian models.

Every layer is drawn by `init`: "torch" (the default) as torch's `nn.Linear` draws it, weights and biases
from U(-1/sqrt(fan_in), 1/sqrt(fan_in)), as in stable-baselines3 and the thesis' code; "flax" is Flax's own
default (LeCun-normal weights, variance 1/fan_in, zero biases). The choice matters: with Flax's default,
mcrl's critics drifted upward on FetchPush where stable-baselines3's settled (docs/studies/sb3-parity.md).

Every layer's matmul runs at `matmul_precision`: "float32" (the default) is a true float32 matmul, Flax's Dense
with `precision=HIGHEST` on its dot_general (and so on the backward pass's dots): JAX's default precision is
TF32 on NVIDIA GPUs (a 10-bit mantissa), and HIGHEST keeps a GPU run float32 like the CPU's (where it changes no
bit). "bfloat16" rounds the layer's input and kernel to bfloat16 and multiplies them with float32 accumulation
and a float32 result. Parameters stay float32 (same names, shapes and initialisation), and the bias add,
activations, log-std clamp and everything outside the matmuls stay float32.
"""
from __future__ import annotations

import math
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0  # as in stable-baselines3 and the thesis' MC models
INITS = ("torch", "flax")
PRECISIONS = ("float32", "bfloat16")


def _uniform(bound: float):
    def init(key, shape, dtype=jnp.float32):
        return jax.random.uniform(key, shape, dtype, -bound, bound)
    return init


def dense_inits(init: str, fan_in: int) -> dict:
    """Keyword arguments of `nn.Dense` for a layer with `fan_in` inputs under the named scheme."""
    if init == "torch":
        return {"kernel_init": nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform"),
                "bias_init": _uniform(1.0 / math.sqrt(fan_in))}
    if init == "flax":
        return {}
    raise ValueError(f"unknown init {init!r}: choose one of {INITS}")


def bf16_dot_general(lhs, rhs, dimension_numbers, precision=None, preferred_element_type=None):
    """`lax.dot_general` on bfloat16-rounded operands with float32 accumulation and a float32 result."""
    del preferred_element_type  # always float32
    return jax.lax.dot_general(lhs.astype(jnp.bfloat16), rhs.astype(jnp.bfloat16), dimension_numbers,
                               precision=precision, preferred_element_type=jnp.float32)


def dense_kwargs(init: str, fan_in: int, matmul_precision: str = "float32") -> dict:
    """Keyword arguments of `nn.Dense`: `dense_inits`, and the matmul for `matmul_precision`."""
    kwargs = dense_inits(init, fan_in)
    if matmul_precision == "bfloat16":
        kwargs["dot_general"] = bf16_dot_general
    elif matmul_precision == "float32":
        kwargs["precision"] = jax.lax.Precision.HIGHEST  # not TF32 on a GPU (see the module's docstring)
    else:
        raise ValueError(f"unknown matmul_precision {matmul_precision!r}: choose one of {PRECISIONS}")
    return kwargs


class MLP(nn.Module):
    hidden: Sequence[int]
    init_scheme: str = "torch"
    matmul_precision: str = "float32"

    @nn.compact
    def __call__(self, x):
        for h in self.hidden:
            x = nn.relu(nn.Dense(h, **dense_kwargs(self.init_scheme, x.shape[-1], self.matmul_precision))(x))
        return x


class GaussianHead(nn.Module):
    """MLP trunk with separate mean and log-std heads; log-std clamped to [-20, 2]."""

    hidden: Sequence[int]
    out_dim: int
    init_scheme: str = "torch"
    matmul_precision: str = "float32"

    @nn.compact
    def __call__(self, x):
        h = MLP(self.hidden, self.init_scheme, self.matmul_precision)(x)
        inits = dense_kwargs(self.init_scheme, h.shape[-1], self.matmul_precision)
        mean = nn.Dense(self.out_dim, name="mean", **inits)(h)
        log_std = jnp.clip(nn.Dense(self.out_dim, name="log_std", **inits)(h), LOG_STD_MIN, LOG_STD_MAX)
        return mean, log_std


class TwinCritic(nn.Module):
    """Two independent Q-networks evaluated as one batched computation; returns (2, batch)."""

    hidden: Sequence[int]
    init_scheme: str = "torch"
    matmul_precision: str = "float32"

    @nn.compact
    def __call__(self, obs, action):
        x = jnp.concatenate([obs, action], -1)
        ensemble = nn.vmap(MLP, variable_axes={"params": 0}, split_rngs={"params": True},
                           in_axes=None, out_axes=0, axis_size=2)
        h = ensemble(self.hidden, self.init_scheme, self.matmul_precision)(x)
        q = nn.vmap(nn.Dense, variable_axes={"params": 0}, split_rngs={"params": True},
                    in_axes=0, out_axes=0, axis_size=2)(
            1, **dense_kwargs(self.init_scheme, h.shape[-1], self.matmul_precision))(h)
        return q[..., 0]


class TransitionModel(nn.Module):
    """p(s' | s, a): diagonal Gaussian over the next MC state."""

    hidden: Sequence[int]
    state_dim: int
    init_scheme: str = "torch"
    matmul_precision: str = "float32"

    @nn.compact
    def __call__(self, s, a):
        x = jnp.concatenate([s, a], -1)
        return GaussianHead(self.hidden, self.state_dim, self.init_scheme, self.matmul_precision)(x)


class ActionModel(nn.Module):
    """p(s' | a): diagonal Gaussian over the next MC state from the action alone."""

    hidden: Sequence[int]
    state_dim: int
    init_scheme: str = "torch"
    matmul_precision: str = "float32"

    @nn.compact
    def __call__(self, a):
        return GaussianHead(self.hidden, self.state_dim, self.init_scheme, self.matmul_precision)(a)


ACTIVATIONS = {"relu": nn.relu, "elu": nn.elu,
               # tf.nn.leaky_relu's default slope, which the RND and Disagreement papers' code used
               "leaky_relu": lambda x: nn.leaky_relu(x, 0.2)}


class Stack(nn.Module):
    """Dense layers of `widths`, each followed by its activation in `acts` (None: linear), e.g. the intrinsic
    rewards' networks (`mcrl.algo.rnd`, `mcrl.algo.icm`), initialised and multiplied like every network here."""

    widths: Sequence[int]
    acts: Sequence[str | None]
    init_scheme: str = "torch"
    matmul_precision: str = "float32"

    @nn.compact
    def __call__(self, x):
        for width, act in zip(self.widths, self.acts, strict=True):
            x = nn.Dense(width, **dense_kwargs(self.init_scheme, x.shape[-1], self.matmul_precision))(x)
            x = x if act is None else ACTIVATIONS[act](x)
        return x
