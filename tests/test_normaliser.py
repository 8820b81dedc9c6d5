"""The percentile normaliser against plain numpy on random streams, its clamping and its mapping."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mcrl.algo import normaliser as N


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


def test_whole_run_history_matches_numpy_over_the_entire_stream():
    # The default (capacity None) never evicts: the thesis' code kept every value of its runs.
    rng = np.random.default_rng(7)
    state = N.init(None)
    assert state.ring.shape == (0,)
    push = jax.jit(N.push)
    pct = jax.jit(N.percentile, static_argnums=1)
    history = []
    for i in range(80):
        v = (rng.lognormal(size=256) * (1 + 0.2 * i)).astype(np.float32)  # growing KL, as in a long run
        state = push(state, jnp.asarray(v))
        history.append(v)
        if i % 10 == 9 or i == 0:
            whole = np.concatenate(history)
            assert int(state.count) == whole.size
            for q in (0.0, 50.0, 94.0, 98.0, 100.0):
                assert float(pct(state, q)) == pytest.approx(np.percentile(whole, q), rel=2e-5), (i, q)
    # a window of the last 1,000 values would give a clearly different upper bound here
    assert abs(float(pct(state, 94.0)) - np.percentile(np.concatenate(history)[-1000:], 94.0)) > 0.05


@pytest.mark.parametrize("n", [2, 1000, 2**24 + 3, 400_000 * 2048, 2**31 - 1])
def test_rank_is_exact_beyond_float32_integers(n):
    for q in (0.0, 37.5, 94.0, 98.0, 100.0):
        lo, frac = N._rank(q, jnp.int32(n))
        exact = q / 100.0 * (n - 1)  # float64
        assert int(lo) == int(np.floor(exact)) and float(frac) == pytest.approx(exact % 1, abs=1e-6), (n, q)


@pytest.mark.parametrize("capacity", [None, 500])
def test_pack_unpack_restores_the_state_exactly(capacity):
    rng = np.random.default_rng(0)
    state = N.init(capacity)
    for _ in range(9):
        state = N.push(state, jnp.asarray(rng.lognormal(size=128).astype(np.float32)))
    packed = N.pack(state)
    assert packed["c3_index"].size < 2000  # sparse: a checkpoint does not carry 2**23 counters
    restored = N.unpack(packed, capacity)
    for a, b in zip(state, restored):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError):
        N.unpack(packed, 1000 if capacity is None else None)


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
