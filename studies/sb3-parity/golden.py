"""stable-baselines3's SAC step as a golden file, so that ``make test`` checks mcrl's step without torch (issue 66,
item 5). ``tests/test_sb3_golden.py`` loads ``golden_sac_step.npz`` (this folder, 0.32 MB) and checks mcrl's own
step against it; ``tests/test_transplant.py``, which runs SB3 itself, skips without torch.

The file holds one gradient step at the thesis' sizes (``fetchpush-sac``: FetchPush-v4, actor and both critics
3 x 256, batch 256, gamma 0.99, tau 0.005, learning rate 3e-4, target entropy -4):

* **the state before the step**, not stored but derived from ``STATE_SEED`` by ``before_state`` (numpy's PCG64
  raw bits, neither torch nor jax): weights and biases uniform in +-1/sqrt(fan_in) (torch's nn.Linear scheme,
  mcrl's ``init=torch``), target critics 5% of that away from the critics, entropy coefficient 0.1, Adam
  moments of the gradients' size after ``ADAM_COUNT`` steps. A real learning state is 1.55 million float32
  numbers (6.2 MB) that do not compress; this one costs nothing, and its stored per-tensor sums and norms tell
  a changed recipe apart from a changed step;
* **what both systems are given**: the step's random key and the Gaussian noise it draws (stored, so a changed
  jax random stream is named as such), and the batch: 256 transitions of 12 random-action FetchPush-v4 episodes
  (``BATCH_SEED``), 205 relabelled with a future achieved goal (mcrl's HER count), 16 rows marked terminated by
  hand (Fetch never terminates; the step must still honour the mask), 8 rows at the time limit, flagged in a
  ``truncated`` column (the test feeds them as terminated and sees the check fail);
* **SB3's numbers after the step**, in two modes: ``exact``, SB3 given mcrl's exact tanh log-determinant
  (``parity_step.sb3_exact_log_prob``, the transplant check's ``sb3-exact``), against mcrl at the preset's
  ``squash_correction=exact``; ``epsilon``, stock SB3 against mcrl at ``squash_correction=epsilon``. Each: the
  critic, actor and entropy-coefficient losses, the coefficient and mean Q; and for every tensor of the actor,
  critics, target critics, log(coefficient) and their Adam states, the gradient (captured at each optimiser's
  step), the value after the step and its Adam moments, as sum, L2 norm and 512 entries at stored indices (all
  entries of smaller tensors). No action saturates in this state (mcrl's saturated_share 0; the two corrections
  differ by 1.5e-5 nats), so the modes check both code paths, not the gap between the corrections
  (``parity_step.py``'s saturating batch measures that).

SB3's side reuses the transplant study's machinery: the state, in mcrl's checkpoint layout, is installed into stock
``stable_baselines3.SAC`` with ``HerReplayBuffer`` by ``_transplant.install_sb3`` (weights, Adam moments and counts,
the Dict observation's input order; read back exactly before the step), SB3's own ``SAC.train`` takes one step on
the batch (``_transplant_check._FixedDictBatch``) with mcrl's noise (``parity_step.fixed_normal_noise``), and
``_transplant.read_sb3`` reads the result back in mcrl's layout. mcrl's side (``mcrl_step``, torch-free, what the
test runs): the state written as an mcrl checkpoint, restored by ``mcrl.run.policy.restore_run`` and stepped once
by the training loop's ``mcrl.run.learner.Learner``. ``comparison`` uses the tolerances of ``parity_step.py``
(read from its source): every loss within 5e-5 relative (or 1e-6 absolute), gradients within 1e-4 relative L2 per
group, parameter updates and Adam moment changes within 1e-2 (the transplant step check's), Adam counts equal.
At generation mcrl was within 4.4e-7 (losses), 3.0e-6 (gradients) and 8.7e-6 (updates) of SB3.

Generated once (2026-12-02, mcrl commit ccb3402, 40 s on 2 cores; a second run wrote the same arrays) from the
repository root, in a separate virtual environment with the ``bench`` extra: torch 2.13.0+cpu,
stable-baselines3 2.9.2, jax 0.10.2, numpy 2.4.6, Python 3.11.7 (the file's ``meta`` records them)::

    python3 -m venv /tmp/benchvenv && /tmp/benchvenv/bin/pip install -c constraints.txt -e ".[bench]"
    /tmp/benchvenv/bin/python studies/sb3-parity/golden.py generate   # writes studies/sb3-parity/golden_sac_step.npz
    .venv/bin/python studies/sb3-parity/golden.py check               # mcrl against the file, without torch

``generate`` writes nothing if mcrl's step does not pass against what it measured. Regenerate only when the
reference should change (another SB3 version, another preset), never to make mcrl's step pass. Unlike the rest
of this folder the script is maintained: the test imports its torch-free part (everything at module level).
"""
from __future__ import annotations

import argparse
import ast
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO_ROOT = HERE.parents[1]
GOLDEN = HERE / "golden_sac_step.npz"

PRESET = "fetchpush-sac"
SEED = 0  # the config's seed (mcrl's template state); the state's values come from STATE_SEED
OVERRIDES = {"seed": SEED, "buffer_size": 10_000}  # SB3's buffer only holds the batch's episodes
MODES = {"exact": "exact", "epsilon": "epsilon"}  # mode -> mcrl's squash_correction
STATE_SEED = 665
BATCH_SEED = 666
ADAM_COUNT = 1000  # Adam steps taken before (bias correction 1 - 0.999^1000 = 0.63)
ENT_COEF = 0.1
TARGET_OFFSET = 0.05  # target critics = critics + U(+-5%) of the layer's bound
# Adam moments before the step, per group: first moment uniform in +-S, sqrt(second moment) in [0.5, 1.5] S, with
# S the root mean square of this state's gradients on the batch (measured: 1.8e-4 actor, 2.6e-4 critics, 6.7 log
# coefficient), so that the update depends on the gradient, the old moments and the bias correction alike
MOMENT_SCALE = {".pi.": 2e-4, ".q.": 3e-4, ".ent.": 5.0}
SAMPLES = 512  # stored entries per tensor
N_EPISODES = 12
N_TERMINATED = 16
N_TRUNCATED = 8
LOSSES = ("critic_loss", "actor_loss", "ent_coef_loss", "ent_coef", "q_mean")
#: parameter groups as mcrl's checkpoint keys start (state.npz, `mcrl.run.checkpoint.flatten`)
GROUPS = {"actor": ".pi.params", "critic": ".q.params", "critic_target": ".q_target", "log_ent_coef": ".ent.params"}
OPTIMISED = ("actor", "critic", "log_ent_coef")
B1 = 0.9  # Adam's first-moment decay (optax's and torch's default)


# ------------------------------------------------------------------------------ tolerances (parity_step.py's)

def tolerances() -> dict[str, float]:
    """The TOL_* constants of parity_step.py, read from its source (importing it would set thread variables)."""
    tree = ast.parse((HERE / "parity_step.py").read_text())
    out = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            name = node.targets[0].id
            if name.startswith("TOL_"):
                out[name] = float(ast.literal_eval(node.value))
    return out


# ------------------------------------------------------------------------------ the state before the step

def _uniform(bits: np.random.PCG64, n: int) -> np.ndarray:
    """n uniforms in [0, 1) from raw 64-bit draws: a BitGenerator's stream is stable across numpy versions
    (Generator's methods are not promised to be)."""
    return (bits.random_raw(n) >> np.uint64(11)).astype(np.float64) * 2.0 ** -53


def _fan_in(key: str, shapes: dict) -> int:
    """Input size of the layer a weight or bias belongs to: its kernel's second-to-last axis."""
    return int(shapes[key.rsplit("[", 1)[0] + "['kernel']"][-2])


def compared_keys(template: dict) -> list[str]:
    """The leaves of mcrl's state the two systems share: actor, critics, target critics, log(coefficient), their
    Adam states (not the step's random key, the step count or intrinsic models)."""
    return sorted(k for k in template if k.startswith((".pi.", ".q.", ".q_target", ".ent.")))


def before_state(shapes: dict[str, tuple], dtypes: dict[str, str]) -> dict[str, np.ndarray]:
    """The state before the step, derived from STATE_SEED; keys and shapes are mcrl's state.npz's."""
    bits = np.random.PCG64(STATE_SEED)
    out: dict[str, np.ndarray] = {}
    for key in sorted(shapes):
        shape, n = tuple(shapes[key]), int(np.prod(shapes[key], dtype=np.int64))
        if key.endswith(".count"):
            out[key] = np.asarray(ADAM_COUNT, dtypes[key])
            continue
        u = _uniform(bits, n).reshape(shape)
        if key == ".ent.params":
            value = np.log(np.float32(ENT_COEF))
        elif ".opt[0].mu" in key or ".opt[0].nu" in key:
            scale = next(v for prefix, v in MOMENT_SCALE.items() if key.startswith(prefix))
            value = scale * (2 * u - 1) if ".mu" in key else (scale * (0.5 + u)) ** 2
        else:  # a weight or bias: torch's nn.Linear, U(+-1/sqrt(fan_in))
            bound = 1.0 / math.sqrt(_fan_in(key, shapes))
            value = bound * (2 * u - 1)
            if key.startswith(".q_target"):
                value = out[".q.params" + key[len(".q_target"):]] + TARGET_OFFSET * value
        out[key] = np.asarray(value, dtypes[key])
    return out


# ------------------------------------------------------------------------------ the file

def load(path: Path = GOLDEN) -> dict:
    with np.load(path, allow_pickle=False) as f:
        g = {k: f[k] for k in f.files}
    g["meta"] = json.loads(str(g["meta"]))
    return g


def _samples(golden: dict, key_list: str, values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each key's entries at the golden's stored indices."""
    keys, idx, off = golden[key_list], golden[f"{key_list}_index"], golden[f"{key_list}_offsets"]
    return {k: np.ravel(values[k])[idx[off[i]:off[i + 1]]] for i, k in enumerate(keys)}


def _summaries(values: dict[str, np.ndarray], keys) -> tuple[np.ndarray, np.ndarray]:
    x = [np.ravel(np.asarray(values[k], np.float64)) for k in keys]
    return np.array([v.sum() for v in x]), np.array([np.linalg.norm(v) for v in x])


# ------------------------------------------------------------------------------ mcrl's side (no torch)

def config(mode: str):
    from mcrl.config import resolve_config

    return resolve_config(PRESET, {**OVERRIDES, "squash_correction": MODES[mode]})


def mcrl_step(golden: dict, mode: str, batch_edit=None, state_edit=None) -> dict:
    """mcrl's step from the golden's state on its batch, as training takes it: the state written as a checkpoint
    and restored by mcrl's reader, one step of the training loop's Learner. `batch_edit(batch) -> batch` and
    `state_edit(state) -> state` (dicts of arrays) change what mcrl is given, not what it is compared with (the
    tests' mutations). Returns the step's metrics, the state before (the golden's) and after (state.npz keys) and
    the noise the step draws."""
    import jax

    from mcrl.algo.sac import Batch
    from mcrl.run import checkpoint
    from mcrl.run.learner import Learner
    from mcrl.run.policy import agent_for, restore_run

    cfg = config(mode)
    agent, _ = agent_for(cfg)
    template = checkpoint.flatten(agent.init(cfg.seed))
    keys = compared_keys(template)
    before = before_state({k: template[k].shape for k in keys}, {k: template[k].dtype.str for k in keys})
    given = before if state_edit is None else state_edit(dict(before))
    arrays = {**template, **given, ".key": np.asarray(golden["key"], template[".key"].dtype),
              ".grad_steps": np.asarray(ADAM_COUNT, template[".grad_steps"].dtype)}
    batch = {k: golden[f"batch_{k}"] for k in ("obs", "action", "reward", "next_obs", "terminated", "truncated")}
    if batch_edit is not None:
        batch = batch_edit(dict(batch))
    with tempfile.TemporaryDirectory() as tmp:
        ckpt = checkpoint.save(Path(tmp), ADAM_COUNT, arrays, {"episode": 0}, None, keep=1)
        state, diag, _ = restore_run(cfg, agent, ckpt)
    learner = Learner(agent, state, diag)
    learner.update([Batch(*(np.asarray(batch[k], np.float32) for k in Batch._fields))])
    (metrics,) = learner.read_metrics()
    after = checkpoint.flatten(learner.state_of(0)[0])
    k_pi, k_next = jax.random.split(jax.numpy.asarray(arrays[".key"]), 3)[1:]
    shape = batch["action"].shape
    noise = [np.asarray(jax.random.normal(k, shape)) for k in (k_pi, k_next)]
    return {"metrics": metrics, "before": before, "after": {k: after[k] for k in keys}, "noise": noise,
            "template_keys": keys, "shapes": {k: list(template[k].shape) for k in keys}}


def _rel_l2(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.linalg.norm(x - y) / max(np.linalg.norm(y), 1e-30))


def comparison(golden: dict, mode: str, res: dict) -> list[dict]:
    """Every quantity the check compares: {what, value, tol, ok}; value is mcrl's deviation from SB3's."""
    tol = tolerances()
    rows: list[dict] = []

    def add(what, value, limit, ok=None):
        rows.append({"what": what, "value": float(value), "tol": float(limit),
                     "ok": bool(value <= limit) if ok is None else bool(ok)})

    keys = list(golden["state_keys"])
    shapes = golden["meta"]["shapes"]
    same_layout = keys == res["template_keys"] and all(shapes[k] == res["shapes"][k] for k in keys)
    add("state layout (keys, shapes) as the golden's", 0 if same_layout else 1, 0)
    if not same_layout:
        return rows
    b_sum, b_l2 = _summaries(res["before"], keys)
    add("before-state recipe: max rel. difference of the tensors' sums and norms",
        max(np.max(np.abs(b_sum - golden["before_sum"]) / np.maximum(golden["before_l2"], 1e-30)),
            np.max(np.abs(b_l2 - golden["before_l2"]) / np.maximum(golden["before_l2"], 1e-30))), 1e-12)
    add("the step's Gaussian noise (jax's random stream), max abs difference",
        max(np.abs(res["noise"][0] - golden["noise_pi"]).max(), np.abs(res["noise"][1] - golden["noise_next"]).max()),
        0.0)
    # losses: relative, or absolute below TOL_LOSS_ABS (a loss near 0 is a cancellation of larger terms)
    sb3_loss = dict(zip(LOSSES, golden[f"{mode}_losses"]))
    for k in LOSSES:
        m, s = res["metrics"][k], sb3_loss[k]
        rel = abs(m - s) / max(abs(m), abs(s), 1e-30)
        add(f"{k}: mcrl {m:.8g}, SB3 {s:.8g}, relative difference", rel, tol["TOL_LOSS_REL"],
            ok=rel <= tol["TOL_LOSS_REL"] or abs(m - s) <= tol["TOL_LOSS_ABS"])
    before, after = res["before"], res["after"]
    s_before = _samples(golden, "state_keys", before)
    s_after_m = _samples(golden, "state_keys", after)
    s_after_s = dict(zip(keys, np.split(golden[f"{mode}_after"], golden["state_keys_offsets"][1:-1])))
    a_sum_s, d_l2_s = golden[f"{mode}_after_sum"], golden[f"{mode}_delta_l2"]
    a_sum_m = _summaries(after, keys)[0]
    d_l2_m = _summaries({k: np.asarray(after[k], np.float64) - before[k] for k in keys}, keys)[1]
    pos = {k: i for i, k in enumerate(keys)}

    def group_check(label, members, limit):
        """rel. L2 of mcrl's change against SB3's over the stored entries of `members`, and what the same tolerance
        on the whole tensors implies for each tensor's norm and sum of the change (stored for all entries)."""
        if not members:
            return
        dm = np.concatenate([s_after_m[k].astype(np.float64) - s_before[k] for k in members])
        ds = np.concatenate([s_after_s[k].astype(np.float64) - s_before[k] for k in members])
        add(f"{label}: relative L2 difference of the change, {dm.size} entries", _rel_l2(dm, ds), limit)
        norm = math.sqrt(sum(d_l2_s[pos[k]] ** 2 for k in members))
        worst_norm = max(abs(d_l2_m[pos[k]] - d_l2_s[pos[k]]) for k in members) / max(norm, 1e-30)
        add(f"{label}: max |change in a tensor's norm| / the group's change, all entries", worst_norm, limit)
        worst_sum = max(abs(a_sum_m[pos[k]] - a_sum_s[pos[k]]) / math.sqrt(np.prod(shapes[k], dtype=np.int64))
                        for k in members) / max(norm, 1e-30)
        add(f"{label}: max |difference of a tensor's sum| / sqrt(size) / the group's change, all entries",
            worst_sum, limit)

    for g, prefix in GROUPS.items():
        group_check(f"update of {g}", [k for k in keys if k.startswith(prefix)], tol["TOL_UPDATE_REL"])
    for g in OPTIMISED:
        opt = GROUPS[g].replace(".params", ".opt[0]")
        for m in ("mu", "nu"):
            group_check(f"Adam {m} of {g}", [k for k in keys if k.startswith(f"{opt}.{m}")], tol["TOL_UPDATE_REL"])
        count = f"{opt}.count"
        add(f"Adam count of {g}: mcrl {int(after[count])}, SB3 {int(s_after_s[count][0])}",
            abs(int(after[count]) - int(s_after_s[count][0])), 0)
    # gradients: mcrl's from its Adam first moment, m1 = b1 m0 + (1 - b1) g
    gkeys = list(golden["grad_keys"])
    s_grad = dict(zip(gkeys, np.split(golden[f"{mode}_grad"], golden["grad_keys_offsets"][1:-1])))
    grad_m = {k: (np.asarray(after[_mu(k)], np.float64) - B1 * np.asarray(before[_mu(k)], np.float64)) / (1 - B1)
              for k in gkeys}
    s_grad_m = _samples(golden, "grad_keys", grad_m)
    g_sum_m, g_l2_m = _summaries(grad_m, gkeys)
    g_sum_s, g_l2_s = golden[f"{mode}_grad_sum"], golden[f"{mode}_grad_l2"]
    gpos = {k: i for i, k in enumerate(gkeys)}
    for g in OPTIMISED:
        members = [k for k in gkeys if k.startswith(GROUPS[g])]
        gm = np.concatenate([s_grad_m[k] for k in members])
        gs = np.concatenate([s_grad[k].astype(np.float64) for k in members])
        add(f"gradient of {g}: relative L2 difference, {gm.size} entries", _rel_l2(gm, gs), tol["TOL_GRAD_REL"])
        norm = math.sqrt(sum(g_l2_s[gpos[k]] ** 2 for k in members))
        add(f"gradient of {g}: max |difference of a tensor's norm| / the group's norm, all entries",
            max(abs(g_l2_m[gpos[k]] - g_l2_s[gpos[k]]) for k in members) / norm, tol["TOL_GRAD_REL"])
        add(f"gradient of {g}: max |difference of a tensor's sum| / sqrt(size) / the group's norm, all entries",
            max(abs(g_sum_m[gpos[k]] - g_sum_s[gpos[k]]) / math.sqrt(np.prod(shapes[k], dtype=np.int64))
                for k in members) / norm, tol["TOL_GRAD_REL"])
    return rows


def _mu(param_key: str) -> str:
    """The Adam first moment's key of a parameter's key."""
    group, rest = param_key.split(".params", 1)
    return f"{group}.opt[0].mu{rest}"


def failures(rows: list[dict]) -> list[str]:
    return [f"{r['what']}: {r['value']:.3g} > {r['tol']:.3g}" for r in rows if not r["ok"]]


def table(rows: list[dict]) -> str:
    return "\n".join(f"{'ok  ' if r['ok'] else 'FAIL'} {r['value']:9.2e} <= {r['tol']:7.1e}  {r['what']}" for r in rows)


# ------------------------------------------------------------------------------ SB3's side (torch)

def _batch_and_buffer(cfg) -> tuple[dict, dict]:
    """The batch (with a `truncated` column) and the episodes it was drawn from, as mcrl's buffer arrays."""
    from mcrl.envs import episode_seed, flatten_obs, inspect, make_env, to_env_action

    env = make_env(cfg)
    spec = inspect(env, cfg)
    rng = np.random.default_rng(BATCH_SEED)
    episodes = []
    for e in range(N_EPISODES):
        obs, _ = env.reset(seed=episode_seed(BATCH_SEED, 7, e))
        ep = {k: [] for k in ("obs", "action", "reward", "next_obs", "terminated", "truncated", "ag_next")}
        while True:
            a = rng.uniform(-1, 1, spec.act_dim).astype(np.float32)
            nxt, r, term, trunc, _ = env.step(to_env_action(a, env, cfg.action_scale))
            for k, v in (("obs", flatten_obs(obs)), ("action", a), ("reward", r), ("next_obs", flatten_obs(nxt)),
                         ("terminated", term), ("truncated", trunc), ("ag_next", nxt["achieved_goal"])):
                ep[k].append(v)
            obs = nxt
            if term or trunc:
                break
        episodes.append({k: np.asarray(v, np.float32) for k, v in ep.items()})
    B = cfg.batch_size
    n_her = int(round(B * cfg.her_k / (cfg.her_k + 1)))  # mcrl's her_rounding=nearest: 205 of 256
    g0 = spec.observation_dim + spec.goal_dim  # desired_goal's slice in the flat observation
    rows = {k: [] for k in ("obs", "action", "reward", "next_obs", "terminated", "truncated")}
    last_rows = set(rng.choice(B, N_TRUNCATED, replace=False).tolist())  # rows drawn at the episode's last step
    for j in range(B):
        ep = episodes[int(rng.integers(N_EPISODES))]
        T = len(ep["obs"])
        t = T - 1 if j in last_rows else int(rng.integers(T - 1))
        o, nx, r = ep["obs"][t].copy(), ep["next_obs"][t].copy(), ep["reward"][t]
        if j < n_her:  # relabelled with an achieved goal of the same episode at or after t
            goal = ep["ag_next"][int(rng.integers(t, T))]
            o[g0:], nx[g0:] = goal, goal
            r = np.float32(env.unwrapped.compute_reward(ep["ag_next"][t], goal, {}))
        for k, v in zip(rows, (o, ep["action"][t], r, nx, ep["terminated"][t], ep["truncated"][t])):
            rows[k].append(v)
    env.close()
    batch = {k: np.asarray(v, np.float32) for k, v in rows.items()}
    assert not batch["terminated"].any() and batch["truncated"].sum() == N_TRUNCATED
    not_last = np.flatnonzero(batch["truncated"] == 0)
    batch["terminated"][rng.choice(not_last, N_TERMINATED, replace=False)] = 1.0  # by hand: Fetch never ends
    cat = {k: np.concatenate([ep[k] for ep in episodes]) for k in ("obs", "action", "reward", "next_obs",
                                                                    "terminated")}
    lengths = [len(ep["obs"]) for ep in episodes]
    first = np.repeat(np.cumsum([0] + lengths[:-1]), lengths)
    n = int(sum(lengths))
    buffer = {**cat, "ep_first": first.astype(np.int64), "ep_last": (first + np.repeat(lengths, lengths) - 1),
              "counters": np.array([n, n, cfg.buffer_size], np.int64)}
    return batch, buffer


def sb3_step(mode: str, golden_in: dict, buffer: dict) -> dict:
    """SB3's step in `mode` from the golden's state on its batch: losses, the state after and the gradients, in
    mcrl's state.npz keys."""
    import torch
    from stable_baselines3 import SAC
    from stable_baselines3.common.logger import Logger

    from _sb3 import build_model
    from _transplant import (TODAY, _goal_slices, _input_order, _modules, _permute_inputs, differences, flat,
                             install_sb3, learning_from_arrays, learning_to_arrays, read_sb3)
    from _transplant_check import _FixedDictBatch
    from mcrl.run import checkpoint
    from mcrl.run.policy import agent_for
    from parity_step import _layout, fixed_normal_noise, sb3_exact_log_prob, torch_to_tree

    cfg = config(mode)
    agent, _ = agent_for(cfg)
    template = checkpoint.flatten(agent.init(cfg.seed))
    keys = compared_keys(template)
    before = before_state({k: template[k].shape for k in keys}, {k: template[k].dtype.str for k in keys})
    arrays = {**template, **before}
    start = learning_from_arrays(arrays, ADAM_COUNT, N_EPISODES, buffer)
    model, _ = build_model(cfg, sac_class=SAC)  # stock SB3: its own SAC.train
    model.set_logger(Logger(folder=None, output_formats=[]))
    install_sb3(model, start)
    moved = differences(start, read_sb3(model, ADAM_COUNT, N_EPISODES))
    assert max(moved.values()) == 0.0, {k: v for k, v in moved.items() if v}
    batch = {k: golden_in[f"batch_{k}"] for k in ("obs", "action", "reward", "next_obs", "terminated")}
    real_buffer, model.replay_buffer = model.replay_buffer, _FixedDictBatch(batch, _goal_slices(model))
    samples = model.replay_buffer.samples
    with torch.no_grad():
        q_mean = float(torch.cat(model.critic(samples.observations, samples.actions), dim=1).mean())
    grads: dict = {}
    for name, opt in (("actor", model.actor.optimizer), ("critic", model.critic.optimizer),
                      ("log_ent_coef", model.ent_coef_optimizer)):
        def step(*a, _f=opt.step, _opt=opt, _name=name, **k):
            grads[_name] = {p: p.grad.detach().clone() for grp in _opt.param_groups for p in grp["params"]}
            return _f(*a, **k)
        opt.step = step
    with fixed_normal_noise() as queue, sb3_exact_log_prob(mode == "exact"):
        queue[:] = [torch.tensor(golden_in["noise_pi"]), torch.tensor(golden_in["noise_next"])]
        model.train(gradient_steps=1, batch_size=cfg.batch_size)
        assert not queue, "SB3 drew fewer Gaussian samples than mcrl"
    model.replay_buffer = real_buffer
    logged = model.logger.name_to_value
    losses = {k: float(logged[f"train/{k}"]) for k in ("critic_loss", "actor_loss", "ent_coef_loss", "ent_coef")}
    losses["q_mean"] = q_mean
    end = read_sb3(model, ADAM_COUNT, N_EPISODES)
    after = learning_to_arrays(end, arrays)
    order = _input_order(model)
    actor_l, critic_l = _layout(len(model.actor.latent_pi) // 2)
    grad_arrays = {}
    for g, layout in (("actor", actor_l), ("critic", critic_l)):
        module, _, stacked = _modules(model)[g]
        tree = _permute_inputs(torch_to_tree(module, layout, stacked, lambda p, g=g: grads[g][p]), g, order, True)
        grad_arrays.update(flat(TODAY[g], tree))
    grad_arrays[".ent.params"] = np.float32(grads["log_ent_coef"][model.log_ent_coef].numpy()[0])
    return {"losses": losses, "after": {k: after[k] for k in keys}, "grads": grad_arrays, "before": before,
            "keys": keys, "shapes": {k: list(template[k].shape) for k in keys}}


def generate(out: Path) -> int:
    import jax
    import stable_baselines3
    import torch

    from mcrl.run.policy import agent_for

    t0 = time.time()
    cfg = config("exact")
    batch, buffer = _batch_and_buffer(cfg)
    key = np.asarray(jax.random.PRNGKey(STATE_SEED), np.uint32)
    k_pi, k_next = jax.random.split(key, 3)[1:]
    noise = [np.asarray(jax.random.normal(k, batch["action"].shape), np.float32) for k in (k_pi, k_next)]
    golden: dict = {f"batch_{k}": v for k, v in batch.items()}
    golden.update(key=key, noise_pi=noise[0], noise_next=noise[1])
    rng = np.random.default_rng(STATE_SEED)
    results = {mode: sb3_step(mode, golden, buffer) for mode in MODES}
    first = results["exact"]
    keys, gkeys = first["keys"], sorted(first["grads"])
    for name, ks in (("state_keys", keys), ("grad_keys", gkeys)):
        sizes = [int(np.prod(first["shapes"][k], dtype=np.int64)) for k in ks]
        idx = [np.sort(rng.choice(n, min(n, SAMPLES), replace=False)) for n in sizes]
        golden[name] = np.array(ks)
        golden[f"{name}_index"] = np.concatenate(idx).astype(np.int32)
        golden[f"{name}_offsets"] = np.cumsum([0] + [len(i) for i in idx]).astype(np.int64)
    golden["before_sum"], golden["before_l2"] = _summaries(first["before"], keys)
    for mode, r in results.items():
        assert r["keys"] == keys
        golden[f"{mode}_losses"] = np.array([r["losses"][k] for k in LOSSES], np.float64)
        golden[f"{mode}_after"] = np.concatenate(  # float32 holds the Adam counts (1001) exactly too
            list(_samples(golden, "state_keys", r["after"]).values())).astype(np.float32)
        golden[f"{mode}_after_sum"], golden[f"{mode}_after_l2"] = _summaries(r["after"], keys)
        golden[f"{mode}_delta_l2"] = _summaries({k: np.asarray(r["after"][k], np.float64) - r["before"][k]
                                                 for k in keys}, keys)[1]
        golden[f"{mode}_grad"] = np.concatenate(list(_samples(golden, "grad_keys", r["grads"]).values())).astype(
            np.float32)
        golden[f"{mode}_grad_sum"], golden[f"{mode}_grad_l2"] = _summaries(r["grads"], gkeys)
    _, spec = agent_for(cfg)
    golden["meta"] = np.array(json.dumps({
        "what": "stable-baselines3's SAC step, studies/sb3-parity/golden.py", "preset": PRESET,
        "overrides": OVERRIDES, "modes": MODES, "losses": LOSSES, "state_seed": STATE_SEED,
        "batch_seed": BATCH_SEED, "env_id": cfg.env_id, "obs_dim": spec.obs_dim, "act_dim": spec.act_dim,
        "shapes": first["shapes"], "versions": {
            "stable_baselines3": stable_baselines3.__version__, "torch": torch.__version__, "jax": jax.__version__,
            "numpy": np.__version__, "python": sys.version.split()[0]},
        "command": "python studies/sb3-parity/golden.py generate", "mcrl_commit": _commit(),
        "sb3_losses": {m: r["losses"] for m, r in results.items()}}, sort_keys=True))
    # the file must pass mcrl's step before it is written
    bad = {}
    for mode in MODES:
        rows = comparison(golden | {"meta": json.loads(str(golden["meta"]))}, mode, mcrl_step(
            golden | {"meta": json.loads(str(golden["meta"]))}, mode))
        print(f"--- mode {mode}\n{table(rows)}")
        bad.update({f"{mode}: {f}": True for f in failures(rows)})
    if bad:
        print(f"error: mcrl's step does not pass against SB3's; nothing written: {list(bad)}", file=sys.stderr)
        return 1
    np.savez_compressed(out, **golden)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB) in {time.time() - t0:.0f} s")
    return 0


def _commit() -> str | None:
    import subprocess

    r = subprocess.run(["git", "-C", str(REPO_ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return r.stdout.strip() or None


def check(path: Path) -> int:
    golden = load(path)
    bad = []
    for mode in MODES:
        rows = comparison(golden, mode, mcrl_step(golden, mode))
        print(f"--- mode {mode}\n{table(rows)}")
        bad += failures(rows)
    return 1 if bad else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("command", choices=("generate", "check"))
    ap.add_argument("--file", type=Path, default=GOLDEN)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(HERE))
    if args.command == "generate":
        import _common

        _common.one_thread()
        import torch

        torch.set_num_threads(1)
        return generate(args.file)
    return check(args.file)


if __name__ == "__main__":
    sys.exit(main())
