"""What a newcomer tripped on (issue 66, item 7): each as a user meets it, through the command line or the API."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

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
    about: ClassVar[intrinsic.About] = intrinsic.About("Mine", "SAC+Mine", raw_label="raw error")

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


# ----------------------------------------------------------------------------- the report of a FetchReach sweep
sys.path.insert(0, str(Path(__file__).parent))
from test_report import _section, _write_run  # noqa: E402  (the fake run directories of the report tests)


def _reach_sweep(exp: Path, finals: dict[str, list[float]]) -> None:
    """What `mcrl sweep --preset fetchreach-sac --alphas ... --seeds N --steps 1000` leaves, with these final
    success rates per alpha: its own sweep.json lines and config.json files (the plan writes both)."""
    from mcrl.sweep import plan_from_args

    plan = plan_from_args("fetchreach-sac", ",".join(finals), len(next(iter(finals.values()))), {"total_steps": 1000})
    for r in plan.runs:
        sr = finals[f"{r.config.intrinsic_alpha:g}"][r.seed]
        _write_run(exp / "runs" / r.name, r.config.intrinsic_alpha, r.seed, (sr, -10.0), config=r.config.to_dict(),
                   final_eval={"success_rate": sr, "mean_return": -10.0, "episodes": 10})
    (exp / "sweep.json").write_text(json.dumps({"preset": plan.preset, "runs": [r.entry() for r in plan.runs]}))


def test_a_fetchreach_sweeps_verdicts_see_its_sac_arm(tmp_path):
    """A task the thesis has no numbers for still has SAC-MC's claim against SAC; the sentence for a report
    without claims names what is missing, not a SAC arm its tables show."""
    from mcrl.analysis.report import write_report

    _reach_sweep(tmp_path / "both", {"0": [0.1, 0.2, 0.3], "0.2": [0.7, 0.8, 0.9]})
    verdicts = _section(write_report(tmp_path / "both", claims=False).read_text(), "Verdicts")
    assert "No claim to decide" not in verdicts
    row = next(ln for ln in verdicts.splitlines() if ln.startswith("| `alpha=0.2` > `alpha=0`"))
    assert "3 / 3" in row and "fewer than" not in row

    _reach_sweep(tmp_path / "sac", {"0": [0.1, 0.2, 0.3]})
    verdicts = _section(write_report(tmp_path / "sac", claims=False).read_text(), "Verdicts")
    assert "No claim to decide" in verdicts and "every finished arm is SAC" in verdicts
    assert "no finished SAC arm" not in verdicts


# ----------------------------------------------------------------------------- a sweep's provenance
def _tiny_sets() -> list[str]:
    return [a for k, v in TINY.items() for a in ("--set", f"{k}={json.dumps(v)}")]


def _git_head() -> str | None:
    """The commit of the mcrl this test imports, when it is a git checkout of itself (found apart from mcrl's
    own code)."""
    import mcrl

    repo = Path(mcrl.__file__).resolve().parents[2]
    res = subprocess.run(["git", "-C", str(repo), "rev-parse", "--show-toplevel", "HEAD"], capture_output=True,
                         text=True)
    if res.returncode != 0 or Path(res.stdout.split()[0]).resolve() != repo:
        return None
    return res.stdout.split()[1]


def test_a_sweep_records_its_provenance_and_the_report_shows_it(tmp_path):
    """Each `mcrl sweep` call into EXP adds its command, code, machine and times to EXP/provenance.json, keeping
    what the file held; the report lists them; a provenance.json it cannot extend stops the sweep."""
    from mcrl.analysis.report import write_report

    exp = tmp_path / "exp"
    args = ["sweep", "--preset", "fetchreach-sac", "--alphas", "0", "--seeds", "1", "--steps", "200", *_tiny_sets(),
            "--exp", str(exp), "--workers", "1", "--no-progress"]
    res = _run(CLI + args)
    assert res.returncode == 0, res.stderr
    prov = json.loads((exp / "provenance.json").read_text())
    (first,) = prov["sweeps"]
    assert first["command"].startswith("mcrl sweep --preset fetchreach-sac --alphas 0") and "--exp" in first["command"]
    assert first["started"] <= first["ended"] and first["mcrl"] and first["machine"]
    assert first.get("commit") == _git_head()

    prov["note"] = "written by hand"  # a key of the committed experiments' kind
    (exp / "provenance.json").write_text(json.dumps(prov))
    res = _run(CLI + ["sweep", "--exp", str(exp), "--no-progress"])  # continues the sweep recorded there
    assert res.returncode == 0, res.stderr
    prov = json.loads((exp / "provenance.json").read_text())
    assert prov["note"] == "written by hand" and prov["sweeps"][0] == first and len(prov["sweeps"]) == 2
    assert prov["sweeps"][1]["command"] == f"mcrl sweep --exp {exp} --no-progress"

    section = _section(write_report(exp, claims=False).read_text(), "Provenance and method")
    assert "sweep call 1: `mcrl sweep --preset fetchreach-sac" in section and "sweep call 2:" in section
    assert first["started"] in section and "written by hand" in section

    (exp / "provenance.json").write_text("{not json")
    sweep_json = (exp / "sweep.json").read_text()
    res = _run(CLI + ["sweep", "--exp", str(exp), "--no-progress"])
    err = res.stderr.strip()
    assert res.returncode == 2 and len(err.splitlines()) == 1 and "provenance.json" in err, err
    assert (exp / "provenance.json").read_text() == "{not json" and (exp / "sweep.json").read_text() == sweep_json


# ----------------------------------------------------------------------------- a run's default name
def test_a_default_run_name_shows_the_settings_that_differ_from_its_preset():
    """`mcrl train --preset fetchreach-sac --set intrinsic=rnd --set intrinsic_alpha=0.2` is not named like plain
    SAC: the name holds the reward and its weight; bookkeeping (seed aside) stays out; any number of settings
    keeps a name a file system takes."""
    from mcrl.config import parse_set, resolve_config
    from mcrl.run.member import default_run_dir

    def name(*sets: str) -> str:
        return default_run_dir(resolve_config("fetchreach-sac", parse_set(list(sets)))).name

    plain, rnd = name(), name("intrinsic=rnd", "intrinsic_alpha=0.2")
    assert plain.startswith("fetchreach-sac-s0-")
    assert rnd.startswith("fetchreach-sac-") and not rnd.startswith("fetchreach-sac-s0-")
    assert "rnd" in rnd and "0.2" in rnd
    assert name("log_every=100", "eval_episodes=3").startswith("fetchreach-sac-s0-")  # how it is recorded
    many = name(*(f"{k}={v}" for k, v in [("batch_size", 128), ("hidden_sizes", "[300, 300, 300, 300]"),
                                          ("intrinsic_hidden_sizes", "[300, 300, 300, 300, 300]"), ("tau", 0.01),
                                          ("gamma", 0.95), ("learning_rate", 0.001), ("intrinsic_lr", 0.001),
                                          ("env_kwargs", "{reward_type: dense}"), ("her_k", 8)]))
    assert len(many) < 200 and "/" not in many and " " not in many


# ----------------------------------------------------------------------------- mcrl measure
def test_measure_says_which_transitions_each_mean_is_over(tmp_path, capsys):
    """The printed held-out mean is over the held-out fifth; the file holds every transition, and the line that
    names it gives that file's mean."""
    import re

    import numpy as np

    from mcrl.algo.mc import measure
    from mcrl.cli import main

    rng = np.random.default_rng(0)
    s, a = rng.normal(size=(300, 3)).astype(np.float32), rng.normal(size=(300, 2)).astype(np.float32)
    s2 = s + 0.3 * a @ np.ones((2, 3), np.float32) + 0.1 * rng.normal(size=(300, 3)).astype(np.float32)
    np.savez(tmp_path / "data.npz", states=s, actions=a, next_states=s2)
    out = tmp_path / "kl.npy"
    opts = ["--max-steps", "100", "--hidden", "16", "16", "--no-progress"]
    assert main(["measure", str(tmp_path / "data.npz"), "--out", str(out), *opts]) == 0
    text = capsys.readouterr().out
    per = np.load(out)
    res = measure(s, a, s2, hidden=(16, 16), max_steps=100)  # the same fit, from Python
    held = len(res.heldout)
    assert 0 < held < len(per) and res.mean_kl == float(per[res.heldout].mean())
    m = re.search(r"mean MC \(KL per transition\): ([\d.]+) nats over the (\d+) held-out transitions .*"
                  r"over all (\d+): ([\d.]+) nats", text)
    assert m, text
    assert float(m[1]) == round(res.mean_kl, 6) and int(m[2]) == held
    assert int(m[3]) == len(per) and float(m[4]) == round(float(per.mean()), 6)
    assert f"of all {len(per)} transitions (mean {per.mean():.6f} nats) written to {out}" in text


# ----------------------------------------------------------------------------- a run from `--env FetchReach`
@pytest.fixture(scope="module")
def reach_run(tmp_path_factory) -> Path:
    """`mcrl train --env FetchReach` (no version), 60 steps: one evaluation, at the end."""
    from mcrl.cli import main

    run = tmp_path_factory.mktemp("reach") / "run"
    sets = [f"--set={k}={json.dumps(v)}" for k, v in {**TINY, "eval_every": 0, "eval_episodes": 1}.items()]
    assert main(["train", "--env", "FetchReach", "--steps", "60", *sets, "--run-dir", str(run), "--no-progress"]) == 0
    return run


def test_an_env_id_without_a_version_is_stored_as_the_one_that_ran(reach_run):
    """`--env FetchReach` trains the newest FetchReach; config.json names that version, not "FetchReach"."""
    import gymnasium as gym

    from mcrl.envs import register_envs

    register_envs()
    newest = max(int(k.rsplit("-v", 1)[1]) for k in gym.registry if k.startswith("FetchReach-v"))
    assert json.loads((reach_run / "config.json").read_text())["env_id"] == f"FetchReach-v{newest}"


# ----------------------------------------------------------------------------- TensorBoard, and a run without success
def test_tensorboard_has_one_tag_per_evaluation_quantity(reach_run):
    """An evaluation's success rate and return are eval/success_rate and eval/mean_return, at the evaluation's
    step; metrics.csv's copies of them (eval_*) add no second tag."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(reach_run))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"eval/success_rate", "eval/mean_return", "train/episodes"} <= tags
    assert not [t for t in tags if "eval_" in t], tags


def test_a_run_without_a_success_signal_prints_n_a(tmp_path, capsys):
    """Pendulum has no success flag: `mcrl train` says 'n/a', as `mcrl eval` and sweeps do, not 'None'."""
    from mcrl.cli import main

    sets = [f"--set={k}={json.dumps(v)}" for k, v in {**TINY, "eval_every": 0, "eval_episodes": 1, "her": False}.items()]
    run = tmp_path / "run"
    assert main(["train", "--env", "Pendulum-v1", "--steps", "60", *sets, "--run-dir", str(run), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "final evaluation: success rate n/a," in out and "None" not in out
    assert main(["eval", str(run), "--episodes", "1", "--no-progress"]) == 0
    assert "success rate: n/a" in capsys.readouterr().out
