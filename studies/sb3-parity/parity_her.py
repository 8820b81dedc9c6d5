"""HER sampling, side by side: mcrl's ``ReplayBuffer`` against stable-baselines3's ``HerReplayBuffer``.

Both buffers get the same ``--episodes`` random-action episodes of the preset's environment, then each draws
``--batches`` batches of ``batch_size`` transitions with its own random numbers. Compared: the batches' mean
reward and relabelled share; the mean reward of relabelled and of original transitions (with standard errors);
where in its episode a sampled transition lies; and, for relabelled transitions, the offset of the goal's source
step from the transition's own (over the transitions whose goal matches exactly one step's next achieved goal).
Run from the repository root (needs ``pip install -e ".[bench]"``)::

    python studies/sb3-parity/parity_her.py [--preset fetchpush-sac] [--episodes 200] [--batches 400] [--seed 0]
                                            [--alpha 0.001]

Prints one JSON object (with each histogram pair's total-variation distance and the p-value of a chi-square test
of homogeneity); exit status 1 if the mean reward of relabelled or of original transitions differs by more than 4
standard errors (of the difference) or a histogram test gives p < ``--alpha``. Results: docs/studies/sb3-parity.md,
"HER sampling, side by side".
"""
from __future__ import annotations

import argparse
import json
import sys

import _common  # noqa: F401  (this checkout's src/ when mcrl is not installed)
import numpy as np


def _episodes(env, n: int, seed: int) -> list[list[tuple]]:
    """n random-action episodes: per step (obs dict, action, reward, next obs dict, terminated, truncated)."""
    rng = np.random.default_rng(seed)
    eps = []
    for e in range(n):
        obs, _ = env.reset(seed=seed * 100_003 + e)
        steps, done = [], False
        while not done:
            a = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
            nxt, r, term, trunc, _ = env.step(a)
            steps.append((obs, a, float(r), nxt, bool(term), bool(trunc)))
            obs, done = nxt, term or trunc
        eps.append(steps)
    return eps


def _stats(obs_b, reward_b, relab_b, index, next_achieved, key_len: int, dg_slice: slice) -> dict:
    """Per-system statistics of a list of sampled batches (numpy arrays of flat observations);
    ``next_achieved[e]`` is episode e's next achieved goals, (T, goal dim)."""
    T = max(len(a) for a in next_achieved)
    pos_hist, off_hist, off_n = np.zeros(T), np.zeros(T), 0
    for obs, relab in zip(obs_b, relab_b):
        for o, is_her in zip(obs, relab):
            e, t = index[o[:key_len].tobytes()]
            pos_hist[t] += 1
            if is_her:
                hits = np.flatnonzero(np.all(next_achieved[e] == o[dg_slice], axis=1))
                if len(hits) == 1:
                    off_hist[hits[0] - t] += 1
                    off_n += 1
    r = np.array([b.mean() for b in reward_b])
    rel = np.concatenate(relab_b)
    rw = np.concatenate(reward_b)

    def se(x: np.ndarray) -> float:
        return float(x.std(ddof=1) / np.sqrt(len(x)))

    return {"batch_mean_reward": float(r.mean()), "batch_mean_reward_se": se(r),
            "relabelled_share": float(rel.mean()), "relabelled_mean_reward": float(rw[rel].mean()),
            "relabelled_mean_reward_se": se(rw[rel]), "original_mean_reward": float(rw[~rel].mean()),
            "original_mean_reward_se": se(rw[~rel]), "position_hist": pos_hist, "offset_hist": off_hist,
            "offsets_identified": off_n}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="fetchpush-sac")
    p.add_argument("--episodes", type=int, default=200)
    p.add_argument("--batches", type=int, default=400)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--alpha", type=float, default=0.001,
                   help="a histogram test's p-value below this counts as a difference (default 0.001)")
    args = p.parse_args(argv)

    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv
    from stable_baselines3.her.her_replay_buffer import HerReplayBuffer

    from mcrl.config import resolve_config
    from mcrl.envs import flatten_obs, goal_terminated_fn, inspect, make_env
    from mcrl.replay import ReplayBuffer

    torch.set_num_threads(1)
    cfg = resolve_config(args.preset)
    env = make_env(cfg)
    spec = inspect(env, cfg)
    if not spec.uses_her(cfg):
        print(f"{args.preset} does not use HER: nothing to compare", file=sys.stderr)
        return 2
    episodes = _episodes(env, args.episodes, args.seed)
    od, gd = spec.observation_dim, spec.goal_dim
    flat = [[flatten_obs(st[0]) for st in ep] for ep in episodes]
    next_achieved = [np.array([st[3]["achieved_goal"] for st in ep], np.float32) for ep in episodes]
    index = {}  # flat (observation | achieved_goal) bytes -> (episode, step): identifies a sampled transition
    for e, ep in enumerate(flat):
        for t, x in enumerate(ep):
            index[x[: od + gd].tobytes()] = (e, t)
    n = sum(len(ep) for ep in episodes)
    if len(index) != n:
        print(f"{n - len(index)} transitions share an observation: cannot identify samples", file=sys.stderr)
        return 2

    ours = ReplayBuffer(n, spec.obs_dim, spec.act_dim, her=True, observation_dim=od, goal_dim=gd,
                        strategy=cfg.her_strategy, k=cfg.her_k, compute_reward=env.unwrapped.compute_reward,
                        compute_terminated=goal_terminated_fn(env))
    vec = DummyVecEnv([lambda: make_env(cfg)])
    theirs = HerReplayBuffer(n, env.observation_space, env.action_space, env=vec, device="cpu",
                             n_sampled_goal=cfg.her_k, goal_selection_strategy=cfg.her_strategy)
    for ep in episodes:
        for obs, a, r, nxt, term, trunc in ep:
            ours.add(flatten_obs(obs), a, r, flatten_obs(nxt), term, term or trunc)
            theirs.add({k: v[None] for k, v in obs.items()}, {k: v[None] for k, v in nxt.items()}, a[None],
                       np.array([r]), np.array([term or trunc]), [{"TimeLimit.truncated": trunc and not term}])

    dg_slice = slice(od + gd, od + 2 * gd)
    rng = np.random.default_rng(args.seed)
    np.random.seed(args.seed)  # stable-baselines3 draws from numpy's global generator
    res = {}
    for name in ("mcrl", "stable-baselines3"):
        obs_b, reward_b, relab_b = [], [], []
        for _ in range(args.batches):
            if name == "mcrl":
                b = ours.sample(cfg.batch_size, rng)
                obs, rew, relab = b.obs, b.reward, ours.relabelled(cfg.batch_size)
            else:
                s = theirs.sample(cfg.batch_size)
                o = {k: v.numpy() for k, v in s.observations.items()}
                obs = np.concatenate([o["observation"], o["achieved_goal"], o["desired_goal"]], axis=1)
                obs = obs.astype(np.float32)  # SB3 keeps the space's float64
                rew = s.rewards.numpy().reshape(-1)
                stored = np.array([flat[e][t][dg_slice] for e, t in (index[x[: od + gd].tobytes()] for x in obs)])
                # SB3 puts the original transitions first, the relabelled (virtual) ones last
                relab = np.arange(len(obs)) >= len(obs) - int(theirs.her_ratio * cfg.batch_size)
                assert np.all(stored[~relab] == obs[~relab, dg_slice])
            obs_b.append(obs)
            reward_b.append(np.asarray(rew, np.float64))
            relab_b.append(np.asarray(relab, bool))
        res[name] = _stats(obs_b, reward_b, relab_b, index, next_achieved, od + gd, dg_slice)

    a, b = res["mcrl"], res["stable-baselines3"]

    def z(key: str) -> float:
        return abs(a[key] - b[key]) / float(np.hypot(a[key + "_se"], b[key + "_se"]))

    # The relabelled share differs by construction (round(256 * 0.8) = 205 against int(0.8 * 256) = 204), which
    # moves the batch mean by the share difference times (original - relabelled mean reward); the test is on the
    # rewards of each kind.
    z_rel, z_orig = z("relabelled_mean_reward"), z("original_mean_reward")
    from_split = (a["relabelled_share"] - b["relabelled_share"]) * (b["relabelled_mean_reward"]
                                                                     - b["original_mean_reward"])
    from scipy.stats import chi2_contingency

    def compare(key: str) -> tuple[float, float]:
        """Total-variation distance of the two histograms, and the p-value of a chi-square homogeneity test."""
        h = np.stack([a[key], b[key]])
        h = h[:, h.sum(0) > 0]
        pa, pb = h / h.sum(1, keepdims=True)
        return 0.5 * float(np.abs(pa - pb).sum()), float(chi2_contingency(h).pvalue)

    (tv_pos, p_pos), (tv_off, p_off) = compare("position_hist"), compare("offset_hist")
    T = len(a["position_hist"])
    out = {"preset": args.preset, "episodes": args.episodes, "transitions": n, "batches": args.batches,
           "batch_size": cfg.batch_size,
           "batch_mean_reward_difference": round(a["batch_mean_reward"] - b["batch_mean_reward"], 5),
           "of_which_from_the_split": round(from_split, 5),
           "z_relabelled_reward": round(z_rel, 2), "z_original_reward": round(z_orig, 2),
           "position": {"tv": round(tv_pos, 4), "p": round(p_pos, 4)},
           "offset": {"tv": round(tv_off, 4), "p": round(p_off, 4)}}
    for k, v in res.items():
        out[k] = {kk: (round(vv, 5) if isinstance(vv, float) else vv) for kk, vv in v.items()
                  if not kk.endswith("_hist")}
        off = v["offset_hist"] / max(v["offsets_identified"], 1)
        out[k]["mean_offset"] = round(float((np.arange(T) * off).sum()), 3)
    out["same"] = bool(max(z_rel, z_orig) <= 4 and p_pos >= args.alpha and p_off >= args.alpha)
    print(json.dumps(out, indent=1))
    return 0 if out["same"] else 1


if __name__ == "__main__":
    sys.exit(main())
