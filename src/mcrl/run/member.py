"""One run of the training loop (`mcrl.run.trainer`): its files, environment, replay buffer, host RNG and
counters, and the steps the loop calls for it. The loop holds the learner's state on the device
(`mcrl.run.learner`); a member gets its own slice of it only when one of its files needs it.

Reproducibility and resume: every environment reset is seeded from (seed, stream, episode), warm-up actions and
replay batches come from the run's own host RNG, and a checkpoint holds all of it (`save` / `open_member`): the
learner's state, the diagnostics of the log interval in progress, the replay buffer, the host RNG and
`Progress` (with the intrinsic weight's schedule state), written at episode ends after that step's evaluation and
log row.

One writer per run: `open_member` locks the run directory (`mcrl.run.lock`) before it writes anything, and
`Member.close` lets go.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mcrl.algo import diagnostics, normaliser
from mcrl.algo.diagnostics import Diagnostics
from mcrl.algo.schedule import Schedule
from mcrl.algo.sac import Agent, TrainState
from mcrl.config import Config
from mcrl.envs import episode_seed, family_of
from mcrl.errors import MCRLError
from mcrl.replay import Batch, ReplayBuffer
from mcrl.run import checkpoint, rundir
from mcrl.run.lock import RunLock
from mcrl.run.lock import acquire as lock_run_dir
from mcrl.run.evaluation import TRAIN_STREAM, Evaluator
from mcrl.run.logger import RunLogger
from mcrl.run.policy import build, restore_run


GOAL_MOVED = 0.01  # an episode "moved its goal" when the achieved goal ends more than this (1 cm on Fetch) from its start


def _new_interval() -> dict:
    return {"returns": [], "successes": [], "moved": []}


@dataclass
class Progress:
    """The loop's counters of one run; JSON in a checkpoint's meta.json."""

    step: int = 0
    episode: int = 0
    eval_round: int = 0
    interval: dict = field(default_factory=_new_interval)  # since the last log row
    last_eval: dict = field(default_factory=lambda: {"success_rate": None, "mean_return": None})
    success_window: list = field(default_factory=list)  # the success flags the intrinsic weight's schedule averages


class Member:
    """One run: the host side of its training (environment, buffer, RNG, counters) and its files."""

    def __init__(self, cfg: Config, run_dir: Path, env, agent: Agent, buffer: ReplayBuffer, rng: np.random.Generator,
                 progress: Progress, resumed: bool, lock: RunLock | None = None):
        self.cfg, self.run_dir, self.env, self.agent, self.buffer = cfg, run_dir, env, agent, buffer
        self.lock = lock  # held until `close`
        self.rng = rng  # warm-up actions and replay sampling
        self.progress = progress
        self.log = RunLogger(run_dir, resume_step=progress.step if resumed else None,
                             metric_columns=rundir.metric_columns(agent.about.metrics))
        self.evaluator = Evaluator(cfg, agent)
        self.obs: np.ndarray | None = None  # the flat observation the next action answers
        self.ep_return = 0.0
        self.ep_start_goal: np.ndarray | None = None  # the achieved goal at the episode's start (goal envs)
        self.last_ckpt, self.ckpt_due = progress.step, False
        self.schedule = Schedule.of(cfg)
        self.alpha = cfg.intrinsic_alpha  # the intrinsic weight in force: of the last step `intrinsic_weight` gave

    # ------------------------------------------------------------------ acting and storing (every step)
    def episode_seed(self) -> int:
        return episode_seed(self.cfg.seed, TRAIN_STREAM, self.progress.episode)

    def random_action(self) -> np.ndarray:
        """A warm-up action (before `learning_starts`): uniform in [-1, 1]."""
        return self.rng.uniform(-1.0, 1.0, self.agent.act_dim).astype(np.float32)

    def _achieved_goal(self) -> np.ndarray:
        return self.obs[self.buffer.od: self.buffer.od + self.buffer.gd]

    def store(self, action: np.ndarray, next_obs: np.ndarray, reward: float, terminated: bool, truncated: bool) -> None:
        if self.ep_start_goal is None and self.buffer.gd:
            self.ep_start_goal = self._achieved_goal().copy()
        self.buffer.add(self.obs, action, reward, next_obs, terminated, terminated or truncated)
        self.ep_return += float(reward)
        self.progress.step += 1
        self.obs = next_obs

    def intrinsic_weight(self, step: int) -> float:
        """The intrinsic weight of env step `step`'s gradient step, as the schedule gives it (host side, pure)."""
        self.alpha = self.schedule.value(step, self.progress.success_window)
        return self.alpha

    def sample(self) -> Batch | None:
        """A replay batch, or None while the buffer cannot be sampled (then the RNG is not advanced)."""
        return self.buffer.sample(self.cfg.batch_size, self.rng) if self.buffer.can_sample() else None

    def end_episode(self, success: float | None) -> None:
        """Count the finished episode (the loop then resets the environment with the next `episode_seed`)."""
        p = self.progress
        p.interval["returns"].append(self.ep_return)
        if success is not None:
            p.interval["successes"].append(success)
        p.success_window = list(self.schedule.observe(p.success_window, success))
        if self.ep_start_goal is not None:  # did the episode move what the goal measures (Fetch: the object)?
            moved = float(np.linalg.norm(self._achieved_goal() - self.ep_start_goal) > GOAL_MOVED)
            p.interval.setdefault("moved", []).append(moved)  # a checkpoint older than this key has none
            self.ep_start_goal = None
        p.episode += 1
        self.ep_return = 0.0
        self.ckpt_due = p.step - self.last_ckpt >= self.cfg.checkpoint_every and p.step < self.cfg.total_steps

    # ------------------------------------------------------------------ the steps the loop calls
    def evaluate(self, state: TrainState, final: bool = False) -> None:
        """Deterministic episodes into eval.csv; `final`: `final_eval_episodes` of them, also final_eval.json."""
        p = self.progress
        episodes = self.cfg.n_final_eval_episodes if final else self.cfg.eval_episodes
        p.last_eval = self.evaluator.run(state.pi.params, p.eval_round, episodes)
        p.eval_round += 1
        self.log.log_eval({"step": p.step, **p.last_eval})
        if final:
            rundir.write_json_atomic(self.run_dir / rundir.FINAL_EVAL, {"step": p.step, **p.last_eval})

    def log_row(self, metrics: dict, elapsed: float, steps_done: int) -> dict:
        """Write the log row: the loop's counters and `metrics`, the gradient steps' means since the last row."""
        p = self.progress
        sps = steps_done / elapsed if elapsed > 0 else None
        mean = lambda xs: float(np.mean(xs)) if xs else None  # noqa: E731
        row = {"step": p.step, "time_s": round(elapsed, 3), "steps_per_s": sps, "episodes": p.episode,
               "train_return": mean(p.interval["returns"]), "train_success_rate": mean(p.interval["successes"]),
               "train_goal_moved": mean(p.interval.get("moved", [])),
               "eval_success_rate": p.last_eval["success_rate"], "eval_mean_return": p.last_eval["mean_return"],
               "intrinsic_alpha": self.alpha, **metrics}
        self.log.log_metrics(row)
        p.interval = _new_interval()
        return row

    def save(self, state: TrainState, diag: Diagnostics) -> None:
        """A checkpoint of everything the run needs to go on exactly."""
        p, cfg = self.progress, self.cfg
        meta = {"episode": p.episode, "eval_round": p.eval_round, "host_rng": self.rng.bit_generator.state,
                "interval": p.interval, "last_eval": p.last_eval, "success_window": p.success_window,
                "config": cfg.to_dict()}
        extra = {"normaliser": normaliser.pack(state.norm)} if state.norm is not None else None
        arrays = {**checkpoint.flatten(state._replace(norm=None)), **checkpoint.flatten(diag)}
        checkpoint.save(self.run_dir, p.step, arrays, meta, self.buffer.state_arrays() if cfg.save_buffer else None,
                        cfg.keep_checkpoints, extra)
        self.last_ckpt, self.ckpt_due = p.step, False

    def finish(self, state: TrainState, diag: Diagnostics) -> None:
        """The last checkpoint, then `done` (last: a run with `done` is finished, whoever reads it)."""
        self.save(state, diag)
        rundir.write_json_atomic(self.run_dir / rundir.DONE, {"step": self.progress.step, **self.progress.last_eval})

    def close(self) -> None:
        try:
            self.log.close()
            self.evaluator.close()
            self.env.close()
        finally:
            if self.lock is not None:
                self.lock.release()


def default_run_dir(cfg: Config) -> Path:
    return Path(cfg.out_dir) / f"{rundir.run_name(cfg)}-s{cfg.seed}-{time.strftime('%Y%m%d-%H%M%S')}"


def open_member(cfg: Config, run_dir: Path | str | None, resume: bool) -> tuple[Member, TrainState, Diagnostics]:
    """A run about to train, with its learner's state and diagnostics: new, or from its newest checkpoint with
    `resume` (new if it has none), its directory locked for this process. Writes its config.json and removes a stale
    `done`."""
    env, _, agent, buffer = build(cfg)  # validates env and spaces before anything is written
    if cfg.intrinsic_schedule == "success" and family_of(cfg.env_id) is None:
        env.close()
        raise MCRLError(f"intrinsic_schedule=success averages the training episodes' success, and mcrl knows no "
                        f"success flag of {cfg.env_id} (mcrl.envs.FAMILIES): choose constant or linear")
    run_dir = Path(run_dir) if run_dir is not None else default_run_dir(cfg)
    lock = None
    try:
        if not resume and (run_dir / rundir.CONFIG).exists():
            raise MCRLError(f"{run_dir} already holds a run: continue it with `mcrl train --resume {run_dir}` or "
                            "choose another --run-dir")
        lock = lock_run_dir(run_dir)  # before anything is written: a second writer is refused here
        ckpt = None
        if resume:
            try:
                ckpt = checkpoint.find(run_dir)
            except MCRLError:
                ckpt = None  # killed before its first checkpoint: start over in the same directory
        rng = np.random.default_rng(cfg.seed)
        if ckpt is None:
            state, diag, progress = agent.init(cfg.seed), diagnostics.init(agent.about.metrics), Progress()
        else:
            state, diag, meta = restore_run(cfg, agent, ckpt)
            arrays = checkpoint.load_buffer_arrays(ckpt) if meta["has_buffer"] else None
            if arrays is None:
                raise MCRLError(f"checkpoint {ckpt} has no replay buffer (save_buffer=false): resuming would not "
                                "reproduce the run; start a new run instead")
            buffer.load_arrays(arrays)
            buffer.end_episode()  # the final checkpoint can be mid-episode; the env restarts with a new one
            rng.bit_generator.state = meta["host_rng"]
            progress = Progress(meta["step"], meta["episode"], meta["eval_round"], meta["interval"], meta["last_eval"],
                                meta.get("success_window", []))  # none before issue 67: every run was constant
        rundir.write_json_atomic(run_dir / rundir.CONFIG, cfg.to_dict())
        (run_dir / rundir.DONE).unlink(missing_ok=True)
        if progress.step < cfg.total_steps:  # killed after its final evaluation and checkpoint: that evaluation stands
            (run_dir / rundir.FINAL_EVAL).unlink(missing_ok=True)
        return Member(cfg, run_dir, env, agent, buffer, rng, progress, resumed=resume, lock=lock), state, diag
    except BaseException:
        env.close()
        if lock is not None:
            lock.release()
        raise
