"""The device side of the training loop: the learner's state and diagnostics, and the compiled calls on them.

`Learner` holds one run's, updated by the plain jitted step; `mcrl.run.group.GroupLearner` holds a group's,
stacked along a leading run axis and updated by one vmapped step. The loop (`mcrl.run.trainer`) talks to both
the same way: `act` answers every member's observation, `update` takes every member's replay batch (None: that
member does not learn this step) and the intrinsic weight its schedule gives this step (`mcrl.algo.schedule`),
`read_metrics` gives each member's log-row means, and `state_of(i)` a member's own state when one of its files
needs it. The weight is an input of the compiled step (`sac.Mix`), put on the device only when it changes.
"""
from __future__ import annotations

import jax
import numpy as np

from mcrl.algo import diagnostics
from mcrl.algo.diagnostics import Diagnostics
from mcrl.algo.sac import Agent, Batch, Hyper, Mix, TrainState
from mcrl.config import Config


def train_step(agent: Agent, state: TrainState, diag: Diagnostics, batch: Batch, hyper: Hyper | None = None,
               mix: Mix | None = None):
    """One gradient step, its metrics added to the diagnostics on the device: what the loop compiles, one call."""
    state, metrics = agent.update(state, batch, hyper, mix)
    return state, diagnostics.add(diag, metrics)


def act_key(cfg: Config) -> jax.Array:
    """The run's exploration key; the step is folded in inside the compiled call (outside, fold_in alone costs a
    dispatch, ~0.15 ms, per step)."""
    return jax.random.fold_in(jax.random.PRNGKey(cfg.seed), 0x5EED)


class Learner:
    """One run's learner: its state and diagnostics, the jitted acting call and the jitted training step."""

    def __init__(self, agent: Agent, state: TrainState, diag: Diagnostics):
        self.agent, self.state, self.diag = agent, state, diag
        key = act_key(agent.cfg)
        self._act = jax.jit(lambda params, obs, t: agent.act(params, obs, jax.random.fold_in(key, t)))
        self._step = jax.jit(lambda s, d, b, w: train_step(agent, s, d, b, mix=w), donate_argnums=(0, 1))
        self._alpha, self._mix = None, None  # the weight last put on the device

    def act(self, obs: np.ndarray, t: int) -> np.ndarray:
        """(1, act_dim) policy actions for observations (1, obs_dim) at step `t`."""
        return np.asarray(self._act(self.state.pi.params, obs, t))

    def update(self, batches: list[Batch | None], alphas: list[float] | None = None) -> None:
        """One gradient step on the batch with intrinsic weight `alphas[0]` (None: the config's intrinsic_alpha)."""
        (batch,) = batches
        (alpha,) = alphas or [self.agent.cfg.intrinsic_alpha]
        if batch is not None:
            if alpha != self._alpha:  # a constant weight is transferred once
                self._alpha, self._mix = alpha, jax.device_put(Mix.of(alpha))
            self.state, self.diag = self._step(self.state, self.diag, batch, self._mix)

    def read_metrics(self) -> list[dict[str, float]]:
        metrics, self.diag = diagnostics.read(self.diag, self.agent.own_metrics)
        return [metrics]

    def state_of(self, i: int) -> tuple[TrainState, Diagnostics]:
        return self.state, self.diag
