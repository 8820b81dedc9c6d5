"""Intrinsic Curiosity Module (ICM): Pathak, Agrawal, Efros and Darrell (2017), "Curiosity-driven Exploration by
Self-supervised Prediction", ICML, arXiv:1705.05363.

An encoder phi maps states to features; an inverse model predicts the action from (phi(s), phi(s')), which shapes
the features to what the agent can influence; a forward model predicts phi(s') from (phi(s), a). The reward of a
transition is the forward model's error in the feature space,

    r = 1/2 ||phi^(s') - phi(s')||^2,   phi^(s') = forward(phi(s), a),

and all three networks minimise (1 - beta) L_I + beta L_F with the paper's beta = 0.2 (L_F: the same error, L_I:
the inverse model's loss, both averaged over the batch). As in the paper's code (noreward-rl, src/model.py), the
forward loss also trains the encoder (no stop-gradient on phi(s')). The paper's scale eta of the reward is left
out: the percentile normaliser removes any constant factor.

From the paper's networks to state vectors: its encoder's four conv layers (ELU) become four Dense layers with ELU,
three of `width` and the last of the paper's feature size, 288; the inverse and forward models are as in the
paper: one hidden layer of `width` (the paper: 256) with ReLU, then linear. The paper's actions are discrete
(cross-entropy loss); mcrl's are continuous in [-1, 1], so L_I = 1/2 ||a^ - a||^2, the negative log-likelihood of
the action under a unit-variance Gaussian around the prediction, up to a constant.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp

from mcrl.algo.intrinsic import ABOUT, About, Raw, Sizes
from mcrl.algo.networks import Stack

FEATURES = 288  # the paper's feature size (4 stride-2 convs of 32 filters on 42x42 frames: 3 x 3 x 32)
BETA = 0.2  # the paper's weight of the forward loss against the inverse loss


@dataclass(frozen=True)
class ICM(Sizes):
    """ICM's networks for states of `state_dim` and actions of `action_dim`; params {"encoder", "inverse",
    "forward"}, nothing untrained."""

    about: ClassVar[About] = ABOUT["icm"]

    @property
    def encoder(self) -> Stack:
        return Stack((self.width,) * 3 + (FEATURES,), ("elu",) * 4, self.init_scheme, self.matmul_precision)

    @property
    def inverse(self) -> Stack:
        return Stack((self.width, self.action_dim), ("relu", None), self.init_scheme, self.matmul_precision)

    @property
    def forward(self) -> Stack:
        return Stack((self.width, FEATURES), ("relu", None), self.init_scheme, self.matmul_precision)

    def init(self, key):
        k_enc, k_inv, k_fwd = jax.random.split(key, 3)
        params = {"encoder": self.encoder.init(k_enc, jnp.zeros((1, self.state_dim)))["params"],
                  "inverse": self.inverse.init(k_inv, jnp.zeros((1, 2 * FEATURES)))["params"],
                  "forward": self.forward.init(k_fwd, jnp.zeros((1, FEATURES + self.action_dim)))["params"]}
        return params, {}

    def _losses(self, params, s, a, s_next):
        """Per-transition forward loss (the reward) and inverse loss, (B,) each."""
        phi_both = self.encoder.apply({"params": params["encoder"]}, jnp.concatenate([s, s_next]))  # one pass
        phi, phi_next = jnp.split(phi_both, 2)
        a_hat = self.inverse.apply({"params": params["inverse"]}, jnp.concatenate([phi, phi_next], -1))
        phi_hat = self.forward.apply({"params": params["forward"]}, jnp.concatenate([phi, a], -1))
        forward = 0.5 * jnp.square(phi_hat - phi_next).sum(-1)
        inverse = 0.5 * jnp.square(a_hat - a).sum(-1)
        return forward, inverse

    def reward(self, params, untrained, s, a, s_next):
        return self._losses(params, s, a, s_next)[0]

    def step(self, params, untrained, s, a, s_next, key=None) -> Raw:
        def loss(p):
            forward, inverse = self._losses(p, s, a, s_next)
            return (1.0 - BETA) * inverse.mean() + BETA * forward.mean(), forward

        (value, forward), grads = jax.value_and_grad(loss, has_aux=True)(params)
        return Raw(forward, grads, untrained, self.generic_metrics(value, forward))
