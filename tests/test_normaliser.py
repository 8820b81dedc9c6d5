"""The percentile normaliser against plain numpy on random streams, its clamping and its mapping."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mcrl import normaliser as N


@pytest.mark.parametrize("capacity,batch,dist", [(1000, 64, "lognormal"), (4096, 256, "exponential"),
                                                 (777, 1, "uniform")])
def test_percentiles_match_numpy_on_streams_with_eviction(capacity, batch, dist):
    rng = np.random.default_rng(capacity)
    state = N.init(capacity)
    push = jax.jit(N.push)
    pct = jax.jit(N.percentile, static_argnums=1)
    history = []
    for i in range(60):
        v = getattr(rng, dist)(size=batch).astype(np.float32) * (1 + i)  # drifting scale
        if dist == "uniform":
            v = v * 3.0
        state = push(state, jnp.asarray(v))
        history.extend(v.tolist())
        window = np.asarray(history[-capacity:], np.float32)
        assert int(state.count) == len(window)
        for q in (0.0, 50.0, 94.0, 98.0, 100.0):
            ref = np.percentile(window, q)
            assert float(pct(state, q)) == pytest.approx(ref, rel=2e-5, abs=1e-30), (i, q)


def test_rebuild_from_ring_equals_incremental_state():
    rng = np.random.default_rng(0)
    state = N.init(500)
    for _ in range(9):
        state = N.push(state, jnp.asarray(rng.lognormal(size=128).astype(np.float32)))
    rebuilt = N.rebuild(state.ring, state.ptr, state.count)
    for a, b in zip(state, rebuilt):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_scale_clamps_and_maps_linearly_into_the_range():
    lo, hi = 2.0, 10.0
    x = jnp.array([0.0, 2.0, 4.0, 6.0, 10.0, 50.0])
    r = np.asarray(N.scale(x, lo, hi, -1.0, 0.0))
    np.testing.assert_allclose(r, [-1.0, -1.0, -0.75, -0.5, 0.0, 0.0])
    r = np.asarray(N.scale(x, lo, hi, 0.0, 1.0))
    np.testing.assert_allclose(r, [0.0, 0.0, 0.25, 0.5, 1.0, 1.0])
    # a degenerate history (all equal) maps to the bottom, values above it to the top
    r = np.asarray(N.scale(jnp.array([1.0, 3.0]), 1.0, 1.0, -1.0, 0.0))
    np.testing.assert_allclose(r, [-1.0, 0.0])


def test_negative_and_nan_free_inputs_are_clamped_at_zero():
    state = N.push(N.init(8), jnp.array([-1.0, 2.0, 4.0]))
    assert float(N.percentile(state, 0.0)) == pytest.approx(0.0, abs=1e-30)
    assert float(N.percentile(state, 100.0)) == pytest.approx(4.0, rel=2e-5)
