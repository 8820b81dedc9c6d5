"""Schedules of the intrinsic weight (issue 67): each schedule's values on a hand-checked sequence, its config keys'
one-line errors, the weight as an input of the one compiled step (`constant` is today's step bit for bit; a new
weight compiles nothing), a vmapped group of runs on different schedules, kill -9 and resume, and `success` learning
FetchReach."""
import subprocess
import sys

import jax
import numpy as np
import pytest

from mcrl.algo import diagnostics
from mcrl.algo.sac import Agent, Batch, Hyper, Mix
from mcrl.algo.schedule import Schedule
from mcrl.cli import main
from mcrl.config import resolve_config
from mcrl.run import rundir
from mcrl.run.learner import Learner, train_step
from mcrl.run.policy import load_policy
from mcrl.run.trainer import train, train_runs
from tests.test_resume import kill_past_first_checkpoint

TINY = {"hidden_sizes": [64, 64], "intrinsic_hidden_sizes": [64, 64], "batch_size": 64, "buffer_size": 5000,
        "intrinsic_history": 2000, "learning_starts": 100, "eval_episodes": 2, "checkpoint_every": 100_000}


# ----------------------------------------------------------------------------- the values, by hand
def test_constant_is_the_configs_weight_whatever_happens():
    s = Schedule.of(resolve_config("fetchreach-sacmc", {"intrinsic_alpha": 0.058}))
    assert [s.value(t, w) for t, w in ((1, ()), (9000, ()), (50, (1.0, 1.0)))] == [0.058] * 3
    assert s.observe((), 1.0) == ()  # no state to carry


def test_linear_goes_from_alpha_to_its_end_over_its_steps_then_stays():
    down = Schedule.of(resolve_config("fetchreach-sacmc", {"intrinsic_alpha": 0.4, "intrinsic_schedule": "linear",
                                                           "intrinsic_schedule_steps": 100}))
    # 0.4 (1 - t/100): 0.4, 0.3 at 25, 0.2 at 50, 0.1 at 75, 0 from 100 on
    assert [down.value(t) for t in (0, 25, 50, 75, 100, 150)] == pytest.approx([0.4, 0.3, 0.2, 0.1, 0.0, 0.0])
    assert down.value(0) == 0.4 and down.value(100) == 0.0  # exactly at both ends
    up = Schedule.of(resolve_config("fetchreach-sacmc", {"intrinsic_alpha": 0.0, "intrinsic_schedule": "linear",
                                                         "intrinsic_alpha_end": 0.5, "total_steps": 1000}))
    assert up.steps == 1000  # the run's total steps unless given
    assert [up.value(t) for t in (200, 500, 1000)] == pytest.approx([0.1, 0.25, 0.5])


def test_success_is_alpha_times_one_minus_the_windows_success():
    s = Schedule.of(resolve_config("fetchreach-sacmc", {"intrinsic_alpha": 0.4, "intrinsic_schedule": "success",
                                                        "intrinsic_success_window": 3}))
    state, values = (), [s.value(1)]
    for success in (0.0, 1.0, 1.0, None, 1.0, 0.0):  # None: an episode without a success flag leaves it alone
        state = s.observe(state, success)
        values.append(s.value(1, state))
    # windows: (), (0), (0 1), (0 1 1), (0 1 1), (1 1 1), (1 1 0): s = 0, 0, 1/2, 2/3, 2/3, 1, 2/3
    assert values == pytest.approx([0.4, 0.4, 0.2, 0.4 / 3, 0.4 / 3, 0.0, 0.4 / 3])
    assert state == (1.0, 1.0, 0.0)


def test_a_linear_rise_from_zero_trains_the_models():
    cfg = resolve_config("fetchreach-sac", {"intrinsic_schedule": "linear", "intrinsic_alpha_end": 0.3})
    assert cfg.intrinsic_alpha == 0.0 and cfg.use_intrinsic_models
    assert not resolve_config("fetchreach-sac", {"intrinsic_alpha_end": 0.3}).use_intrinsic_models  # constant 0


@pytest.mark.parametrize("sets,needle", [
    (["intrinsic_schedule=cosine"], "intrinsic_schedule='cosine': choose constant"),
    (["intrinsic_schedule=linear", "intrinsic_alpha_end=1.5"], "intrinsic_alpha_end=1.5 is outside [0, 1]"),
    (["intrinsic_alpha_end=-0.1"], "intrinsic_alpha_end=-0.1 is outside [0, 1]"),
    (["intrinsic_schedule=success", "intrinsic_success_window=0"], "intrinsic_success_window=0 must be at least 1"),
    (["intrinsic_success_window=-3"], "intrinsic_success_window=-3 must be at least 1"),
    (["intrinsic_schedule_steps=0"], "intrinsic_schedule_steps=0 must be at least 1"),
    (["intrinsic_schedule=linear", "intrinsic_alpha_end=0.3", "intrinsic_models=false"],
     "intrinsic_alpha_end=0.3 needs the intrinsic reward's models"),
])
def test_bad_schedule_input_is_one_line_and_writes_nothing(sets, needle, tmp_path, capsys):
    args = ["train", "--preset", "fetchreach-sac", "--out-dir", str(tmp_path / "runs")]
    for s in sets:
        args += ["--set", s]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1, err
    assert not list(tmp_path.iterdir())


def test_success_needs_an_environment_with_a_success_flag(tmp_path, capsys):
    rc = main(["train", "--env", "Pendulum-v1", "--set", "intrinsic_alpha=0.2", "--set", "intrinsic_schedule=success",
               "--run-dir", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "success flag of Pendulum-v1" in err and len(err.splitlines()) == 1, err
    assert not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------- the weight as an input of the step
def _batches(agent, n, seed=0):
    rng = np.random.default_rng(seed)
    b = agent.cfg.batch_size
    return [Batch(rng.normal(size=(b, agent.obs_dim)).astype(np.float32),
                  rng.uniform(-1, 1, (b, agent.act_dim)).astype(np.float32),
                  -(rng.random(b) < 0.8).astype(np.float32), rng.normal(size=(b, agent.obs_dim)).astype(np.float32),
                  np.zeros(b, np.float32)) for _ in range(n)]


def _same(a, b):
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


@pytest.mark.parametrize("alpha,models", [(0.058, None), (0.0, True)])
def test_the_weight_as_data_is_the_constant_step_bit_for_bit(alpha, models):
    """Five gradient steps with the weight an input (`Mix`) equal those with it a compile-time constant (the step
    before issue 67), in every leaf and metric; for a vmapped group against alpha in `Hyper` (its step before).
    0.058 is a weight where float32 1 - alpha differs from float64's rounded: each learner keeps its own."""
    cfg = resolve_config("fetchreach-sac", {**TINY, "intrinsic_alpha": alpha, "intrinsic_models": models})
    agent = Agent(10, 4, 6, cfg)
    batches = _batches(agent, 5)
    today, mixed = jax.jit(agent.update), jax.jit(lambda s, b, w: agent.update(s, b, mix=w))
    a = b = agent.init(0)
    for batch in batches:
        a, ma = today(a, batch)
        b, mb = mixed(b, batch, Mix.of(alpha))
        assert _same(ma, mb)
    assert _same(a, b)
    states = jax.tree.map(lambda *x: np.stack(x), agent.init(0), agent.init(1))
    stacked = [Batch(*(np.stack(x) for x in zip(*pair))) for pair in zip(batches, _batches(agent, 5, seed=1))]
    hyper = Hyper(*(np.full(2, v, np.float32) for v in Hyper.of(cfg)))
    group_today = jax.jit(jax.vmap(lambda s, b, h: agent.update(s, b, h)))
    group_mixed = jax.jit(jax.vmap(lambda s, b, h, w: agent.update(s, b, h, w)))
    a = b = states
    for batch in stacked:
        a, ma = group_today(a, batch, hyper)
        b, mb = group_mixed(b, batch, hyper, Mix.of_float32([alpha, alpha]))
        assert _same(ma, mb)
    assert _same(a, b)
    assert Mix.of(0.058).ext != Mix.of_float32(0.058).ext  # why the two learners compute 1 - alpha apart


class _TodaysLearner(Learner):
    """The learner before issue 67: the weight a compile-time constant of its step."""

    def __init__(self, agent, state, diag):
        super().__init__(agent, state, diag)
        self._today = jax.jit(lambda s, d, b: train_step(agent, s, d, b), donate_argnums=(0, 1))

    def update(self, batches, alphas=None):
        (batch,) = batches
        if batch is not None:
            self.state, self.diag = self._today(self.state, self.diag, batch)


@pytest.mark.slow
def test_a_constant_run_is_todays_run_bit_for_bit(tmp_path):
    """A whole run (acting, HER, evaluation, log rows) with the weight an input of its step writes the numbers of
    the same run with the weight a constant of it: every learning column and the final state."""
    alpha = 0.058  # where a float32 1 - alpha would differ from the constant's
    cfg = resolve_config("fetchreach-sac", {**TINY, "intrinsic_alpha": alpha, "total_steps": 300, "eval_every": 150,
                                            "log_every": 50})
    now = train(cfg, tmp_path / "now", progress=False)
    (before,) = train_runs([cfg], [tmp_path / "before"], False,
                           lambda ms, ss, ds: _TodaysLearner(ms[0].agent, ss[0], ds[0]))
    cols = rundir.LEARNING_COLUMNS
    rows = [[{c: r[c] for c in cols} for r in rundir.read_rows(d / rundir.METRICS)] for d in (now, before)]
    assert rows[0] == rows[1] and len(rows[0]) == 6 and {r["intrinsic_alpha"] for r in rows[0]} == {alpha}
    assert (now / rundir.EVAL).read_text() == (before / rundir.EVAL).read_text()
    assert _same(load_policy(now)[2], load_policy(before)[2])


def test_a_new_weight_compiles_nothing():
    cfg = resolve_config("fetchreach-sac", {**TINY, "intrinsic_alpha": 0.4, "intrinsic_schedule": "linear"})
    agent = Agent(10, 4, 6, cfg)
    learner = Learner(agent, agent.init(0), diagnostics.init())
    for alpha, batch in zip((0.4, 0.3, 0.2, 0.1, 0.0), _batches(agent, 5)):
        learner.update([batch], [alpha])
    assert learner._step._cache_size() == 1
    assert float(learner.read_metrics()[0]["mean_total_reward"]) != pytest.approx(
        float(np.mean([b.reward.mean() for b in _batches(agent, 5)])))  # the weights were used: not r_ext alone


# ----------------------------------------------------------------------------- groups, resume
def _alphas(run_dir):
    return [(r["step"], r["intrinsic_alpha"]) for r in rundir.read_rows(run_dir / rundir.METRICS)]


@pytest.mark.slow
def test_a_group_holds_runs_on_different_schedules(tmp_path):
    """constant, linear and success in one vmapped group (one compiled step): each run's weights follow its own
    schedule, and its numbers those of the run trained alone (to the float tolerance of tests/test_vmap.py)."""
    from mcrl.run.group import plan_groups, train_group

    over = {**TINY, "total_steps": 150, "eval_every": 75, "log_every": 25}
    cfgs = [resolve_config("fetchreach-sacmc", {**over, "seed": 0}),
            resolve_config("fetchreach-sac", {**over, "seed": 1, "intrinsic_alpha": 0.4,
                                              "intrinsic_schedule": "linear", "intrinsic_schedule_steps": 100}),
            resolve_config("fetchreach-sac", {**over, "seed": 2, "intrinsic_alpha": 0.3, "intrinsic_schedule": "success",
                                              "intrinsic_success_window": 2})]
    assert plan_groups(cfgs) == [[0, 1, 2]]
    group = train_group(cfgs, [tmp_path / f"g{i}" for i in range(3)])
    assert _alphas(group[0]) == [(25.0 * k, 0.2) for k in range(1, 7)]
    assert [a for _, a in _alphas(group[1])] == pytest.approx([0.3, 0.2, 0.1, 0.0, 0.0, 0.0])  # 0.4 (1 - t/100)
    assert {a for _, a in _alphas(group[2])} == {0.3}  # no training episode succeeds this early
    for i, cfg in enumerate(cfgs):
        alone = train(cfg, tmp_path / f"alone{i}", progress=False)
        assert _alphas(group[i]) == _alphas(alone)
        g, a = rundir.read_rows(group[i] / rundir.METRICS), rundir.read_rows(alone / rundir.METRICS)
        for x, y in zip(g, a, strict=True):
            for k in ("q_mean", "critic_loss", "mean_total_reward", "mean_intrinsic_reward"):
                assert (x[k] is None) == (y[k] is None) and (x[k] is None or x[k] == pytest.approx(
                    y[k], rel=1e-4, abs=1e-5)), (i, k, x["step"])


# Training episodes succeed by a rule of the episode's index (1 in 3 fail), so that the success window changes the
# weight every episode from the first: the learner's success flags are 0 this early in FetchReach.
_FAKE_SUCCESS = """
import sys
from mcrl.run.member import Member
_end = Member.end_episode
Member.end_episode = lambda self, success: _end(self, float(self.progress.episode % 3 != 0))
from mcrl.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.slow
def test_kill9_and_resume_follow_the_same_weights(tmp_path):
    """A `success` run killed with SIGKILL after its first checkpoint and resumed writes the alpha sequence and
    every learning number of the uninterrupted run: the success window comes back from the checkpoint."""
    sets = {**TINY, "intrinsic_alpha": 0.4, "intrinsic_schedule": "success", "intrinsic_success_window": 2,
            "total_steps": 600, "eval_every": 300, "log_every": 50, "checkpoint_every": 200}
    args = ["train", "--preset", "fetchreach-sac", "--no-progress"]
    for k, v in sets.items():
        args += ["--set", f"{k}={v}"]
    cmd = [sys.executable, "-c", _FAKE_SUCCESS, *args]
    full, killed = tmp_path / "full", tmp_path / "killed"
    subprocess.run([*cmd, "--run-dir", str(full)], check=True, capture_output=True)
    proc = subprocess.Popen([*cmd, "--run-dir", str(killed)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    kill_past_first_checkpoint(proc, killed, sets["checkpoint_every"])
    assert not (killed / rundir.DONE).exists()
    res = subprocess.run([sys.executable, "-c", _FAKE_SUCCESS, "train", "--resume", str(killed), "--no-progress"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    alphas = _alphas(full)
    assert _alphas(killed) == alphas and len({a for _, a in alphas}) > 2, alphas  # the weight moved
    cols = rundir.LEARNING_COLUMNS
    rows = [[{c: r[c] for c in cols} for r in rundir.read_rows(d / rundir.METRICS)] for d in (killed, full)]
    assert rows[0] == rows[1] and len(rows[0]) == 12
    assert (killed / rundir.EVAL).read_text() == (full / rundir.EVAL).read_text()


# ----------------------------------------------------------------------------- where the weight shows
@pytest.fixture(scope="module")
def linear_run(tmp_path_factory):
    cfg = resolve_config("fetchreach-sacmc", {**TINY, "intrinsic_alpha": 0.4, "intrinsic_schedule": "linear",
                                              "total_steps": 300, "eval_every": 150, "log_every": 50})
    return train(cfg, tmp_path_factory.mktemp("lin") / "run", progress=False)


def test_the_weight_is_a_metrics_column_in_mlflow_and_the_runs_plot(linear_run, tmp_path):
    from mlflow import MlflowClient
    from PIL import Image

    from mcrl.analysis.plots import plot_run
    from mcrl.sweep import RunPlan
    from mcrl.sweep.tracking import Tracker

    alphas = _alphas(linear_run)
    assert [a for _, a in alphas] == pytest.approx([0.4 * (1 - k / 6) for k in range(1, 7)])  # 0.4 (1 - t/300)
    tracker = Tracker.check(None, tmp_path / "exp")
    tracker.open(tmp_path / "exp", "sweep-id", "fetchreach-sacmc")
    cfg = rundir.read_config(linear_run)
    rid = tracker.log_run(RunPlan("lin", "linear", cfg.seed, {}, cfg), linear_run)
    history = MlflowClient(tracking_uri=tracker.uri).get_metric_history(rid, "intrinsic_alpha")
    got = sorted((m.step, m.value) for m in history)
    assert [s for s, _ in got] == [int(s) for s, _ in alphas]
    assert [v for _, v in got] == pytest.approx([a for _, a in alphas], rel=1e-12)
    # SAC-MC's eight panels and the weight's: five rows of two
    assert Image.open(plot_run(linear_run, tmp_path / "curves.png")).height == 5 * 320


def test_the_report_draws_the_weight_beside_success(tmp_path):
    import csv

    from PIL import Image

    from mcrl.analysis.report import write_report
    from tests.test_report import _experiment, _section

    for schedule, panels in (("constant", 2), ("success", 3)):
        exp = _experiment(tmp_path / schedule, {0.0: [(0.2, -40.0)] * 3, 0.4: [(0.6, -20.0)] * 3},
                          config={"intrinsic_schedule": schedule})
        for metrics in (exp / "runs").glob("*/metrics.csv"):
            rows = list(csv.DictReader(metrics.open()))
            for r in rows:  # the weight a success schedule gives as the training success (step / 2000) rises
                r["intrinsic_alpha"] = float(metrics.parent.name.startswith("a0.4")) * 0.4 * (1 - float(r["step"]) / 2000)
            with metrics.open("w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=rundir.METRIC_COLUMNS)
                w.writeheader()
                w.writerows(rows)
        md = write_report(exp, tmp_path / f"rep-{schedule}").read_text()
        caption = _section(md, "Learning curves")
        assert ("intrinsic weight in force" in caption) == (schedule != "constant"), caption
        assert Image.open(tmp_path / f"rep-{schedule}" / "learning_curves.png").width == panels * 500


# ----------------------------------------------------------------------------- learning
@pytest.mark.slow
@pytest.mark.timeout(900)
def test_success_hands_over_to_the_task_and_learns_fetchreach(tmp_path):
    """SAC-MC with the `success` schedule from 0.4 (window 20 episodes) solves FetchReach: an evaluation of 10
    episodes reaches 0.9 within 8,000 steps (the sizes of tests/test_intrinsic.py's learning tests), and the weight
    falls from 0.4 to at most 0.1 as the training episodes succeed. Measured on seed 0 (AMD EPYC, 2 cores): success
    0 to 4,500 steps, 0.1 at 5,000, 0.5, 0.6, 0.8, then 1.0 from 7,000; the weight 0.4 to 5,250, 0.22 at 6,250,
    0.06 at 7,000 and 0 at 8,000."""
    cfg = resolve_config("fetchreach-sac", {"intrinsic_alpha": 0.4, "intrinsic_schedule": "success",
                                            "intrinsic_success_window": 20, "hidden_sizes": [128, 128, 128],
                                            "intrinsic_hidden_sizes": [64, 64], "ent_coef_init": 0.1,
                                            "total_steps": 8000, "eval_every": 500, "eval_episodes": 10,
                                            "checkpoint_every": 100_000})
    run = train(cfg, tmp_path / "reach", progress=False)
    evals = rundir.read_rows(run / rundir.EVAL)
    assert max(e["success_rate"] for e in evals) >= 0.9, evals
    alphas = _alphas(run)
    assert alphas[0][1] == 0.4 and alphas[-1][1] <= 0.1, alphas
