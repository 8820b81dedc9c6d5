"""`matmul_precision`: float32 (the default) or bfloat16 (bfloat16 matmul inputs; float32 accumulation, parameters
and everything outside the matmuls)."""
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mcrl.algo.mc import MCModels
from mcrl.algo.networks import GaussianHead, TwinCritic
from mcrl.algo.sac import Agent, Batch
from mcrl.config import Config, resolve_config
from mcrl.errors import MCRLError

HIDDEN = (256, 256, 256)  # the thesis' actor and critic sizes
BATCH = 256


def _bf16(x):
    """x rounded to bfloat16, as float64 (a product of two bfloat16 values is exact in float64)."""
    return np.asarray(x, np.float32).astype(jnp.bfloat16).astype(np.float64)  # numpy (ml_dtypes), round to even


def _dense(x, p, bf16: bool):
    """A Dense layer by hand in float64: on bfloat16-rounded input and kernel, or on the float32 values."""
    x, k = (_bf16(x), _bf16(p["kernel"])) if bf16 else (np.asarray(x, np.float64), np.asarray(p["kernel"], np.float64))
    return x @ k + np.asarray(p["bias"], np.float64)


def _rel(a, ref):  # largest error, relative to the largest value
    return float(np.abs(np.asarray(a, np.float64) - ref).max() / np.abs(ref).max())


def _mrel(a, ref):  # mean relative error
    return float(np.abs(np.asarray(a, np.float64) - ref).mean() / np.abs(ref).mean())


def _inputs(n_in: int, seed: int = 1):
    return jax.random.normal(jax.random.PRNGKey(seed), (BATCH, n_in))


def _leaves_equal(a, b):
    return jax.tree.structure(a) == jax.tree.structure(b) and all(
        x.shape == y.shape and x.dtype == y.dtype and bool(jnp.array_equal(x, y))
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def _agent(prec: str) -> Agent:
    """SAC-MC at the thesis' FetchPush sizes."""
    cfg = resolve_config("fetchpush-sacmc-0.2", {"matmul_precision": prec})
    return Agent(obs_dim=31, act_dim=4, intrinsic_dim=25, cfg=cfg)


@pytest.fixture(scope="module")
def states():
    return {prec: _agent(prec).init(3) for prec in ("float32", "bfloat16")}


def test_parameters_stay_float32_and_identical(states):
    for net in ("pi", "q", "intrinsic"):
        f32, bf16 = (getattr(states[p], net).params for p in ("float32", "bfloat16"))
        assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(bf16)), net
        assert _leaves_equal(f32, bf16), net  # same names, shapes, dtypes and values: old checkpoints restore


def _mlp_head_layers(params, inter, x):
    """(name, layer input, layer params, layer output) of every Dense layer of a GaussianHead, from its
    captured intermediates (each layer's input is the previous layer's output after the ReLU)."""
    mlp, out = params["MLP_0"], inter["MLP_0"]
    h = x
    for i in range(len(mlp)):
        y = out[f"Dense_{i}"]["__call__"][0]
        yield f"Dense_{i}", h, mlp[f"Dense_{i}"], y
        h = jax.nn.relu(y)
    for head in ("mean", "log_std"):
        yield head, h, params[head], inter[head]["__call__"][0]


def test_every_layer_is_a_bfloat16_matmul_with_float32_accumulation():
    """Layer by layer (each from the network's own input, so bfloat16 rounding of a hidden value cannot flip
    between the network and the reference): the layer equals the bfloat16-rounded matmul to float32 accuracy and
    differs from the float32 one by bfloat16's rounding. (Flax captures no intermediates inside the critics'
    `nn.vmap`; they are checked whole below, and in the update's HLO.)"""
    cases = []
    x = _inputs(31)
    actor = GaussianHead(HIDDEN, 4, matmul_precision="bfloat16")
    p = actor.init(jax.random.PRNGKey(0), x)["params"]
    _, st = actor.apply({"params": p}, x, capture_intermediates=True)
    cases += [("actor/" + n, *c) for n, *c in _mlp_head_layers(p, st["intermediates"], x)]

    mc = MCModels(state_dim=25, hidden=(256,) * 5, matmul_precision="bfloat16")
    s, a = _inputs(25, 2), _inputs(4, 3)
    mp = mc.init(jax.random.PRNGKey(0), 4)
    _, st = mc.transition.apply({"params": mp["transition"]}, s, a, capture_intermediates=True)
    cases += [("transition/" + n, *c) for n, *c in _mlp_head_layers(
        mp["transition"]["GaussianHead_0"], st["intermediates"]["GaussianHead_0"], jnp.concatenate([s, a], -1))]
    _, st = mc.action.apply({"params": mp["action"]}, a, capture_intermediates=True)
    cases += [("action/" + n, *c) for n, *c in _mlp_head_layers(
        mp["action"]["GaussianHead_0"], st["intermediates"]["GaussianHead_0"], a)]

    assert len(cases) == 5 + 7 + 7
    for name, h, lp, y in cases:
        assert y.dtype == jnp.float32, name
        assert _rel(y, _dense(h, lp, bf16=True)) < 1e-5, name
        assert _rel(y, _dense(h, lp, bf16=False)) > 1e-4, name


def _actor_ref(p, x, bf16):
    h = x
    for i in range(len(p["MLP_0"])):
        h = np.maximum(_dense(h, p["MLP_0"][f"Dense_{i}"], bf16), 0.0)
    return _dense(h, p["mean"], bf16), np.clip(_dense(h, p["log_std"], bf16), -20.0, 2.0)


def _critic_ref(p, x, bf16):
    p, qs = jax.tree.map(np.asarray, p), []
    mlp = p["VmapMLP_0"]
    for c in range(2):
        h = x
        for i in range(len(mlp)):
            h = np.maximum(_dense(h, jax.tree.map(lambda v: v[c], mlp[f"Dense_{i}"]), bf16), 0.0)
        qs.append(_dense(h, jax.tree.map(lambda v: v[c], p["VmapDense_0"]), bf16)[:, 0])
    return np.stack(qs)


def _actor_case(prec):
    net, x = GaussianHead(HIDDEN, 4, matmul_precision=prec), _inputs(31)
    p = net.init(jax.random.PRNGKey(0), x)["params"]
    return (lambda p, x: net.apply({"params": p}, x)), p, (x,), (lambda bf16: _actor_ref(p, x, bf16))


def _critic_case(prec):
    net, o, a = TwinCritic(HIDDEN, matmul_precision=prec), _inputs(31), jnp.tanh(_inputs(4, 2))
    p = net.init(jax.random.PRNGKey(0), o, a)["params"]
    return ((lambda p, o, a: (net.apply({"params": p}, o, a),)), p, (o, a),
            (lambda bf16: (_critic_ref(p, jnp.concatenate([o, a], -1), bf16),)))


def _mc_case(prec):
    models = MCModels(state_dim=25, hidden=(256,) * 5, matmul_precision=prec)
    s, a = _inputs(25), jnp.tanh(_inputs(4, 2))
    p = models.init(jax.random.PRNGKey(0), 4)
    t, ac = p["transition"]["GaussianHead_0"], p["action"]["GaussianHead_0"]
    return (models.forward, p, (s, a),
            (lambda bf16: (*_actor_ref(t, jnp.concatenate([s, a], -1), bf16), *_actor_ref(ac, a, bf16))))


@pytest.mark.parametrize("case", [_actor_case, _critic_case, _mc_case], ids=["actor", "critic", "mc"])
def test_outputs_are_float32_and_bfloat16_is_really_used(case):
    """Whole networks at the thesis' sizes: float32 outputs, and the bfloat16 network follows a bfloat16
    reference by hand, far from the float32 network. Compared on the mean error: the network and the reference
    accumulate in different orders, so a few hidden values round to the neighbouring bfloat16 number and move some
    outputs by up to ~1e-3 (the layer-by-layer test above is exact to 1e-5)."""
    outs = {}
    for prec in ("float32", "bfloat16"):
        apply, p, args, ref = case(prec)  # the same parameters for both (initialisation ignores the precision)
        outs[prec] = jax.jit(apply)(p, *args)
    for y32, y16, r32, r16 in zip(outs["float32"], outs["bfloat16"], ref(False), ref(True)):
        assert y32.dtype == y16.dtype == jnp.float32
        assert _rel(y32, r32) < 1e-5  # the float32 network is plain float32
        y32 = np.asarray(y32, np.float64)
        assert _rel(y16, y32) > 1e-4 and _mrel(y16, y32) > 1e-4  # bfloat16 is really used
        assert _mrel(y16, r16) < 2e-5 and _mrel(y16, r16) < 0.05 * _mrel(y16, y32)


def test_compiled_update_uses_bfloat16_dots_only_when_asked(states):
    state, r = states["float32"], np.random.default_rng(0)
    obs, next_obs = (jnp.asarray(r.normal(size=(256, 31)), jnp.float32) for _ in range(2))
    batch = Batch(obs=obs, action=jnp.asarray(r.uniform(-1, 1, (256, 4)), jnp.float32), reward=-jnp.ones(256),
                  next_obs=next_obs, terminated=jnp.zeros(256))

    agent = _agent("bfloat16")
    assert agent.cfg.use_intrinsic_models
    update = jax.jit(agent.update)
    dots = [line for line in update.lower(state, batch).as_text().splitlines() if "dot_general" in line]
    bf16_dot = re.compile(r"\(tensor<[0-9x]*xbf16>, tensor<[0-9x]*xbf16>\) -> tensor<[0-9x]*xf32>")
    bf16_dots = [d for d in dots if bf16_dot.search(d)]
    # every forward pass: MC models 2 x (5 + 2 heads), critics (target, current, the actor's) 3 x (3 + 1),
    # actor (next action, current) 2 x (3 + 2 heads); the backward passes' matmuls stay float32
    assert len(bf16_dots) == 14 + 12 + 10, len(bf16_dots)
    new, _ = update(state, batch)
    for learned in (new.pi, new.q, new.intrinsic):
        assert all(x.dtype == jnp.float32 and bool(jnp.isfinite(x).all()) for x in jax.tree.leaves(learned.params))

    text32 = jax.jit(_agent("float32").update).lower(state, batch).as_text()
    assert "dot_general" in text32 and "bf16" not in text32


def test_bad_precision_is_refused():
    with pytest.raises(MCRLError, match="float32.*bfloat16"):
        resolve_config(None, {"matmul_precision": "fp16"})
    assert resolve_config("fetchreach-sacmc").matmul_precision == "float32"


def test_bad_precision_on_the_command_line(tmp_path, capsys):
    from mcrl.cli import main

    rc = main(["train", "--set", "matmul_precision=fp16", "--out-dir", str(tmp_path / "runs")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "float32" in err and "bfloat16" in err, err
    assert not any(tmp_path.iterdir())


def test_old_run_config_without_the_key_loads_as_float32():
    d = Config().to_dict()
    del d["matmul_precision"]
    assert Config.from_run_json(d).matmul_precision == "float32"


@pytest.mark.slow
def test_sac_bfloat16_learns_fetchreach(tmp_path):
    """Plain SAC with bfloat16 matmuls reaches FetchReach's goal as float32 does: an evaluation of 10 episodes
    reaches 0.9 within 6,500 steps (3x128 networks, initial entropy coefficient 0.1, as the intrinsic rewards'
    learning tests; tests/test_learning.py trains at the thesis' sizes).

    Measured (seed 0, Intel Xeon family 6 model 167), success every 500 steps from 3,500: bfloat16 0, 0.1, 0.2,
    0.4, 1.0 (5,500), 1.0 ...; float32 at the same settings 0, 0.1, 0.3, 0.5, 1.0 (5,500). A broken update (the
    critics' target bootstrapped from s instead of s') reaches at most 0.7 through 7,000 steps (0.6 at 5,000, 0.7
    at 6,500)."""
    from mcrl.run.rundir import read_rows
    from mcrl.run.trainer import train

    cfg = resolve_config("fetchreach-sac", {"matmul_precision": "bfloat16", "hidden_sizes": [128, 128, 128],
                                            "ent_coef_init": 0.1, "total_steps": 6500, "eval_every": 500,
                                            "eval_episodes": 10, "checkpoint_every": 100_000})
    run = train(cfg, tmp_path / "reach", progress=False)
    evals = read_rows(run / "eval.csv")
    assert evals[-1]["step"] == 6500 and evals[-1]["episodes"] == 10
    assert max(e["success_rate"] for e in evals) >= 0.9, evals


def _lowered_dots(agent: Agent, vmapped: bool = False) -> dict[str, list[str]]:
    """The dot_general lines of the lowered update (forward and backward passes, every network it trains) and of
    both policies, from the agent's shapes alone (nothing is run)."""
    state = jax.eval_shape(lambda: agent.init(0))
    f32 = lambda *shape: jax.ShapeDtypeStruct(shape, jnp.float32)  # noqa: E731
    batch = Batch(obs=f32(BATCH, 31), action=f32(BATCH, 4), reward=f32(BATCH), next_obs=f32(BATCH, 31),
                  terminated=f32(BATCH))
    if vmapped:  # as a group trains: the step vmapped over 2 runs, hyperparameters as data
        from mcrl.algo.sac import Hyper

        two = lambda x: jax.ShapeDtypeStruct((2, *x.shape), x.dtype)  # noqa: E731
        update = jax.jit(jax.vmap(agent.update)).lower(*jax.tree.map(two, (state, batch, Hyper(*[f32()] * 5))))
    else:
        update = jax.jit(agent.update).lower(state, batch)
    key = jax.ShapeDtypeStruct((2,), jnp.uint32)
    lowered = {"update": update, "act": jax.jit(agent.act).lower(state.pi.params, f32(1, 31), key),
               "act_deterministic": jax.jit(agent.act_deterministic).lower(state.pi.params, f32(1, 31))}
    return {k: [line for line in v.as_text().splitlines() if "dot_general" in line] for k, v in lowered.items()}


@pytest.mark.parametrize("intrinsic", ["mc", "rnd", "icm", "disagreement"])
def test_float32_asks_for_the_highest_precision_on_every_dot(intrinsic):
    """On NVIDIA GPUs JAX's default matmul precision is TF32 (a 10-bit mantissa): float32 must ask for HIGHEST on
    every dot_general of the jitted step (actor, critics, the intrinsic reward's networks, forward and backward)
    and of the policy, so that a GPU run is float32 as the CPU's is (on the CPU it changes no number: a FetchPush
    SAC-MC run gave the same metrics.csv and checkpoint bit for bit before and after)."""
    cfg = resolve_config("fetchpush-sacmc-0.2", {"intrinsic": intrinsic})
    for vmapped in (False, True) if intrinsic == "mc" else (False,):
        for name, dots in _lowered_dots(Agent(31, 4, 25, cfg), vmapped).items():
            assert dots, name
            loose = [d for d in dots if "precision = [HIGHEST, HIGHEST]" not in d]
            assert not loose, (name, vmapped, loose[:2])


def test_bfloat16_stays_bfloat16_and_asks_for_no_precision():
    """bfloat16 is unchanged by the float32 fix: its forward dots multiply bfloat16 operands (36 of them, counted
    in the test above) at the default precision, and none asks for HIGHEST."""
    dots = _lowered_dots(_agent("bfloat16"))
    bf16 = re.compile(r"\(tensor<[0-9x]*xbf16>, tensor<[0-9x]*xbf16>\) -> tensor<[0-9x]*xf32>")
    assert sum(bool(bf16.search(d)) for d in dots["update"]) == 36
    assert all(bf16.search(d) for d in dots["act"] + dots["act_deterministic"])
    assert not any("HIGHEST" in d for ds in dots.values() for d in ds)
