"""Ensemble disagreement: Pathak, Gandhi and Gupta (2019), "Self-Supervised Exploration via Disagreement", ICML,
arXiv:1906.04161.

An ensemble of K = 5 forward models f_1..f_K, each trained to predict the next state's features from the state's
features and the action; the reward of a transition is the variance of their predictions,

    r = mean_d Var_k [f_k(phi(s), a)_d],

large where the models have not been trained (they extrapolate differently) and shrinking where they agree, and,
unlike a prediction error, not kept high by noise the models cannot learn. Each model minimises the squared error
of its prediction (mean over dimensions) on the batch; as in the paper's code (exploration-by-disagreement,
dynamics.py `get_loss_partial`), each model's per-transition losses go through dropout with keep probability 0.8,
so every model trains on its own random ~80% of each batch.

From the paper's code to state vectors: its features phi are a fixed random network of the normalised frame
(random features); for a state vector the normalised state itself is the feature: phi(s) = (s - mu) / sigma with
the running mean and standard deviation of the next states (updated with every batch before it is used; the code
normalised with statistics of a random agent). Each forward model is the code's: a Dense layer, four residual
blocks of two Dense layers, and a linear output, the action concatenated to every layer's input, leaky ReLU
(slope 0.2), its width `width` (the code: 512). The variance is averaged over dimensions as the code does (the
paper sums them: the same up to a constant, which the percentile normaliser removes).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp

from mcrl.algo.intrinsic import ABOUT, About, Raw, Sizes
from mcrl.algo.moments import moments_init, moments_update, standardise
from mcrl.algo.networks import ACTIVATIONS, dense_kwargs

MEMBERS = 5  # the paper's ensemble size (its code's num_dynamics)
KEEP = 0.8  # keep probability of the dropout on each model's per-transition losses
BLOCKS = 4  # residual blocks of a forward model


class ForwardModel(nn.Module):
    """f(phi, a): the paper's code's residual forward model, the action fed to every layer."""

    width: int
    out_dim: int
    init_scheme: str = "torch"
    matmul_precision: str = "float32"

    @nn.compact
    def __call__(self, x, a):
        act = ACTIVATIONS["leaky_relu"]

        def dense(n, h):
            h = jnp.concatenate([h, a], -1)
            return nn.Dense(n, **dense_kwargs(self.init_scheme, h.shape[-1], self.matmul_precision))(h)

        h = act(dense(self.width, x))
        for _ in range(BLOCKS):
            h = h + dense(self.width, act(dense(self.width, h)))
        return dense(self.out_dim, h)


class Ensemble(ForwardModel):
    """MEMBERS independent forward models of these sizes, evaluated as one batched computation; returns
    (MEMBERS, batch, out)."""

    @nn.compact
    def __call__(self, x, a):
        models = nn.vmap(ForwardModel, variable_axes={"params": 0}, split_rngs={"params": True}, in_axes=None,
                         out_axes=0, axis_size=MEMBERS)
        return models(self.width, self.out_dim, self.init_scheme, self.matmul_precision)(x, a)


@dataclass(frozen=True)
class Disagreement(Sizes):
    """The ensemble for states of `state_dim` and actions of `action_dim`; params {"ensemble"}, untrained {"obs"}."""

    about: ClassVar[About] = ABOUT["disagreement"]

    @property
    def ensemble(self) -> Ensemble:
        return Ensemble(self.width, self.state_dim, self.init_scheme, self.matmul_precision)

    def init(self, key):
        s, a = jnp.zeros((1, self.state_dim)), jnp.zeros((1, self.action_dim))
        return {"ensemble": self.ensemble.init(key, s, a)["params"]}, {"obs": moments_init(self.state_dim)}

    def _predict(self, params, untrained, s, a):
        return self.ensemble.apply({"params": params["ensemble"]}, standardise(untrained["obs"], s), a)

    def reward(self, params, untrained, s, a, s_next):
        return self._predict(params, untrained, s, a).var(0).mean(-1)

    def step(self, params, untrained, s, a, s_next, key) -> Raw:
        untrained = {**untrained, "obs": moments_update(untrained["obs"], s_next)}
        target = standardise(untrained["obs"], s_next)
        keep = jax.random.bernoulli(key, KEEP, (MEMBERS, s.shape[0])).astype(jnp.float32) / KEEP

        def loss(p):
            pred = self._predict(p, untrained, s, a)  # (MEMBERS, B, d)
            per_model = (jnp.square(pred - target[None]).mean(-1) * keep).mean(-1)
            return per_model.sum(), pred

        (value, pred), grads = jax.value_and_grad(loss, has_aux=True)(params)
        raw = pred.var(0).mean(-1)
        return Raw(raw, grads, untrained, self.generic_metrics(value, raw))
