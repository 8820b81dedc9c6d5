"""mcrl.report and mcrl.plots on a synthetic experiment directory (fake CSVs, no training)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from mcrl.errors import MCRLError
from mcrl.logger import EVAL_COLUMNS, METRIC_COLUMNS
from mcrl.plots import plot_run
from mcrl.report import THESIS_RESULTS, thesis_experiment, write_report

TOTAL = 1000
# Final eval per seed. SAC: success 0.2/0.4/0.6 (mean 0.4, sample var 0.04), return -40/-30/-20 (mean -30).
# SAC-MC 0.2: success 0.6/0.8/1.0 (mean 0.8, var 0.04), return -20/-10/0 (mean -10).
FINALS = {"alpha=0": [(0.2, -40.0), (0.4, -30.0), (0.6, -20.0)],
          "alpha=0.2": [(0.6, -20.0), (0.8, -10.0), (1.0, 0.0)]}


def _write_csv(path: Path, columns: tuple[str, ...], rows: list[dict]) -> None:
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns)
        w.writeheader()
        w.writerows([{k: r.get(k, "") for k in columns} for r in rows])


def _write_run(run_dir: Path, alpha: float, seed: int, final: tuple[float, float], upto: int = TOTAL,
               done: bool = True) -> None:
    run_dir.mkdir(parents=True)
    (run_dir / "config.json").write_text(json.dumps(
        {"preset": "fetchpush-test", "mc_alpha": alpha, "seed": seed, "total_steps": TOTAL, "env_id": "FetchPush-v4"}))
    evals = [{"step": s, "success_rate": final[0] * s / TOTAL, "mean_return": -50 + (final[1] + 50) * s / TOTAL,
              "episodes": 10} for s in range(0, upto + 1, 250)]
    _write_csv(run_dir / "eval.csv", EVAL_COLUMNS, evals)
    rng = np.random.default_rng(seed)
    metrics = []
    for s in range(100, upto + 1, 100):
        row = {"step": s, "actor_loss": -s / 100 + rng.normal(), "critic_loss": 1 + rng.random(),
               "ent_coef": 0.1 * np.exp(-s / 500), "train_return": -45 + s / 100, "train_success_rate": s / 2000}
        if alpha > 0:  # MC columns stay empty for SAC runs, as the logger writes them
            row.update(transition_model_loss=-s / 200, action_model_loss=-s / 300, mean_mc_reward=-0.5 + s / 4000,
                       mean_raw_kl=0.1 + s / 1000)
        metrics.append(row)
    _write_csv(run_dir / "metrics.csv", METRIC_COLUMNS, metrics)
    if done:
        (run_dir / "done").write_text("")


@pytest.fixture
def experiment(tmp_path: Path) -> Path:
    """Three finished seeds each of SAC and SAC-MC 0.2, one SAC seed unfinished, one SAC-MC seed never started."""
    exp = tmp_path / "exp"
    runs = []
    for key, alpha in (("alpha=0", 0.0), ("alpha=0.2", 0.2)):
        for seed, final in enumerate(FINALS[key]):
            name = f"a{alpha:g}-s{seed}"
            _write_run(exp / "runs" / name, alpha, seed, final)
            runs.append({"name": name, "config_key": key, "seed": seed, "overrides": {"mc_alpha": alpha}})
    _write_run(exp / "runs" / "a0-s3", 0.0, 3, (0.9, -5.0), upto=500, done=False)
    runs.append({"name": "a0-s3", "config_key": "alpha=0", "seed": 3, "overrides": {"mc_alpha": 0.0}})
    runs.append({"name": "a0.2-s3", "config_key": "alpha=0.2", "seed": 3, "overrides": {"mc_alpha": 0.2}})
    (exp / "sweep.json").write_text(json.dumps({"preset": "fetchpush-test", "runs": runs}))
    return exp


def _section(text: str, heading: str) -> str:
    """The Markdown of one '## heading' section."""
    start = text.index(f"## {heading}")
    end = text.find("\n## ", start + 1)
    return text[start:end if end > 0 else None]


def _row(section: str, first_cell: str) -> list[str]:
    line = next(ln for ln in section.splitlines() if ln.startswith(f"| {first_cell}"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_markdown_report_values(experiment: Path, tmp_path: Path) -> None:
    out = write_report(experiment, tmp_path / "rep")
    assert out == tmp_path / "rep" / "report.md"
    md = out.read_text()
    for png in ("learning_curves.png", "mc_reward_kl.png"):
        assert f"]({png})" in md and (tmp_path / "rep" / png).stat().st_size > 1000

    final = _section(md, "Final performance per configuration")
    sac, mc = _row(final, "`alpha=0`"), _row(final, "`alpha=0.2`")
    assert sac[2] == "3 / 4" and mc[2] == "3 / 4"  # the unfinished and the missing seed are left out
    assert sac[4].startswith("0.400 [") and sac[5] == "0.0400" and sac[6].startswith("-30.00 [")
    assert mc[4].startswith("0.800 [") and mc[5] == "0.0400" and mc[6].startswith("-10.00 [")

    robust = _section(md, "IQM and probability of improvement")
    assert _row(robust, "`alpha=0`")[2].startswith("0.400 [")  # 3 seeds: IQM = mean
    poi = _row(robust, "`alpha=0.2` > `alpha=0`")
    assert poi[2].startswith("0.944 [")  # 8 wins + 1 tie of 9 pairs
    assert poi[4].startswith("0.944 [")  # returns: -20 vs -20 is the one tie

    thesis = _section(md, "Comparison with the thesis (FetchPush)")
    assert "Not like-for-like" in thesis and "1,000" in thesis and "150,000" in thesis
    assert _row(thesis, "SAC (`alpha=0`)")[1] == "0.52"
    assert _row(thesis, "SAC-MC alpha=0.2 (`alpha=0.2`)")[5] == "-23.0"
    assert "SAC (`alpha=0`) mean return: the thesis' -31.3 lies inside our 95% CI" in thesis
    # All three SAC-MC returns are above -23, so every bootstrap mean is too.
    assert "SAC-MC alpha=0.2 (`alpha=0.2`) mean return: the thesis' -23.0 lies below our 95% CI" in thesis
    assert "P(`alpha=0.2` > `alpha=0`) = 0.944 [" in thesis and "the claim is supported" in thesis

    mcs = _section(md, "MC reward and raw KL during training")
    assert _row(mcs, "`alpha=0.2`")[2:] == ["-0.2500", "1.1000"]  # last logged values at step 1000
    assert "`alpha=0`" not in mcs.split("|", 1)[1]  # SAC has no MC data

    missing = _section(md, "Missing and unfinished runs")
    assert "2 of 8 runs" in missing
    gone = _row(missing, "`a0.2-s3`")
    assert "missing (no run directory)" in gone[3] and gone[4] == "- / 1,000"  # budget from its config's runs
    partial = _row(missing, "`a0-s3`")
    assert "unfinished" in partial[3] and partial[4] == "500 / 1,000"
    assert "runs finished: 6 of 8" in md


def test_report_is_deterministic(experiment: Path, tmp_path: Path) -> None:
    a = write_report(experiment, tmp_path / "a").read_text()
    b = write_report(experiment, tmp_path / "b").read_text()
    assert a == b


def test_html_report_is_self_contained(experiment: Path, tmp_path: Path) -> None:
    out = write_report(experiment, tmp_path / "html", fmt="html")
    assert [p.name for p in (tmp_path / "html").iterdir()] == ["report.html"]
    text = out.read_text()
    assert text.count("data:image/png;base64,") == 2
    assert "<td><code>alpha=0.2</code> &gt; <code>alpha=0</code></td>" in text
    assert "Missing and unfinished runs" in text


def test_default_out_dir_and_no_baseline(tmp_path: Path) -> None:
    exp = tmp_path / "only-mc"
    _write_run(exp / "runs" / "r0", 0.4, 0, (0.5, -25.0))
    (exp / "sweep.json").write_text(json.dumps(
        {"preset": "custom", "runs": [{"name": "r0", "config_key": "alpha=0.4", "seed": 0, "overrides": {}}]}))
    md = write_report(exp).read_text()
    assert (exp / "report" / "report.md").is_file()
    assert "not computed, the sweep has no finished SAC configuration" in md
    assert "Comparison with the thesis" not in md  # preset 'custom' matches no thesis experiment
    assert "None: all 1 runs finished." in md


@pytest.mark.parametrize("make", ["missing", "empty", "no-runs", "no-evals"])
def test_errors_name_the_fix(tmp_path: Path, make: str) -> None:
    exp = tmp_path / "exp"
    if make != "missing":
        exp.mkdir()
    if make == "no-runs":
        (exp / "sweep.json").write_text(json.dumps({"preset": "x", "runs": []}))
    if make == "no-evals":
        (exp / "sweep.json").write_text(json.dumps({"preset": "x", "runs": [{"name": "r", "config_key": "k", "seed": 0}]}))
    with pytest.raises(MCRLError) as e:
        write_report(exp)
    msg = str(e.value)
    assert "\n" not in msg and str(exp) in msg and ":" in msg


def test_thesis_numbers_and_matching() -> None:
    assert thesis_experiment("fetchpush-sacmc") == "FetchPush"
    assert thesis_experiment("AntMaze-dense") == "AntMaze"
    assert thesis_experiment("fetchreach-sac") is None
    fp, am = THESIS_RESULTS["FetchPush"], THESIS_RESULTS["AntMaze"]
    assert (fp["total_steps"], fp["seeds"], am["total_steps"], am["seeds"]) == (150_000, 6, 400_000, 4)
    assert fp["by_alpha"][0.2] == {"success_mean": 0.75, "success_var": 0.2, "mean_reward": -23.0}
    assert am["by_alpha"][0.0] == {"success_mean": 0.38, "success_var": 0.14, "mean_reward": 155.3}


def test_plot_run_writes_a_real_png(experiment: Path, tmp_path: Path) -> None:
    for name in ("a0.2-s1", "a0-s3"):  # an SAC-MC run, and an unfinished SAC run without MC columns
        out = plot_run(experiment / "runs" / name, tmp_path / f"{name}.png")
        assert out.stat().st_size > 1000
        img = imread(out)
        assert img.ndim == 3 and float(img[..., :3].std()) > 0.01  # not a single colour
    assert plot_run(experiment / "runs" / "a0-s0") == experiment / "runs" / "a0-s0" / "curves.png"
    with pytest.raises(MCRLError):
        plot_run(tmp_path / "nope")
