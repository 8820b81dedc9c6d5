"""Issue 49 item 1: is the replay-reward gap in the data pipeline? Both systems' collection and HER sampling,
learning switched off, driven by the same fixed policy.

    python studies/sac-baseline/pipeline.py run --system mcrl|sb3 --policy random|RUN_DIR[@STEP] --seed N \\
        [--steps 20000] --out FILE.json
    python studies/sac-baseline/pipeline.py table FILE.json... [--from 1000]
    python studies/sac-baseline/pipeline.py resets [--seeds 10] [--resets 2000]

`run` trains nothing. mcrl's side is mcrl's own loop (`mcrl.run.trainer.train_runs`, so its warm-up, act / step /
store / sample order, episode ends and seeding) with a learner that only draws the replay batch each step and
records its rewards. stable-baselines3's side is SB3's own `collect_rollouts` and `HerReplayBuffer.sample` at the
same preset's settings (`_sb3.py: build_model`, see `_benchmarks`), with a `train` that only samples and records. Both
act with the same policy: uniform random actions, or the stochastic policy of an mcrl checkpoint (tanh of a
Gaussian sample of its actor), each system with its own random stream. Per gradient step it records the batch's
mean reward, and of its real and its relabelled rows separately; at the end, per episode (from the buffer), whether
the object moved more than 1 cm. `table` compares the systems per policy: per-run means over steps >= --from, the
difference with a bootstrap interval and an exact rank-sum p.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

GOAL_MOVED = 0.01
EVERY = 1000  # the JSON keeps the batch records' means over each EVERY env steps (as metrics.csv rows do)


def _benchmarks() -> Path:
    """The SB3 runner's folder of the mcrl this Python imports (run with a pinned clone's venv, its own runner is
    used): studies/sb3-parity/, or benchmarks/ in clones from before it moved there."""
    import mcrl

    root = Path(mcrl.__file__).resolve().parents[2]
    return next((d for d in (root / "studies" / "sb3-parity", root / "benchmarks") if (d / "_sb3.py").is_file()))


def _policy(spec: str, seed: int):
    """`act(flat_obs (obs_dim,), step) -> action in [-1, 1]^4` and a description of the policy."""
    if spec == "random":
        rng = np.random.default_rng([seed, 0xAC7])
        return (lambda obs, t: rng.uniform(-1.0, 1.0, 4).astype(np.float32)), {"policy": "uniform random"}
    import jax
    import jax.numpy as jnp

    from mcrl.run.policy import load_policy

    run_dir, _, step = spec.partition("@")
    cfg, agent, state = load_policy(Path(run_dir), int(step) if step else None)
    key = jax.random.PRNGKey(seed + 0xAC7)
    act = jax.jit(lambda p, o, t: agent.act(p, o[None], jax.random.fold_in(key, t))[0])
    params = state.pi.params
    digest = float(sum(float(jnp.abs(x).sum()) for x in jax.tree.leaves(params)))
    return (lambda obs, t: np.asarray(act(params, jnp.asarray(obs), t))), {
        "policy": f"stochastic actor of {run_dir} at step {int(state.grad_steps) + cfg.learning_starts}",
        "actor_abs_sum": digest}


def _batch_record(rewards: np.ndarray, relabelled: np.ndarray) -> tuple[float, float, float]:
    return float(rewards.mean()), float(rewards[~relabelled].mean()), float(rewards[relabelled].mean())


def _moved(first_goal: np.ndarray, last_goal: np.ndarray) -> list[float]:
    return [float(x) for x in np.linalg.norm(last_goal - first_goal, axis=1) > GOAL_MOVED]


def _collected(rewards: np.ndarray, first_achieved: np.ndarray, first_desired: np.ndarray) -> dict:
    """What collection alone decides: the buffer's mean reward (every stored transition, what real rows estimate)
    and the share of episodes that start with the object already within 5 cm of the goal."""
    start = np.linalg.norm(first_achieved - first_desired, axis=1) < 0.05
    return {"buffer_reward": float(np.mean(rewards)), "start_within": float(start.mean())}


def run_mcrl(cfg, act, out_dir: Path, sample: bool = True) -> dict:
    from mcrl.algo.diagnostics import init as diag_init
    from mcrl.run.trainer import train_runs

    rec: list[tuple[float, float, float]] = []
    buffers = []

    class Frozen:
        """A learner that learns nothing: the fixed policy acts, each step's replay batch is only recorded."""

        def __init__(self, members, states, diags):
            self.m, self.state = members[0], states[0]
            buffers.append(self.m.buffer)

        def act(self, obs, t):
            return act(obs[0], t)[None]

        def update(self, batches):
            (b,) = batches
            if b is not None and sample:
                rec.append(_batch_record(np.asarray(b.reward), self.m.buffer.relabelled(len(b.reward))))

        def read_metrics(self):
            return [{}]

        def state_of(self, i):
            return self.state, diag_init()

    train_runs([cfg], [out_dir], False, Frozen)
    buf = buffers[0]
    n, T = buf.total - buf.total % 50, 50
    od, gd = buf.od, buf.gd
    moved = _moved(buf.obs[:n:T, od:od + gd], buf.next_obs[T - 1:n:T, od:od + gd])
    return {"batches": rec, "moved": moved, "relabelled_rows": int(buf.relabelled(cfg.batch_size).sum()),
            **_collected(buf.reward[:n], buf.obs[:n:T, od:od + gd], buf.obs[:n:T, od + gd:od + 2 * gd])}


def run_sb3(cfg, act, sample: bool = True) -> dict:
    sys.path.insert(0, str(_benchmarks()))
    from _sb3 import build_model  # noqa: E402
    from stable_baselines3 import SAC

    from mcrl.envs import GOAL_KEYS, flatten_obs

    rec: list[tuple[float, float, float]] = []

    class Frozen(SAC):
        def predict(self, observation, state=None, episode_start=None, deterministic=False):
            flat = flatten_obs({k: observation[k][0] for k in GOAL_KEYS})
            return act(flat, self.num_timesteps)[None].astype(np.float32), None

        def train(self, gradient_steps: int, batch_size: int = 64) -> None:
            for _ in range(gradient_steps if sample else 0):
                b = self.replay_buffer.sample(batch_size)
                r = b.rewards.numpy().ravel()
                n_real = batch_size - int(self.replay_buffer.her_ratio * batch_size)  # SB3: real rows first
                rec.append(_batch_record(r, np.arange(batch_size) >= n_real))

    model, _ = build_model(cfg, Frozen)
    model.learn(total_timesteps=cfg.total_steps)
    rb = model.replay_buffer
    size = rb.buffer_size if rb.full else rb.pos
    n, T = size - size % 50, 50
    moved = _moved(rb.observations["achieved_goal"][:n:T, 0], rb.next_observations["achieved_goal"][T - 1:n:T, 0])
    return {"batches": rec, "moved": moved, "relabelled_rows": int(rb.her_ratio * cfg.batch_size),
            **_collected(rb.rewards[:n, 0], rb.observations["achieved_goal"][:n:T, 0],
                         rb.observations["desired_goal"][:n:T, 0])}


def cmd_run(a) -> int:
    from mcrl.config import resolve_config

    cfg = resolve_config("fetchpush-sac", {"seed": a.seed, "total_steps": a.steps, "eval_every": 0,
                                           "final_eval_episodes": 1, "eval_episodes": 1, "save_buffer": False,
                                           "checkpoint_every": 10 ** 9, "buffer_size": max(a.steps, 1000)})
    act, about = _policy(a.policy, a.seed)
    if a.system == "mcrl":
        res = run_mcrl(cfg, act, a.out.with_suffix(".run"), not a.collect_only)
    else:
        res = run_sb3(cfg, act, not a.collect_only)
    b = np.asarray(res["batches"] or [[np.nan] * 3])
    # gradient step i follows env step learning_starts + 1 + i: one row per EVERY env steps, as metrics.csv's
    first = cfg.learning_starts + 1
    rows = [(end, *b[max(0, end - EVERY + 1 - first):end - first + 1].mean(0).tolist())
            for end in range(EVERY, a.steps + 1, EVERY) if end >= first] if res["batches"] else []
    import mcrl

    res.update(system=a.system, seed=a.seed, steps=a.steps, learning_starts=cfg.learning_starts, batches=rows,
               columns=["step", "batch", "real", "relabelled"], mcrl=str(Path(mcrl.__file__).resolve().parents[2]),
               **about)
    a.out.write_text(json.dumps(res))
    print(f"{a.system} seed {a.seed}: mean batch reward {b[:, 0].mean():.4f} (real rows {b[:, 1].mean():.4f}, "
          f"relabelled {b[:, 2].mean():.4f}), relabelled rows {res['relabelled_rows']}, "
          f"episodes that moved the object {np.mean(res['moved']):.3f}")
    return 0


def cmd_table(a) -> int:
    from mcrl.analysis.hypothesis import rank_sum_test
    from mcrl.analysis.stats import mean_difference_ci

    runs = [json.loads(Path(f).read_text()) for f in a.files]
    by: dict[tuple[str, str], list[dict]] = {}
    for r in runs:
        kind = r["policy"].split(" of ")[0] + (", collection only" if not r["batches"] else "")
        by.setdefault((kind, r["system"]), []).append(r)
    cols = ("mean batch reward", "real rows", "relabelled rows", "episodes that moved the object",
            "buffer's mean reward", "episodes starting within 5 cm")
    extra = {3: "moved", 4: "buffer_reward", 5: "start_within"}
    print("| policy | quantity | mcrl (seeds) | SB3 (seeds) | mcrl - SB3 [95% CI] | rank-sum p (two-sided) |")
    print("|---|---|---|---|---|---|")
    for policy in sorted({p for p, _ in by}):
        m, s = by.get((policy, "mcrl"), []), by.get((policy, "sb3"), [])
        if not m or not s:
            continue
        for j, col in enumerate(cols):
            def per_run(rs):
                if j in extra:
                    return np.array([np.mean(r.get(extra[j], np.nan)) for r in rs])
                return np.array([np.mean([row[j + 1] for row in r["batches"] if row[0] > a.start] or [np.nan])
                                 for r in rs])
            x, y = per_run(m), per_run(s)
            x, y = x[np.isfinite(x)], y[np.isfinite(y)]  # runs from before a quantity was recorded lack it
            if x.size == 0 or y.size == 0:
                continue
            est, lo, hi = mean_difference_ci(x, y)
            ci_s = f"[{lo:+.4f}, {hi:+.4f}]"
            print(f"| {policy} | {col} | {x.mean():.4f} ({len(x)}) | {y.mean():.4f} ({len(y)}) | {est:+.4f} {ci_s} "
                  f"| {rank_sum_test(x, y, 'two-sided'):.3g} |")
    return 0


def cmd_resets(a) -> int:
    """Do mcrl's per-episode seeded resets start episodes like SB3's (one seed, then unseeded resets)?"""
    from mcrl.config import resolve_config
    from mcrl.envs import episode_seed, make_env
    from mcrl.run.evaluation import TRAIN_STREAM

    env = make_env(resolve_config("fetchpush-sac"))

    def near(obs) -> bool:
        return bool(np.linalg.norm(obs["achieved_goal"] - obs["desired_goal"]) < 0.05)

    per_episode, seed_once = [], []
    for seed in range(a.seeds):
        per_episode += [near(env.reset(seed=episode_seed(seed, TRAIN_STREAM, i))[0]) for i in range(a.resets)]
        seed_once += [near(env.reset(seed=seed)[0])] + [near(env.reset()[0]) for _ in range(a.resets - 1)]
    for name, x in (("per-episode seeds (mcrl)", per_episode), ("one seed, then unseeded (SB3)", seed_once)):
        p = float(np.mean(x))
        print(f"{name}: {p:.4f} +- {np.sqrt(p * (1 - p) / len(x)):.4f} of {len(x)} episodes start within 5 cm")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--system", choices=("mcrl", "sb3"), required=True)
    r.add_argument("--policy", default="random", help="random, or an mcrl run directory (RUN_DIR[@STEP])")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--steps", type=int, default=20_000)
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--collect-only", action="store_true",
                   help="draw no replay batches: only what collection decides (buffer reward, starts, moves)")
    t = sub.add_parser("table")
    t.add_argument("files", nargs="+")
    t.add_argument("--from", dest="start", type=int, default=1000,
                   help="per-run means over the rows after this env step (each row: the EVERY steps up to it)")
    z = sub.add_parser("resets", help="the share of episodes starting within 5 cm, both ways of resetting")
    z.add_argument("--seeds", type=int, default=10)
    z.add_argument("--resets", type=int, default=2000)
    a = p.parse_args(argv)
    return {"run": cmd_run, "table": cmd_table, "resets": cmd_resets}[a.cmd](a)


if __name__ == "__main__":
    sys.exit(main())
