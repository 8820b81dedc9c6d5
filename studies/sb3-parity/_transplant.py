"""The learning state of a SAC+HER run, moved between mcrl's checkpoint files and stable-baselines3 (SB3).

``Learning`` is the state that decides how training goes on, in mcrl's layout as plain numpy: the actor, both
critics, the target critics, log(entropy coefficient), the Adam state (step count, first and second moments) of
the actor, the critics and the coefficient, and the replay buffer with its episode structure (mcrl's buffer
arrays: ``ep_first``/``ep_last`` are what HER relabels from). Readers and writers:

* mcrl checkpoint directories (``state.npz`` + ``buffer.npz`` + ``meta.json``) of today's format, or of commit
  83e6d8d's (``.actor``, ``.actor_opt[0]...``), converted first by ``scripts/migrate_checkpoint.py``; written
  back in today's format with a fresh key, host RNG and seed (the random streams);
* an SB3 ``SAC`` with ``HerReplayBuffer`` (``install_sb3`` / ``read_sb3``). SB3's ``CombinedExtractor`` feeds
  the networks ``achieved_goal | desired_goal | observation`` (the Dict space's sorted keys) where mcrl feeds
  ``observation | achieved_goal | desired_goal``, so the first layers' input rows are permuted on the way.
  SB3 stores observations as float64, its networks see them as float32: mcrl's float32 values go in exactly,
  SB3's come out rounded to float32 (what its networks saw). SB3's ``dones`` are episode ends and its
  ``timeouts`` the truncated ones; mcrl stores ``terminated`` (= done and not timeout) and the episode bounds.
"""
from __future__ import annotations

import json
import re
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from _common import REPO_ROOT

GROUPS = ("actor", "critic", "critic_target", "log_ent_coef")
OPTIMISED = ("actor", "critic", "log_ent_coef")
# where each group lives in today's state.npz
TODAY = {"actor": ".pi.params", "critic": ".q.params", "critic_target": ".q_target", "log_ent_coef": ".ent.params"}
TODAY_OPT = {"actor": ".pi.opt[0]", "critic": ".q.opt[0]", "log_ent_coef": ".ent.opt[0]"}
BUFFER_KEYS = ("obs", "action", "reward", "next_obs", "terminated", "ep_first", "ep_last", "counters")


class TransplantError(Exception):
    """Input the transplant cannot use; the message names the fix."""


@dataclass
class Learning:
    step: int
    episode: int
    params: dict  # group -> flax-shaped tree (log_ent_coef: a float32 scalar)
    opt: dict  # group -> {"count": int, "mu": tree, "nu": tree}
    buffer: dict  # mcrl's ReplayBuffer.state_arrays()


# ----------------------------------------------------------------------------------------- flat keys <-> trees

_PART = re.compile(r"\['([^']*)'\]")


def subtree(arrays: dict, prefix: str):
    """The tree under `prefix` of a flat ``keystr`` dict (a leaf if `prefix` is a key itself)."""
    if prefix in arrays:
        return np.asarray(arrays[prefix])
    tree: dict = {}
    for k, v in arrays.items():
        if k.startswith(prefix + "["):
            path = _PART.findall(k[len(prefix):])
            node = tree
            for p in path[:-1]:
                node = node.setdefault(p, {})
            node[path[-1]] = np.asarray(v)
    if not tree:
        raise KeyError(prefix)
    return tree


def flat(prefix: str, tree) -> dict:
    if not isinstance(tree, dict):
        return {prefix: np.asarray(tree)}
    out = {}
    for k, v in tree.items():
        out.update(flat(f"{prefix}['{k}']", v))
    return out


def learning_from_arrays(arrays: dict, step: int, episode: int, buffer: dict) -> Learning:
    """Learning from a flat dict of today's state.npz keys."""
    params = {g: subtree(arrays, TODAY[g]) for g in GROUPS}
    opt = {}
    for g in OPTIMISED:
        o = TODAY_OPT[g]
        opt[g] = {"count": int(arrays[o + ".count"]), "mu": subtree(arrays, o + ".mu"), "nu": subtree(arrays, o + ".nu")}
    return Learning(step, episode, params, opt, {k: np.asarray(buffer[k]) for k in BUFFER_KEYS})


def learning_to_arrays(learning: Learning, template: dict) -> dict:
    """Today's state.npz arrays: `template` (a fresh state's, e.g. of ``Agent.init(seed)``: its key is the new
    update-noise stream) with every learned leaf replaced; refuses if a leaf has no place or another shape."""
    new = {}
    for g in GROUPS:
        new.update(flat(TODAY[g], learning.params[g]))
    for g in OPTIMISED:
        o = learning.opt[g]
        new[TODAY_OPT[g] + ".count"] = np.int32(o["count"])
        new.update(flat(TODAY_OPT[g] + ".mu", o["mu"]))
        new.update(flat(TODAY_OPT[g] + ".nu", o["nu"]))
    missing = sorted(set(new) - set(template))
    if missing:
        raise TransplantError(f"the state has arrays today's mcrl state does not ({missing[:3]}): the config's "
                              "network sizes or mcrl's state layout differ")
    out = dict(template)
    for k, v in new.items():
        if np.shape(v) != np.shape(template[k]):
            raise TransplantError(f"{k} has shape {np.shape(v)}, today's mcrl state {np.shape(template[k])}")
        out[k] = np.asarray(v, np.asarray(template[k]).dtype)
    if ".grad_steps" in out:
        out[".grad_steps"] = np.int32(learning.opt["critic"]["count"])
    return out


# ----------------------------------------------------------------------------------------- mcrl checkpoints

def is_mcrl_checkpoint(path: Path) -> bool:
    return (path / "state.npz").is_file() and (path / "meta.json").is_file()


def read_mcrl(ckpt: Path) -> tuple[Learning, dict]:
    """(Learning, the run's config dict) of an mcrl checkpoint directory; an older format (commit 83e6d8d's)
    is converted first by scripts/migrate_checkpoint.py into a temporary copy."""
    sys.path.insert(0, str(REPO_ROOT / "scripts"))
    from migrate_checkpoint import MigrationError, format_of, migrate

    with tempfile.TemporaryDirectory() as tmp:
        with np.load(ckpt / "state.npz", allow_pickle=False) as f:
            current = format_of(f.files) == "current"
        try:
            src = ckpt if current else migrate(ckpt, Path(tmp) / ckpt.name)
        except MigrationError as e:
            raise TransplantError(str(e)) from None
        meta = json.loads((src / "meta.json").read_text())
        with np.load(src / "state.npz", allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
        if not (src / "buffer.npz").is_file():
            raise TransplantError(f"{ckpt} has no buffer.npz (save_buffer=false): the replay buffer is part of "
                                  "the state; use a checkpoint of a run with save_buffer=true")
        with np.load(src / "buffer.npz", allow_pickle=False) as f:
            buffer = {k: f[k] for k in f.files}
    cfg = meta.get("config")
    if cfg is None:
        cfg = json.loads((ckpt.parent.parent / "config.json").read_text())
    return learning_from_arrays(arrays, int(meta["step"]), int(meta["episode"]), buffer), cfg


def write_mcrl(run_dir: Path, learning: Learning, cfg) -> Path:
    """A resumable mcrl run directory at the state's step: config.json (`cfg`, whose seed names the new random
    streams) and checkpoints/step_<N>/ in today's format, with the update key of ``Agent.init(cfg.seed)``, the
    host RNG (replay sampling, HER goals) of ``default_rng(cfg.seed)`` and no running episode."""
    import jax

    from mcrl.run import rundir
    from mcrl.run.policy import agent_for

    agent, _ = agent_for(cfg)
    template = {jax.tree_util.keystr(p): np.asarray(leaf)
                for p, leaf in jax.tree_util.tree_flatten_with_path(agent.init(cfg.seed))[0]}
    template = {k: v for k, v in template.items() if not k.startswith(".norm")}  # MC normaliser: not SAC's
    arrays = learning_to_arrays(learning, template)
    ckpt = rundir.checkpoint_root(run_dir) / rundir.checkpoint_name(learning.step)
    ckpt.mkdir(parents=True)
    np.savez(ckpt / "state.npz", **arrays)
    np.savez(ckpt / "buffer.npz", **learning.buffer)
    meta = {"episode": learning.episode, "eval_round": 0,
            "host_rng": np.random.default_rng(cfg.seed).bit_generator.state,
            "interval": {"returns": [], "successes": []}, "last_eval": {"success_rate": None, "mean_return": None},
            "config": cfg.to_dict(), "step": learning.step, "has_buffer": True}
    (ckpt / "meta.json").write_text(json.dumps(meta))
    rundir.write_latest(run_dir, ckpt.name)
    rundir.write_json_atomic(run_dir / rundir.CONFIG, cfg.to_dict())
    return ckpt


# ----------------------------------------------------------------------------------------- SB3

def _input_order(model) -> np.ndarray | None:
    """mcrl's flat-input index of each SB3 feature (None for a Box observation: the same order)."""
    from mcrl.envs import GOAL_KEYS

    spaces = getattr(model.observation_space, "spaces", None)
    if spaces is None:
        return None
    sizes = {k: int(np.prod(spaces[k].shape)) for k in GOAL_KEYS}
    start = dict(zip(GOAL_KEYS, np.cumsum([0] + [sizes[k] for k in GOAL_KEYS])))
    return np.concatenate([np.arange(start[k], start[k] + sizes[k]) for k in spaces])


def _permute_inputs(tree: dict, group: str, order: np.ndarray | None, back: bool) -> dict:
    """The tree with its first layer's input rows in SB3's feature order (`back`: into mcrl's)."""
    if order is None or group == "log_ent_coef":
        return tree
    idx = np.argsort(order) if back else order
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in tree.items()}
    if group == "actor":
        layer = dict(out["MLP_0"]["Dense_0"])
        layer["kernel"] = layer["kernel"][idx]
        out["MLP_0"] = {**out["MLP_0"], "Dense_0": layer}
    else:  # critics: (2, obs + act, hidden); the action rows follow the observation's
        layer = dict(out["VmapMLP_0"]["Dense_0"])
        k = layer["kernel"]
        rows = np.concatenate([idx, np.arange(len(idx), k.shape[1])])
        layer["kernel"] = k[:, rows]
        out["VmapMLP_0"] = {**out["VmapMLP_0"], "Dense_0": layer}
    return out


def _modules(model):
    """group -> (torch module, optimiser, stacked critics?)."""
    return {"actor": (model.actor, model.actor.optimizer, False), "critic": (model.critic, model.critic.optimizer, True),
            "critic_target": (model.critic_target, None, True)}


def install_sb3(model, learning: Learning) -> None:
    """Put `learning` into an SB3 SAC (HerReplayBuffer of the same capacity): weights, target critics, Adam
    states, log(entropy coefficient), step counters and the replay buffer."""
    import copy

    import torch

    from parity_step import _layout, tree_to_torch

    order = _input_order(model)
    actor_l, critic_l = _layout(len(model.actor.latent_pi) // 2)
    layouts = {"actor": actor_l, "critic": critic_l, "critic_target": critic_l}
    for g, (module, opt, stacked) in _modules(model).items():
        tree_to_torch(_permute_inputs(learning.params[g], g, order, False), module, layouts[g], stacked)
        if opt is None:
            continue
        o = learning.opt[g]
        moments = {}
        for m in ("mu", "nu"):
            scratch = copy.deepcopy(module)
            tree_to_torch(_permute_inputs(o[m], g, order, False), scratch, layouts[g], stacked)
            moments[m] = dict(scratch.named_parameters())
        for name, p in module.named_parameters():
            opt.state[p] = {"step": torch.tensor(float(o["count"])),
                            "exp_avg": moments["mu"][name].detach().clone(),
                            "exp_avg_sq": moments["nu"][name].detach().clone()}
    o = learning.opt["log_ent_coef"]
    with torch.no_grad():
        model.log_ent_coef.copy_(torch.tensor([float(learning.params["log_ent_coef"])]))
    model.ent_coef_optimizer.state[model.log_ent_coef] = {
        "step": torch.tensor(float(o["count"])), "exp_avg": torch.tensor([float(o["mu"])]),
        "exp_avg_sq": torch.tensor([float(o["nu"])])}
    model.num_timesteps = learning.step
    model._n_updates = learning.opt["critic"]["count"]
    _buffer_to_sb3(model.replay_buffer, learning.buffer, model)


def read_sb3(model, step: int | None = None, episode: int = 0) -> Learning:
    """The Learning of an SB3 SAC with HerReplayBuffer (inverse of install_sb3)."""
    from parity_step import _layout, torch_to_tree

    order = _input_order(model)
    actor_l, critic_l = _layout(len(model.actor.latent_pi) // 2)
    layouts = {"actor": actor_l, "critic": critic_l, "critic_target": critic_l}
    params, opt = {}, {}
    for g, (module, optim, stacked) in _modules(model).items():
        params[g] = _permute_inputs(torch_to_tree(module, layouts[g], stacked), g, order, True)
        if optim is None:
            continue
        st = [optim.state[p] for p in module.parameters()]
        counts = {int(s["step"]) for s in st}
        if len(counts) != 1:
            raise TransplantError(f"SB3's {g} optimiser has several step counts {counts}")
        opt[g] = {"count": counts.pop()}
        for m, key in (("mu", "exp_avg"), ("nu", "exp_avg_sq")):
            opt[g][m] = _permute_inputs(torch_to_tree(module, layouts[g], stacked, lambda p, k=key: optim.state[p][k]),
                                        g, order, True)
    params["log_ent_coef"] = np.float32(model.log_ent_coef.detach().numpy()[0])
    s = model.ent_coef_optimizer.state[model.log_ent_coef]
    opt["log_ent_coef"] = {"count": int(s["step"]), "mu": np.float32(s["exp_avg"].numpy()[0]),
                           "nu": np.float32(s["exp_avg_sq"].numpy()[0])}
    return Learning(model.num_timesteps if step is None else step, episode, params, opt,
                    _buffer_from_sb3(model.replay_buffer, model))


def _goal_slices(model) -> dict[str, slice]:
    from mcrl.envs import GOAL_KEYS

    spaces = model.observation_space.spaces
    sizes = [int(np.prod(spaces[k].shape)) for k in GOAL_KEYS]
    ends = np.cumsum(sizes)
    return {k: slice(int(e - s), int(e)) for k, s, e in zip(GOAL_KEYS, sizes, ends)}


def _buffer_to_sb3(rb, buf: dict, model) -> None:
    total, episode_first, capacity = (int(x) for x in buf["counters"])
    if capacity != rb.buffer_size or total >= capacity:
        raise TransplantError(f"replay buffer of {total} transitions in capacity {capacity}, SB3's holds "
                              f"{rb.buffer_size}: only a buffer that has not wrapped, of the same capacity, maps "
                              "onto SB3's HerReplayBuffer (which drops whole episodes when it wraps)")
    n = total
    for k, sl in _goal_slices(model).items():
        rb.observations[k][:n, 0] = buf["obs"][:, sl]
        rb.next_observations[k][:n, 0] = buf["next_obs"][:, sl]
    rb.actions[:n, 0] = buf["action"]
    rb.rewards[:n, 0] = buf["reward"]
    last = buf["ep_last"] == np.arange(n)
    rb.dones[:n, 0] = last
    rb.timeouts[:n, 0] = last & (buf["terminated"] == 0)
    rb.ep_start[:n, 0] = buf["ep_first"]
    rb.ep_length[:n, 0] = np.where(buf["ep_last"] >= 0, buf["ep_last"] - buf["ep_first"] + 1, 0)
    rb.pos, rb.full = n, False
    rb._current_ep_start[0] = episode_first


def _buffer_from_sb3(rb, model) -> dict:
    if rb.full or rb.n_envs != 1:
        raise TransplantError("SB3's buffer has wrapped (or holds several envs): mcrl's layout needs one env's "
                              "transitions in order from the first")
    n = rb.pos
    sl = _goal_slices(model)
    obs = np.concatenate([rb.observations[k][:n, 0] for k in sl], axis=1).astype(np.float32)
    nxt = np.concatenate([rb.next_observations[k][:n, 0] for k in sl], axis=1).astype(np.float32)
    length = rb.ep_length[:n, 0]
    return {"obs": obs, "action": rb.actions[:n, 0].astype(np.float32), "reward": rb.rewards[:n, 0].astype(np.float32),
            "next_obs": nxt, "terminated": (rb.dones[:n, 0] * (1 - rb.timeouts[:n, 0])).astype(np.float32),
            "ep_first": rb.ep_start[:n, 0].astype(np.int64),
            "ep_last": np.where(length > 0, rb.ep_start[:n, 0] + length - 1, -1).astype(np.int64),
            "counters": np.array([n, int(rb._current_ep_start[0]), rb.buffer_size], np.int64)}


def load_sb3_checkpoint(ckpt: Path, cfg):
    """(ParitySAC, episodes so far) from an SB3 parity checkpoint (``studies/sb3-parity/_sb3.py``'s model.zip,
    replay_buffer.pkl, state.pkl). Pickles: load only checkpoints this project's scripts wrote."""
    import pickle

    from _sb3 import check_mirrorable, make_parity_sac_class
    from mcrl.envs import make_env

    env = make_env(cfg)
    check_mirrorable(cfg, env)
    model = make_parity_sac_class().load(ckpt / "model.zip", env=env, device="cpu")
    model.load_replay_buffer(ckpt / "replay_buffer.pkl", truncate_last_traj=False)  # taken at an episode end
    episode = 0
    if (ckpt / "state.pkl").is_file():
        with open(ckpt / "state.pkl", "rb") as f:
            episode = int(pickle.load(f)["recorder"]["episodes"])
    return model, episode


# ----------------------------------------------------------------------------------------- comparison

def differences(a: Learning, b: Learning) -> dict[str, float]:
    """Max |a - b| per part (parameters, Adam moments and counts, buffer arrays); all 0.0 = identical."""
    import jax

    def md(x, y):
        lx, ly = jax.tree.leaves(x), jax.tree.leaves(y)
        if len(lx) != len(ly) or any(np.shape(p) != np.shape(q) for p, q in zip(lx, ly)):
            return float("inf")
        return max((float(np.max(np.abs(np.asarray(p, np.float64) - np.asarray(q, np.float64)), initial=0.0))
                    for p, q in zip(lx, ly)), default=0.0)

    out = {f"params.{g}": md(a.params[g], b.params[g]) for g in GROUPS}
    for g in OPTIMISED:
        for m in ("mu", "nu"):
            out[f"adam_{m}.{g}"] = md(a.opt[g][m], b.opt[g][m])
        out[f"adam_count.{g}"] = float(abs(a.opt[g]["count"] - b.opt[g]["count"]))
    for k in BUFFER_KEYS:
        out[f"buffer.{k}"] = md(a.buffer[k], b.buffer[k])
    out["step"] = float(abs(a.step - b.step))
    return out
