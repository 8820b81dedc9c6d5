"""The training loop, one for a single run and for a vmapped group of runs: a single run is a group of one.

Every step, as in CleanRL's loop: act (uniformly at random before `learning_starts`, then the policy with a key
folded from (seed, step)), step each run's environment (`EnvPool`), store each transition in its run's replay
buffer, and take one gradient step on each run's (HER-relabelled) batch; then the steps the loop calls at their
schedule: evaluation (and its video), the log row, a checkpoint, in this order. The members (`Member`) are
the host side of each run, the learner (`Learner` for one run, `mcrl.run.group.GroupLearner` for a group) the
device side; the video step is passed in by the caller (`mcrl.video.render.record_training_video`), since
rendering sits above the run.

A checkpoint is taken at an episode end, after that step's evaluation and log row, so a resumed run repeats
none of them and ends with the same numbers as an uninterrupted run on the CPU. On SIGINT or SIGTERM
(`mcrl.run.stop`) each run saves such a checkpoint at its next episode end and the loop raises `stop.Stopped`;
a full disk ends the run with a one-line MCRLError, its last complete checkpoint intact.
"""
from __future__ import annotations

import contextlib
import dataclasses
import errno
import shutil
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

from mcrl.config import Config
from mcrl.envs import resolve_env_id
from mcrl.errors import MCRLError
from mcrl.progress import progress as progress_bar
from mcrl.run import rundir, stop
from mcrl.run.envpool import EnvPool
from mcrl.run.learner import Learner
from mcrl.run.lock import check_free
from mcrl.run.member import Member, open_member

VideoStep = Callable  # (cfg, agent, state, run_dir, step, logger, alpha=) -> the video's path: record_training_video


def run_loop(members: list[Member], learner, pool: EnvPool, video: VideoStep | None = None, bar=None) -> None:
    """Train `members` (equal schedules: `mcrl.run.group.group_key`) from their common step to `total_steps`;
    after a stop request (`mcrl.run.stop.requested`), raise `stop.Stopped` once each has saved at an episode end."""
    cfg = members[0].cfg
    step = members[0].progress.step
    saved_for_stop: set[int] | None = None  # the members that saved since the stop was noticed
    t_start, steps_at_start = time.perf_counter(), step
    for i, m in enumerate(members):
        m.obs = pool.reset(i, m.episode_seed())
    while step < cfg.total_steps:
        if step < cfg.learning_starts:
            actions = np.stack([m.random_action() for m in members])
        else:
            actions = learner.act(np.stack([m.obs for m in members]), step)
        res = pool.step(actions)
        step += 1
        for i, m in enumerate(members):
            m.store(actions[i], res.next_obs[i], res.reward[i], bool(res.terminated[i]), bool(res.truncated[i]))
        alphas = [m.intrinsic_weight(step) for m in members]  # every step: the log row shows the one in force
        if step > cfg.learning_starts:
            learner.update([m.sample() for m in members], alphas)
        for i, m in enumerate(members):
            if res.terminated[i] or res.truncated[i]:
                m.end_episode(res.success[i])
                m.obs = pool.reset(i, m.episode_seed())

        final = step == cfg.total_steps  # the final evaluation (thesis: "after training") lands in the last row
        if final or (cfg.eval_every and step % cfg.eval_every == 0):
            for i, m in enumerate(members):
                state, _ = learner.state_of(i)
                m.evaluate(state, final)
                if video is not None and cfg.video_every and step % cfg.video_every == 0:
                    video(m.cfg, m.agent, state, m.run_dir, step, m.log, alpha=m.alpha)
        if final or step % cfg.log_every == 0:
            elapsed = time.perf_counter() - t_start
            rows = [m.log_row(mx, elapsed, step - steps_at_start) for m, mx in zip(members, learner.read_metrics())]
            if bar is not None:
                bar.postfix(_postfix(members, rows[-1]))
        for i, m in enumerate(members):
            if m.ckpt_due:  # after this step's evaluation and log row, so a resume repeats none of them
                m.save(*learner.state_of(i))
        if stop.requested() is not None and not final:
            if saved_for_stop is None:
                saved_for_stop = set()
                _say(stop.announcement(step), bar)
            for i, m in enumerate(members):  # an episode end is the first point from which a resume is exact
                if i not in saved_for_stop and (res.terminated[i] or res.truncated[i]):
                    if m.last_ckpt != step:
                        m.save(*learner.state_of(i))
                    saved_for_stop.add(i)
            if len(saved_for_stop) == len(members):
                raise stop.Stopped(stop.requested(), [(m.run_dir, m.last_ckpt) for m in members])
        if bar is not None:
            bar.update(1)
    for i, m in enumerate(members):
        m.finish(*learner.state_of(i))


def _postfix(members: list[Member], row: dict) -> str:
    post = {"sps": f"{row['steps_per_s']:.0f}" if row["steps_per_s"] else "-"}
    if len(members) > 1:
        post["runs"] = len(members)
    elif members[0].progress.last_eval["success_rate"] is not None:
        post["success"] = f"{members[0].progress.last_eval['success_rate']:.2f}"
    return ", ".join(f"{k}={v}" for k, v in post.items())


def _say(msg: str | None, bar) -> None:
    if msg is not None:
        bar.write(msg) if bar is not None else print(msg, file=sys.stderr, flush=True)


def _disk_full(e: OSError, run_dirs: list[Path]) -> MCRLError:
    """The one-line error of a write that found no space: the disk, and what each run kept."""
    kept = []
    for d in run_dirs:
        name = rundir.latest_checkpoint(d)
        step = rundir.checkpoint_step(name) if name else None
        kept.append(f"{d} resumes from step {step:,}" if step is not None else f"{d} starts over")
    where = e.filename or (run_dirs[0] if run_dirs else None)
    try:
        free = f", {shutil.disk_usage(Path(where).parent if e.filename else where).free / 2**20:,.0f} MiB free"
    except (OSError, TypeError):
        free = ""
    return MCRLError(f"{e.strerror or 'no space left on device'} ({where}{free}): each run keeps its last complete "
                     f"checkpoint ({'; '.join(kept)}); free space, then resume with `mcrl train --resume RUN_DIR` "
                     "(a sweep: run it again)")


def train_runs(cfgs: list[Config], run_dirs: list[Path | str | None], resume: bool, make_learner: Callable,
               env_workers: int = 0, progress: bool = False, video: VideoStep | None = None) -> list[Path]:
    """Open the runs (new, or with `resume` from their newest checkpoints), train them through `run_loop` with
    the learner `make_learner(members, states, diagnostics)` builds, close them; their directories."""
    if video is None and any(c.video_every for c in cfgs):
        raise MCRLError(f"video_every={cfgs[0].video_every} records evaluation videos, and this call passes no video "
                        "step: use mcrl.train or `mcrl train`, or pass video=mcrl.video.render.record_training_video")
    cfgs = [resolve_env_id(c) for c in cfgs]  # config.json and the run's name get the id gymnasium makes
    members, states, diags = [], [], []
    pool = bar = None
    ok = False
    try:
        with stop.handle():
            for d in run_dirs:  # a run another process writes: refused before this call writes anything
                if d is not None:
                    check_free(d)
            for cfg, d in zip(cfgs, run_dirs):
                m, s, dg = open_member(cfg, d, resume)
                members.append(m)
                states.append(s)
                diags.append(dg)
            steps = {m.progress.step for m in members}
            if len(steps) != 1:
                raise MCRLError(f"the runs of a group must resume from the same step, not {sorted(steps)}: "
                                "group them by their checkpoints' steps")
            learner = make_learner(members, states, diags)
            # each run's own env recomputes its HER rewards; the pool steps it, or steps copies in worker processes
            pool = EnvPool(cfgs, env_workers, envs=[m.env for m in members])
            bar = progress_bar(cfgs[0].total_steps, "train", initial=steps.pop(), enabled=progress)
            run_loop(members, learner, pool, video, bar)
        ok = True
    except OSError as e:
        if e.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        raise _disk_full(e, [m.run_dir for m in members]) from None
    finally:
        for close in [*([bar.close] if bar is not None else []), *([pool.close] if pool is not None else []),
                      *(m.close for m in members)]:
            with contextlib.suppress(*(() if ok else (OSError,))):  # an error on its way out stays the error
                close()
    return [m.run_dir for m in members]


def train(cfg: Config, run_dir: Path | str | None = None, progress: bool = True, resume: bool = False,
          video: VideoStep | None = None) -> Path:
    """Train one run; with `resume`, continue `run_dir` from its newest checkpoint (or start it if it has none).
    `video` records the evaluation videos `video_every` asks for (`mcrl.video.render.record_training_video`)."""
    (out,) = train_runs([cfg], [run_dir], resume, lambda ms, ss, ds: Learner(ms[0].agent, ss[0], ds[0]),
                        progress=progress, video=video)
    return out


def resume(run_dir: Path | str, progress: bool = True, total_steps: int | None = None,
           video: VideoStep | None = None) -> Path:
    """Continue a run from its newest checkpoint; `total_steps` extends a finished one."""
    cfg = rundir.read_config(run_dir)
    if total_steps is not None:
        cfg = dataclasses.replace(cfg, total_steps=total_steps)
    if rundir.is_done(run_dir) and total_steps is None:
        raise MCRLError(f"{run_dir} already finished: pass --steps N (more than {cfg.total_steps}) to continue it")
    return train(cfg, run_dir, progress=progress, resume=True, video=video)
