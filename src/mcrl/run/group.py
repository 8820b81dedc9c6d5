"""A group of runs trained as one computation: one gradient step `jax.vmap`-ed over the runs, jitted once.

Runs whose configs agree in everything but `PER_RUN_KEYS` have learner states of one shape; `GroupLearner`
stacks them along a leading run axis. The loop is the single run's (`mcrl.run.trainer.run_loop`): every run
acts, steps its own environment, stores its transition in its own replay buffer and samples its own batch (host
side, with its own RNG, in the same order as alone), then one compiled call updates all of them. The per-run
scalars (intrinsic_alpha, gamma, tau, learning rates) are data (`sac.Hyper`), so a grid over alpha compiles once;
so is each run's intrinsic weight of the step (`sac.Mix`), which its own schedule gives (`mcrl.algo.schedule`).

SAC runs (intrinsic_alpha = 0, no intrinsic models) in a group with SAC-MC runs carry the group's intrinsic
models (MC's, or those of the group's `intrinsic`, which all its runs share) as ballast so that the shapes agree:
their reward is 1 * r + 0 * r_int = r exactly, and the ballast never reaches their files (their checkpoints,
metrics and config are a SAC run's; a resumed group re-draws it). Each run writes
exactly what `mcrl train` writes, so `mcrl eval`, `render`, `report` and `--resume` see an ordinary run, and a run
started in a group may finish alone.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from mcrl.algo import diagnostics
from mcrl.algo.diagnostics import Diagnostics
from mcrl.algo.metrics import reported
from mcrl.algo.sac import Agent, Batch, Hyper, Mix, TrainState
from mcrl.config import Config
from mcrl.errors import MCRLError
from mcrl.run.learner import act_key, train_step
from mcrl.run.member import Member
from mcrl.run.trainer import VideoStep, train_runs

# Config keys that may differ inside a group (per-run data or host-side only); all others must agree.
PER_RUN_KEYS = ("seed", "intrinsic_alpha", "intrinsic_models", "learning_rate", "intrinsic_lr", "gamma", "tau",
                "preset", "out_dir", "intrinsic_schedule", "intrinsic_alpha_end", "intrinsic_schedule_steps",
                "intrinsic_success_window")


def group_key(cfg: Config) -> str:
    """Runs with equal keys can train as one group."""
    d = cfg.to_dict()
    for k in PER_RUN_KEYS:
        d.pop(k)
    return json.dumps(d, sort_keys=True, default=str)


def plan_groups(cfgs: list[Config], max_size: int | None = None) -> list[list[int]]:
    """Indices of `cfgs` split into groups of equal `group_key` (in order), at most `max_size` runs each."""
    by_key: dict[str, list[int]] = {}
    for i, c in enumerate(cfgs):
        by_key.setdefault(group_key(c), []).append(i)
    size = max_size or max(len(cfgs), 1)
    return [ix[j:j + size] for ix in by_key.values() for j in range(0, len(ix), size)]


def stack(trees):
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


def take(tree, i: int):
    return jax.tree.map(lambda x: x[i], tree)


class GroupLearner:
    """The learner of a group: the members' states and diagnostics stacked, one vmapped training step."""

    def __init__(self, members: list[Member], states: list[TrainState], diags: list[Diagnostics]):
        self.own = [m.agent.own_metrics for m in members]  # metrics of its own intrinsic models (None: ballast)
        a = members[0].agent
        self.cfg = dataclasses.replace(members[0].cfg, intrinsic_alpha=0.0,
                                       intrinsic_models=any(o is not None for o in self.own))
        self.agent = agent = Agent(a.obs_dim, a.act_dim, a.intrinsic_dim, self.cfg)
        states = [s if own is not None or not self.cfg.use_intrinsic_models else self._with_ballast(s, m.cfg.seed)
                  for s, m, own in zip(states, members, self.own)]
        self.state: TrainState = stack(states)
        self.diag: Diagnostics = stack(diags)
        self.hyper = Hyper(*(jnp.asarray([getattr(Hyper.of(m.cfg), f) for m in members], jnp.float32)
                             for f in Hyper._fields))
        vstep = jax.vmap(lambda s, d, b, h, w: train_step(agent, s, d, b, h, w))
        self._step = jax.jit(vstep, donate_argnums=(0, 1))
        self._alphas, self._mix = None, None  # the weights last put on the device
        self._default_alphas = [m.cfg.intrinsic_alpha for m in members]

        def masked(state, diag, batch, hyper, mix, active):  # runs whose buffer cannot be sampled yet keep theirs
            new = vstep(state, diag, batch, hyper, mix)
            return jax.tree.map(lambda n, o: jnp.where(active.reshape((-1,) + (1,) * (n.ndim - 1)), n, o),
                                new, (state, diag))

        self._masked = jax.jit(masked, donate_argnums=(0, 1))
        keys = jnp.stack([act_key(m.cfg) for m in members])
        # the same key and computation as a run's Learner, run by run
        one = lambda p, o, k, t: agent.act(p, o[None], jax.random.fold_in(k, t))[0]  # noqa: E731
        self._act = jax.jit(lambda actors, obs, t: jax.vmap(one, in_axes=(0, 0, 0, None))(actors, obs, keys, t))

    def _with_ballast(self, state: TrainState, seed: int) -> TrainState:
        """A SAC run's state with the intrinsic models and normaliser a fresh run of its seed would have."""
        fresh = self.agent.init(seed)
        return state._replace(intrinsic=fresh.intrinsic, norm=fresh.norm)

    def act(self, obs: np.ndarray, t: int) -> np.ndarray:
        return np.asarray(self._act(self.state.pi.params, obs, t))

    def update(self, batches: list[Batch | None], alphas: list[float] | None = None) -> None:
        """One vmapped gradient step; run i with intrinsic weight `alphas[i]` (None: the configs' intrinsic_alpha)."""
        active = np.array([b is not None for b in batches])
        if not active.any():
            return
        alphas = list(alphas or self._default_alphas)
        if alphas != self._alphas:
            self._alphas, self._mix = alphas, jax.device_put(Mix.of_float32(alphas))
        ref = next(b for b in batches if b is not None)
        zeros = Batch(*(np.zeros_like(x) for x in ref))  # for the runs the mask keeps out
        batch = Batch(*(np.stack(xs) for xs in zip(*(b if b is not None else zeros for b in batches))))
        if active.all():
            self.state, self.diag = self._step(self.state, self.diag, batch, self.hyper, self._mix)
        else:
            self.state, self.diag = self._masked(self.state, self.diag, batch, self.hyper, self._mix,
                                                 jnp.asarray(active))

    def read_metrics(self) -> list[dict[str, float]]:
        sums, counts, bounds = jax.device_get((self.diag.metric_sums, self.diag.metric_count, self.diag.bounds))
        out = [diagnostics.means({k: v[i] for k, v in sums.items()}, int(n), bounds[i], own) if n > 0 else {}
               for i, (n, own) in enumerate(zip(counts, self.own))]
        self.diag = diagnostics.reset(self.diag)
        return out

    def state_of(self, i: int) -> tuple[TrainState, Diagnostics]:
        """Run `i`'s own state and diagnostics (a SAC run's without the ballast and its metrics)."""
        s, d = take(self.state, i), take(self.diag, i)
        if self.cfg.use_intrinsic_models and self.own[i] is None:
            sac = reported(None)  # what a SAC run reports; the ballast's intrinsic sums, a reward's own too, are 0
            sums = {k: (v if k in sac else jnp.float32(0)) for k, v in d.metric_sums.items()}
            s = s._replace(intrinsic=None, norm=None)
            d = Diagnostics(sums, d.metric_count, jnp.zeros(2, jnp.float32))
        return s, d


def train_group(cfgs: list[Config], run_dirs: list[Path | str], env_workers: int = 0, progress: bool = False,
                video: VideoStep | None = None) -> list[Path]:
    """Train (or resume, from their newest checkpoints) runs of one group as one computation; their dirs."""
    if not cfgs or len(cfgs) != len(run_dirs):
        raise MCRLError("a group needs one run directory per config")
    if len({group_key(c) for c in cfgs}) != 1:
        raise MCRLError("these runs differ in more than seed, intrinsic_alpha and its schedule, intrinsic_models, "
                        "learning rates, gamma and tau: train them in separate groups (mcrl.run.group.plan_groups)")
    return train_runs(list(cfgs), [Path(d) for d in run_dirs], True, GroupLearner, env_workers, progress, video)
