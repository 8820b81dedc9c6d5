"""Is the transplant faithful? ``transplant.py check``'s three parts.

1. mcrl -> SB3 -> mcrl: an mcrl checkpoint's Learning installed into a fresh SB3 SAC and read back; and written
   as today's mcrl checkpoint and read back by mcrl's own reader (``mcrl.run.policy.restore`` and the
   ``ReplayBuffer``). Every parameter, Adam moment and count, log(entropy coefficient) and buffer array must be
   equal (max |difference| 0.0).
2. SB3 -> mcrl -> SB3: an SB3 model's state written as an mcrl checkpoint, read by mcrl's reader, installed into
   a fresh SB3 SAC: its torch parameters, optimiser states and replay-buffer arrays must equal the original's
   (observations after rounding to float32, what SB3's networks see).
3. Gradient steps, side by side, from each transplanted state (with its Adam moments) on the same replay
   batch and the same Gaussian noise (``parity_step``'s noise hand-over and tanh-correction patch): in mode
   ``sb3-exact`` (SB3 given mcrl's exact tanh correction) losses and parameter updates must agree to float32
   round-off (``parity_step``'s tolerances); ``as-is`` is reported.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from _transplant import GROUPS, OPTIMISED, Learning, differences, learning_from_arrays, read_sb3, write_mcrl


def read_with_mcrl(run_dir: Path):
    """(Learning, agent, train state) of a run directory's newest checkpoint, read by mcrl's own code."""
    import jax

    from mcrl.run import checkpoint, rundir
    from mcrl.run.policy import build, restore

    cfg = rundir.read_config(run_dir)
    env, _, agent, buffer = build(cfg)
    env.close()
    ckpt = checkpoint.find(Path(run_dir))
    state, meta = restore(cfg, agent, ckpt)
    buffer.load_arrays(checkpoint.load_buffer_arrays(ckpt))
    return learning_of(state, meta["step"], meta["episode"], buffer.state_arrays()), agent, state


def learning_of(state, step: int, episode: int, buffer: dict) -> Learning:
    import jax

    arrays = {jax.tree_util.keystr(p): np.asarray(x) for p, x in jax.tree_util.tree_flatten_with_path(state)[0]}
    return learning_from_arrays(arrays, step, episode, buffer)


def torch_differences(a, b) -> dict[str, float]:
    """Max |a - b| between two SB3 SAC models: parameters, optimiser states, log ent_coef, replay buffer."""
    out = {}
    pairs = {"actor": (a.actor, b.actor, a.actor.optimizer, b.actor.optimizer),
             "critic": (a.critic, b.critic, a.critic.optimizer, b.critic.optimizer),
             "critic_target": (a.critic_target, b.critic_target, None, None)}
    for g, (ma, mb, oa, ob) in pairs.items():
        out[f"params.{g}"] = max(float((p - q).detach().abs().max()) for p, q in zip(ma.parameters(), mb.parameters()))
        if oa is not None:
            for k in ("step", "exp_avg", "exp_avg_sq"):
                out[f"{k}.{g}"] = max(float((oa.state[p][k] - ob.state[q][k]).abs().max())
                                      for p, q in zip(ma.parameters(), mb.parameters()))
    sa, sb = a.ent_coef_optimizer.state[a.log_ent_coef], b.ent_coef_optimizer.state[b.log_ent_coef]
    out["params.log_ent_coef"] = float((a.log_ent_coef - b.log_ent_coef).detach().abs().max())
    for k in ("step", "exp_avg", "exp_avg_sq"):
        out[f"{k}.log_ent_coef"] = float((sa[k] - sb[k]).abs().max())
    ra, rb = a.replay_buffer, b.replay_buffer
    n = ra.pos
    out["buffer.length"] = float(abs(ra.pos - rb.pos))
    for name in ("observations", "next_observations"):
        da, db = getattr(ra, name), getattr(rb, name)
        out[f"buffer.{name}"] = max(float(np.abs(da[k][:n].astype(np.float32) - db[k][:n].astype(np.float32)).max())
                                    for k in da)
    for name in ("actions", "rewards", "dones", "timeouts", "ep_start", "ep_length"):
        out[f"buffer.{name}"] = float(np.abs(getattr(ra, name)[:n].astype(np.float64)
                                             - getattr(rb, name)[:n]).max())
    out["buffer.current_ep_start"] = float(abs(int(ra._current_ep_start[0]) - int(rb._current_ep_start[0])))
    return out


class _FixedDictBatch:
    """Stands in for SB3's replay buffer: every sample() is the given mcrl batch, split into the Dict keys."""

    def __init__(self, batch: dict, slices: dict):
        import torch
        from stable_baselines3.common.type_aliases import DictReplayBufferSamples

        t = lambda x: torch.from_numpy(np.array(x, np.float32))  # noqa: E731
        self.samples = DictReplayBufferSamples(
            observations={k: t(batch["obs"][:, s]) for k, s in slices.items()}, actions=t(batch["action"]),
            next_observations={k: t(batch["next_obs"][:, s]) for k, s in slices.items()},
            dones=t(batch["terminated"])[:, None], rewards=t(batch["reward"])[:, None])

    def sample(self, batch_size, env=None):
        return self.samples


def one_step(cfg, mcrl_run: Path, mode: str, steps: int = 3, seed: int = 0) -> dict:
    """`steps` gradient steps of mcrl and of SB3 from the state in `mcrl_run` (SB3's copy made by install_sb3),
    on one batch of that state's replay buffer and the same noise; returns the worst relative differences."""
    import jax
    import jax.numpy as jnp
    import torch
    from stable_baselines3.common.logger import Logger

    from _sb3 import build_model
    from _transplant import _goal_slices, install_sb3
    from mcrl.algo.sac import Batch
    from parity_step import fixed_normal_noise, host_noise, sb3_exact_log_prob

    start, agent, state = read_with_mcrl(mcrl_run)
    model, _ = build_model(cfg)
    model.set_logger(Logger(folder=None, output_formats=[]))
    install_sb3(model, start)
    from mcrl.run.policy import build

    env, _, _, buffer = build(cfg)
    env.close()
    buffer.load_arrays(start.buffer)
    batch = buffer.sample(cfg.batch_size, np.random.default_rng(seed))
    batch = batch._asdict() if hasattr(batch, "_asdict") else batch  # a dict before issue 27, a Batch after
    key = jax.tree_util.tree_flatten_with_path(state)[0]
    key = next(x for p, x in key if jax.tree_util.keystr(p) == ".key")
    noise = host_noise(key, steps, batch["action"].shape)

    update = jax.jit(agent.update)
    m_loss, s_loss = [], []
    for _ in range(steps):
        out = update(state, Batch(*(jnp.asarray(batch[k]) for k in ("obs", "action", "reward", "next_obs",
                                                                     "terminated"))))
        if "pi" in getattr(out, "_fields", ()):  # a TrainState that sums its metrics
            metrics, state = agent.read_metrics(out)
        else:  # issue 27: update returns (state, metrics)
            state, metrics = out
            metrics = {k: float(v) for k, v in metrics.items()}
        m_loss.append(metrics)
    real_buffer, model.replay_buffer = model.replay_buffer, _FixedDictBatch(batch, _goal_slices(model))
    with fixed_normal_noise() as queue, sb3_exact_log_prob(mode == "sb3-exact"):
        for eps_pi, eps_next in noise:
            queue[:] = [torch.tensor(eps_pi), torch.tensor(eps_next)]  # SB3's order: current, next
            model.train(gradient_steps=1, batch_size=cfg.batch_size)
            assert not queue, "SB3 drew fewer Gaussian samples than mcrl"
            s_loss.append(model.read_diagnostics())
    model.replay_buffer = real_buffer
    end_m = learning_of(state, start.step, start.episode, start.buffer)
    end_s = read_sb3(model, start.step, start.episode)

    def rel_l2(x, y, base=None):
        x, y = (np.concatenate([np.ravel(np.asarray(v, np.float64)) for v in jax.tree.leaves(t)]) for t in (x, y))
        if base is not None:
            b = np.concatenate([np.ravel(np.asarray(v, np.float64)) for v in jax.tree.leaves(base)])
            x, y = x - b, y - b
        return float(np.linalg.norm(x - y) / max(np.linalg.norm(x), 1e-30))

    res = {"mode": mode, "steps": steps, "losses": {}, "update_rel_l2": {}, "adam_rel_l2": {}}
    for k in ("critic_loss", "actor_loss", "ent_coef_loss", "q_mean"):
        res["losses"][k] = {"mcrl": m_loss[0][k], "sb3": s_loss[0][k],
                            "max_rel": max(abs(m[k] - s[k]) / max(abs(m[k]), abs(s[k]), 1e-30)
                                           for m, s in zip(m_loss, s_loss)),
                            "max_abs": max(abs(m[k] - s[k]) for m, s in zip(m_loss, s_loss))}
    for g in GROUPS:
        res["update_rel_l2"][g] = rel_l2(end_m.params[g], end_s.params[g], start.params[g])
    for g in OPTIMISED:
        res["adam_rel_l2"][g] = max(rel_l2(end_m.opt[g][m], end_s.opt[g][m]) for m in ("mu", "nu"))
        res.setdefault("adam_count", {})[g] = [end_m.opt[g]["count"], end_s.opt[g]["count"]]
    return res


def step_failures(r: dict) -> list[str]:
    from parity_step import TOL_LOSS_ABS, TOL_LOSS_REL, TOL_UPDATE_REL

    bad = [f"{k} rel {v['max_rel']:.1e}" for k, v in r["losses"].items()
           if v["max_rel"] > TOL_LOSS_REL and v["max_abs"] > TOL_LOSS_ABS]
    bad += [f"update {g} rel {v:.1e}" for g, v in r["update_rel_l2"].items() if v > TOL_UPDATE_REL]
    bad += [f"Adam moments {g} rel {v:.1e}" for g, v in r["adam_rel_l2"].items() if v > TOL_UPDATE_REL]
    bad += [f"Adam count {g} {c}" for g, c in r["adam_count"].items() if c[0] != c[1]]
    return bad


def run_check(mcrl_learning: Learning, mcrl_cfg, sb3_model, sb3_cfg, sb3_episode: int = 0, steps: int = 3) -> dict:
    """The three parts of the check; ``pass`` is True when all hold."""
    from _sb3 import build_model
    from _transplant import install_sb3

    res: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        # 1. mcrl -> SB3 -> mcrl, and mcrl -> today's files -> mcrl's reader
        model, _ = build_model(mcrl_cfg)
        install_sb3(model, mcrl_learning)
        res["mcrl_sb3_mcrl"] = differences(mcrl_learning, read_sb3(model, mcrl_learning.step, mcrl_learning.episode))
        del model
        write_mcrl(Path(tmp) / "a", mcrl_learning, mcrl_cfg)
        res["mcrl_files_mcrl"] = differences(mcrl_learning, read_with_mcrl(Path(tmp) / "a")[0])
        # 2. SB3 -> mcrl files -> mcrl's reader -> SB3
        original = read_sb3(sb3_model, episode=sb3_episode)
        write_mcrl(Path(tmp) / "b", original, sb3_cfg)
        via_mcrl = read_with_mcrl(Path(tmp) / "b")[0]
        res["sb3_files_mcrl"] = differences(original, via_mcrl)
        copy, _ = build_model(sb3_cfg)
        install_sb3(copy, via_mcrl)
        res["sb3_mcrl_sb3"] = torch_differences(sb3_model, copy)
        del copy
        # 3. gradient steps from each transplanted state, both systems (SB3's copy equals the original, part 2)
        res["one_step"] = [{"origin": origin, **one_step(cfg, Path(tmp) / d, mode, steps)}
                           for origin, cfg, d in (("mcrl", mcrl_cfg, "a"), ("sb3", sb3_cfg, "b"))
                           for mode in ("as-is", "sb3-exact")]
    exact = {k: [n for n, v in res[k].items() if v != 0.0]
             for k in ("mcrl_sb3_mcrl", "mcrl_files_mcrl", "sb3_files_mcrl", "sb3_mcrl_sb3")}
    res["not_exact"] = {k: v for k, v in exact.items() if v}
    res["step_failures"] = [f"{r['origin']} origin: {x}" for r in res["one_step"] if r["mode"] == "sb3-exact"
                            for x in step_failures(r)]
    res["pass"] = not res["not_exact"] and not res["step_failures"]
    return res
