"""Random Network Distillation (RND): Burda, Edwards, Storkey and Klimov (2018), "Exploration by Random Network
Distillation", arXiv:1810.12894.

A fixed, randomly initialised target network f maps the next state to an embedding; a predictor f^ is trained to
reproduce it. The reward of a transition is the predictor's error on its next state,

    r = mean_k (f^(x')_k - f(x')_k)^2,   x' = clip((s' - mu) / sigma, -5, 5),

high where the predictor has seen few similar states. mu and sigma are the running mean and standard deviation of
the next states (the paper's observation normalisation of the networks' input, with its clip to [-5, 5]), updated
with every batch before it is used. The predictor minimises the same error, averaged over the batch.

From the paper's Atari networks (its code, policies/cnn_gru_policy_dynamics.py) to state vectors: each of the
target's three conv layers becomes a Dense layer of `width` with the same leaky ReLU (slope 0.2), followed by the
linear embedding of 512; the predictor has the same three, then two more layers of `width` with ReLU (the paper's
predictor is deeper than its target), then the linear 512. The reward is the mean over the 512 outputs, as the
code computes it (the paper writes the squared norm: the same up to a constant, which the percentile normaliser
removes). The paper's reward normalisation (by a running std of intrinsic returns) is replaced by mcrl's percentile
normaliser, shared by every intrinsic reward.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp

from mcrl.algo.intrinsic import ABOUT, About, Raw, Sizes
from mcrl.algo.moments import moments_init, moments_update, standardise
from mcrl.algo.networks import Stack

EMBEDDING = 512  # the paper's output size of both networks
CLIP = 5.0  # normalised inputs are clipped to [-5, 5]


@dataclass(frozen=True)
class RND(Sizes):
    """RND's networks for states of `state_dim` (`action_dim` unused: RND looks at the next state alone); params
    {"predictor"}, untrained {"target", "obs"}."""

    about: ClassVar[About] = ABOUT["rnd"]

    @property
    def target(self) -> Stack:
        return Stack((self.width,) * 3 + (EMBEDDING,), ("leaky_relu",) * 3 + (None,), self.init_scheme,
                     self.matmul_precision)

    @property
    def predictor(self) -> Stack:
        return Stack((self.width,) * 5 + (EMBEDDING,), ("leaky_relu",) * 3 + ("relu",) * 2 + (None,),
                     self.init_scheme, self.matmul_precision)

    def init(self, key):
        k_target, k_predictor = jax.random.split(key)
        x = jnp.zeros((1, self.state_dim))
        untrained = {"target": self.target.init(k_target, x)["params"], "obs": moments_init(self.state_dim)}
        return {"predictor": self.predictor.init(k_predictor, x)["params"]}, untrained

    def _errors(self, params, untrained, s_next):
        x = standardise(untrained["obs"], s_next, CLIP)
        y = jax.lax.stop_gradient(self.target.apply({"params": untrained["target"]}, x))
        return jnp.square(self.predictor.apply({"params": params["predictor"]}, x) - y).mean(-1)

    def reward(self, params, untrained, s, a, s_next):
        return self._errors(params, untrained, s_next)

    def step(self, params, untrained, s, a, s_next, key=None) -> Raw:
        untrained = {**untrained, "obs": moments_update(untrained["obs"], s_next)}

        def loss(p):
            err = self._errors(p, untrained, s_next)
            return err.mean(), err

        (value, err), grads = jax.value_and_grad(loss, has_aux=True)(params)
        return Raw(err, grads, untrained, self.generic_metrics(value, err))
