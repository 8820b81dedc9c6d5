"""The stable-baselines3 side of ``benchmarks/parity_sb3.py``: SAC+HER at an mcrl preset's settings,
writing an mcrl-format run directory.

Nothing here imports torch or stable-baselines3 at module import time, so ``parity_sb3.py compare`` (and
``--help``) work without the ``bench`` extra, and ``OMP_NUM_THREADS`` can still be set before torch loads.

Per-gradient-step diagnostics
-----------------------------
mcrl logs, per log interval, the mean over the interval's gradient steps of ``critic_loss``,
``actor_loss``, ``ent_coef`` (the value used in that step, read before its own update), ``ent_coef_loss``
and ``q_mean`` (the mean over both critics of Q(obs, action) on that step's replay batch). To get the same
quantities from SB3, :class:`ParitySAC` overrides ``SAC.train``: it is a re-implementation of SB3 2.9.2's
``SAC.train`` (same operations, same order, so the same random numbers are drawn: the run is the run stock
SB3 would make, checked bit for bit by ``parity_sb3.py check``), which additionally sums those values per
gradient step. The alternative, SB3's logger values plus a Q estimate on one extra replay sample in a
callback, would give ``q_mean`` on a different batch than the one trained on and would draw extra random
numbers from the replay sampler (changing the run); so the subclass is used.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

#: Per-gradient-step diagnostics ParitySAC sums (all are METRIC_COLUMNS of mcrl.run.logger).
DIAGNOSTICS = ("actor_loss", "critic_loss", "ent_coef", "ent_coef_loss", "q_mean", "mean_ext_reward",
               "mean_total_reward")

# mcrl's evaluation seeding (mcrl.run.trainer): stream 1, episode index round * 100_003 + i. Using the same
# seeds makes both systems' evaluation rounds play the same start states and goals.
_EVAL_STREAM = 1


class UnsupportedConfig(Exception):
    """An mcrl config option stable-baselines3 cannot mirror."""


def final_eval_episodes(cfg) -> int:
    """Episodes of the evaluation at the end, as mcrl counts them (None = eval_episodes)."""
    n = getattr(cfg, "final_eval_episodes", 100)
    return int(cfg.eval_episodes if n is None else n)


def check_mirrorable(cfg, env) -> bool:
    """Raise UnsupportedConfig for settings SB3 cannot reproduce; return whether HER is used."""
    problems = []
    if cfg.mc_alpha > 0 or cfg.use_mc_models:
        problems.append(f"mc_alpha={cfg.mc_alpha}, mc_models={cfg.mc_models}: stable-baselines3 has no "
                        "morphological-computation reward or models (use a SAC preset, e.g. fetchpush-sac)")
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
    """Keyword arguments of SB3's SAC for an mcrl Config (see docs/parity.md for the mapping)."""
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


class Evaluator:
    """Deterministic episodes of an SB3 model on a separate environment, seeded as mcrl seeds its own."""

    def __init__(self, cfg):
        from mcrl.envs import make_env

        self.cfg = cfg
        self.env = make_env(cfg)

    def run(self, model, round_index: int, episodes: int) -> dict:
        import numpy as np
        from mcrl.envs import episode_seed, success_of

        returns, successes = [], []
        for i in range(episodes):
            obs, _ = self.env.reset(seed=episode_seed(self.cfg.seed, _EVAL_STREAM, round_index * 100_003 + i))
            done, ret, info = False, 0.0, {}
            while not done:
                action, _ = model.predict(obs, deterministic=True)
                obs, r, term, trunc, info = self.env.step(action)
                ret += float(r)
                done = term or trunc
            returns.append(ret)
            s = success_of(info)  # read at the episode's last step
            successes.append(np.nan if s is None else s)
        succ = float(np.mean(successes)) if not np.all(np.isnan(successes)) else None
        return {"success_rate": succ, "mean_return": float(np.mean(returns)), "episodes": episodes}

    def close(self) -> None:
        self.env.close()


def _write_json_atomic(path: Path, obj: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(obj))
    tmp.replace(path)


def _append_csv(path: Path, columns, row: dict) -> None:
    import csv

    with open(path, "a", newline="") as f:
        csv.DictWriter(f, fieldnames=columns, extrasaction="ignore").writerow(
            {k: ("" if row.get(k) is None else row[k]) for k in columns})


def _make_recorder(cfg, run_dir: Path, model, evaluator: Evaluator, progress: bool):
    """A BaseCallback that writes mcrl's metrics.csv / eval.csv rows at mcrl's points of the loop.

    mcrl, after env step N (and its gradient step): evaluates if N % eval_every == 0 and N < total;
    logs a metrics row if N % log_every == 0 or N == total, doing the final evaluation first at N == total.
    In SB3's loop the gradient step of env step N follows the rollout of step N, so "after step N" is the
    start of the next rollout (``_on_rollout_start``) or, for the last step, the end of training.
    """
    import numpy as np
    from mcrl.envs import success_of
    from mcrl.run.rundir import EVAL_COLUMNS, METRIC_COLUMNS
    from stable_baselines3.common.callbacks import BaseCallback

    total = cfg.total_steps
    n_final = final_eval_episodes(cfg)

    class Recorder(BaseCallback):
        def __init__(self):
            super().__init__(verbose=0)
            self.episodes = 0
            self.eval_round = 0
            self.interval = {"returns": [], "successes": []}
            self.last_eval: dict[str, Any] = {"success_rate": None, "mean_return": None}
            self.t_start = time.perf_counter()
            self.bar = None
            if progress:
                from tqdm import tqdm

                self.bar = tqdm(total=total, unit="step", dynamic_ncols=True, smoothing=0.05, mininterval=1.0)

        def _on_training_start(self) -> None:
            self.t_start = time.perf_counter()

        def _on_step(self) -> bool:
            for info, done in zip(self.locals["infos"], self.locals["dones"]):
                if done:
                    ep = info.get("episode")  # SB3's Monitor wrapper: the episode's return and length
                    self.interval["returns"].append(float(ep["r"]))
                    s = success_of(info)
                    if s is not None:
                        self.interval["successes"].append(s)
                    self.episodes += 1
            if self.bar is not None:
                self.bar.update(1)
            return True

        def _on_rollout_start(self) -> None:
            if self.num_timesteps > 0:
                self._after_step(self.num_timesteps)

        def _on_training_end(self) -> None:
            self._after_step(self.num_timesteps)

        def _evaluate(self, step: int, episodes: int) -> None:
            res = evaluator.run(self.model, self.eval_round, episodes)
            self.eval_round += 1
            self.last_eval = res
            _append_csv(run_dir / "eval.csv", EVAL_COLUMNS, {"step": step, **res})

        def _after_step(self, step: int) -> None:
            if cfg.eval_every and step % cfg.eval_every == 0 and step < total:
                self._evaluate(step, cfg.eval_episodes)
            if step % cfg.log_every == 0 or step == total:
                if step == total:
                    self._evaluate(step, n_final)
                    _write_json_atomic(run_dir / "final_eval.json", {"step": step, **self.last_eval})
                elapsed = time.perf_counter() - self.t_start
                sps = step / elapsed if elapsed > 0 else None
                iv = self.interval
                row = {"step": step, "time_s": round(elapsed, 3), "steps_per_s": sps, "episodes": self.episodes,
                       "train_return": float(np.mean(iv["returns"])) if iv["returns"] else None,
                       "train_success_rate": float(np.mean(iv["successes"])) if iv["successes"] else None,
                       "eval_success_rate": self.last_eval["success_rate"],
                       "eval_mean_return": self.last_eval["mean_return"],
                       **model.read_diagnostics()}
                _append_csv(run_dir / "metrics.csv", METRIC_COLUMNS, row)
                self.interval = {"returns": [], "successes": []}
                if self.bar is not None:
                    post = {"sps": f"{sps:.0f}" if sps else "-"}
                    if self.last_eval["success_rate"] is not None:
                        post["success"] = f"{self.last_eval['success_rate']:.2f}"
                    self.bar.set_postfix(post, refresh=False)

        def close(self) -> None:
            if self.bar is not None:
                self.bar.close()

    return Recorder()


#: Files an SB3 parity run writes (removed first by --overwrite).
RUN_FILES = ("config.json", "peer.json", "metrics.csv", "eval.csv", "final_eval.json", "done", "sb3_model.zip")


def train(cfg, run_dir: Path, threads: int = 1, progress: bool = True, overwrite: bool = False) -> Path:
    """Train SB3 SAC(+HER) with ``cfg`` into ``run_dir`` (an mcrl-format run directory)."""
    import torch

    run_dir = Path(run_dir)
    if (run_dir / "config.json").exists():
        if not overwrite:
            raise FileExistsError(f"{run_dir} already holds a run (SB3 runs cannot be resumed): choose another "
                                  "--run-dir or pass --overwrite")
        for name in RUN_FILES:
            (run_dir / name).unlink(missing_ok=True)

    torch.set_num_threads(threads)
    model, _ = build_model(cfg)  # validates before anything is written
    import stable_baselines3

    from mcrl.run.rundir import EVAL_COLUMNS, METRIC_COLUMNS

    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(cfg.to_json())
    (run_dir / "peer.json").write_text(json.dumps({
        "system": "stable-baselines3", "version": stable_baselines3.__version__,
        "torch": torch.__version__, "torch_threads": torch.get_num_threads()}, indent=2) + "\n")
    import csv

    for name, cols in (("metrics.csv", METRIC_COLUMNS), ("eval.csv", EVAL_COLUMNS)):
        with open(run_dir / name, "w", newline="") as f:
            csv.DictWriter(f, fieldnames=cols).writeheader()

    evaluator = Evaluator(cfg)
    recorder = _make_recorder(cfg, run_dir, model, evaluator, progress)
    try:
        model.learn(total_timesteps=cfg.total_steps, callback=recorder)
        model.save(run_dir / "sb3_model.zip")  # the policy and optimisers (not the replay buffer)
        _write_json_atomic(run_dir / "done", {"step": int(model.num_timesteps), **recorder.last_eval})
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
