"""The initialisation every network starts from (issue 13): torch's Linear by default, Flax's as an option."""
import jax
import numpy as np
import pytest

from mcrl.config import resolve_config
from mcrl.algo.sac import Agent


def _layers(params, prefix=""):
    """(name, kernel, bias) of every Dense layer in a parameter tree."""
    if "kernel" in params:
        yield prefix, np.asarray(params["kernel"]), np.asarray(params["bias"])
        return
    for k, v in params.items():
        yield from _layers(v, f"{prefix}/{k}")


def _all_layers(init: str):
    cfg = resolve_config("fetchpush-sacmc-0.2", {"init": init})
    state = Agent(obs_dim=31, act_dim=4, intrinsic_dim=25, cfg=cfg).init(3)
    nets = {"actor": state.pi.params, "critic": state.q.params, "mc": state.intrinsic.params}
    layers = [(f"{n}{name}", k, b) for n, p in nets.items() for name, k, b in _layers(p)]
    # actor 3 + 2 heads, critics 2 x (3 + 1) (stacked), MC models 2 x (5 + 2 heads)
    assert len(layers) == 5 + 4 + 14
    return layers


def test_torch_init_draws_weights_and_biases_like_torch_linear():
    for name, kernel, bias in _all_layers("torch"):
        fan_in = kernel.shape[-2]
        bound = 1.0 / np.sqrt(fan_in)
        assert np.abs(kernel).max() <= bound and np.abs(bias).max() <= bound, name
        # U(-b, b): std b / sqrt(3), mean 0
        assert kernel.std() == pytest.approx(bound / np.sqrt(3), rel=0.1 if kernel.size >= 500 else 0.35), name
        assert abs(kernel.mean()) < 0.1 * bound, name
        assert np.abs(kernel).max() > 0.9 * bound, name  # the whole interval is used, not a narrower one
        if bias.size >= 200:
            assert bias.std() == pytest.approx(bound / np.sqrt(3), rel=0.15), name
        assert np.count_nonzero(bias) == bias.size, name  # biases are drawn, not zero


def test_flax_init_is_lecun_normal_with_zero_biases():
    for name, kernel, bias in _all_layers("flax"):
        fan_in = kernel.shape[-2]
        assert kernel.std() == pytest.approx(1.0 / np.sqrt(fan_in), rel=0.1 if kernel.size >= 500 else 0.35), name
        assert np.all(bias == 0), name


def test_default_is_torch_for_every_preset():
    from mcrl.config import PRESETS

    assert all(resolve_config(p).init == "torch" for p in PRESETS)


def test_the_two_critics_start_different():
    cfg = resolve_config("fetchpush-sac")
    critic = Agent(obs_dim=31, act_dim=4, intrinsic_dim=25, cfg=cfg).init(0).q.params
    k = jax.tree.leaves(critic)[0]
    assert not np.allclose(k[0], k[1])
