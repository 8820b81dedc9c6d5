"""The environments of the training loop's runs (`mcrl.run.trainer`), stepped together: one for a single run,
several for a group (`mcrl.run.group`).

One environment per run, each made from its run's config and reset with its run's episode seeds, so a run
sees the same episodes in a group as alone. With ``workers=0`` they step in this process one after another
(a few FetchPush environments cost well under a millisecond each, small beside a vmapped gradient step);
with ``workers=N`` they are spread over N processes that step their share in parallel, for hosts whose
cores would otherwise wait on the accelerator.

The interface is the same either way: ``reset(i, seed) -> flat obs`` and ``step(actions) -> StepResult``
with actions in the policy's [-1, 1] (scaled and mapped to each environment's Box here).
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np

from mcrl.config import Config
from mcrl.envs import flatten_obs, make_env, success_of, to_env_action


@dataclass
class StepResult:
    next_obs: list[np.ndarray]  # flat next observations, one per run
    reward: np.ndarray  # (R,)
    terminated: np.ndarray  # (R,) bool
    truncated: np.ndarray  # (R,) bool
    success: list[float | None]  # the step's success flag (None: the environment has none)


def _step_all(envs, cfgs, actions):
    out = []
    for env, cfg, a in zip(envs, cfgs, actions):
        obs, r, term, trunc, info = env.step(to_env_action(np.asarray(a), env, cfg.action_scale))
        out.append((flatten_obs(obs), float(r), bool(term), bool(trunc), success_of(info)))
    return out


def _worker(cfg_dicts: list[dict], conn) -> None:
    """A worker process: make its environments, then answer ("step", actions), ("reset", [(j, seed)]),
    ("close", None) until closed; a dead parent closes the pipe, which ends the worker too."""
    cfgs = [Config.from_dict(d) for d in cfg_dicts]
    envs = [make_env(c) for c in cfgs]
    try:
        while True:
            cmd, arg = conn.recv()
            if cmd == "step":
                conn.send(_step_all(envs, cfgs, arg))
            elif cmd == "reset":
                conn.send([flatten_obs(envs[j].reset(seed=seed)[0]) for j, seed in arg])
            else:
                break
    except (EOFError, KeyboardInterrupt):
        pass
    finally:
        for e in envs:
            e.close()
        conn.close()


class EnvPool:
    """One environment per config; ``workers`` > 0 steps them in that many processes."""

    def __init__(self, cfgs: list[Config], workers: int = 0, envs: list | None = None):
        """`envs`: environments made already (one per config), stepped in-process when `workers` is 0; the
        caller keeps them and closes them."""
        self.cfgs = list(cfgs)
        self.n = len(self.cfgs)
        self.workers = min(max(0, int(workers)), self.n)
        self.envs, self._procs, self._conns, self._slices = [], [], [], []
        self._own_envs = envs is None
        if self.workers == 0:
            self.envs = [make_env(c) for c in self.cfgs] if envs is None else list(envs)
            return
        import multiprocessing as mp

        ctx = mp.get_context("spawn")  # no fork of a process that holds jax's threads
        bounds = np.linspace(0, self.n, self.workers + 1).round().astype(int)
        for lo, hi in zip(bounds[:-1], bounds[1:]):
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=_worker, args=([c.to_dict() for c in self.cfgs[lo:hi]], child),
                               daemon=True, name=f"mcrl-envs-{lo}-{hi}")
            proc.start()
            child.close()
            self._procs.append(proc)
            self._conns.append(parent)
            self._slices.append((int(lo), int(hi)))

    def reset(self, i: int, seed: int) -> np.ndarray:
        """Reset run `i`'s environment with `seed`; its flat first observation."""
        if self.workers == 0:
            return flatten_obs(self.envs[i].reset(seed=seed)[0])
        w = next(k for k, (lo, hi) in enumerate(self._slices) if lo <= i < hi)
        self._conns[w].send(("reset", [(i - self._slices[w][0], seed)]))
        return self._recv(w)[0]

    def step(self, actions: np.ndarray) -> StepResult:
        """Step every environment with its run's action (row i of `actions`, in [-1, 1])."""
        if self.workers == 0:
            out = _step_all(self.envs, self.cfgs, actions)
        else:
            for conn, (lo, hi) in zip(self._conns, self._slices):
                conn.send(("step", np.asarray(actions[lo:hi])))
            out = [x for w in range(self.workers) for x in self._recv(w)]
        return StepResult([o[0] for o in out], np.array([o[1] for o in out], np.float64),
                          np.array([o[2] for o in out]), np.array([o[3] for o in out]), [o[4] for o in out])

    def _recv(self, w: int):
        try:
            return self._conns[w].recv()
        except EOFError:
            raise RuntimeError(f"environment worker {w} died (exit code {self._procs[w].exitcode})") from None

    def close(self) -> None:
        for e in self.envs if self._own_envs else []:
            e.close()
        for conn in self._conns:
            with contextlib.suppress(OSError, BrokenPipeError):
                conn.send(("close", None))
            conn.close()
        for proc in self._procs:
            proc.join(5)
            if proc.is_alive():
                proc.kill()
        self.envs, self._conns, self._procs = [], [], []
