"""MC is a reward like the others (issue 66, item 2): what the config, metrics.csv, the report and the video say of a
reward comes from its `About`, so a reward registered here, with a metrics.csv column of its own, shows everywhere
the built-in ones do: its column in metrics.csv (filled, kept on resume), its arm's name and raw value in the report,
its panels in `mcrl plot`, its rows in the video's timeline. A config key of another reward is refused."""
from __future__ import annotations

import json
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest

from mcrl.algo import intrinsic
from mcrl.config import resolve_config
from mcrl.errors import MCRLError
from mcrl.run import rundir

sys.path.insert(0, str(Path(__file__).parent))
from test_intrinsic import Toy as LinearToy  # noqa: E402  (the fifth reward of tests/test_intrinsic.py)
from test_report import _row, _section  # noqa: E402  (reading a report's Markdown)

TOY = intrinsic.About("Toy", "SAC+Toy", metrics=("toy_energy",), raw_metric="toy_energy",
                      raw_label="raw toy energy", values_per_step=lambda cfg: 1)


@dataclass(frozen=True)
class Toy(LinearToy):
    """test_intrinsic's linear model, reporting its squared error as a metric no built-in reward has; one
    batch-mean value a step into the normaliser's history."""

    about: ClassVar[intrinsic.About] = TOY

    def step(self, params, untrained, s, a, s_next, key):
        out = super().step(params, untrained, s, a, s_next, key)
        return out._replace(metrics={"toy_energy": out.raw.mean()}, history=out.raw.mean()[None])


@pytest.fixture
def toy(monkeypatch):
    monkeypatch.setattr(intrinsic, "_REGISTRY", dict(intrinsic._REGISTRY))  # undone after the test
    intrinsic.register("toy", Toy)
    return "toy"


def _cfg(**extra):
    return resolve_config("fetchreach-sac", {"hidden_sizes": [64, 64], "intrinsic_hidden_sizes": [64, 64],
                                             "batch_size": 64, "buffer_size": 5000, "learning_starts": 100,
                                             "eval_episodes": 2, "total_steps": 300, "eval_every": 150,
                                             "log_every": 50, "checkpoint_every": 200, "keep_checkpoints": 5,
                                             **extra})


def test_the_config_reads_a_reward_from_its_about(toy):
    """The normaliser's window is counted in the values the reward's `About` says a step adds; a key of MC's,
    given for another reward, is one line naming the key, its reward and the fix."""
    cfg = _cfg(intrinsic=toy, intrinsic_alpha=0.2, intrinsic_history=40)
    assert cfg.intrinsic_values_per_step == 1 and cfg.intrinsic_history_values == 40
    assert _cfg(intrinsic_alpha=0.2, intrinsic_history=40).intrinsic_history_values == 40 * 64  # MC: the batch
    assert intrinsic.about(toy) is TOY and intrinsic.about("rnd") is intrinsic.ABOUT["rnd"]
    assert intrinsic.about("gone").algorithm == "SAC+gone"  # a foreign run's reward: named, not an error
    with pytest.raises(MCRLError) as e:
        _cfg(intrinsic=toy, intrinsic_alpha=0.2, mc_reduction="batch")
    msg = str(e.value)
    assert len(msg.splitlines()) == 1 and "mc_reduction=batch" in msg and "intrinsic=mc" in msg
    assert "intrinsic=toy" in msg and "mc_reduction=transition" in msg
    assert _cfg(intrinsic_alpha=0.2, mc_reduction="batch").intrinsic_values_per_step == 1  # MC's own key, for MC


@pytest.mark.slow
def test_a_rewards_own_column_reaches_metrics_csv_the_report_the_plot_and_the_video(toy, tmp_path, monkeypatch):
    import mcrl.analysis.plots as plots
    import mcrl.analysis.reward_curves as reward_curves
    from mcrl.analysis.report import write_report
    from mcrl.run.policy import load_policy
    from mcrl.run.trainer import resume, train
    from mcrl.video.render import intrinsic_timeline
    from mcrl.video.timeline import Timeline

    exp = tmp_path / "exp"
    sac = train(_cfg(), exp / "runs" / "sac", progress=False)
    run = train(_cfg(intrinsic=toy, intrinsic_alpha=0.2), tmp_path / "toy", progress=False)

    # metrics.csv: every built-in reward's columns, then the toy's own, filled on every row after learning starts
    header = (run / "metrics.csv").read_text().splitlines()[0].split(",")
    assert tuple(header) == rundir.METRIC_COLUMNS + ("toy_energy",)
    assert (sac / "metrics.csv").read_text().splitlines()[0].split(",") == list(rundir.METRIC_COLUMNS)
    rows = rundir.read_rows(run / "metrics.csv")
    learnt = [r for r in rows if r["actor_loss"] is not None]  # rows after a gradient step
    assert len(rows) == 6 and len(learnt) >= 3 and all(r["toy_energy"] > 0 for r in learnt)
    assert all(r["mean_raw_intrinsic"] is None and r["mean_raw_kl"] is None for r in rows)
    assert -1.0 <= rows[-1]["mean_intrinsic_reward"] <= 0.0

    # a resume from the step-200 checkpoint (its sum of toy_energy included) writes the same rows
    part = tmp_path / "part"
    shutil.copytree(run, part)
    shutil.rmtree(part / "checkpoints" / rundir.checkpoint_name(300))
    rundir.write_latest(part, rundir.checkpoint_name(200))
    for name in (rundir.DONE, rundir.FINAL_EVAL):
        (part / name).unlink()
    resume(part, progress=False)
    learning = [c for c in header if c not in rundir.TIMING_COLUMNS]
    assert ([{k: r[k] for k in learning} for r in rundir.read_rows(part / "metrics.csv")]
            == [{k: r[k] for k in learning} for r in rows])

    # the report: the arm is named by the reward's algorithm, its raw value read from its own column
    (exp / "sweep.json").write_text(json.dumps({"preset": "fetchreach-sac", "runs": [
        {"name": "sac", "config_key": "fetchreach-sac", "seed": 0, "overrides": {}}]}))
    drawn: list[tuple[str, list[str]]] = []

    def record(ax, steps, curves, **kw):
        drawn.append((kw.get("title", ""), list(curves)))
        return draw(ax, steps, curves, **kw)

    draw = plots.plot_curves_with_band
    monkeypatch.setattr(reward_curves, "plot_curves_with_band", record)
    md = write_report(exp, tmp_path / "report", extra_runs=[run], claims=False).read_text()
    assert "`SAC+Toy 0.2`" in md and "`SAC`" in md
    section = _section(md, "Intrinsic reward and raw value during training")
    assert "Toy: raw toy energy (`toy_energy`)" in section and "MC" not in section
    assert _row(section, "`SAC+Toy 0.2`")[2:] == ["toy", f"{rows[-1]['mean_intrinsic_reward']:.4f}",
                                                  f"{rows[-1]['toy_energy']:.4f}"]
    assert ("Toy: mean raw toy energy", ["SAC+Toy 0.2"]) in drawn
    assert (tmp_path / "report" / "intrinsic_reward.png").stat().st_size > 1000

    # `mcrl plot`: the toy's panels, by its title and raw label
    drawn.clear()
    monkeypatch.setattr(plots, "plot_curves_with_band", record)
    plots.plot_run(run, tmp_path / "curves.png")
    assert {"mean Toy reward (replay batches)", "raw toy energy (Toy)"} <= {t for t, _ in drawn}
    assert ("raw toy energy (Toy)", ["raw toy energy"]) in drawn

    # the video's timeline: the toy's rows, by its raw label and title
    cfg, agent, state = load_policy(run)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(21, agent.obs_dim)).astype(np.float32)
    series = intrinsic_timeline(cfg, agent, state, obs, rng.uniform(-1, 1, (20, agent.act_dim)).astype(np.float32))
    assert list(series) == ["raw toy energy", "Toy reward (normalised)"]
    boxes = {text for text, _ in Timeline({**series, "extrinsic reward": -np.ones(20)}, None, 480).text_boxes()}
    assert {"raw toy energy", "Toy reward (normalised)"} <= boxes
