"""What the gradient steps report, summed on the device between two log rows: a value of its own, beside
the learner's state (`mcrl.algo.sac.TrainState`), not inside it.

`add` is pure and runs inside the compiled training step, so the host reads the sums only at log intervals
(`read`, one transfer) and never waits on a step. A checkpoint keeps the sums of the interval in progress, so a
resumed run writes the same log rows as an uninterrupted one.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from mcrl.algo.metrics import BOUNDS, reported, update_metrics


class Diagnostics(NamedTuple):
    metric_sums: dict  # name -> float32 sum since the last read
    metric_count: jax.Array  # gradient steps since the last read
    bounds: jax.Array  # (2,) the normaliser's bounds at the last step (zeros without intrinsic models)


def init(own: tuple[str, ...] = ()) -> Diagnostics:
    """Zero sums of what a run whose reward reports `own` (its `About.metrics`) sums: `update_metrics(own)`, the
    same for every built-in reward (a checkpoint without a sum a reward adds keeps this zero: `restore_state`)."""
    return Diagnostics({k: jnp.float32(0) for k in update_metrics(own)}, jnp.int32(0), jnp.zeros(2, jnp.float32))


def add(diag: Diagnostics, metrics: dict) -> Diagnostics:
    """`diag` with one gradient step's `metrics` (`Agent.update`'s) added to the sums it holds (`init`); metrics
    it lacks count as 0."""
    sums = {k: diag.metric_sums[k] + metrics.get(k, 0.0) for k in diag.metric_sums}
    bounds = jnp.stack([metrics[b] for b in BOUNDS]) if BOUNDS[0] in metrics else diag.bounds
    return Diagnostics(sums, diag.metric_count + 1, bounds)


def means(sums: dict, count: int, bounds, own: tuple[str, ...] | None) -> dict[str, float]:
    """The log row's means from the sums of `count` gradient steps: the metrics of a run whose intrinsic reward
    reports `own` (`Agent.own_metrics`; None: plain SAC) (`mcrl.algo.metrics.reported`), and the bounds if it has
    intrinsic models."""
    keep = reported(own)
    out = {k: float(v) / count for k, v in sums.items() if k in keep}
    if own is not None:
        out.update(zip(BOUNDS, (float(bounds[0]), float(bounds[1]))))
    return out


def read(diag: Diagnostics, own: tuple[str, ...] | None) -> tuple[dict[str, float], Diagnostics]:
    """Means since the last read ({} if no step was taken), and the diagnostics with the sums reset (host side)."""
    sums, count, bounds = jax.device_get((diag.metric_sums, diag.metric_count, diag.bounds))
    if int(count) == 0:
        return {}, diag
    return means(sums, int(count), bounds, own), reset(diag)


def reset(diag: Diagnostics) -> Diagnostics:
    """Sums and count back to zero (the same shapes, so a vmapped group's stack stays a stack); bounds kept."""
    return diag._replace(metric_sums={k: jnp.zeros_like(v) for k, v in diag.metric_sums.items()},
                         metric_count=jnp.zeros_like(diag.metric_count))
