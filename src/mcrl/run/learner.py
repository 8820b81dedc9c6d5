"""The device side of the training loop: the learner's state and diagnostics, and the compiled calls on them.

`Learner` holds one run's, updated by the plain jitted step; `mcrl.run.group.GroupLearner` holds a group's,
stacked along a leading run axis and updated by one vmapped step. The loop (`mcrl.run.trainer`) talks to both
the same way: `act` answers every member's observation, `update` takes every member's replay batch (None: that
member does not learn this step), `read_metrics` gives each member's log-row means, and `state_of(i)` a
member's own state when one of its files needs it.
"""
from __future__ import annotations

import jax
import numpy as np

from mcrl.algo import diagnostics
from mcrl.algo.diagnostics import Diagnostics
from mcrl.algo.sac import Agent, Batch, Hyper, TrainState
from mcrl.config import Config


def train_step(agent: Agent, state: TrainState, diag: Diagnostics, batch: Batch, hyper: Hyper | None = None):
    """One gradient step, its metrics added to the diagnostics on the device: what the loop compiles, one call."""
    state, metrics = agent.update(state, batch, hyper)
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
        self._step = jax.jit(lambda s, d, b: train_step(agent, s, d, b), donate_argnums=(0, 1))

    def act(self, obs: np.ndarray, t: int) -> np.ndarray:
        """(1, act_dim) policy actions for observations (1, obs_dim) at step `t`."""
        return np.asarray(self._act(self.state.pi.params, obs, t))

    def update(self, batches: list[Batch | None]) -> None:
        (batch,) = batches
        if batch is not None:
            self.state, self.diag = self._step(self.state, self.diag, batch)

    def read_metrics(self) -> list[dict[str, float]]:
        metrics, self.diag = diagnostics.read(self.diag, self.agent.own_metrics)
        return [metrics]

    def state_of(self, i: int) -> tuple[TrainState, Diagnostics]:
        return self.state, self.diag
