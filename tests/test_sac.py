"""SAC(-MC) equivalences: mc_alpha = 0 is exactly SAC, and the MC reward really changes learning."""
import numpy as np

from mcrl.run import checkpoint
from mcrl.config import resolve_config
from mcrl.run.policy import load_policy
from mcrl.run.trainer import train


def _run(tmp_path, name, small, **over):
    cfg = resolve_config("fetchreach-sac", {**small, "total_steps": 300, "eval_every": 150, "log_every": 100,
                                            "checkpoint_every": 10_000, **over})
    return train(cfg, tmp_path / name, progress=False)


def _params(run_dir):
    _, _, state = load_policy(run_dir)
    return state


def _same(a, b):
    import jax

    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_alpha_zero_with_mc_models_is_bit_identical_to_sac(tmp_path, small):
    sac = _run(tmp_path, "sac", small)
    mc0 = _run(tmp_path, "mc0", small, mc_alpha=0.0, mc_models=True)
    mc2 = _run(tmp_path, "mc2", small, mc_alpha=0.2)
    s_sac, s_mc0, s_mc2 = _params(sac), _params(mc0), _params(mc2)
    assert s_mc0.intrinsic is not None and s_sac.intrinsic is None  # the MC models really trained alongside
    assert _same(s_sac.pi.params, s_mc0.pi.params) and _same(s_sac.q.params, s_mc0.q.params)
    assert np.array_equal(s_sac.ent.params, s_mc0.ent.params)
    assert _same(s_sac.q.opt, s_mc0.q.opt) and _same(s_sac.q_target, s_mc0.q_target)
    assert (sac / "eval.csv").read_text() == (mc0 / "eval.csv").read_text()
    # control: a non-zero weight changes the critic (the test can fail)
    assert not _same(s_sac.q.params, s_mc2.q.params)


def test_same_seed_same_run_and_different_seed_differs(tmp_path, small):
    a, b = _run(tmp_path, "a", small, mc_alpha=0.2), _run(tmp_path, "b", small, mc_alpha=0.2)
    c = _run(tmp_path, "c", small, mc_alpha=0.2, seed=1)
    assert _same(_params(a), _params(b))
    assert not _same(_params(a).pi.params, _params(c).pi.params)


def test_checkpoint_holds_everything_and_no_pickle(tmp_path, small):
    run = _run(tmp_path, "ck", small, mc_alpha=0.2)
    ck = checkpoint.find(run)
    with np.load(ck / "state.npz", allow_pickle=False) as f:
        keys = set(f.files)
    for part in (".pi.params", ".pi.opt", ".q.params", ".q.opt", ".q_target", ".ent.params", ".ent.opt",
                 ".intrinsic.params", ".intrinsic.opt", ".key"):
        assert any(k.startswith(part) for k in keys), part
    with np.load(ck / "normaliser.npz", allow_pickle=False) as f:
        assert {"ring", "ptr", "count", "c3_index", "c3_count"} <= set(f.files)
        assert int(f["count"]) == int(f["c3_count"].sum()) > 0
    assert (ck / "buffer.npz").is_file()
    meta = checkpoint.load_meta(ck)
    assert meta["step"] == 300 and "host_rng" in meta
