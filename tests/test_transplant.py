"""studies/sb3-parity/transplant.py (issue 26 item 3): a learning state moves between mcrl's checkpoint files and
stable-baselines3 exactly, and one gradient step from the moved state agrees between the two systems."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("stable_baselines3")

BENCH = Path(__file__).resolve().parents[1] / "studies" / "sb3-parity"
sys.path.insert(0, str(BENCH))

TINY = {"hidden_sizes": [32, 32], "buffer_size": 5_000, "batch_size": 32, "learning_starts": 100,
        "total_steps": 300}


@pytest.fixture(scope="module")
def trained_sb3():
    """An SB3 SAC+HER trained 300 FetchPush steps: non-trivial weights, Adam moments and 6 whole episodes."""
    import torch

    from _sb3 import build_model
    from mcrl.config import resolve_config

    torch.set_num_threads(1)
    cfg = resolve_config("fetchpush-sac", TINY)
    model, _ = build_model(cfg)
    model.learn(total_timesteps=cfg.total_steps)
    return cfg, model


def test_sb3_state_survives_mcrl_files_exactly(trained_sb3, tmp_path):
    from _sb3 import build_model
    from _transplant import differences, install_sb3, read_sb3, write_mcrl
    from _transplant_check import read_with_mcrl, torch_differences

    cfg, model = trained_sb3
    original = read_sb3(model, episode=6)
    assert original.opt["critic"]["count"] == 200  # gradient steps after 100 warm-up steps
    assert int(original.buffer["counters"][0]) == 300 and (original.buffer["ep_last"] >= 0).all()
    write_mcrl(tmp_path / "run", original, cfg)
    via_mcrl = read_with_mcrl(tmp_path / "run")[0]  # read by mcrl's own checkpoint and buffer code
    assert max(differences(original, via_mcrl).values()) == 0.0
    copy, _ = build_model(cfg)
    install_sb3(copy, via_mcrl)
    diffs = torch_differences(model, copy)
    assert max(diffs.values()) == 0.0, {k: v for k, v in diffs.items() if v}


@pytest.mark.slow
def test_one_step_agrees_and_catches_a_wrong_input_order(trained_sb3, tmp_path, monkeypatch):
    import _transplant
    from _transplant import read_sb3, write_mcrl
    from _transplant_check import one_step, step_failures

    cfg, model = trained_sb3
    write_mcrl(tmp_path / "run", read_sb3(model, episode=6), cfg)
    res = one_step(cfg, tmp_path / "run", "sb3-exact", steps=2)
    assert step_failures(res) == []
    assert res["losses"]["q_mean"]["max_rel"] < 1e-5
    # SB3 without the Dict observation's key order (achieved | desired | observation) sees other inputs
    monkeypatch.setattr(_transplant, "_input_order", lambda model: None)
    assert step_failures(one_step(cfg, tmp_path / "run", "sb3-exact", steps=2))


def test_streams_are_distinct_and_stable():
    from transplant import stream_seed

    seeds = [stream_seed(k) for k in range(100)]
    assert len(set(seeds)) == 100 and all(0 <= s < 2**31 for s in seeds)
    assert seeds == [stream_seed(k) for k in range(100)]
    assert not set(seeds) & set(range(1000))  # apart from the small seeds of the origin runs


def test_continue_refuses_a_non_checkpoint(tmp_path):
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, str(BENCH / "transplant.py"), "continue", "--from", str(tmp_path),
                        "--system", "sb3", "--stream", "0", "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().startswith("mcrl: error:") and "checkpoint" in r.stderr
    assert not out.exists()


def test_input_order_of_a_goal_dict():
    from _transplant import _input_order, _permute_inputs

    class Space:  # SB3's Dict space: keys sorted
        spaces = {"achieved_goal": np.zeros(3), "desired_goal": np.zeros(3), "observation": np.zeros(25)}

    class Model:
        observation_space = Space()

    order = _input_order(Model())
    assert list(order) == [25, 26, 27, 28, 29, 30] + list(range(25))
    actor = {"MLP_0": {"Dense_0": {"kernel": np.arange(31 * 2).reshape(31, 2), "bias": np.zeros(2)}}}
    moved = _permute_inputs(actor, "actor", order, back=False)
    assert moved["MLP_0"]["Dense_0"]["kernel"][0].tolist() == [50, 51]  # achieved_goal's first row comes first
    back = _permute_inputs(moved, "actor", order, back=True)
    assert np.array_equal(back["MLP_0"]["Dense_0"]["kernel"], actor["MLP_0"]["Dense_0"]["kernel"])
