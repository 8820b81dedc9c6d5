"""Percentile normaliser of the raw MC (KL) values, at a cost per step that does not depend on history size.

The thesis maps each KL value into the task's reward range using percentiles of a bounded history of
past values: upper bound = `max_percentile`, lower bound = `min_percentile`, clamp, then linear. Its
code kept the history in a Python list and re-sorted it every step (O(history) per step).

Here the history is a ring buffer plus a three-level histogram over the top 24 bits of the float32
bit pattern (non-negative floats order like their bit patterns). Pushing B values costs O(B) scatter-adds;
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
    ring: jax.Array  # (capacity,) float32 raw values, oldest overwritten first
    ptr: jax.Array  # int32: next slot to write
    count: jax.Array  # int32: valid values, <= capacity
    c1: jax.Array  # (2**7,) int32 counts by the top 8 bits
    c2: jax.Array  # (2**15,) int32 counts by the top 16 bits
    c3: jax.Array  # (2**23,) int32 counts by the top 24 bits


def init(capacity: int) -> NormaliserState:
    return NormaliserState(jnp.zeros(capacity, jnp.float32), jnp.int32(0), jnp.int32(0),
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
    """Append `values` (1-d, length <= capacity), evicting the oldest when full."""
    capacity = state.ring.shape[0]
    values = jnp.maximum(jnp.asarray(values, jnp.float32).reshape(-1), 0.0)
    n = values.shape[0]
    idx = (state.ptr + jnp.arange(n, dtype=jnp.int32)) % capacity
    occupied = (idx < state.count).astype(jnp.int32)  # the ring fills 0, 1, 2, ... so this marks old values
    state = _add(state, _key(state.ring[idx]), -occupied)
    state = _add(state, _key(values), jnp.ones(n, jnp.int32))
    return state._replace(ring=state.ring.at[idx].set(values), ptr=(state.ptr + n) % capacity,
                          count=jnp.minimum(state.count + n, capacity))


def rebuild(ring, ptr, count) -> NormaliserState:
    """The full state from its ring buffer (checkpoints store only ring, ptr and count)."""
    state = init(ring.shape[0])._replace(ring=jnp.asarray(ring, jnp.float32), ptr=jnp.int32(ptr),
                                         count=jnp.int32(count))
    valid = (jnp.arange(ring.shape[0]) < count).astype(jnp.int32)
    return _add(state, _key(state.ring), valid)


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


def percentile(state: NormaliserState, q: float):
    """`numpy.percentile(history, q)` (linear interpolation); 0 for an empty history."""
    n = jnp.maximum(state.count, 1)
    pos = (q / 100.0) * (n - 1).astype(jnp.float32)
    lo = jnp.floor(pos).astype(jnp.int32)
    hi = jnp.minimum(lo + 1, n - 1)
    v_lo, v_hi = order_statistic(state, lo), order_statistic(state, hi)
    v = v_lo + (pos - lo.astype(jnp.float32)) * (v_hi - v_lo)
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


def reference_percentile(history: np.ndarray, q: float) -> float:
    """Plain numpy reference, used by tests and documentation."""
    return float(np.percentile(np.maximum(history, 0.0), q))
