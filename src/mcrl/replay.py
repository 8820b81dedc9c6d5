"""Replay buffer with Hindsight Experience Replay (HER), host-side numpy, vectorised sampling.

Transitions are stored flat in a circular buffer; each slot remembers the global indices of its
episode's first and last transition, so HER goals are found with array arithmetic, no Python loop.
Relabelling follows stable-baselines3's `HerReplayBuffer`: a fraction k/(k+1) of each batch gets a new
goal, the next achieved goal of a transition from the same episode chosen by the strategy
(`future`: this or a later step; `final`: the last step; `episode`: any step), and its reward is
recomputed with the environment's own `compute_reward`, and its `terminated` flag with `compute_terminated`
(for environments that end episodes on success). Only finished episodes are sampled when HER is on.

A sample is a `Batch`, the gradient step's input (`mcrl.algo.sac.Agent.update`); no JAX here.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numpy as np

from mcrl.errors import MCRLError

_ARRAYS = ("obs", "action", "reward", "next_obs", "terminated", "ep_first", "ep_last")


class Batch(NamedTuple):
    """Transitions for one gradient step (numpy from the buffer, device arrays inside the update)."""

    obs: Any  # (B, obs_dim): observation | achieved_goal | desired_goal for goal envs
    action: Any  # (B, act_dim) in [-1, 1]
    reward: Any  # (B,) extrinsic (HER-recomputed) reward
    next_obs: Any
    terminated: Any  # (B,) 1.0 only for true terminations, never for time-limit truncations


class ReplayBuffer:
    def __init__(self, capacity: int, obs_dim: int, act_dim: int, *, her: bool = False,
                 observation_dim: int = 0, goal_dim: int = 0, strategy: str = "future", k: int = 4,
                 compute_reward: Callable | None = None, compute_terminated: Callable | None = None,
                 rounding: str = "nearest"):
        self.capacity = capacity
        self.her = her
        self.od, self.gd = observation_dim, goal_dim
        self.strategy, self.k = strategy, k
        self.rounding = rounding  # of the relabelled share: nearest (205 of 256 at k=4) | floor (SB3's int(): 204)
        self.compute_reward = compute_reward
        self.compute_terminated = compute_terminated  # (achieved, desired) -> (n,) float32
        self.obs = np.zeros((capacity, obs_dim), np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), np.float32)
        self.action = np.zeros((capacity, act_dim), np.float32)
        self.reward = np.zeros(capacity, np.float32)
        self.terminated = np.zeros(capacity, np.float32)
        self.ep_first = np.zeros(capacity, np.int64)  # global index of the episode's first transition
        self.ep_last = np.full(capacity, -1, np.int64)  # ... of its last one; -1 while the episode runs
        self.total = 0  # transitions ever added (global index of the next one)
        self.episode_first = 0

    def __len__(self) -> int:
        return min(self.total, self.capacity)

    def add(self, obs, action, reward, next_obs, terminated: bool, episode_done: bool) -> None:
        i = self.total % self.capacity
        self.obs[i], self.action[i], self.next_obs[i] = obs, action, next_obs
        self.reward[i], self.terminated[i] = reward, float(terminated)
        self.ep_first[i], self.ep_last[i] = self.episode_first, -1
        self.total += 1
        if episode_done:
            self.end_episode()

    def end_episode(self) -> None:
        """Close the running episode (also used when a run resumes from a checkpoint taken mid-episode)."""
        if self.episode_first == self.total:
            return
        first = max(self.episode_first, self.total - self.capacity)
        g = np.arange(first, self.total)
        self.ep_last[g % self.capacity] = self.total - 1
        self.episode_first = self.total

    def _sampleable(self) -> tuple[int, int]:
        """[lo, hi) global indices that may be sampled."""
        lo = max(0, self.total - self.capacity)
        hi = self.episode_first if self.her else self.total
        return lo, hi

    def can_sample(self) -> bool:
        lo, hi = self._sampleable()
        return hi > lo

    def relabelled(self, batch_size: int) -> np.ndarray:
        """(batch_size,) bool: the rows of a `sample` that HER relabelled (the first k/(k+1) of them)."""
        share = batch_size * self.k / (self.k + 1)
        n_her = (int(share) if self.rounding == "floor" else int(round(share))) if self.her else 0
        return np.arange(batch_size) < n_her

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        lo, hi = self._sampleable()
        g = rng.integers(lo, hi, size=batch_size)
        idx = g % self.capacity
        batch = Batch(self.obs[idx], self.action[idx], self.reward[idx], self.next_obs[idx], self.terminated[idx])
        if not self.her:
            return batch
        n_her = int(self.relabelled(batch_size).sum())
        first, last = self.ep_first[idx[:n_her]], self.ep_last[idx[:n_her]]
        first = np.maximum(first, lo)  # earlier steps of a partly overwritten episode are gone
        if self.strategy == "future":
            goal_g = rng.integers(g[:n_her], last + 1)
        elif self.strategy == "final":
            goal_g = last
        else:  # episode
            goal_g = rng.integers(first, last + 1)
        goal = self.next_obs[goal_g % self.capacity, self.od:self.od + self.gd]
        batch.obs[:n_her, self.od + self.gd:] = goal
        batch.next_obs[:n_her, self.od + self.gd:] = goal
        achieved = batch.next_obs[:n_her, self.od:self.od + self.gd]
        batch.reward[:n_her] = np.asarray(self.compute_reward(achieved, goal, {}), np.float32).reshape(-1)
        if self.compute_terminated is not None:
            batch.terminated[:n_her] = self.compute_terminated(achieved, goal)
        return batch

    # ------------------------------------------------------------------ checkpointing
    def state_arrays(self) -> dict[str, np.ndarray]:
        n = len(self)
        out = {k: getattr(self, k)[:n] for k in _ARRAYS}
        out["counters"] = np.array([self.total, self.episode_first, self.capacity], np.int64)
        return out

    def load_arrays(self, arrays) -> None:
        total, episode_first, capacity = (int(x) for x in arrays["counters"])
        if capacity != self.capacity:
            raise MCRLError(f"checkpointed buffer capacity {capacity} != configured buffer_size {self.capacity}: "
                            "resume with the run's own config")
        n = min(total, capacity)
        for k in _ARRAYS:
            a = arrays[k]
            dst = getattr(self, k)
            if a.shape[0] != n or a.shape[1:] != dst.shape[1:]:
                raise MCRLError(f"checkpointed buffer array {k!r} has shape {a.shape}, expected "
                                f"({n}, *{dst.shape[1:]}): the checkpoint does not belong to this config")
            dst[:n] = a
        self.total, self.episode_first = total, episode_first
