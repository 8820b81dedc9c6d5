"""The training loop (imperative shell): environment, replay, the jitted update, and the steps it calls.

The whole state of a run is one value, `RunState`: the device train state, the replay buffer, the host RNG
and the loop's counters (`Progress`). A checkpoint stores it whole (`save_run_state` / `load_run_state`).
Evaluation, logging and checkpoints are steps the loop calls (`Trainer.evaluate`, `.log`, `.checkpoint`).

Reproducibility and resume: every environment reset is seeded from (seed, stream, episode), actions are
sampled with keys folded from (seed, step), and checkpoints are taken at episode ends, after that step's
evaluation and log row. A resumed run continues exactly where the killed one was, and ends with the same
numbers as an uninterrupted run on the CPU.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import numpy as np

from mcrl.algo import normaliser
from mcrl.algo.sac import Agent, Batch, TrainState
from mcrl.config import Config
from mcrl.envs import episode_seed, flatten_obs, success_of, to_env_action
from mcrl.errors import MCRLError
from mcrl.replay import ReplayBuffer
from mcrl.run import checkpoint, rundir
from mcrl.run.evaluation import TRAIN_STREAM, Evaluator
from mcrl.run.logger import RunLogger
from mcrl.run.policy import build, restore


@dataclass
class Progress:
    """The loop's counters; JSON in a checkpoint's meta.json."""

    step: int = 0
    episode: int = 0
    eval_round: int = 0
    interval: dict = field(default_factory=lambda: {"returns": [], "successes": []})  # since the last log row
    last_eval: dict = field(default_factory=lambda: {"success_rate": None, "mean_return": None})


@dataclass
class RunState:
    train: TrainState
    buffer: ReplayBuffer
    rng: np.random.Generator  # warm-up actions and replay sampling
    progress: Progress


def new_run_state(cfg: Config, agent: Agent, buffer: ReplayBuffer) -> RunState:
    return RunState(agent.init(cfg.seed), buffer, np.random.default_rng(cfg.seed), Progress())


def save_run_state(run_dir: Path, cfg: Config, rs: RunState) -> None:
    p = rs.progress
    meta = {"episode": p.episode, "eval_round": p.eval_round, "host_rng": rs.rng.bit_generator.state,
            "interval": p.interval, "last_eval": p.last_eval, "config": cfg.to_dict()}
    extra = {"normaliser": normaliser.pack(rs.train.norm)} if rs.train.norm is not None else None
    checkpoint.save(run_dir, p.step, rs.train._replace(norm=None), meta,
                    rs.buffer.state_arrays() if cfg.save_buffer else None, cfg.keep_checkpoints, extra)


def load_run_state(cfg: Config, agent: Agent, buffer: ReplayBuffer, ckpt: Path) -> RunState:
    train_state, meta = restore(cfg, agent, ckpt)
    arrays = checkpoint.load_buffer_arrays(ckpt) if meta["has_buffer"] else None
    if arrays is None:
        raise MCRLError(f"checkpoint {ckpt} has no replay buffer (save_buffer=false): resuming would not "
                        "reproduce the run; start a new run instead")
    buffer.load_arrays(arrays)
    buffer.end_episode()  # the final checkpoint can be mid-episode; the env restarts with a new one
    rng = np.random.default_rng(cfg.seed)
    rng.bit_generator.state = meta["host_rng"]
    progress = Progress(meta["step"], meta["episode"], meta["eval_round"], meta["interval"], meta["last_eval"])
    return RunState(train_state, buffer, rng, progress)


def default_run_dir(cfg: Config) -> Path:
    name = cfg.preset or f"{cfg.env_id}-a{cfg.mc_alpha:g}"
    return Path(cfg.out_dir) / f"{name}-s{cfg.seed}-{time.strftime('%Y%m%d-%H%M%S')}"


class Trainer:
    """One run: its environment, evaluator, logger and compiled functions, and the steps the loop calls."""

    def __init__(self, cfg: Config, run_dir: Path, env, spec, agent: Agent, resume_step: int | None):
        self.cfg, self.run_dir, self.env, self.spec, self.agent = cfg, run_dir, env, spec, agent
        self.log = RunLogger(run_dir, resume_step=resume_step)
        self.evaluator = Evaluator(cfg, agent)
        self.update = jax.jit(agent.update, donate_argnums=0)
        act_key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), 0x5EED)
        # The key is folded inside the compiled call: outside, fold_in alone costs a dispatch (~0.15 ms) per step.
        self.act = jax.jit(lambda params, obs, t: agent.act(params, obs, jax.random.fold_in(act_key, t)))

    def env_step(self, rs: RunState, flat: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Act (uniformly at random before `learning_starts`), step the environment, store the transition."""
        if rs.progress.step < self.cfg.learning_starts:
            action = rs.rng.uniform(-1.0, 1.0, self.spec.act_dim).astype(np.float32)
        else:
            action = np.asarray(self.act(rs.train.actor, flat[None], rs.progress.step))[0]
        next_obs, reward, term, trunc, info = self.env.step(to_env_action(action, self.env, self.cfg.action_scale))
        next_flat = flatten_obs(next_obs)
        rs.buffer.add(flat, action, reward, next_flat, term, term or trunc)
        return next_flat, float(reward), term, trunc, info

    def evaluate(self, rs: RunState, episodes: int) -> None:
        p = rs.progress
        p.last_eval = self.evaluator.run(rs.train.actor, p.eval_round, episodes)
        p.eval_round += 1
        self.log.log_eval({"step": p.step, **p.last_eval})
        if self.cfg.video_every and p.step % self.cfg.video_every == 0:
            from mcrl.video.render import record_training_video  # rendering stack only when videos are asked for

            record_training_video(self.cfg, self.agent, rs.train, self.run_dir, p.step, self.log)

    def final_evaluation(self, rs: RunState) -> None:
        self.evaluate(rs, self.cfg.n_final_eval_episodes)
        rundir.write_json_atomic(self.run_dir / rundir.FINAL_EVAL, {"step": rs.progress.step, **rs.progress.last_eval})

    def log_row(self, rs: RunState, elapsed: float, steps_done: int, metrics: dict | None = None) -> dict:
        """Write the log row; `metrics` are the update's means (read from `rs.train` when not given)."""
        p = rs.progress
        if metrics is None:
            metrics, rs.train = self.agent.read_metrics(rs.train)
        sps = steps_done / elapsed if elapsed > 0 else None
        mean = lambda xs: float(np.mean(xs)) if xs else None  # noqa: E731
        row = {"step": p.step, "time_s": round(elapsed, 3), "steps_per_s": sps, "episodes": p.episode,
               "train_return": mean(p.interval["returns"]), "train_success_rate": mean(p.interval["successes"]),
               "eval_success_rate": p.last_eval["success_rate"], "eval_mean_return": p.last_eval["mean_return"],
               **metrics}
        self.log.log_metrics(row)
        p.interval = {"returns": [], "successes": []}
        return row

    def checkpoint(self, rs: RunState) -> None:
        save_run_state(self.run_dir, self.cfg, rs)

    def close(self) -> None:
        self.log.close()
        self.evaluator.close()
        if self.env is not None:
            self.env.close()

    def run(self, rs: RunState, bar=None) -> RunState:
        cfg, env, p = self.cfg, self.env, rs.progress
        t_start, steps_at_start, last_ckpt = time.perf_counter(), p.step, p.step
        obs, _ = env.reset(seed=episode_seed(cfg.seed, TRAIN_STREAM, p.episode))
        flat = flatten_obs(obs)
        ep_return, ckpt_due = 0.0, False
        while p.step < cfg.total_steps:
            next_flat, reward, term, trunc, info = self.env_step(rs, flat)
            ep_return += reward
            p.step += 1
            # one gradient step on a (HER-relabelled) replay batch
            if p.step > cfg.learning_starts and rs.buffer.can_sample():
                b = rs.buffer.sample(cfg.batch_size, rs.rng)
                rs.train = self.update(rs.train, Batch(b["obs"], b["action"], b["reward"], b["next_obs"],
                                                       b["terminated"]))
            flat = next_flat
            if term or trunc:
                p.interval["returns"].append(ep_return)
                s = success_of(info)
                if s is not None:
                    p.interval["successes"].append(s)
                p.episode += 1
                ep_return = 0.0
                obs, _ = env.reset(seed=episode_seed(cfg.seed, TRAIN_STREAM, p.episode))
                flat = flatten_obs(obs)
                ckpt_due = p.step - last_ckpt >= cfg.checkpoint_every and p.step < cfg.total_steps
            # the steps around it: evaluation, the log row, a checkpoint (in this order)
            if cfg.eval_every and p.step % cfg.eval_every == 0 and p.step < cfg.total_steps:
                self.evaluate(rs, cfg.eval_episodes)
            if p.step % cfg.log_every == 0 or p.step == cfg.total_steps:
                if p.step == cfg.total_steps:  # the final evaluation (thesis: "after training") lands in the last row
                    self.final_evaluation(rs)
                row = self.log_row(rs, time.perf_counter() - t_start, p.step - steps_at_start)
                if bar is not None:
                    post = {"sps": f"{row['steps_per_s']:.0f}" if row["steps_per_s"] else "-"}
                    if p.last_eval["success_rate"] is not None:
                        post["success"] = f"{p.last_eval['success_rate']:.2f}"
                    bar.set_postfix(post, refresh=False)
            if ckpt_due:  # after this step's evaluation and log row, so a resume repeats none of them
                self.checkpoint(rs)
                last_ckpt, ckpt_due = p.step, False
            if bar is not None:
                bar.update(1)
        return rs


def open_run(cfg: Config, run_dir: Path | str | None, resume: bool):
    """(env, spec, agent, run_dir, RunState) of a run about to train: new, or from its newest checkpoint with
    `resume` (new if it has none). Writes its config.json and removes a stale `done`."""
    env, spec, agent, buffer = build(cfg)  # validates env and spaces before anything is written
    run_dir = Path(run_dir) if run_dir is not None else default_run_dir(cfg)
    if not resume and (run_dir / rundir.CONFIG).exists():
        env.close()
        raise MCRLError(f"{run_dir} already holds a run: continue it with `mcrl train --resume {run_dir}` or "
                        "choose another --run-dir")
    ckpt = None
    if resume:
        try:
            ckpt = checkpoint.find(run_dir)
        except MCRLError:
            ckpt = None  # killed before its first checkpoint: start over in the same directory
    rs = load_run_state(cfg, agent, buffer, ckpt) if ckpt is not None else new_run_state(cfg, agent, buffer)
    run_dir.mkdir(parents=True, exist_ok=True)
    rundir.write_json_atomic(run_dir / rundir.CONFIG, cfg.to_dict())
    for stale in (rundir.DONE, rundir.FINAL_EVAL):
        (run_dir / stale).unlink(missing_ok=True)
    return env, spec, agent, run_dir, rs


def finish_run(trainer: Trainer, rs: RunState) -> None:
    """The last checkpoint, then `done` (last: a run with `done` is finished, whoever reads it)."""
    trainer.checkpoint(rs)
    rundir.write_json_atomic(trainer.run_dir / rundir.DONE, {"step": rs.progress.step, **rs.progress.last_eval})


def train(cfg: Config, run_dir: Path | str | None = None, progress: bool = True, resume: bool = False) -> Path:
    """Train; with `resume`, continue `run_dir` from its newest checkpoint (or start it if it has none)."""
    env, spec, agent, run_dir, rs = open_run(cfg, run_dir, resume)
    trainer = Trainer(cfg, run_dir, env, spec, agent, resume_step=rs.progress.step if resume else None)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.total_steps, initial=rs.progress.step, unit="step", dynamic_ncols=True, smoothing=0.05,
                   mininterval=1.0)
    try:
        rs = trainer.run(rs, bar)
        finish_run(trainer, rs)
    finally:
        if bar is not None:
            bar.close()
        trainer.close()
    return run_dir


def resume(run_dir: Path | str, progress: bool = True, total_steps: int | None = None) -> Path:
    cfg = rundir.read_config(run_dir)
    if total_steps is not None:
        cfg = dataclasses.replace(cfg, total_steps=total_steps)
    if rundir.is_done(run_dir) and total_steps is None:
        raise MCRLError(f"{run_dir} already finished: pass --steps N (more than {cfg.total_steps}) to continue it")
    return train(cfg, run_dir, progress=progress, resume=True)
