"""Did a run's critics leave what a soft Q-value can be? A divergence criterion from theory, not from a peer.

SAC's critics estimate the soft Q-value Q(s, a) = E[r_0 + sum_{t >= 1} gamma^t (r_t + c_t H_t)], where c_t is the
entropy coefficient and H_t the entropy of the policy at step t. Two facts bound it from above:

- rewards are at most ``r_max`` (FetchPush's sparse reward is -1 or 0, so 0; SAC-MC mixes in an MC reward whose
  range the config sets, so ``(1 - intrinsic_alpha) r_max + intrinsic_alpha intrinsic_reward_high``);
- a tanh-squashed policy lives on the box [-1, 1]^d, where no density has more entropy than the uniform one:
  H <= d log 2 (d = the action dimension; FetchPush: 4 log 2 = 2.77 nats).

So Q <= r_max / (1 - gamma) + c_max d log 2 gamma / (1 - gamma). For FetchPush (r_max 0, gamma 0.99):
Q <= 274.5 c_max.

The coefficient c falls fast at the start (from 1 to about 0.01 in 20,000 steps) while the critics follow slowly, so
the bound at step T takes c_max as the largest coefficient of the preceding ``lag`` gradient steps. The lag is the
critics' time constant: the target network moves a share tau of the way per step and a Bellman backup shrinks an
error by gamma, so an error in Q decays like (1 - tau (1 - gamma))^steps, with time constant
1 / (tau (1 - gamma)) = 20,000 steps at tau 0.005, gamma 0.99. A critic whose logged mean Q (``q_mean``: the mean of
both critics over the interval's training batches) is above that lagged bound holds a value no policy can have
earned: it has left the bound.

The bound is generous (the entropy at SAC's target of -d nats is far below d log 2, so the true soft value sits well
under it): a run flagged here is wrong by theory, and a run not flagged may still overestimate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mcrl.analysis.hypothesis import clopper_pearson
from mcrl.envs import family_of

def _known(config: dict[str, Any]) -> tuple[float, int] | None:
    """(largest per-step extrinsic reward, action dimension) of the run's environment family (mcrl.envs.FAMILIES,
    a table, so that a report needs no simulator), or None for an environment outside them."""
    fam = family_of(str(config.get("env_id", "")))
    return None if fam is None else (fam.reward_max, fam.act_dim)


def reward_max(config: dict[str, Any]) -> float | None:
    """The largest reward a run's update can see (after MC mixing), or None when the environment's is not known."""
    known = _known(config)
    if known is None:
        return None
    r = known[0]
    a = float(config.get("intrinsic_alpha") or 0.0)
    if a > 0:
        return (1 - a) * r + a * float(config.get("intrinsic_reward_high", 0.0))
    return r


def lag_steps(gamma: float, tau: float) -> int:
    """The critics' time constant in gradient steps, 1 / (tau (1 - gamma))."""
    return int(round(1.0 / (tau * (1.0 - gamma))))


def soft_q_bound(c_max: Any, act_dim: int, gamma: float, r_max: float) -> Any:
    """The largest soft Q-value with rewards <= r_max and entropy coefficient <= c_max on [-1, 1]^act_dim."""
    return (r_max + gamma * np.asarray(c_max) * act_dim * math.log(2.0)) / (1.0 - gamma)


def lagged_bound(steps: Any, ent_coef: Any, act_dim: int, gamma: float, tau: float, r_max: float) -> np.ndarray:
    """The bound at each logged step: ``soft_q_bound`` of the largest coefficient logged in the preceding
    ``lag_steps`` steps (the row itself included). Rows must be in step order."""
    s, c = np.asarray(steps, dtype=float), np.asarray(ent_coef, dtype=float)
    lag = lag_steps(gamma, tau)
    c_max = np.array([np.nanmax(np.where((s >= t - lag) & (s <= t), c, np.nan)) for t in s]) if s.size else s
    return soft_q_bound(c_max, act_dim, gamma, r_max)


@dataclass(frozen=True)
class CriticCheck:
    """How one run's critics stood against the lagged soft-Q bound."""

    rows: int  # logged rows with q_mean and ent_coef
    rows_outside: int
    first_outside: int | None  # the first step whose q_mean was above the bound
    outside_at_end: bool
    peak_q: float
    peak_step: int
    bound_at_peak: float
    max_excess: float  # the largest q_mean - bound (negative: always inside)
    max_excess_step: int

    @property
    def left(self) -> bool:
        return self.rows_outside > 0


def check_critics(metrics: dict[str, np.ndarray], config: dict[str, Any]) -> CriticCheck | None:
    """Check a run's metrics.csv columns (``step``, ``q_mean``, ``ent_coef``) against the lagged bound; None when
    the run has no such rows or its environment's reward bound is unknown (not in mcrl.envs.FAMILIES)."""
    r_max, known = reward_max(config), _known(config)
    need = ("step", "q_mean", "ent_coef")
    if r_max is None or known is None or any(k not in metrics for k in need):
        return None
    act_dim = known[1]
    s, q, c = (np.asarray(metrics[k], dtype=float) for k in need)
    ok = np.isfinite(s) & np.isfinite(q) & np.isfinite(c)
    if not ok.any():
        return None
    s, q, c = s[ok], q[ok], c[ok]
    order = np.argsort(s, kind="stable")
    s, q, c = s[order], q[order], c[order]
    b = lagged_bound(s, c, act_dim, float(config.get("gamma", 0.99)), float(config.get("tau", 0.005)), r_max)
    out = q > b
    i_peak, i_ex = int(np.argmax(q)), int(np.argmax(q - b))
    return CriticCheck(rows=int(s.size), rows_outside=int(out.sum()),
                       first_outside=int(s[out][0]) if out.any() else None, outside_at_end=bool(out[-1]),
                       peak_q=float(q[i_peak]), peak_step=int(s[i_peak]), bound_at_peak=float(b[i_peak]),
                       max_excess=float((q - b)[i_ex]), max_excess_step=int(s[i_ex]))


@dataclass(frozen=True)
class Rate:
    """k of n runs, with an exact (Clopper-Pearson) 95% interval."""

    k: int
    n: int

    @property
    def interval(self) -> tuple[float, float]:
        return clopper_pearson(self.k, self.n)

    def __str__(self) -> str:
        lo, hi = self.interval
        return f"{self.k} of {self.n} ({self.k / self.n:.2f} [{lo:.2f}, {hi:.2f}])" if self.n else "0 of 0"
