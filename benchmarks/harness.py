"""Speed measurements of mcrl's own training (used by bench.py, flat_cost.py and scaling.py).

- steps/s: the real training loop (`mcrl.run.trainer.train`), read off the per-interval wall-clock times
  in metrics.csv after warm-up; one interval per repetition, median reported.
- ms per gradient step: the jitted update alone on replay batches, synchronised, median of repetitions.
- ms per environment step: policy forward pass + env.step + buffer insert, median of repetitions.
- GFLOP per gradient step: XLA's own cost analysis of the compiled update.
"""
from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from mcrl.algo import diagnostics, normaliser
from mcrl.config import resolve_config
from mcrl.envs import flatten_obs, to_env_action
from mcrl.run.envpool import EnvPool
from mcrl.run.learner import Learner, train_step
from mcrl.run.member import open_member
from mcrl.run.policy import build
from mcrl.run.rundir import read_rows
from mcrl.run.trainer import train


def _flops(compiled) -> float:
    cost = compiled.cost_analysis()
    if isinstance(cost, (list, tuple)):
        cost = cost[0]
    return float(cost.get("flops", float("nan")))


def update_timer(preset: str, overrides: dict | None = None, full_history: bool = False):
    """(time_block, GFLOP): `time_block(calls)` runs `calls` jitted gradient steps of `preset` (what the training
    loop compiles) on replay batches of real transitions and returns ms per step; compiled and warmed up here.

    With `full_history`, the normaliser starts as late in a run: a full window, or `total_steps` steps' worth
    of values for the whole-run history.
    """
    cfg = resolve_config(preset, {"buffer_size": 20_000, **(overrides or {})})
    env, spec, agent, buffer = build(cfg)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    for i in range(max(cfg.batch_size * 2, 1000)):  # a buffer of real transitions with finished episodes
        a = rng.uniform(-1, 1, spec.act_dim).astype(np.float32)
        nxt, r, term, trunc, _ = env.step(to_env_action(a, env, cfg.action_scale))
        buffer.add(flatten_obs(obs), a, r, flatten_obs(nxt), term, term or trunc)
        obs = nxt if not (term or trunc) else env.reset(seed=i)[0]
    env.close()
    batches = [buffer.sample(cfg.batch_size, rng) for _ in range(8)]
    state = agent.init(0)
    if full_history and state.norm is not None:
        n = cfg.intrinsic_history_values or cfg.total_steps * cfg.intrinsic_values_per_step
        values = rng.lognormal(2.0, 1.5, n).astype(np.float32)
        if cfg.intrinsic_history_values is None:
            state = state._replace(norm=normaliser.from_values(values, None))
        else:
            state = state._replace(norm=normaliser.push(state.norm, values))
    step = jax.jit(lambda s, d, b: train_step(agent, s, d, b), donate_argnums=(0, 1))  # what the loop compiles
    gflop = _flops(jax.jit(agent.update).lower(state, batches[0]).compile()) / 1e9
    carry = [state, diagnostics.init()]

    def time_block(calls: int) -> float:
        s, d = carry
        t = time.perf_counter()
        for i in range(calls):
            s, d = step(s, d, batches[i % 8])
        jax.block_until_ready(s)
        carry[:] = [s, d]
        return (time.perf_counter() - t) / calls * 1e3

    time_block(10)
    return time_block, gflop


def measure_update(preset: str, repeats: int = 5, calls: int = 100, overrides: dict | None = None,
                   full_history: bool = False) -> dict:
    """ms per jitted gradient step (median over `repeats` blocks of `calls`) and its GFLOP."""
    time_block, gflop = update_timer(preset, overrides, full_history)
    times = [time_block(calls) for _ in range(repeats)]
    return {"ms_per_grad_step": statistics.median(times), "ms_per_grad_step_all": times, "grad_step_gflop": gflop}


def measure_env_step(preset: str, repeats: int = 5, steps: int = 500) -> dict:
    """ms per environment step of the training loop's acting path (`mcrl.run.trainer.run_loop`): actor forward +
    env.step + buffer insert."""
    cfg = resolve_config(preset, {"buffer_size": 20_000})
    times = []
    with tempfile.TemporaryDirectory() as d:
        member, state, diag = open_member(cfg, Path(d), resume=False)
        learner, pool = Learner(member.agent, state, diag), EnvPool([cfg], envs=[member.env])
        member.progress.step = cfg.learning_starts  # act with the policy, not the warm-up's uniform actions
        member.obs = pool.reset(0, member.episode_seed())
        for rep in range(repeats + 1):
            t = time.perf_counter()
            for _ in range(steps):
                actions = learner.act(member.obs[None], member.progress.step)
                res = pool.step(actions)
                member.store(actions[0], res.next_obs[0], res.reward[0], bool(res.terminated[0]),
                             bool(res.truncated[0]))
                if res.terminated[0] or res.truncated[0]:
                    member.end_episode(res.success[0])
                    member.obs = pool.reset(0, member.episode_seed())
            if rep > 0:  # the first block compiles
                times.append((time.perf_counter() - t) / steps * 1e3)
        pool.close()
        member.close()
    return {"ms_per_env_step": statistics.median(times), "ms_per_env_step_all": times}


def measure_loop(preset: str, steps: int = 1000, repeats: int = 3, warmup: int = 1000,
                 overrides: dict | None = None) -> dict:
    """Env steps/s of the real training loop: `repeats` intervals of `steps` after `warmup` learning steps."""
    cfg = resolve_config(preset, {"eval_every": 0, "eval_episodes": 1, "checkpoint_every": 10**9,
                                  "save_buffer": False, "log_every": steps, **(overrides or {})})
    first = cfg.learning_starts + warmup
    first += (-first) % steps  # start timing on an interval boundary
    cfg.total_steps = first + (repeats + 1) * steps  # one extra interval: the last one holds the final eval
    with tempfile.TemporaryDirectory() as d:
        run = train(cfg, Path(d) / "bench", progress=False)
        rows = read_rows(run / "metrics.csv")
    t = {int(r["step"]): r["time_s"] for r in rows}
    rates = [steps / (t[s + steps] - t[s]) for s in range(first, first + repeats * steps, steps)]
    return {"steps_per_s": statistics.median(rates), "steps_per_s_all": rates}


def measure_training(preset: str, steps: int = 1000, repeats: int = 3) -> dict:
    """All of the above for one preset (the numbers benchmarks/bench.py reports)."""
    out = {"preset": preset}
    out.update(measure_loop(preset, steps=steps, repeats=repeats))
    out.update(measure_update(preset, repeats=max(repeats, 3)))
    out.update(measure_env_step(preset, repeats=max(repeats, 3)))
    return out
