"""mcrl's SAC step against stable-baselines3's, without torch (issue 66, item 5).

studies/sb3-parity/golden_sac_step.npz holds SB3's losses, gradients and parameters after one gradient step at the
thesis' sizes (FetchPush-v4, 3 x 256, batch 256), generated once by studies/sb3-parity/golden.py (which needs torch
and stable-baselines3; how and with which versions: its docstring). Here mcrl takes the same step, from the same
state, batch and Gaussian noise, through the training loop's own Learner, and must agree to the tolerances of the
transplant and one-step checks (parity_step.py's). tests/test_transplant.py runs SB3 itself and skips without torch;
this one never skips.
"""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

_spec = importlib.util.spec_from_file_location(
    "sb3_golden", Path(__file__).resolve().parents[1] / "studies" / "sb3-parity" / "golden.py")
golden = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(golden)


@pytest.fixture(scope="module")
def reference():
    return golden.load()


@pytest.fixture(scope="module")
def exact_step(reference):
    return golden.mcrl_step(reference, "exact")


def test_the_golden_file_is_small_and_at_the_thesis_sizes(reference):
    assert golden.GOLDEN.stat().st_size < 1_000_000
    meta = reference["meta"]
    assert meta["preset"] == "fetchpush-sac" and meta["env_id"] == "FetchPush-v4"
    assert meta["versions"]["stable_baselines3"] == "2.9.2" and meta["versions"]["torch"].startswith("2.13.0")
    cfg = golden.config("exact")
    assert tuple(cfg.hidden_sizes) == (256, 256, 256) and cfg.batch_size == 256
    assert meta["shapes"][".q.params['VmapMLP_0']['Dense_1']['kernel']"] == [2, 256, 256]  # twin critics, 3 x 256
    assert reference["batch_obs"].shape == (256, 31) and reference["batch_action"].shape == (256, 4)
    # rows that exercise the termination mask, and time-limit rows for the mutation below, apart
    term, trunc = reference["batch_terminated"], reference["batch_truncated"]
    assert term.sum() == 16 and trunc.sum() == 8 and not (term * trunc).any()
    # the tolerances are the transplant and one-step checks' (studies/sb3-parity/parity_step.py)
    assert golden.tolerances() == {"TOL_LOSS_REL": 5e-5, "TOL_LOSS_ABS": 1e-6, "TOL_GRAD_REL": 1e-4,
                                   "TOL_UPDATE_REL": 1e-2}


@pytest.mark.parametrize("mode", ["exact", "epsilon"])
def test_mcrl_step_agrees_with_sb3(reference, exact_step, mode):
    """exact: mcrl at the preset's exact tanh correction against SB3 given the same; epsilon: mcrl's
    squash_correction=epsilon against stock SB3. Losses, gradients, updates, Adam moments and counts."""
    res = exact_step if mode == "exact" else golden.mcrl_step(reference, mode)
    rows = golden.comparison(reference, mode, res)
    assert len(rows) == 50 and golden.failures(rows) == [], golden.table(rows)


def _truncated_as_done(b):
    return {**b, "terminated": np.maximum(b["terminated"], b["truncated"])}


def _mask_ignored(b):
    return {**b, "terminated": np.zeros_like(b["terminated"])}


def _target_is_online(s):
    return {k: (s[".q.params" + k[len(".q_target"):]] if k.startswith(".q_target") else v) for k, v in s.items()}


# Each a bug the check must see, made through what mcrl is given (robust to how its step is written inside): the
# time-limit rows bootstrapped as terminal, the (1 - terminated) mask dropped, the target computed with the
# online critics. `failing` names what at least must fail.
MUTATIONS = {
    "truncated as done": ({"batch_edit": _truncated_as_done}, ("critic_loss", "gradient of critic")),
    "termination mask ignored": ({"batch_edit": _mask_ignored}, ("critic_loss", "gradient of critic")),
    "target critics = online critics": ({"state_edit": _target_is_online}, ("critic_loss", "update of critic_target")),
}


@pytest.mark.parametrize("name", list(MUTATIONS))
def test_the_check_fails_on_a_wrong_step(reference, exact_step, name):
    edits, failing = MUTATIONS[name]
    bad = golden.failures(golden.comparison(reference, "exact", golden.mcrl_step(reference, "exact", **edits)))
    for what in failing:
        assert any(f.startswith(what) for f in bad), (what, bad)
    # and the unchanged step passes the same comparison (the mutation, not the fixture, fails)
    assert golden.failures(golden.comparison(reference, "exact", exact_step)) == []
