"""The stable-baselines3 side of ``parity_sb3.py`` and ``transplant.py``: SB3's SAC+HER at an mcrl preset's
settings (``ParitySAC``: SB3's gradient step, also summing mcrl's per-step diagnostics), evaluated with mcrl's own
episode runner and seeds, writing an mcrl-format run directory and resumable checkpoints
(``RUN_DIR/sb3_checkpoints/``). Run it through ``python studies/sb3-parity/parity_sb3.py sb3 ...``; the design
and its checks are in docs/studies/sb3-parity.md.

Nothing here imports torch or stable-baselines3 at import time, so ``parity_sb3.py compare`` and ``--help`` work
without the ``bench`` extra, and ``OMP_NUM_THREADS`` can still be set before torch loads.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

#: Per-gradient-step diagnostics ParitySAC sums (all are METRIC_COLUMNS of mcrl.run.logger).
DIAGNOSTICS = ("actor_loss", "critic_loss", "ent_coef", "ent_coef_loss", "q_mean", "mean_ext_reward",
               "mean_total_reward", "saturated_share", "logp_gap")
GOAL_MOVED = 0.01  # as mcrl.run.member.GOAL_MOVED: the achieved goal ended more than 1 cm from its start

#: Where an SB3 run keeps its checkpoints (mcrl's tools read ``checkpoints/`` as their own format).
CHECKPOINTS = "sb3_checkpoints"


class UnsupportedConfig(Exception):
    """An mcrl config option stable-baselines3 cannot mirror."""


def final_eval_episodes(cfg) -> int:
    """Episodes of the evaluation at the end, as mcrl counts them (None = eval_episodes)."""
    n = getattr(cfg, "final_eval_episodes", 100)
    return int(cfg.eval_episodes if n is None else n)


def check_mirrorable(cfg, env) -> bool:
    """Raise UnsupportedConfig for settings SB3 cannot reproduce; return whether HER is used."""
    problems = []
    if cfg.intrinsic_alpha > 0 or cfg.use_intrinsic_models:
        problems.append(f"intrinsic_alpha={cfg.intrinsic_alpha}, intrinsic_models={cfg.intrinsic_models}: "
                        "stable-baselines3 has no intrinsic reward or models (use a SAC preset, e.g. fetchpush-sac)")
    if cfg.init != "torch":
        problems.append(f"init={cfg.init!r}: stable-baselines3 initialises layers as torch's nn.Linear does "
                        "(init=torch) and cannot use Flax's scheme")
    if cfg.action_scale != 1.0:
        problems.append(f"action_scale={cfg.action_scale}: SB3 maps the squashed action straight onto the "
                        "action Box; only action_scale=1 is mirrored")
    if cfg.video_every:
        problems.append(f"video_every={cfg.video_every}: SB3 parity runs record no videos (set video_every=0)")
    from mcrl.envs import GOAL_KEYS

    import gymnasium as gym

    space = env.observation_space
    goal_env = isinstance(space, gym.spaces.Dict) and all(k in space.spaces for k in GOAL_KEYS)
    her = goal_env if cfg.her is None else bool(cfg.her)
    if her and not goal_env:
        problems.append(f"her=true but {cfg.env_id} has no observation/achieved_goal/desired_goal Dict "
                        "observation (set her=false)")
    if not isinstance(env.action_space, gym.spaces.Box):
        problems.append(f"{cfg.env_id} has a {type(env.action_space).__name__} action space: SAC needs a Box")
    steps = env.spec.max_episode_steps if env.spec is not None else None
    if her and steps and cfg.learning_starts < steps:
        problems.append(f"learning_starts={cfg.learning_starts} < the episode length {steps}: SB3's "
                        "HerReplayBuffer raises when asked for a batch before the first episode has ended "
                        "(mcrl waits instead); use learning_starts >= the episode length")
    if problems:
        raise UnsupportedConfig("; ".join(problems))
    return her


def sac_kwargs(cfg, her: bool) -> dict[str, Any]:
    """Keyword arguments of SB3's SAC for an mcrl Config (see docs/studies/sb3-parity.md for the mapping)."""
    kw: dict[str, Any] = dict(
        learning_rate=cfg.learning_rate,
        buffer_size=cfg.buffer_size,
        learning_starts=cfg.learning_starts,
        batch_size=cfg.batch_size,
        tau=cfg.tau,
        gamma=cfg.gamma,
        train_freq=1,
        gradient_steps=1,
        ent_coef=f"auto_{cfg.ent_coef_init}",
        target_entropy="auto" if cfg.target_entropy is None else float(cfg.target_entropy),
        policy_kwargs=dict(net_arch=list(cfg.hidden_sizes)),  # a list: the same for the actor and both critics
        seed=cfg.seed,
        device="cpu",
        verbose=0,
    )
    if her:
        from stable_baselines3 import HerReplayBuffer

        kw["replay_buffer_class"] = HerReplayBuffer
        kw["replay_buffer_kwargs"] = dict(n_sampled_goal=cfg.her_k, goal_selection_strategy=cfg.her_strategy)
    return kw


def make_parity_sac_class():
    """SB3's SAC with a ``train`` that also sums mcrl's per-gradient-step diagnostics."""
    import numpy as np
    import torch as th
    from stable_baselines3 import SAC
    from stable_baselines3.common.utils import polyak_update
    from torch.nn import functional as F

    class ParitySAC(SAC):
        """SAC whose gradient step is SB3 2.9.2's, re-written to record per-step diagnostics.

        Per gradient step, in SB3's order: sample a batch; sample the current policy on its observations
        (``actions_pi``, ``log_prob``); entropy-coefficient loss and Adam step (the coefficient used in this
        step is the value read before that step); next actions from the policy and the clipped double-Q
        target; critic loss, Adam step; actor loss against the updated critics with ``actions_pi``, Adam
        step; Polyak update of the target critics.
        """

        def _setup_model(self) -> None:
            super()._setup_model()
            self.reset_diagnostics()

        def reset_diagnostics(self) -> None:
            self.diag_sums = {k: 0.0 for k in DIAGNOSTICS}
            self.diag_count = 0

        def read_diagnostics(self) -> dict[str, float]:
            """Means over the gradient steps since the last read ({} if there were none); resets the sums."""
            n = self.diag_count
            out = {k: v / n for k, v in self.diag_sums.items()} if n else {}
            if n and self.ent_coef_optimizer is None:
                out.pop("ent_coef_loss", None)
            self.reset_diagnostics()
            return out

        def train(self, gradient_steps: int, batch_size: int = 64) -> None:
            self.policy.set_training_mode(True)
            opts = [self.actor.optimizer, self.critic.optimizer]
            learn_ent = self.ent_coef_optimizer is not None and self.log_ent_coef is not None
            if learn_ent:
                opts.append(self.ent_coef_optimizer)
            self._update_learning_rate(opts)

            per_step: dict[str, list[float]] = {k: [] for k in DIAGNOSTICS}
            for i in range(gradient_steps):
                batch = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
                discount = self.gamma if getattr(batch, "discounts", None) is None else batch.discounts
                if self.use_sde:
                    self.actor.reset_noise()

                # The current policy on the batch: used by the entropy-coefficient loss and the actor loss.
                actions_pi, log_prob = self.actor.action_log_prob(batch.observations)
                log_prob = log_prob.reshape(-1, 1)
                with th.no_grad():  # mcrl.algo.sac.saturation of the same pre-tanh sample (no RNG drawn)
                    u = self.actor.action_dist.gaussian_actions.double()
                    exact = 2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))  # log(1 - tanh(u)^2) per entry
                    eps = th.log(1.0 - th.tanh(u.float()) ** 2 + 1e-6).double()
                    per_step["saturated_share"].append((exact < math.log(1e-6)).double().mean().item())
                    per_step["logp_gap"].append((eps - exact).sum(-1).mean().item())

                if learn_ent:
                    alpha = th.exp(self.log_ent_coef.detach())  # this step's coefficient, before its update
                    alpha_loss = -(self.log_ent_coef * (log_prob + self.target_entropy).detach()).mean()
                    self.ent_coef_optimizer.zero_grad()
                    alpha_loss.backward()
                    self.ent_coef_optimizer.step()
                    per_step["ent_coef_loss"].append(alpha_loss.item())
                else:
                    alpha = self.ent_coef_tensor
                per_step["ent_coef"].append(alpha.item())

                with th.no_grad():
                    next_actions, next_log_prob = self.actor.action_log_prob(batch.next_observations)
                    q_next = th.cat(self.critic_target(batch.next_observations, next_actions), dim=1)
                    q_next = th.min(q_next, dim=1, keepdim=True)[0] - alpha * next_log_prob.reshape(-1, 1)
                    target = batch.rewards + (1 - batch.dones) * discount * q_next

                q_taken = self.critic(batch.observations, batch.actions)  # one (B, 1) tensor per critic
                critic_loss = 0.5 * sum(F.mse_loss(q, target) for q in q_taken)
                per_step["critic_loss"].append(critic_loss.item())
                per_step["q_mean"].append(th.cat(q_taken, dim=1).mean().item())
                per_step["mean_ext_reward"].append(batch.rewards.mean().item())
                self.critic.optimizer.zero_grad()
                critic_loss.backward()
                self.critic.optimizer.step()

                q_pi = th.cat(self.critic(batch.observations, actions_pi), dim=1)
                actor_loss = (alpha * log_prob - th.min(q_pi, dim=1, keepdim=True)[0]).mean()
                per_step["actor_loss"].append(actor_loss.item())
                self.actor.optimizer.zero_grad()
                actor_loss.backward()
                self.actor.optimizer.step()

                if i % self.target_update_interval == 0:
                    polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                    polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)

            per_step["mean_total_reward"] = per_step["mean_ext_reward"]  # no MC reward: total = extrinsic
            self._n_updates += gradient_steps
            for k, vals in per_step.items():
                self.diag_sums[k] += float(sum(vals))
            self.diag_count += gradient_steps

            # The same logger records as SB3's train().
            self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
            for k in ("ent_coef", "actor_loss", "critic_loss"):
                self.logger.record(f"train/{k}", np.mean(per_step[k]))
            if per_step["ent_coef_loss"]:
                self.logger.record("train/ent_coef_loss", np.mean(per_step["ent_coef_loss"]))

    return ParitySAC


def build_model(cfg, sac_class=None):
    """(model, her) for the config: SB3 SAC (ParitySAC by default) on mcrl's environment."""
    from mcrl.envs import make_env

    env = make_env(cfg)
    try:
        her = check_mirrorable(cfg, env)
    except UnsupportedConfig:
        env.close()
        raise
    policy = "MultiInputPolicy" if hasattr(env.observation_space, "spaces") else "MlpPolicy"
    cls = sac_class or make_parity_sac_class()
    return cls(policy, env, **sac_kwargs(cfg, her)), her


def sb3_policy(model, env):
    """SB3's deterministic policy as an ``act`` of ``mcrl.run.evaluation.run_episode``: mcrl's flat policy input
    -> an action in [-1, 1].

    The input goes back into the environment's observation layout (SB3 casts it to float32, as mcrl's flattening
    did), and SB3's action on the Box comes back to [-1, 1] in float64; ``run_episode`` maps it onto the Box again,
    exactly for Fetch's bounds of +-1 (and any of +-2**k), so ``env.step`` gets SB3's own action bit for bit.
    """
    import numpy as np
    from mcrl.envs import GOAL_KEYS

    space, box = env.observation_space, env.action_space
    low, high = np.asarray(box.low, np.float64), np.asarray(box.high, np.float64)
    if hasattr(space, "spaces"):  # a goal Dict, flattened as observation | achieved_goal | desired_goal
        shapes = [space.spaces[k].shape for k in GOAL_KEYS]
        cuts = np.cumsum([int(np.prod(sh)) for sh in shapes])[:-1]

        def unflatten(flat):
            return {k: part.reshape(sh) for k, sh, part in zip(GOAL_KEYS, shapes, np.split(flat, cuts))}
    else:
        def unflatten(flat):
            return flat.reshape(space.shape)

    def act(flat: np.ndarray) -> np.ndarray:
        action, _ = model.predict(unflatten(flat), deterministic=True)
        return 2.0 * (np.asarray(action, np.float64) - low) / (high - low) - 1.0

    return act


class Evaluator:
    """Deterministic episodes of an SB3 model on a separate environment: mcrl's evaluation rounds (the same
    episode seeds, episode runner and summary), so both systems play the same start states and goals."""

    def __init__(self, cfg):
        import numpy as np
        from mcrl.envs import make_env

        # mcrl.run.evaluation imports jax, whose import draws from numpy's global random state, the one SB3
        # samples replay batches from: put it back, so that evaluating changes nothing in training.
        state = np.random.get_state()
        from mcrl.run import evaluation

        np.random.set_state(state)
        self.evaluation = evaluation
        self.cfg = cfg
        self.env = make_env(cfg)

    def run(self, model, round_index: int, episodes: int) -> dict:
        ev, act = self.evaluation, sb3_policy(model, self.env)
        seeds = [ev.eval_episode_seed(self.cfg.seed, round_index, i) for i in range(episodes)]
        results = [ev.run_episode(self.env, act, self.cfg.action_scale, seed) for seed in seeds]
        return ev.summarise([r for r, _ in results], [s for _, s in results])

    def close(self) -> None:
        self.env.close()


def sim_snapshot(env) -> dict | None:
    """The state that decides a MuJoCo env's future: integration state (incl. the solver's warm start),
    goal and random generator; None for an env without MuJoCo ``model``/``data``."""
    import mujoco
    import numpy as np

    u = env.unwrapped
    model, data = getattr(u, "model", None), getattr(u, "data", None)
    if not isinstance(data, mujoco.MjData):
        return None
    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    state = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state, spec)
    goal = getattr(u, "goal", None)
    return {"mj_state": state, "goal": None if goal is None else np.array(goal),
            "np_random": u.np_random.bit_generator.state}


def sim_restore(env, snap: dict) -> None:
    """Put a snapshot of :func:`sim_snapshot` back into an env of the same kind."""
    import mujoco

    u = env.unwrapped
    mujoco.mj_setState(u.model, u.data, snap["mj_state"], mujoco.mjtState.mjSTATE_INTEGRATION)
    mujoco.mj_forward(u.model, u.data)
    if snap["goal"] is not None:
        u.goal = snap["goal"].copy()
    u.np_random.bit_generator.state = snap["np_random"]


def _rng_snapshot() -> dict:
    import random

    import numpy as np
    import torch

    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def _rng_restore(snap: dict) -> None:
    import random

    import numpy as np
    import torch

    torch.set_rng_state(snap["torch"])
    np.random.set_state(snap["numpy"])
    random.setstate(snap["python"])


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The newest complete SB3 checkpoint of a run (``state.pkl`` is written last), or None."""
    done = [p for p in sorted((Path(run_dir) / CHECKPOINTS).glob("step_*")) if (p / "state.pkl").is_file()]
    return done[-1] if done else None


def save_checkpoint(run_dir: Path, model, step: int, state: dict, keep: int) -> Path:
    """model.zip + replay_buffer.pkl + state.pkl under sb3_checkpoints/step_<N>, written under a temporary
    name and renamed into place, so a kill at any moment leaves the previous checkpoint usable."""
    import os
    import pickle
    import shutil

    root = Path(run_dir) / CHECKPOINTS
    root.mkdir(parents=True, exist_ok=True)
    final = root / f"step_{step:09d}"
    tmp = root / f".tmp-{final.name}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    model.save(tmp / "model.zip")
    model.save_replay_buffer(tmp / "replay_buffer.pkl")
    with open(tmp / "state.pkl", "wb") as f:
        pickle.dump(state, f, protocol=pickle.HIGHEST_PROTOCOL)
        f.flush()
        os.fsync(f.fileno())
    shutil.rmtree(final, ignore_errors=True)
    os.rename(tmp, final)
    for old in sorted(root.glob("step_*"))[:-max(1, keep)]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def _make_recorder(cfg, run_dir: Path, model, evaluator: Evaluator, progress: bool, resume: dict | None = None,
                   checkpoints: bool = True):
    """A BaseCallback that writes mcrl's metrics.csv / eval.csv rows at mcrl's points of the loop, and
    the checkpoints.

    mcrl, after env step N (and its gradient step): evaluates if N % eval_every == 0 and N < total;
    logs a metrics row if N % log_every == 0 or N == total, doing the final evaluation first at N == total.
    In SB3's loop the gradient step of env step N follows the rollout of step N, so "after step N" is the
    start of the next rollout (``_on_rollout_start``) or, for the last step, the end of training. A
    checkpoint is written there too, once N has passed the next multiple of checkpoint_every and the
    episode has just ended (``resume`` is the recorder part of the checkpoint resumed from).
    """
    import numpy as np
    from mcrl.envs import success_of
    from mcrl.run.rundir import EVAL_COLUMNS, METRIC_COLUMNS, append_row, write_json_atomic
    from stable_baselines3.common.callbacks import BaseCallback

    total = cfg.total_steps
    n_final = final_eval_episodes(cfg)
    every = cfg.checkpoint_every

    class Recorder(BaseCallback):
        def __init__(self):
            super().__init__(verbose=0)
            r = resume or {}
            self.episodes = r.get("episodes", 0)
            self.eval_round = r.get("eval_round", 0)
            self.interval = {"moved": [], **r.get("interval", {"returns": [], "successes": []})}
            self.start_goal = None  # the achieved goal at the episode's start (checkpoints fall at episode ends)
            self.last_eval: dict[str, Any] = r.get("last_eval", {"success_rate": None, "mean_return": None})
            self.elapsed0 = r.get("elapsed", 0.0)  # training time before this process (time_s continues)
            self.done_step = r.get("step", 0)  # the last step whose rows are written
            self.next_ckpt = (self.done_step // every + 1) * every if every else None
            self.episode_ended = True  # a fresh run starts at an episode's start, a resumed one too
            self.t_start = time.perf_counter()
            self.bar = None
            if progress:
                from tqdm import tqdm

                self.bar = tqdm(total=total, initial=self.done_step, unit="step", dynamic_ncols=True,
                                smoothing=0.05, mininterval=1.0)

        def _on_training_start(self) -> None:
            self.t_start = time.perf_counter() - self.elapsed0

        def _on_step(self) -> bool:
            last = self.model._last_obs  # the observation this step's action answered (stored after _on_step)
            if self.start_goal is None and isinstance(last, dict) and "achieved_goal" in last:
                self.start_goal = np.array(last["achieved_goal"][0])
            for info, done in zip(self.locals["infos"], self.locals["dones"]):
                if done:
                    if self.start_goal is not None:
                        end = np.asarray(info["terminal_observation"]["achieved_goal"])
                        self.interval["moved"].append(float(np.linalg.norm(end - self.start_goal) > GOAL_MOVED))
                        self.start_goal = None
                    ep = info.get("episode")  # SB3's Monitor wrapper: the episode's return and length
                    self.interval["returns"].append(float(ep["r"]))
                    s = success_of(info)
                    if s is not None:
                        self.interval["successes"].append(s)
                    self.episodes += 1
            self.episode_ended = bool(self.locals["dones"][0])
            if self.bar is not None:
                self.bar.update(1)
            return True

        def _on_rollout_start(self) -> None:
            if self.num_timesteps > self.done_step:  # a resumed run has written step N's rows already
                self._after_step(self.num_timesteps)

        def _on_training_end(self) -> None:
            if self.num_timesteps > self.done_step:
                self._after_step(self.num_timesteps)

        def _evaluate(self, step: int, episodes: int) -> None:
            res = evaluator.run(self.model, self.eval_round, episodes)
            self.eval_round += 1
            self.last_eval = res
            append_row(run_dir / "eval.csv", EVAL_COLUMNS, {"step": step, **res})

        def _after_step(self, step: int) -> None:
            if cfg.eval_every and step % cfg.eval_every == 0 and step < total:
                self._evaluate(step, cfg.eval_episodes)
            if step % cfg.log_every == 0 or step == total:
                if step == total:
                    self._evaluate(step, n_final)
                    write_json_atomic(run_dir / "final_eval.json", {"step": step, **self.last_eval})
                elapsed = time.perf_counter() - self.t_start
                sps = step / elapsed if elapsed > 0 else None
                iv = self.interval
                row = {"step": step, "time_s": round(elapsed, 3), "steps_per_s": sps, "episodes": self.episodes,
                       "train_return": float(np.mean(iv["returns"])) if iv["returns"] else None,
                       "train_success_rate": float(np.mean(iv["successes"])) if iv["successes"] else None,
                       "train_goal_moved": float(np.mean(iv["moved"])) if iv["moved"] else None,
                       "eval_success_rate": self.last_eval["success_rate"],
                       "eval_mean_return": self.last_eval["mean_return"],
                       **model.read_diagnostics()}
                append_row(run_dir / "metrics.csv", METRIC_COLUMNS, row)
                self.interval = {"returns": [], "successes": [], "moved": []}
                if self.bar is not None:
                    post = {"sps": f"{sps:.0f}" if sps else "-"}
                    if self.last_eval["success_rate"] is not None:
                        post["success"] = f"{self.last_eval['success_rate']:.2f}"
                    self.bar.set_postfix(post, refresh=False)
            self.done_step = step
            if checkpoints and every and step >= self.next_ckpt and self.episode_ended and step < total:
                self._checkpoint(step)
                self.next_ckpt = (step // every + 1) * every

        def _checkpoint(self, step: int) -> None:
            recorder = {"step": step, "episodes": self.episodes, "eval_round": self.eval_round,
                        "interval": self.interval, "last_eval": self.last_eval,
                        "elapsed": time.perf_counter() - self.t_start}
            state = {"recorder": recorder, "diagnostics": (dict(model.diag_sums), model.diag_count),
                     "rng": _rng_snapshot(), "train_env": sim_snapshot(model.get_env().envs[0]),
                     "eval_env": sim_snapshot(evaluator.env),
                     "action_space": model.action_space.np_random.bit_generator.state}
            save_checkpoint(run_dir, model, step, state, cfg.keep_checkpoints)

        def close(self) -> None:
            if self.bar is not None:
                self.bar.close()

    return Recorder()


#: Files an SB3 parity run writes (removed first by --overwrite; CHECKPOINTS too).
RUN_FILES = ("config.json", "peer.json", "metrics.csv", "eval.csv", "final_eval.json", "done", "sb3_model.zip")


def _resume_model(cfg, ckpt: Path, evaluator: Evaluator):
    """ParitySAC, its replay buffer, the random states and both environments as they were at ``ckpt``;
    returns (model, the recorder's state)."""
    import pickle

    from mcrl.envs import make_env

    with open(ckpt / "state.pkl", "rb") as f:
        state = pickle.load(f)
    env = make_env(cfg)
    check_mirrorable(cfg, env)
    # force_reset=False keeps the saved last observation; load() re-seeds everything (set_random_seed), so
    # the saved random states go back afterwards.
    model = make_parity_sac_class().load(ckpt / "model.zip", env=env, device="cpu", force_reset=False)
    model.load_replay_buffer(ckpt / "replay_buffer.pkl", truncate_last_traj=False)  # an episode had ended
    vec = model.get_env()
    vec._reset_seeds()  # load() asked for a seeded reset: the original run's next reset was unseeded
    vec.envs[0].reset()  # the wrappers' episode counters start afresh, as after the original's auto-reset
    sim_restore(vec.envs[0], state["train_env"])
    if state["eval_env"] is not None:
        sim_restore(evaluator.env, state["eval_env"])
    model.action_space.np_random.bit_generator.state = state["action_space"]
    model.diag_sums, model.diag_count = dict(state["diagnostics"][0]), state["diagnostics"][1]
    _rng_restore(state["rng"])
    return model, state["recorder"]


def train(cfg, run_dir: Path, threads: int = 1, progress: bool = True, overwrite: bool = False,
          resume: bool = False) -> Path:
    """Train SB3 SAC(+HER) with ``cfg`` into ``run_dir`` (an mcrl-format run directory).

    ``resume`` continues the run in ``run_dir`` from its newest checkpoint (``cfg`` must be its config).
    """
    import shutil

    import torch

    run_dir = Path(run_dir)
    if resume:
        if (run_dir / "done").exists():
            raise FileExistsError(f"{run_dir} is finished: there is nothing to resume")
        ckpt = latest_checkpoint(run_dir)
        if ckpt is None:
            raise FileNotFoundError(f"{run_dir} has no SB3 checkpoint to resume from (it died before its first "
                                    "one, or is not an SB3 run): start it again with --overwrite")
    elif (run_dir / "config.json").exists():
        if not overwrite:
            raise FileExistsError(f"{run_dir} already holds a run: continue it with --resume, replace it with "
                                  "--overwrite, or choose another --run-dir")
        for name in RUN_FILES:
            (run_dir / name).unlink(missing_ok=True)
        shutil.rmtree(run_dir / CHECKPOINTS, ignore_errors=True)

    torch.set_num_threads(threads)
    import stable_baselines3

    from mcrl.run.rundir import EVAL_COLUMNS, METRIC_COLUMNS, start_csv, truncate_rows, write_json_atomic

    evaluator = Evaluator(cfg)
    try:
        if resume:
            model, rec_state = _resume_model(cfg, ckpt, evaluator)
            step = rec_state["step"]
            for name, cols in (("metrics.csv", METRIC_COLUMNS), ("eval.csv", EVAL_COLUMNS)):
                truncate_rows(run_dir / name, cols, step)  # rows a killed process wrote after its checkpoint
            peer = json.loads((run_dir / "peer.json").read_text())
            peer["resumed_at"] = [*peer.get("resumed_at", []), step]
            (run_dir / "peer.json").write_text(json.dumps(peer, indent=2) + "\n")
        else:
            model, _ = build_model(cfg)  # validates before anything is written
            rec_state = None
            run_dir.mkdir(parents=True, exist_ok=True)
            (run_dir / "config.json").write_text(cfg.to_json())
            (run_dir / "peer.json").write_text(json.dumps({
                "system": "stable-baselines3", "version": stable_baselines3.__version__,
                "torch": torch.__version__, "torch_threads": torch.get_num_threads()}, indent=2) + "\n")
            for name, cols in (("metrics.csv", METRIC_COLUMNS), ("eval.csv", EVAL_COLUMNS)):
                start_csv(run_dir / name, cols)
    except BaseException:
        evaluator.close()
        raise

    checkpoints = cfg.save_buffer and sim_snapshot(model.get_env().envs[0]) is not None
    recorder = _make_recorder(cfg, run_dir, model, evaluator, progress, rec_state, checkpoints)
    try:
        model.learn(total_timesteps=cfg.total_steps - model.num_timesteps, callback=recorder,
                    reset_num_timesteps=not resume)
        model.save(run_dir / "sb3_model.zip")  # the policy and optimisers (not the replay buffer)
        write_json_atomic(run_dir / "done", {"step": int(model.num_timesteps), **recorder.last_eval})
        shutil.rmtree(run_dir / CHECKPOINTS, ignore_errors=True)  # finished: the replay buffers are dead weight
    finally:
        recorder.close()
        evaluator.close()
        model.get_env().close()
    return run_dir


def check_train_equivalence(steps: int = 400, seed: int = 0, preset: str = "fetchpush-sac") -> dict:
    """Train stock SB3 SAC and ParitySAC side by side for ``steps`` env steps; compare every parameter.

    Returns {"steps", "max_abs_diff", "identical"}; identical means bit-for-bit equal parameters of the
    actor, both critics, the target critics and log(ent_coef).
    """
    import torch
    from mcrl.config import resolve_config
    from stable_baselines3 import SAC

    torch.set_num_threads(1)
    cfg = resolve_config(preset, {"total_steps": steps, "seed": seed})
    params = []
    for cls in (SAC, make_parity_sac_class()):
        model, _ = build_model(cfg, cls)
        model.learn(total_timesteps=steps)
        tensors = [p.detach().clone() for p in model.policy.parameters()]
        tensors += [p.detach().clone() for p in model.critic_target.parameters()]
        tensors.append(model.log_ent_coef.detach().clone())
        params.append(tensors)
        model.get_env().close()
    diff = max(float((a - b).abs().max()) for a, b in zip(*params))
    return {"steps": steps, "max_abs_diff": diff, "identical": diff == 0.0 and not math.isnan(diff)}


def _params(run_dir: Path) -> list:
    """Every parameter of a finished run's sb3_model.zip (actor, critics, target critics, log ent_coef)."""
    from stable_baselines3.common.save_util import load_from_zip_file

    _, params, variables = load_from_zip_file(run_dir / "sb3_model.zip", device="cpu")
    return [t for name in sorted(params) for t in params[name].values() if hasattr(t, "shape")] + \
        [variables[k] for k in sorted(variables or {})]


def check_resume_equivalence(workdir: Path, steps: int = 600, kill_after: int = 400, seed: int = 0,
                             preset: str = "fetchpush-sac") -> dict:
    """Run A trains ``steps`` steps uninterrupted; run B is the same run killed (SIGKILL) once its
    checkpoint at ``kill_after`` steps and a metrics row after it exist, then resumed. Compares their final
    parameters and every metrics.csv / eval.csv value (wall-clock columns aside).

    Returns {"steps", "killed_at", "resumed_from", "max_abs_diff", "rows_equal", "identical"}.
    """
    import csv
    import os
    import signal
    import subprocess
    import sys

    import torch
    from mcrl.config import resolve_config

    workdir = Path(workdir)
    sets = {"total_steps": steps, "checkpoint_every": kill_after // 2, "keep_checkpoints": 3, "eval_every": 200,
            "eval_episodes": 2, "log_every": 100, "final_eval_episodes": 2, "seed": seed}
    cfg = resolve_config(preset, sets)
    train(cfg, workdir / "a", progress=False, overwrite=True)

    b = workdir / "b"
    script = Path(__file__).with_name("parity_sb3.py")
    cmd = [sys.executable, str(script), "sb3", "--preset", preset, "--seed", str(seed), "--steps", str(steps),
           "--run-dir", str(b), "--overwrite", "--no-progress", "--threads", "1"]
    cmd += [a for k, v in sets.items() if k not in ("total_steps", "seed") for a in ("--set", f"{k}={v}")]
    proc = subprocess.Popen(cmd, env={**os.environ, "OMP_NUM_THREADS": "1"}, start_new_session=True)
    target = b / CHECKPOINTS / f"step_{kill_after:09d}" / "state.pkl"

    def last_row() -> int:
        try:
            with open(b / "metrics.csv", newline="") as f:
                return max((int(r["step"]) for r in csv.DictReader(f)), default=0)
        except (OSError, ValueError, KeyError):
            return 0

    # Kill once rows past the checkpoint exist: the resume must drop them and write them again.
    while proc.poll() is None and not (target.exists() and last_row() > kill_after):
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    if not target.exists() or (b / "done").exists():
        raise RuntimeError(f"the run in {b} was not killed between its checkpoint at {kill_after} and its end")
    killed_at = last_row()
    resumed_from = int(latest_checkpoint(b).name.split("_")[1])
    torch.set_num_threads(1)
    train(cfg, b, progress=False, resume=True)

    diff = max(float((x - y).detach().abs().max()) for x, y in zip(_params(workdir / "a"), _params(b)))

    def rows_of(path: Path) -> list[dict]:  # every column but the wall-clock ones
        with open(path, newline="") as f:
            return [{k: v for k, v in r.items() if k not in ("time_s", "steps_per_s")} for r in csv.DictReader(f)]

    rows = {name: rows_of(workdir / "a" / name) == rows_of(b / name) for name in ("metrics.csv", "eval.csv")}
    return {"steps": steps, "killed_at": killed_at, "resumed_from": resumed_from, "max_abs_diff": diff,
            "rows_equal": rows, "identical": diff == 0.0 and all(rows.values())}
