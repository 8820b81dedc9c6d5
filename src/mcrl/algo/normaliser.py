"""Percentile normaliser of the raw intrinsic rewards (MC: KL values), at a cost per step that does not depend on
history size; every intrinsic reward's raw values go through it.

The thesis maps each KL value into the task's reward range using percentiles of the history of past
values: upper bound = `max_percentile`, lower bound = `min_percentile`, clamp, then linear. Its code kept
the history in a Python list (capped at 400,000 values, more than one value per step over its longest run,
so in effect the whole run) and re-sorted it every step (O(history) per step).

Here the history is a three-level histogram over the top 24 bits of the float32 bit pattern
(non-negative floats order like their bit patterns). By default it counts every value of the run
(capacity None: no ring buffer at all; counts are int32, so up to 2**31 - 1 values). With a capacity, a ring
buffer of the last `capacity` values is kept too, and the oldest value leaves the histogram when a new one
arrives (a sliding window). Pushing B values costs O(B) scatter-adds;
the k-th order statistic is found by walking down 128 + 256 + 256 counters. The result is the
order statistic to within 2**-16 relative error (the midpoint of its 24-bit bin), which is far
below the run-to-run spread of the KL itself. Percentiles interpolate linearly between order
statistics, like `numpy.percentile`'s default method.

All functions are pure and jit-friendly; `NormaliserState` is part of the agent's train state.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

_L1, _L2, _L3 = 1 << 7, 1 << 15, 1 << 23  # bins per level: top 8, 16 and 24 bits (sign bit is 0)


class NormaliserState(NamedTuple):
    ring: jax.Array  # (capacity,) float32 raw values, oldest overwritten first; (0,) = keep every value
    ptr: jax.Array  # int32: next slot to write
    count: jax.Array  # int32: values in the histogram (<= capacity for a window)
    c1: jax.Array  # (2**7,) int32 counts by the top 8 bits
    c2: jax.Array  # (2**15,) int32 counts by the top 16 bits
    c3: jax.Array  # (2**23,) int32 counts by the top 24 bits


def init(capacity: int | None = None) -> NormaliserState:
    """An empty history: a window of the last `capacity` values, or every value (None)."""
    return NormaliserState(jnp.zeros(capacity or 0, jnp.float32), jnp.int32(0), jnp.int32(0),
                           jnp.zeros(_L1, jnp.int32), jnp.zeros(_L2, jnp.int32), jnp.zeros(_L3, jnp.int32))


def _key(x):
    """Top 24 bits of the bit pattern of max(x, 0) (monotone in x)."""
    x = jnp.maximum(jnp.asarray(x, jnp.float32), 0.0)
    return (jax.lax.bitcast_convert_type(x, jnp.uint32) >> 8).astype(jnp.int32)


def _add(state: NormaliserState, keys, weights) -> NormaliserState:
    return state._replace(c1=state.c1.at[keys >> 16].add(weights),
                          c2=state.c2.at[keys >> 8].add(weights),
                          c3=state.c3.at[keys].add(weights))


def push(state: NormaliserState, values) -> NormaliserState:
    """Append `values` (1-d, length <= capacity), evicting the oldest when a window is full."""
    capacity = state.ring.shape[0]
    values = jnp.maximum(jnp.asarray(values, jnp.float32).reshape(-1), 0.0)
    n = values.shape[0]
    if capacity == 0:  # whole-run history: count, never evict
        return _add(state, _key(values), jnp.ones(n, jnp.int32))._replace(count=state.count + n)
    idx = (state.ptr + jnp.arange(n, dtype=jnp.int32)) % capacity
    occupied = (idx < state.count).astype(jnp.int32)  # the ring fills 0, 1, 2, ... so this marks old values
    state = _add(state, _key(state.ring[idx]), -occupied)
    state = _add(state, _key(values), jnp.ones(n, jnp.int32))
    return state._replace(ring=state.ring.at[idx].set(values), ptr=(state.ptr + n) % capacity,
                          count=jnp.minimum(state.count + n, capacity))


def pack(state: NormaliserState) -> dict[str, np.ndarray]:
    """What a checkpoint stores: the ring (if any), counters and the non-zero finest-level bins."""
    c3 = np.asarray(state.c3)
    nz = np.flatnonzero(c3).astype(np.int32)
    return {"ring": np.asarray(state.ring), "ptr": np.asarray(state.ptr), "count": np.asarray(state.count),
            "c3_index": nz, "c3_count": c3[nz]}


def from_values(values, capacity: int | None = None) -> NormaliserState:
    """A history that has seen `values` (oldest first): every one, or the newest `capacity` in its window."""
    values = np.maximum(np.asarray(values, np.float32).reshape(-1), 0.0)
    ring = np.zeros(capacity or 0, np.float32)
    if capacity:
        values = values[-capacity:]
        ring[: len(values)] = values
    keys = (values.view(np.uint32) >> 8).astype(np.int64)
    idx, cnt = np.unique(keys, return_counts=True)
    return unpack({"ring": ring, "ptr": len(values) % capacity if capacity else 0, "count": len(values),
                   "c3_index": idx, "c3_count": cnt}, capacity)


def unpack(arrays: dict[str, np.ndarray], capacity: int | None) -> NormaliserState:
    """Inverse of `pack`; the coarser levels are sums of the finest one."""
    ring = np.asarray(arrays["ring"], np.float32)
    if ring.shape[0] != (capacity or 0):
        raise ValueError(f"normaliser window holds {ring.shape[0]} values, the config asks for {capacity or 0}")
    c3 = np.zeros(_L3, np.int64)
    c3[np.asarray(arrays["c3_index"], np.int64)] = arrays["c3_count"]
    c2 = c3.reshape(_L2, 256).sum(1)
    c1 = c2.reshape(_L1, 256).sum(1)
    return NormaliserState(jnp.asarray(ring), jnp.int32(arrays["ptr"]), jnp.int32(arrays["count"]),
                           jnp.asarray(c1, jnp.int32), jnp.asarray(c2, jnp.int32), jnp.asarray(c3, jnp.int32))


def _walk(counts, k):
    """Index of the bin holding the k-th (0-based) value, and k's rank inside that bin."""
    cs = jnp.cumsum(counts)
    i = jnp.minimum(jnp.searchsorted(cs, k, side="right"), counts.shape[0] - 1)
    before = jnp.where(i > 0, cs[i - 1], 0)
    return i, k - before


def order_statistic(state: NormaliserState, k):
    """The k-th smallest value in the history (0-based), to 2**-16 relative precision."""
    i1, k = _walk(state.c1, k)
    i2, k = _walk(jax.lax.dynamic_slice(state.c2, (i1 * 256,), (256,)), k)
    i2 = i1 * 256 + i2
    i3, _ = _walk(jax.lax.dynamic_slice(state.c3, (i2 * 256,), (256,)), k)
    bits = ((i2 * 256 + i3).astype(jnp.uint32) << 8) | jnp.uint32(0x80)  # midpoint of the 24-bit bin
    return jax.lax.bitcast_convert_type(bits, jnp.float32)


def _rank(q: float, n):
    """floor and fraction of (q / 100) * (n - 1), exactly, for n up to 2**31 - 1 in int32 arithmetic.

    A float32 product would be off by whole ranks beyond 2**24 values (a long AntMaze run holds ~8e8), so
    q is taken in hundredths (Q = 100 q, percentiles resolve to 0.01) and n - 1 = 10000 a + b:
    Q (n - 1) / 10000 = Q a + Q b / 10000, where Q a <= 10000 * 214748 still fits in int32.
    """
    big_q = int(round(q * 100))
    m = n - 1
    a, b = m // 10000, m % 10000
    qb = big_q * b
    return big_q * a + qb // 10000, (qb % 10000).astype(jnp.float32) / 10000.0


def percentile(state: NormaliserState, q: float):
    """`numpy.percentile(history, q)` (linear interpolation); 0 for an empty history."""
    n = jnp.maximum(state.count, 1)
    lo, frac = _rank(q, n)
    lo = jnp.minimum(lo, n - 1)
    hi = jnp.minimum(lo + 1, n - 1)
    v_lo, v_hi = order_statistic(state, lo), order_statistic(state, hi)
    v = v_lo + frac * (v_hi - v_lo)
    return jnp.where(state.count > 0, v, 0.0)


def bounds(state: NormaliserState, min_percentile: float, max_percentile: float):
    return percentile(state, min_percentile), percentile(state, max_percentile)


def scale(values, low_bound, high_bound, reward_low: float, reward_high: float):
    """Clamp raw values to [low_bound, high_bound] and map linearly onto [reward_low, reward_high]."""
    width = high_bound - low_bound
    unit = jnp.where(width > 0, jnp.clip((values - low_bound) / jnp.where(width > 0, width, 1.0), 0.0, 1.0),
                     # A degenerate history (all values equal): above it is the top, otherwise the bottom.
                     (values > high_bound).astype(jnp.float32))
    return reward_low + unit * (reward_high - reward_low)


def reward(state: NormaliserState, raw, min_percentile: float, max_percentile: float, reward_low: float,
           reward_high: float):
    """The normalised reward of raw values (MC: KL) under the history in `state`: (reward, (low bound, high
    bound))."""
    lo, hi = bounds(state, min_percentile, max_percentile)
    return scale(raw, lo, hi, reward_low, reward_high), (lo, hi)


def reference_percentile(history: np.ndarray, q: float) -> float:
    """Plain numpy reference, used by tests and documentation."""
    return float(np.percentile(np.maximum(history, 0.0), q))
