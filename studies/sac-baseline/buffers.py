"""Issue 49 item 1, the learning side: where in the replay buffer does mcrl's higher batch reward come from?

With learning off both systems' batches match (pipeline.py); with learning on mcrl's are higher. This reads what
each system's training actually stored, the replay buffer at 20,000 steps (mcrl: a run's checkpoint
``buffer.npz``; stable-baselines3: its runner's ``sb3_checkpoints/step_000020000/replay_buffer.pkl``), and
predicts the logged batch reward from it exactly, split into its parts.

    python studies/sac-baseline/buffers.py extract SB3_CKPT_DIR --out FILE.npz   # (a venv with SB3) pickle -> npz
    python studies/sac-baseline/buffers.py episodes BUFFER.npz --metrics METRICS.csv --system mcrl|sb3 \\
        --label NAME --out FILE.json [--steps 20000]
    python studies/sac-baseline/buffers.py starts --out STARTS.json    # each seed's starts, both ways of resetting
    python studies/sac-baseline/buffers.py gap --mcrl RUN_DIR... --sb3 RUN_DIR... --starts STARTS.json \
        --buffers FILE.json...
    python studies/sac-baseline/buffers.py table FILE.json...

Per gradient step s (after storing env step s) a batch draws 256 rows uniformly from the finished episodes: n_real
rows keep their goal, the others take a future achieved goal of the same episode, uniform over steps t..T-1
(both systems). So its expected mean reward is (n_real * mean real reward + n_her * mean relabelled reward) / 256
over the episodes finished by s, each known exactly from the buffer; averaged like metrics.csv's rows (one row per
1,000 env steps, from learning_starts on) it must reproduce the logged ``mean_ext_reward``: the check that the
buffer is read right. Per episode it also records what could carry a difference: whether it starts with the
object within 5 cm of the goal and ends there, whether the object moved (> 1 cm end to start, as the loop
counts it), on how many steps the object moved (> 1 mm), and the actions' mean magnitude.
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

T = 50  # FetchPush episode length
OBS, GOAL = 25, 3  # policy input: observation | achieved_goal | desired_goal
THRESHOLD = 0.05  # FetchPush's success distance
GOAL_MOVED = 0.01
STEP_MOVED = 0.001
BATCH, LEARNING_STARTS, LOG_EVERY = 256, 100, 1000
N_HER = {"mcrl": round(BATCH * 0.8), "sb3": int(BATCH * 0.8)}  # 205 (round) and 204 (int)


def cmd_extract(a) -> int:
    """SB3's HerReplayBuffer pickle (1M rows allocated) -> the filled rows in mcrl's buffer.npz layout."""
    import pickle

    with open(Path(a.ckpt) / "replay_buffer.pkl", "rb") as f:
        b = pickle.load(f)
    n = int(b.pos)

    def flat(d):
        return np.concatenate([d[k][:n, 0] for k in ("observation", "achieved_goal", "desired_goal")], axis=1)

    np.savez_compressed(a.out, obs=flat(b.observations), next_obs=flat(b.next_observations),
                        action=b.actions[:n, 0], reward=b.rewards[:n, 0])
    print(f"{a.ckpt}: {n} rows -> {a.out}")
    return 0


def _reward(achieved: np.ndarray, goal: np.ndarray) -> np.ndarray:
    return -(np.linalg.norm(achieved - goal, axis=-1) > THRESHOLD).astype(float)


def per_episode(buf: dict) -> dict[str, np.ndarray]:
    """Per-episode quantities of a buffer whose rows are whole episodes of T steps, in order."""
    n = buf["reward"].shape[0] // T
    obs = buf["obs"][: n * T].reshape(n, T, -1)
    nxt = buf["next_obs"][: n * T].reshape(n, T, -1)
    ag0 = obs[:, 0, OBS:OBS + GOAL]
    ag = nxt[:, :, OBS:OBS + GOAL]  # achieved goal after each step: the HER goals and the rewards' argument
    g = obs[:, 0, OBS + GOAL:]
    real = _reward(ag, g[:, None])
    stored = buf["reward"][: n * T].reshape(n, T)
    if not np.array_equal(real, stored):  # the reward is a function of (achieved, goal): read right or not at all
        raise SystemExit(f"buffer rewards differ from the recomputed ones in {int((real != stored).sum())} rows")
    # relabelled: row t with the goal ag[j], j uniform over t..T-1
    pair = _reward(ag[:, :, None], ag[:, None, :])  # (n, t, j)
    upper = np.triu(np.ones((T, T)))
    relab = ((pair * upper).sum(2) / upper.sum(1)).mean(1)
    prev = np.concatenate([ag0[:, None], ag[:, :-1]], axis=1)
    act = buf["action"][: n * T].reshape(n, T, -1)
    return {
        "real": real.mean(1),
        "relabelled": relab,
        "start_at_goal": (np.linalg.norm(ag0 - g, axis=-1) <= THRESHOLD).astype(float),
        "end_at_goal": (real[:, -1] == 0).astype(float),
        "moved": (np.linalg.norm(ag[:, -1] - ag0, axis=-1) > GOAL_MOVED).astype(float),
        "moving_steps": (np.linalg.norm(ag - prev, axis=-1) > STEP_MOVED).sum(1).astype(float),
        "abs_action": np.abs(act).mean((1, 2)),
    }


def _gradient_steps(steps: int) -> tuple[np.ndarray, np.ndarray]:
    """For each gradient step with a finished episode to draw from (env steps LEARNING_STARTS + 1..steps): the
    episodes finished after storing that step, and the metrics row that logs it."""
    s = np.arange(LEARNING_STARTS + 1, steps + 1)
    s = s[s // T > 0]
    return s // T, ((s - 1) // LOG_EVERY + 1) * LOG_EVERY


def predicted_rows(ep: dict[str, np.ndarray], n_her: int, steps: int) -> dict[str, np.ndarray]:
    """Expected batch means per metrics row (env steps in (row - LOG_EVERY, row], from LEARNING_STARTS + 1)."""
    cum = {k: np.concatenate([[0.0], np.cumsum(ep[k])]) for k in ("real", "relabelled")}
    done, row = _gradient_steps(steps)
    real, relab = cum["real"][done] / done, cum["relabelled"][done] / done
    batch = ((BATCH - n_her) * real + n_her * relab) / BATCH
    rows = np.unique(row)
    mean = lambda v: np.array([v[row == r].mean() for r in rows])  # noqa: E731
    return {"step": rows, "batch": mean(batch), "real_part": mean((BATCH - n_her) * real / BATCH),
            "relabelled_part": mean(n_her * relab / BATCH)}


def episode_weights(n: int, steps: int, start: int = LOG_EVERY) -> np.ndarray:
    """Each episode's weight in the mean of the metrics rows >= ``start`` of the expected batch reward (rows
    weigh equally, the steps within a row equally, and a batch draws its finished episodes uniformly)."""
    done, row = _gradient_steps(steps)
    done, row = done[row >= start], row[row >= start]
    w = np.zeros(n + 1)
    rows = np.unique(row)
    for r in rows:
        d = done[row == r]
        # each step adds 1/done to episodes 1..done: a difference array over episode indices
        add = np.zeros(n + 2)
        add[1] += (1.0 / d).sum()
        np.add.at(add, d + 1, -1.0 / d)
        w += np.cumsum(add)[: n + 1] / len(d)
    return w[1:] / len(rows)


def cmd_starts(a) -> int:
    """The share of training episodes that start with the object within 5 cm of the goal, per seed, as each
    system resets (mcrl: a seed per episode; SB3: reset(seed) once, then unseeded), weighted like the batch mean.
    It depends on the seed only, not on the policy (Fetch draws starts at reset)."""
    from mcrl.config import resolve_config
    from mcrl.envs import episode_seed, make_env
    from mcrl.run.evaluation import TRAIN_STREAM

    env = make_env(resolve_config("fetchpush-sac"))
    n = a.steps // T
    w = episode_weights(n, a.steps, a.start)
    out = {}
    for system in ("mcrl", "sb3"):
        for seed in a.seeds:
            if system == "mcrl":
                firsts = [env.reset(seed=episode_seed(seed, TRAIN_STREAM, i))[0] for i in range(n)]
            else:
                firsts = [env.reset(seed=seed)[0]] + [env.reset()[0] for _ in range(n - 1)]
            near = np.array([np.linalg.norm(o["achieved_goal"] - o["desired_goal"]) <= THRESHOLD for o in firsts],
                            dtype=float)
            out[f"{system}-s{seed}"] = {"start_at_goal": near.tolist(), "weighted": float(w @ near),
                                        "share": float(near.mean())}
            print(f"{system} seed {seed}: {near.mean():.4f} of {n} episodes start within 5 cm (weighted "
                  f"{w @ near:.4f})")
    Path(a.out).write_text(json.dumps(out))
    return 0


def cmd_episodes(a) -> int:
    buf = {k: v[: a.steps] for k, v in np.load(a.buffer).items() if k in ("obs", "next_obs", "action", "reward")}
    ep = per_episode(buf)
    steps = len(ep["real"]) * T
    pred = predicted_rows(ep, N_HER[a.system], steps)
    with open(a.metrics) as f:
        logged = {int(r["step"]): float(r["mean_ext_reward"]) for r in csv.DictReader(f)
                  if r.get("mean_ext_reward") not in (None, "") and int(r["step"]) <= steps}
    out = {"label": a.label, "system": a.system, "n_her": N_HER[a.system], "steps": steps,
           "rows": {"step": pred["step"].tolist(), "predicted": pred["batch"].tolist(),
                    "real_part": pred["real_part"].tolist(), "relabelled_part": pred["relabelled_part"].tolist(),
                    "logged": [logged.get(int(s)) for s in pred["step"]]},
           "episodes": {k: v.tolist() for k, v in ep.items()}}
    Path(a.out).write_text(json.dumps(out))
    lg = [v for v in out["rows"]["logged"] if v is not None]
    print(f"{a.label}: predicted {np.mean(pred['batch']):.5f}, logged {np.mean(lg) if lg else float('nan'):.5f} "
          f"over {len(lg)} rows")
    return 0


def _share(r: dict, event: str, given: str) -> float:
    e, g = (np.array(r["episodes"][k]) for k in (event, given))
    return float((e * g).sum() / max(g.sum(), 1))


def _logged(metrics: Path, start: int, steps: int) -> float:
    with open(metrics) as f:
        v = [float(r["mean_ext_reward"]) for r in csv.DictReader(f)
             if r.get("mean_ext_reward") not in (None, "") and start <= int(r["step"]) <= steps]
    if len(v) != (steps - start) // LOG_EVERY + 1:
        raise SystemExit(f"{metrics}: {len(v)} rows of mean_ext_reward between steps {start} and {steps}")
    return float(np.mean(v))


def cmd_gap(a) -> int:
    """The logged batch-reward gap between two arms (run directories of any length >= --steps), raw and with
    what is known about each run removed: its seed's starts at the goal (policy-independent, `starts`), valued
    at what a start-at-goal episode's real rows gain in the buffers, and the relabelled-row count."""
    from mcrl.analysis.hypothesis import rank_sum_test
    from mcrl.analysis.stats import mean_difference_ci

    starts = json.loads(Path(a.starts).read_text())
    eps = [json.loads(Path(f).read_text())["episodes"] for f in a.buffers]
    at = np.concatenate([np.array(e["real"])[np.array(e["start_at_goal"]) == 1] for e in eps])
    off = np.concatenate([np.array(e["real"])[np.array(e["start_at_goal"]) == 0] for e in eps])
    gain = float(at.mean() - off.mean())  # real reward per step an episode gains by starting at the goal
    print(f"a start-at-goal episode's real rows: {at.mean():+.4f} per step ({len(at)} episodes) against "
          f"{off.mean():+.4f} ({len(off)}): gain {gain:.4f}; {len(eps)} buffers")
    arms = {}
    for name, system, dirs in (("mcrl", "mcrl", a.mcrl), ("SB3", "sb3", a.sb3)):
        rows = []
        for d in dirs:
            cfg = json.loads((Path(d) / "config.json").read_text())
            w = starts[f"{system}-s{cfg['seed']}"]["weighted"]
            logged = _logged(Path(d) / "metrics.csv", a.start, a.steps)
            n_real = BATCH - N_HER[system]
            # what the run's batches would carry with no start at the goal and mcrl's 205 relabelled rows
            rows_only = logged + (N_HER["mcrl"] - N_HER[system]) / BATCH * a.row_gap
            rows.append((cfg["seed"], logged, w, rows_only, rows_only - n_real / BATCH * gain * w))
        arms[name] = np.array(sorted(rows))
        print(f"{name}: seeds {[int(r[0]) for r in arms[name]]}; weighted start-at-goal share "
              f"{arms[name][:, 2].mean():.4f}")
    x, y = arms["mcrl"], arms["SB3"]
    for j, what in ((1, "logged batch reward"), (2, "weighted start-at-goal share"),
                    (3, "batch reward less the row count"), (4, "batch reward less row count and starts at goal")):
        est, lo, hi = mean_difference_ci(x[:, j], y[:, j])
        print(f"| {what} | {x[:, j].mean():.4f} ({len(x)}) | {y[:, j].mean():.4f} ({len(y)}) | {est:+.4f} "
              f"[{lo:+.4f}, {hi:+.4f}] | {rank_sum_test(x[:, j], y[:, j], 'two-sided'):.2g} |")
    return 0


def cmd_table(a) -> int:
    from mcrl.analysis.hypothesis import rank_sum_test
    from mcrl.analysis.stats import mean_difference_ci

    runs = [json.loads(Path(f).read_text()) for f in a.files]
    groups: dict[str, list[dict]] = {}
    for r in runs:
        groups.setdefault(r["label"], []).append(r)
    names = list(groups)  # in the order given: pairs read first - second

    def row_mean(r, key):  # over metrics rows from --from on
        st = np.array(r["rows"]["step"])
        v = np.array([np.nan if x is None else x for x in r["rows"][key]], dtype=float)
        return float(np.nanmean(v[st >= a.start]))

    def ep_mean(r, key, first=0):
        return float(np.mean(np.array(r["episodes"][key])[first:]))

    quantities = [
        ("batch reward, logged", lambda r: row_mean(r, "logged")),
        ("batch reward, predicted from the buffer", lambda r: row_mean(r, "predicted")),
        ("  of it real rows", lambda r: row_mean(r, "real_part")),
        ("  of it relabelled rows", lambda r: row_mean(r, "relabelled_part")),
        ("real reward per step (all 400 episodes)", lambda r: ep_mean(r, "real")),
        ("relabelled reward per row", lambda r: ep_mean(r, "relabelled")),
        ("episodes starting within 5 cm of the goal", lambda r: ep_mean(r, "start_at_goal")),
        ("episodes ending within 5 cm of the goal", lambda r: ep_mean(r, "end_at_goal")),
        ("of those starting there, share ending there", lambda r: _share(r, "end_at_goal", "start_at_goal")),
        ("episodes that moved the object (> 1 cm)", lambda r: ep_mean(r, "moved")),
        ("steps the object moved (> 1 mm) per episode", lambda r: ep_mean(r, "moving_steps")),
        ("mean |action|", lambda r: ep_mean(r, "abs_action")),
    ]
    pairs = [(x, y) for i, x in enumerate(names) for y in names[i + 1:]]
    head = " | ".join(f"{n} ({len(groups[n])})" for n in names)
    print(f"| quantity (steps >= {a.start}) | {head} | " + " | ".join(f"{x} - {y} [95% CI], p" for x, y in pairs)
          + " |")
    print("|---" * (1 + len(names) + len(pairs)) + "|")
    for name, fn in quantities:
        vals = {n: np.array([fn(r) for r in groups[n]]) for n in names}
        cells = [f"{vals[n].mean():.4f}" for n in names]
        for x, y in pairs:
            est, lo, hi = mean_difference_ci(vals[x], vals[y])
            cells.append(f"{est:+.4f} [{lo:+.4f}, {hi:+.4f}], {rank_sum_test(vals[x], vals[y], 'two-sided'):.2g}")
        print(f"| {name} | " + " | ".join(cells) + " |")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("extract")
    e.add_argument("ckpt")
    e.add_argument("--out", required=True)
    r = sub.add_parser("episodes")
    r.add_argument("buffer")
    r.add_argument("--metrics", required=True)
    r.add_argument("--system", choices=sorted(N_HER), required=True)
    r.add_argument("--label", required=True)
    r.add_argument("--steps", type=int, default=20000, help="the buffer's first STEPS rows (a later checkpoint's "
                   "buffer starts with the same rows)")
    r.add_argument("--out", required=True)
    z = sub.add_parser("starts")
    z.add_argument("--seeds", type=lambda v: [int(x) for x in v.split(",")], default=list(range(12)))
    z.add_argument("--steps", type=int, default=20000)
    z.add_argument("--from", dest="start", type=int, default=LOG_EVERY)
    z.add_argument("--out", required=True)
    g = sub.add_parser("gap")
    g.add_argument("--mcrl", nargs="+", required=True, help="mcrl run directories")
    g.add_argument("--sb3", nargs="+", required=True, help="SB3 run directories")
    g.add_argument("--starts", required=True, help="the JSON of `starts`")
    g.add_argument("--buffers", nargs="+", required=True, help="JSONs of `episodes` (for a start's value)")
    g.add_argument("--from", dest="start", type=int, default=LOG_EVERY)
    g.add_argument("--steps", type=int, default=20000)
    g.add_argument("--row-gap", type=float, default=0.91,
                   help="real minus relabelled reward per row (the pipeline study: -0.03 against -0.94)")
    t = sub.add_parser("table")
    t.add_argument("files", nargs="+")
    t.add_argument("--from", dest="start", type=int, default=1000)
    a = p.parse_args(argv)
    return {"extract": cmd_extract, "episodes": cmd_episodes, "starts": cmd_starts, "gap": cmd_gap,
            "table": cmd_table}[a.cmd](a)


if __name__ == "__main__":
    sys.exit(main())
