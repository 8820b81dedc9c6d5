"""What a newcomer tripped on (issue 66, item 7): each as a user meets it, through the command line or the API."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

# tests/test_sweep.py's tiny sizes: these tests check plumbing, not learning
TINY = {"hidden_sizes": [64, 64], "intrinsic_hidden_sizes": [64, 64], "batch_size": 64, "buffer_size": 20_000,
        "eval_every": 150, "eval_episodes": 2, "log_every": 100, "learning_starts": 100, "checkpoint_every": 100}
CLI = [sys.executable, "-c", "import sys; from mcrl.cli import main; sys.exit(main())"]


def _run(args: list[str], env: dict | None = None, timeout: int = 400) -> subprocess.CompletedProcess:
    return subprocess.run(args, capture_output=True, text=True, timeout=timeout, env={**os.environ, **(env or {})})


# ----------------------------------------------------------------------------- a reward from a package of its own
REWARD_MODULE = '''
"""A reward shipped in a package of its own: a linear model's squared error predicting s' from (s, a)."""
from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp

from mcrl.algo import intrinsic


@dataclass(frozen=True)
class Mine(intrinsic.Sizes):
    title: ClassVar[str] = "Mine"
    raw_label: ClassVar[str] = "raw error"

    def init(self, key):
        return {"w": 0.01 * jax.random.normal(key, (self.state_dim + self.action_dim, self.state_dim))}, {}

    def reward(self, params, untrained, s, a, s_next):
        return jnp.square(jnp.concatenate([s, a], -1) @ params["w"] - s_next).mean(-1)

    def step(self, params, untrained, s, a, s_next, key):
        def loss(p):
            err = self.reward(p, untrained, s, a, s_next)
            return err.mean(), err

        (value, err), grads = jax.value_and_grad(loss, has_aux=True)(params)
        return intrinsic.Raw(err, grads, untrained, self.generic_metrics(value, err))
'''


def _installed_package(root: Path) -> Path:
    """A directory as `pip install` leaves a package in site-packages: its module and its dist-info, whose
    entry_points.txt declares the reward in the group mcrl.intrinsic. On PYTHONPATH, importlib.metadata finds it."""
    root.mkdir()
    (root / "mine_reward.py").write_text(REWARD_MODULE)
    info = root / "mine_reward-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: mine-reward\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[mcrl.intrinsic]\nmine = mine_reward:Mine\n")
    return root


def test_a_reward_from_an_installed_package_trains_and_evaluates_in_other_processes(tmp_path):
    """The reward is named in config.json only; `mcrl eval` (a new process, as render and --resume are) finds its
    class through the installed package's entry point. Without the package, the error names the fix."""
    site = _installed_package(tmp_path / "site")
    env = {"PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    run = tmp_path / "run"
    train = (f"import mcrl; cfg = mcrl.resolve_config('fetchreach-sac', {{**{TINY!r}, 'total_steps': 200, "
             f"'intrinsic': 'mine', 'intrinsic_alpha': 0.2}}); mcrl.train(cfg, {str(run)!r}, progress=False)")
    res = _run([sys.executable, "-c", train], env)
    assert res.returncode == 0, res.stderr
    assert json.loads((run / "config.json").read_text())["intrinsic"] == "mine"

    res = _run(CLI + ["eval", str(run), "--episodes", "1", "--no-progress"], env)
    assert res.returncode == 0, res.stderr
    assert "episodes: 1" in res.stdout

    res = _run(CLI + ["eval", str(run), "--episodes", "1", "--no-progress"])  # the package not installed
    err = res.stderr.strip()
    assert res.returncode == 2 and len(err.splitlines()) == 1, err
    assert "'mine'" in err and "mcrl.intrinsic" in err and "install" in err
