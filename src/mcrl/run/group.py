"""A group of runs trained as one computation: one gradient step `jax.vmap`-ed over the runs, jitted once.

Runs whose configs agree in everything but `PER_RUN_KEYS` have train states of one shape; their states are
stacked along a leading run axis, and each step every run acts, steps its own environment (`EnvPool`),
stores its transition in its own replay buffer and samples its own batch (host side, with its own RNG, in
the same order as a run alone), then one compiled call updates all of them. The per-run scalars (mc_alpha,
gamma, tau, learning rates) are data (`sac.Hyper`), so a grid over alpha compiles once.

SAC runs (mc_alpha = 0, no MC models) in a group with SAC-MC runs carry MC models as ballast so that the
shapes agree: their reward is 1 * r + 0 * r_mc = r exactly, and the ballast never reaches their files (their
checkpoints, metrics and config are a SAC run's; a resumed group re-draws it). Each run writes exactly what
`mcrl train` writes, through its own `Trainer` (evaluation, log rows, checkpoints), so `mcrl eval`,
`render`, `report` and `--resume` see an ordinary run, and a run started in a group may finish alone.
"""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from mcrl.algo.metrics import MC_METRICS, UPDATE_METRICS
from mcrl.algo.sac import Agent, Batch, Hyper, TrainState, metric_means
from mcrl.config import Config
from mcrl.envs import episode_seed
from mcrl.errors import MCRLError
from mcrl.run.envpool import EnvPool
from mcrl.run.evaluation import TRAIN_STREAM
from mcrl.run.trainer import RunState, Trainer, finish_run, open_run

# Config keys that may differ inside a group (per-run data or host-side only); all others must agree.
PER_RUN_KEYS = ("seed", "mc_alpha", "mc_models", "learning_rate", "mc_lr", "gamma", "tau", "preset", "out_dir")


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


@dataclass
class Member:
    """One run of the group: its own config, files, buffer, host RNG and counters (`rs.train` is only set
    to its slice of the group's state when a file needs it)."""

    cfg: Config
    trainer: Trainer
    rs: RunState
    flat: np.ndarray | None = None
    ep_return: float = 0.0
    last_ckpt: int = 0
    ckpt_due: bool = False

    @property
    def has_mc(self) -> bool:
        """Its own MC models (SAC-MC, or SAC measuring MC); otherwise it carries ballast in a group with them."""
        return self.cfg.use_mc_models


class Group:
    def __init__(self, cfgs: list[Config], run_dirs: list[Path], env_workers: int = 0):
        if not cfgs or len(cfgs) != len(run_dirs):
            raise MCRLError("a group needs one run directory per config")
        keys = {group_key(c) for c in cfgs}
        if len(keys) != 1:
            raise MCRLError("these runs differ in more than seed, mc_alpha, mc_models, learning rates, gamma and tau: "
                            "train them in separate groups (mcrl.run.group.plan_groups)")
        self.members: list[Member] = []
        try:
            for cfg, d in zip(cfgs, run_dirs):
                env, spec, agent, run_dir, rs = open_run(cfg, d, resume=True)
                # its env recomputes HER rewards; EnvPool steps it too, or steps its own in worker processes
                trainer = Trainer(cfg, run_dir, env, spec, agent, resume_step=rs.progress.step)
                self.members.append(Member(cfg, trainer, rs, last_ckpt=rs.progress.step))
            steps = {m.rs.progress.step for m in self.members}
            if len(steps) != 1:
                raise MCRLError(f"the runs of a group must resume from the same step, not {sorted(steps)}: "
                                "group them by their checkpoints' steps")
            self.step = steps.pop()
            spec = self.members[0].trainer.spec
            any_mc = any(m.has_mc for m in self.members)
            self.cfg = dataclasses.replace(cfgs[0], mc_alpha=0.0, mc_models=any_mc)
            self.agent = Agent(spec.obs_dim, spec.act_dim, spec.mc_dim, self.cfg)
            states = []
            for m in self.members:
                s = m.rs.train
                if any_mc and not m.has_mc:  # ballast MC models of a SAC run
                    ballast = self.agent.init(m.cfg.seed)
                    s = s._replace(mc_models=ballast.mc_models, norm=ballast.norm)
                states.append(s)
                m.rs.train = None
            self.state: TrainState = stack(states)
            self.hyper = Hyper(*(jnp.asarray([getattr(Hyper.of(m.cfg), f) for m in self.members], jnp.float32)
                                 for f in Hyper._fields))
            self.pool = EnvPool(cfgs, env_workers, envs=[m.trainer.env for m in self.members])
        except BaseException:
            self.close()
            raise
        self._compile()

    def _compile(self) -> None:
        agent = self.agent
        vupdate = jax.vmap(agent.update)
        self.update = jax.jit(vupdate, donate_argnums=0)

        def masked(state, batch, hyper, active):  # runs whose buffer cannot be sampled yet keep their state
            new = vupdate(state, batch, hyper)
            return jax.tree.map(lambda n, o: jnp.where(active.reshape((-1,) + (1,) * (n.ndim - 1)), n, o),
                                new, state)

        self.update_masked = jax.jit(masked, donate_argnums=0)
        act_keys = jnp.stack([jax.random.fold_in(jax.random.PRNGKey(m.cfg.seed), 0x5EED) for m in self.members])
        # the same key and computation as Trainer.act, run by run
        one = lambda p, o, k, t: agent.act(p, o[None], jax.random.fold_in(k, t))[0]  # noqa: E731
        self.act = jax.jit(lambda actors, obs, t: jax.vmap(one, in_axes=(0, 0, 0, None))(actors, obs, act_keys, t))

    # ------------------------------------------------------------------ one run's view of the group state
    def member_state(self, i: int) -> TrainState:
        s = take(self.state, i)
        if not self.members[i].has_mc and self.cfg.use_mc_models:  # a SAC run's state, without the ballast
            sums = {k: (jnp.float32(0) if k in MC_METRICS else v) for k, v in s.metric_sums.items()}
            s = s._replace(mc_models=None, norm=None, bounds=jnp.zeros(2, jnp.float32), metric_sums=sums)
        return s

    def _with_state(self, i: int) -> RunState:
        m = self.members[i]
        m.rs.train = self.member_state(i)
        return m.rs

    def read_metrics(self) -> list[dict]:
        sums, counts, bounds = jax.device_get((self.state.metric_sums, self.state.metric_count, self.state.bounds))
        out = [metric_means({k: v[i] for k, v in sums.items()}, int(counts[i]), bounds[i], m.has_mc)
               if counts[i] > 0 else {} for i, m in enumerate(self.members)]
        r = len(self.members)
        self.state = self.state._replace(metric_sums={k: jnp.zeros(r, jnp.float32) for k in UPDATE_METRICS},
                                         metric_count=jnp.zeros(r, jnp.int32))
        return out

    # ------------------------------------------------------------------ the loop
    def _actions(self) -> np.ndarray:
        if self.step < self.cfg.learning_starts:
            return np.stack([m.rs.rng.uniform(-1.0, 1.0, m.trainer.spec.act_dim).astype(np.float32)
                             for m in self.members])
        obs = np.stack([m.flat for m in self.members])
        return np.asarray(self.act(self.state.pi.params, obs, self.step))

    def _gradient_step(self) -> None:
        cfg = self.cfg
        active = np.array([m.rs.buffer.can_sample() for m in self.members])
        if not active.any():
            return
        batches = []
        for m, a in zip(self.members, active):
            if a:
                b = m.rs.buffer.sample(cfg.batch_size, m.rs.rng)
                batches.append((b["obs"], b["action"], b["reward"], b["next_obs"], b["terminated"]))
            else:  # kept out by the mask; its RNG is not advanced, as alone it would not sample
                batches.append(None)
        ref = next(b for b in batches if b is not None)
        batches = [b if b is not None else tuple(np.zeros_like(x) for x in ref) for b in batches]
        batch = Batch(*(np.stack(xs) for xs in zip(*batches)))
        if active.all():
            self.state = self.update(self.state, batch, self.hyper)
        else:
            self.state = self.update_masked(self.state, batch, self.hyper, jnp.asarray(active))

    def run(self, bar=None) -> None:
        cfg, members = self.cfg, self.members
        t_start, steps_at_start = time.perf_counter(), self.step
        for i, m in enumerate(members):
            m.flat = self.pool.reset(i, episode_seed(m.cfg.seed, TRAIN_STREAM, m.rs.progress.episode))
        while self.step < cfg.total_steps:
            actions = self._actions()
            res = self.pool.step(actions)
            self.step += 1
            for i, m in enumerate(members):
                term, trunc = bool(res.terminated[i]), bool(res.truncated[i])
                m.rs.buffer.add(m.flat, actions[i], res.reward[i], res.next_obs[i], term, term or trunc)
                m.ep_return += float(res.reward[i])
                m.rs.progress.step = self.step
                m.flat = res.next_obs[i]
            if self.step > cfg.learning_starts:
                self._gradient_step()
            for i, m in enumerate(members):
                if not (res.terminated[i] or res.truncated[i]):
                    continue
                p = m.rs.progress
                p.interval["returns"].append(m.ep_return)
                if res.success[i] is not None:
                    p.interval["successes"].append(res.success[i])
                p.episode += 1
                m.ep_return = 0.0
                m.flat = self.pool.reset(i, episode_seed(m.cfg.seed, TRAIN_STREAM, p.episode))
                m.ckpt_due = self.step - m.last_ckpt >= cfg.checkpoint_every and self.step < cfg.total_steps
            # evaluation, the log row, checkpoints: in the order of Trainer.run
            if cfg.eval_every and self.step % cfg.eval_every == 0 and self.step < cfg.total_steps:
                for i, m in enumerate(members):
                    m.trainer.evaluate(self._with_state(i), cfg.eval_episodes)
            if self.step % cfg.log_every == 0 or self.step == cfg.total_steps:
                if self.step == cfg.total_steps:
                    for i, m in enumerate(members):
                        m.trainer.final_evaluation(self._with_state(i))
                metrics = self.read_metrics()
                elapsed = time.perf_counter() - t_start
                for m, mx in zip(members, metrics):
                    row = m.trainer.log_row(m.rs, elapsed, self.step - steps_at_start, metrics=mx)
                if bar is not None:
                    bar.set_postfix({"runs": len(members), "sps": f"{row['steps_per_s'] or 0:.0f}"}, refresh=False)
            for i, m in enumerate(members):
                if m.ckpt_due:
                    m.trainer.checkpoint(self._with_state(i))
                    m.last_ckpt, m.ckpt_due = self.step, False
            for m in members:
                m.rs.train = None  # the group state is the only copy while training
            if bar is not None:
                bar.update(1)
        for i, m in enumerate(members):
            finish_run(m.trainer, self._with_state(i))

    def close(self) -> None:
        if getattr(self, "pool", None) is not None:
            self.pool.close()
            self.pool = None
        for m in self.members:
            m.trainer.close()
        self.members = []


def train_group(cfgs: list[Config], run_dirs: list[Path | str], env_workers: int = 0,
                progress: bool = False) -> list[Path]:
    """Train (or resume, from their newest checkpoints) runs of one group as one computation; their dirs."""
    group = Group(list(cfgs), [Path(d) for d in run_dirs], env_workers)
    dirs = [m.trainer.run_dir for m in group.members]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=group.cfg.total_steps, initial=group.step, unit="step", dynamic_ncols=True,
                   smoothing=0.05, mininterval=1.0)
    try:
        group.run(bar)
    finally:
        if bar is not None:
            bar.close()
        group.close()
    return dirs
