"""mcrl.analysis (experiment loading, report, plots) on a synthetic experiment directory (fake CSVs, no training)."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from mcrl.analysis.experiment import load_experiment
from mcrl.analysis.plots import plot_run
from mcrl.analysis.report import write_report
from mcrl.analysis.stats import (MIN_SEEDS_FOR_VERDICT, minimum_detectable_difference, probability_of_improvement,
                                 seeds_to_detect)
from mcrl.analysis.thesis import THESIS_RESULTS, thesis_experiment
from mcrl.cli import main
from mcrl.errors import MCRLError
from mcrl.run.logger import EVAL_COLUMNS, METRIC_COLUMNS

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
               done: bool = True, config: dict | None = None, final_eval: dict | None = None,
               peer: dict | None = None) -> None:
    """A fake run directory; ``config`` adds config.json keys, ``final_eval``/``peer`` write those files."""
    run_dir.mkdir(parents=True)
    (run_dir / "config.json").write_text(json.dumps(
        {"preset": "fetchpush-test", "mc_alpha": alpha, "seed": seed, "total_steps": TOTAL, "env_id": "FetchPush-v4",
         **(config or {})}))
    if final_eval is not None:
        (run_dir / "final_eval.json").write_text(json.dumps(final_eval))
    if peer is not None:
        (run_dir / "peer.json").write_text(json.dumps(peer))
    evals = [{"step": s, "success_rate": final[0] * s / TOTAL, "mean_return": -50 + (final[1] + 50) * s / TOTAL,
              "episodes": 10} for s in range(0, upto + 1, 250)]
    _write_csv(run_dir / "eval.csv", EVAL_COLUMNS, evals)
    rng = np.random.default_rng(seed)
    metrics = []
    for s in range(100, upto + 1, 100):
        row = {"step": s, "actor_loss": -s / 100 + rng.normal(), "critic_loss": 1 + rng.random(),
               "ent_coef": 0.1 * np.exp(-s / 500), "train_return": -45 + s / 100, "train_success_rate": s / 2000}
        if alpha > 0:  # MC columns stay empty for SAC runs, as the logger writes them
            row.update(transition_model_loss=-s / 200, action_model_loss=-s / 300,
                       mean_intrinsic_reward=-0.5 + s / 4000, mean_raw_kl=0.1 + s / 1000)
        metrics.append(row)
    _write_csv(run_dir / "metrics.csv", METRIC_COLUMNS, metrics)
    if done:
        (run_dir / "done").write_text("")


def _sweep(exp: Path, arms: dict[str, tuple[float, dict, list[float]]]) -> Path:
    """A sweep of fake runs: per arm key, (alpha, config.json keys, finals of seeds 0, 1, ...)."""
    runs = []
    for key, (alpha, config, finals) in arms.items():
        for seed, s in enumerate(finals):
            name = f"{key}-s{seed}"
            _write_run(exp / "runs" / name, alpha, seed, (s, -50 * (1 - s)), config=config)
            runs.append({"name": name, "config_key": key, "seed": seed})
    (exp / "sweep.json").write_text(json.dumps({"preset": "fetchpush-test", "runs": runs}))
    return exp


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
    # 3 vs 3 seeds with a tie at 0.6: the exact one-sided p is 2/20, so no verdict; the power is stated
    assert ("**Not decidable with this many seeds**: the thesis' claim that SAC-MC alpha=0.2 reaches a higher final "
            "success rate than SAC (thesis: +0.23), X = `alpha=0.2`, Y = mcrl SAC `alpha=0`, 3 vs 3 seeds: one-sided "
            "exact rank-sum test of X > Y: p = 0.1000 (the only claim against this baseline, so unadjusted: "
            "0.1000)") in thesis
    assert "Effect sizes: P(X > Y) = 0.944 [" in thesis and "Power of these seeds to detect the thesis' +0.23: " in thesis
    # the second claim has no arm here: it is named, with no verdict
    assert ("**Not decidable with this many seeds**: the thesis' claim that the thesis' code's variant of SAC-MC "
            "alpha=0.2 (one batch-mean KL, the whole observation) reaches a higher final success rate than SAC "
            "(thesis: +0.23): this report has no finished run of the thesis' code's variant") in thesis
    assert "0 seeds (add its experiment with `--with DIR`)." in thesis

    mcs = _section(md, "MC reward and raw KL during training")
    assert _row(mcs, "`alpha=0.2`")[2:] == ["mc", "-0.2500", "1.1000"]  # last logged values at step 1000
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
    assert text.count("data:image/png;base64,") == 4  # learning curves, alpha curve, critics, MC reward
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
    # the table of the runs' environment family (mcrl.envs.FAMILIES), for presets named after it
    assert thesis_experiment("fetchpush-sacmc", ["FetchPush-v4"]) == "FetchPush"
    assert thesis_experiment("fetchpush-sac") == "FetchPush"  # no runs yet: the preset's own environment
    assert thesis_experiment("AntMaze-dense", ["AntMaze_UMazeDense-v5"]) == "AntMaze"
    assert thesis_experiment("fetchreach-sac") is None
    assert thesis_experiment("fetchpush-sac", ["FetchReach-v4"]) is None  # a thesis preset on another task
    assert thesis_experiment("custom", ["FetchPush-v4"]) is None
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


def test_band_only_where_enough_seeds_have_the_point() -> None:
    """A bootstrap band over two seeds is their range: the band is shaded only where >= 3 seeds have
    the point, and elsewhere the seeds' own curves are drawn thin."""
    from matplotlib.collections import PolyCollection
    from matplotlib.figure import Figure as MplFigure

    from mcrl.analysis.plots import plot_curves_with_band

    x = np.arange(5.0)
    rng = np.random.default_rng(0)

    def draw(curves: np.ndarray):
        ax = MplFigure().add_subplot()
        plot_curves_with_band(ax, x, {"arm": curves})
        bands = [c for c in ax.collections if isinstance(c, PolyCollection)]
        return bands, ax.lines

    bands, lines = draw(rng.random((2, 5)))  # two seeds: no band, mean + both seeds
    assert bands == [] and len(lines) == 3
    assert lines[0].get_label() == "arm (n=2)" and lines[1].get_linewidth() < lines[0].get_linewidth()

    bands, lines = draw(rng.random((3, 5)))  # three seeds everywhere: band, mean only
    assert len(bands) == 1 and len(lines) == 1

    partial = rng.random((3, 5))
    partial[2, 3:] = np.nan  # the third seed stopped early: band up to x = 2, seeds' curves after
    bands, lines = draw(partial)
    assert len(bands) == 1 and len(lines) == 4
    band_x = bands[0].get_paths()[0].vertices[:, 0]
    assert band_x.max() <= 2.0 + 1e-9
    thin = lines[1].get_ydata()
    assert np.isnan(thin[:3]).all() and np.allclose(thin[3:], partial[0, 3:])


# ------------------------------------------------------------------ verdicts need enough seeds

VERDICT_WORDS = ("better", "worse", "supported", "contradicted", "**reproduced**", "**not reproduced**")


def _experiment(exp: Path, finals: dict[float, list[tuple[float, float]]], preset: str = "fetchpush-test",
                **run_kwargs) -> Path:
    """An experiment of finished runs: {mc_alpha: [(final success, final return) per seed]}."""
    runs = []
    for alpha, per_seed in finals.items():
        for seed, final in enumerate(per_seed):
            name = f"a{alpha:g}-s{seed}"
            _write_run(exp / "runs" / name, alpha, seed, final, **run_kwargs)
            runs.append({"name": name, "config_key": f"alpha={alpha:g}", "seed": seed, "overrides": {"mc_alpha": alpha}})
    (exp / "sweep.json").write_text(json.dumps({"preset": preset, "runs": runs}))
    return exp


@pytest.mark.parametrize("n_seeds", [1, 2])
def test_no_verdict_from_too_few_seeds(tmp_path: Path, n_seeds: int) -> None:
    sac = [(0.9, -10.0), (0.8, -12.0)][:n_seeds]
    mc = [(0.1, -40.0), (0.2, -38.0)][:n_seeds]
    exp = _experiment(tmp_path / "exp", {0.0: sac, 0.2: mc})
    # Without the rule the bootstrap would read "worse than SAC": every resample gives P = 0.
    assert probability_of_improvement([s for s, _ in mc], [s for s, _ in sac]) == (0.0, 0.0, 0.0)
    md = write_report(exp, tmp_path / "rep").read_text()
    for line in md.splitlines():
        assert not any(w in line.lower() for w in VERDICT_WORDS), line
    few = f"too few seeds for a verdict: n = {n_seeds} vs {n_seeds}, need >= {MIN_SEEDS_FOR_VERDICT}"
    poi = _row(_section(md, "IQM and probability of improvement"), "`alpha=0.2` > `alpha=0`")
    assert poi[3] == few and poi[5] == few
    assert poi[2] == f"0.000 (no CI from {n_seeds} seed{'s' if n_seeds > 1 else ''}, need >= 3)"
    thesis = _section(md, "Comparison with the thesis (FetchPush)")
    assert (f"**Not decidable with this many seeds**: the thesis' claim that SAC-MC alpha=0.2 reaches a higher final "
            f"success rate than SAC (thesis: +0.23), X = `alpha=0.2`, Y = mcrl SAC `alpha=0`, {n_seeds} vs {n_seeds} "
            f"seeds: fewer than the {MIN_SEEDS_FOR_VERDICT} seeds per arm a verdict needs.") in thesis
    assert f"SAC (`alpha=0`) success rate: too few seeds for a verdict: n = {n_seeds}, need >= 3" in thesis
    # no interval either: a bootstrap over two seeds is just their range
    final = _row(_section(md, "Final performance per configuration"), "`alpha=0`")
    plural = "s" if n_seeds > 1 else ""
    assert final[4] == f"{np.mean([s for s, _ in sac]):.3f} (no CI from {n_seeds} seed{plural}, need >= 3)"
    assert "[" not in final[6]
    assert _row(_section(md, "How large a difference can these seeds detect"), "`alpha=0.2` vs `alpha=0`")[5] == few
    assert f"at least {MIN_SEEDS_FOR_VERDICT} finished seeds" in md  # the rule is stated in the overview


def test_clear_difference_with_enough_seeds_gives_a_verdict(tmp_path: Path) -> None:
    sac = [(0.1, -45.0), (0.2, -40.0), (0.3, -35.0)]
    mc = [(0.7, -20.0), (0.8, -15.0), (0.9, -10.0)]
    md = write_report(_experiment(tmp_path / "exp", {0.0: sac, 0.2: mc}), tmp_path / "rep").read_text()
    poi = _row(_section(md, "IQM and probability of improvement"), "`alpha=0.2` > `alpha=0`")
    # 3 vs 3 fully separated: the one-sided claim test reaches p = 1/20 = 0.05, a two-sided reading cannot (0.1)
    assert poi[2].startswith("1.000 [1.000, 1.000]") and poi[3] == "no clear difference (adjusted p = 0.1000)"
    assert "**Reproduced**: the thesis' claim that SAC-MC alpha=0.2" in md and "p = 0.0500" in md
    assert "too few seeds" not in md.split("## Learning")[1].split("## Provenance and method")[0]
    # at the verdict's test, the claim's one-sided one at 0.05 (the only claim against SAC):
    # MDE = (z_.95 + z_.8) * sqrt(0.01/3 + 0.01/3); seeds to detect 0.6: 2.4865^2 * 0.02 / 0.36 -> 2
    mde = _row(_section(md, "How large a difference can these seeds detect"), "`alpha=0.2` vs `alpha=0`")
    assert mde[1:] == ["3 / 3", "0.100 / 0.100", "0.600", "one-sided X > Y, 0.05", "0.203", "2"]
    # with 5 seeds each the two-sided reading finds it too (p = 2/252)
    sac5, mc5 = sac + [(0.15, -44.0), (0.25, -38.0)], mc + [(0.75, -18.0), (0.85, -12.0)]
    md = write_report(_experiment(tmp_path / "exp5", {0.0: sac5, 0.2: mc5}), tmp_path / "rep5").read_text()
    poi = _row(_section(md, "IQM and probability of improvement"), "`alpha=0.2` > `alpha=0`")
    assert poi[3] == "better than SAC (adjusted p = 0.0079)" and poi[5] == poi[3]


def test_detectable_difference_is_at_the_verdicts_test_and_level(tmp_path: Path) -> None:
    """Three claims against SAC (0.2 above, 0.4 about the same, 0.8 below): each comparison's MDE and seeds are at
    the test its verdict uses, at Holm's first level 0.05 / 3 (not two-sided at 0.05), and the table says which."""
    sac = [0.10, 0.25, 0.30, 0.45, 0.50, 0.62]
    arms = {0.0: sac, 0.2: [s + 0.2 for s in sac], 0.4: [s + 0.03 for s in sac], 0.8: [s - 0.08 for s in sac]}
    exp = _experiment(tmp_path / "exp", {a: [(round(s, 2), -50 * (1 - s)) for s in v] for a, v in arms.items()})
    sec = _section(write_report(exp, tmp_path / "rep").read_text(), "How large a difference can these seeds detect")
    y = np.array([round(s, 2) for s in sac])
    tests = {0.2: ("one-sided X > Y", "one-sided"), 0.4: ("two-sided (of 'about the same')", "two-sided"),
             0.8: ("one-sided X < Y", "one-sided")}
    for alpha, (test, sides) in tests.items():
        x = np.array([round(s, 2) for s in arms[alpha]])
        row = _row(sec, f"`alpha={alpha:g}` vs `alpha=0`")
        assert row[4] == f"{test}, 0.0167 = 0.05 / 3"
        assert row[5] == f"{minimum_detectable_difference(x, y, 0.05 / 3, 0.8, sides):.3f}"
        assert row[6] == str(seeds_to_detect(x, y, x.mean() - y.mean(), 0.05 / 3, 0.8, sides))
        assert row[5] != f"{minimum_detectable_difference(x, y):.3f}"  # not the unadjusted two-sided one
    assert "'test, level'" in sec and "z_(1-a) + z_0.8" in sec


# ------------------------------------------------------------------ final_eval.json, per-seed table


def test_final_numbers_prefer_final_eval_json(tmp_path: Path) -> None:
    exp = tmp_path / "exp"
    fe = {0: {"step": TOTAL, "success_rate": 0.5, "mean_return": -25.0, "episodes": 100},
          1: {"step": TOTAL, "success_rate": 0.7, "mean_return": -15.0, "episodes": 100}}
    runs = []
    for seed in range(3):  # seed 2 has no final_eval.json: its last eval.csv row (10 episodes) is used
        _write_run(exp / "runs" / f"s{seed}", 0.0, seed, (0.1, -45.0), final_eval=fe.get(seed))
        runs.append({"name": f"s{seed}", "config_key": "alpha=0", "seed": seed})
    # unfinished (no done): its final_eval.json does not make it finished
    _write_run(exp / "runs" / "s3", 0.0, 3, (0.9, -5.0), done=False, final_eval=fe[0])
    runs.append({"name": "s3", "config_key": "alpha=0", "seed": 3})
    (exp / "sweep.json").write_text(json.dumps({"preset": "custom", "runs": runs}))
    loaded = load_experiment(exp)
    assert [r.final for r in loaded.runs] == [(0.5, -25.0), (0.7, -15.0), (0.1, -45.0), None]
    assert [r.final_source for r in loaded.runs[:3]] == [("final_eval.json", 100)] * 2 + [("eval.csv", 10)]

    md = write_report(exp, tmp_path / "rep").read_text()
    final = _row(_section(md, "Final performance per configuration"), "`alpha=0`")
    assert final[2] == "3 / 4" and final[4].startswith("0.433 [") and final[6].startswith("-28.33 [")
    assert final[7] == "final_eval.json, 100 episodes (2); last eval.csv row, 10 episodes (1)"
    per_seed = _section(md, "Final performance per seed")
    assert _row(per_seed, "`alpha=0` | 0")[2:] == ["`s0`", "0.500", "-25.00", "final_eval.json, 100 episodes"]
    assert _row(per_seed, "`alpha=0` | 2")[2:] == ["`s2`", "0.100", "-45.00", "last eval.csv row, 10 episodes"]
    assert _row(per_seed, "`alpha=0` | 3")[2:] == ["`s3`", "unfinished", "-", "-"]


# ------------------------------------------------------------------ grouping, reference arms, provenance


def test_groups_differ_by_every_setting(tmp_path: Path) -> None:
    exp = tmp_path / "exp"
    runs = []
    variants = {"sac": (0.0, {}), "mc": (0.2, {}), "mc-full": (0.2, {"mc_reduction": "batch", "mc_state": "full"})}
    for seed in range(2):
        for tag, (alpha, extra) in variants.items():
            name = f"{tag}-s{seed}"
            # out_dir and video_every only place or record a run: they must not split a configuration
            _write_run(exp / "runs" / name, alpha, seed, (0.5, -25.0),
                       config={**extra, "out_dir": f"/elsewhere/{seed}", "video_every": seed * 100})
            # sweep.json's labels do not tell mc from mc-full apart
            runs.append({"name": name, "config_key": f"alpha={alpha:g}", "seed": seed})
    # never started: they join by sweep label, or by their overrides where the label spans two groups
    runs.append({"name": "sac-s2", "config_key": "alpha=0", "seed": 2})
    runs.append({"name": "mc-full-s2", "config_key": "alpha=0.2", "seed": 2,
                 "overrides": {"mc_alpha": 0.2, "mc_reduction": "batch", "mc_state": "full", "seed": 2}})
    (exp / "sweep.json").write_text(json.dumps({"preset": "custom", "runs": runs}))
    groups = {g.key: [r.name for r in g.runs] for g in load_experiment(exp).configs}
    assert groups == {
        "intrinsic_alpha=0, intrinsic_state=observation, mc_reduction=transition": ["sac-s0", "sac-s1", "sac-s2"],
        "intrinsic_alpha=0.2, intrinsic_state=full, mc_reduction=batch": ["mc-full-s0", "mc-full-s1", "mc-full-s2"],
        "intrinsic_alpha=0.2, intrinsic_state=observation, mc_reduction=transition": ["mc-s0", "mc-s1"],
    }


@pytest.mark.parametrize("layout", ["flat", "runs"])
def test_reference_arms_and_provenance(tmp_path: Path, capsys: pytest.CaptureFixture[str], layout: str) -> None:
    exp = _experiment(tmp_path / "exp", {0.0: FINALS["alpha=0"], 0.2: FINALS["alpha=0.2"]})
    sb3 = {"system": "stable-baselines3", "version": "2.9.2"}
    # Same config as mcrl's SAC runs: one peer run inside EXP/runs (not in sweep.json), two elsewhere, either
    # directly in --with's directory or in its runs/ (the layout of docs/reproduction/fetchpush/sb3-sac).
    _write_run(exp / "runs" / "sb3-s0", 0.0, 0, (0.5, -25.0), peer=sb3, done=False,
               final_eval={"step": TOTAL, "success_rate": 0.55, "mean_return": -24.0, "episodes": 100})
    peers = tmp_path / "peers"
    for seed in (1, 2):
        _write_run(peers / ("runs" if layout == "runs" else "") / f"sb3-s{seed}", 0.0, seed, (0.5, -25.0), peer=sb3)
    (exp / "provenance.json").write_text(json.dumps(
        {"commit": "0123abc", "machine": "1x H100", "command": "mcrl sweep --file push.yaml --exp EXP",
         "rerun_one_seed": "mcrl train --preset fetchpush-sac --seed 3"}))

    (peers / "provenance.json").write_text(json.dumps(
        {"commit": "4567def", "machine": "A (runs sb3-s1); B (runs sb3-s2)", "machines": {"sb3-s1": "A", "sb3-s2": "B"}}))

    loaded = load_experiment(exp, extra_runs=[peers])
    assert [(g.key, g.peer, len(g.finished)) for g in loaded.configs] == [
        ("alpha=0", None, 3), ("alpha=0.2", None, 3), ("stable-baselines3 SAC", "stable-baselines3 2.9.2", 3)]

    rc = main(["report", str(exp), "--with", str(peers), "--out", str(tmp_path / "rep")])
    assert rc == 0, capsys.readouterr().err
    md = (tmp_path / "rep" / "report.md").read_text()
    # the answer first, how it was made last
    assert md.index("## Verdicts") < md.index("## Learning curves") < md.index("## Provenance and method") \
        < md.index("**Provenance**")
    for text in ("code commit: `0123abc`", "machine: `1x H100`", "command: `mcrl sweep --file push.yaml --exp EXP`",
                 "re-run one seed: `mcrl train --preset fetchpush-sac --seed 3`",
                 f"**Provenance of `peers`** (from `{peers / 'provenance.json'}`):", "code commit: `4567def`",
                 "machine: `A (runs sb3-s1); B (runs sb3-s2)`"):
        assert text in md
    assert "- machines:" not in md and "sb3-s1': 'A" not in md  # the per-run map is what "machine" summarises
    assert "Dashed: reference arms" in md
    final = _row(_section(md, "Final performance per configuration"), "`stable-baselines3 SAC` (reference)")
    assert final[2] == "3 / 3" and final[4].startswith("0.517 [")  # (0.55 + 0.5 + 0.5) / 3
    assert _row(_section(md, "Final performance per configuration"), "`alpha=0`")[2] == "3 / 3"  # not merged
    per_seed = _section(md, "Final performance per seed")
    assert _row(per_seed, "`stable-baselines3 SAC` (reference) | 0")[2:4] == ["`sb3-s0`", "0.550"]
    assert _row(per_seed, "`stable-baselines3 SAC` (reference) | 2")[2] == "`peers/sb3-s2`"
    assert _row(_section(md, "IQM and probability of improvement"), "`alpha=0` > `stable-baselines3 SAC`")
    assert _row(_section(md, "Comparison with the thesis (FetchPush)"), "SAC, reference (`stable-baselines3 SAC`)")


def test_provenance_counts_every_resume_from_the_runs(tmp_path: Path) -> None:
    """Each resume a reference run's peer.json records (`resumed_at`, one step per resume) is in the provenance of
    its directory, counted, whatever provenance.json's own text says."""
    exp = _experiment(tmp_path / "exp", {0.0: FINALS["alpha=0"], 0.2: FINALS["alpha=0.2"]})
    peers = tmp_path / "peers"
    resumed = {0: [110_000], 1: [], 3: [20_000, 20_000, 60_000], 6: [30_000]}
    for seed, steps in resumed.items():
        peer = {"system": "stable-baselines3", "version": "2.9.2", **({"resumed_at": steps} if steps else {})}
        _write_run(peers / "runs" / f"sb3-s{seed}", 0.0, seed, (0.5, -25.0), peer=peer)
    (peers / "provenance.json").write_text(json.dumps({"commit": "4567def", "command": "runner --seed N"}))
    md = write_report(exp, tmp_path / "rep", extra_runs=[peers]).read_text()
    prov = md[md.index("**Provenance of `peers`**"):]
    assert ("- resumed (each run's peer.json, resumed_at): 3 of 4 runs, 5 resumes: sb3-s0 once, from step 110,000; "
            "sb3-s3 3 times, from steps 20,000, 20,000 and 60,000; sb3-s6 once, from step 30,000") in prov
    assert "resumed" not in md[:md.index("**Provenance of `peers`**")]  # mcrl's runs record none


def test_with_a_missing_directory_is_one_line(tmp_path: Path, experiment: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["report", str(experiment), "--with", str(tmp_path / "nope")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "--with" in err and "nope" in err
    assert not (experiment / "report").exists()


def test_thesis_claims_get_one_of_three_verdicts_and_the_code_variant_is_named(tmp_path: Path) -> None:
    # 6 seeds each, SAC-MC no better than SAC: an improvement of the thesis' +0.23 is excluded
    sac = [(s, -30.0) for s in (0.5, 0.55, 0.6, 0.5, 0.55, 0.6)]
    mc = [(s, -30.0) for s in (0.5, 0.55, 0.6, 0.45, 0.5, 0.55)]
    code = {"mc_reduction": "batch", "mc_state": "full"}
    exp = _experiment(tmp_path / "exp", {0.0: sac, 0.2: mc}, config=code)
    sweep = json.loads((exp / "sweep.json").read_text())  # a seed not started yet (no config.json) changes nothing
    sweep["runs"].append({"name": "a0.2-s6", "config_key": "alpha=0.2", "seed": 6, "overrides": {"mc_alpha": 0.2}})
    (exp / "sweep.json").write_text(json.dumps(sweep))
    md = write_report(exp, tmp_path / "rep").read_text()
    thesis = _section(md, "Comparison with the thesis (FetchPush)")
    assert ("**Not reproduced**: the thesis' claim that the thesis' code's variant of SAC-MC alpha=0.2 (one "
            "batch-mean KL, the whole observation) reaches a higher final success rate than SAC") in thesis
    # every SAC seed is above every code-variant seed lowered by 0.23: p = 1/924
    assert "of X falling short of Y +0.23: p = 0.0011 (adjusted 0.0011)" in thesis
    assert "mean difference -0.025 [" in thesis
    assert "| SAC-MC alpha=0.2, the thesis' code's variant (`alpha=0.2`) | 0.75 |" in thesis
    assert "| SAC (`alpha=0`) | 0.52 |" in thesis  # the MC reward's settings do not matter without it
    # the plain algorithm is not in this experiment: not decidable, not silently missing
    assert ("**Not decidable with this many seeds**: the thesis' claim that SAC-MC alpha=0.2 reaches a higher final "
            "success rate than SAC (thesis: +0.23): this report has no finished run of SAC-MC alpha=0.2, 0 seeds.") in thesis


# ------------------------------------------------------------------ arm names, critics against the soft-Q bound


def test_arms_are_named_by_what_they_are_and_can_be_labelled(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    exp = _experiment(tmp_path / "exp", {0.0: FINALS["alpha=0"], 0.2: FINALS["alpha=0.2"]})
    # another sweep whose only configuration is keyed by the main preset's name, as the code variant's was
    variant = tmp_path / "code-variant"
    runs = []
    for seed, final in enumerate([(0.5, -25.0), (0.6, -20.0), (0.7, -15.0)]):
        _write_run(variant / "runs" / f"s{seed}", 0.2, seed, final, config={"mc_reduction": "batch", "mc_state": "full"})
        runs.append({"name": f"s{seed}", "config_key": "fetchpush-sacmc-0.2", "seed": seed})
    (variant / "sweep.json").write_text(json.dumps({"preset": "fetchpush-sacmc-0.2", "runs": runs}))

    keys = [g.key for g in load_experiment(exp, [variant]).configs]
    assert "fetchpush-sacmc-0.2" not in keys  # two sweeps: their keys no longer name the arms
    assert "intrinsic_alpha=0.2, intrinsic_state=full, mc_reduction=batch" in keys
    assert "intrinsic_alpha=0.2, intrinsic_state=observation, mc_reduction=transition" in keys
    keys = [g.key for g in load_experiment(exp, [f"{variant}=SAC-MC, code variant"]).configs]
    assert set(keys) == {"alpha=0", "alpha=0.2", "SAC-MC, code variant"}
    # a second unnamed sweep (the alpha curve beside the main arms): the sweeps' keys no longer name the arms, and
    # the unnamed arms differ only in alpha, so they are named by their algorithm, not by the labelled variant's
    # settings
    curve = _experiment(tmp_path / "alpha-curve", {0.4: FINALS["alpha=0.2"]})
    keys = [g.key for g in load_experiment(exp, [f"{variant}=SAC-MC, code variant", str(curve)]).configs]
    assert set(keys) == {"SAC", "SAC-MC 0.2", "SAC-MC 0.4", "SAC-MC, code variant"}

    rc = main(["report", str(exp), "--with", f"{variant}=SAC-MC, code variant", "--out", str(tmp_path / "rep")])
    assert rc == 0, capsys.readouterr().err
    md = (tmp_path / "rep" / "report.md").read_text()
    assert _row(_section(md, "Final performance per configuration"), "`SAC-MC, code variant`")[2] == "3 / 3"
    rc = main(["report", str(exp), "--with", f"{variant}=", "--out", str(tmp_path / "rep2")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "label" in err and not (tmp_path / "rep2").exists()


def test_critics_against_the_soft_q_bound(tmp_path: Path) -> None:
    exp = _experiment(tmp_path / "exp", {0.0: FINALS["alpha=0"], 0.2: FINALS["alpha=0.2"]})
    for name, blow_up in (("a0-s0", True), ("a0-s1", False), ("a0.2-s0", False)):
        path = exp / "runs" / name / "metrics.csv"
        rows = list(csv.DictReader(path.open()))
        for r in rows:  # coefficient 0.01 throughout: bound 2.74; a critic at 50 from step 500 has left it
            r["ent_coef"], r["q_mean"] = 0.01, (50.0 if blow_up and int(r["step"]) >= 500 else -5.0)
        _write_csv(path, METRIC_COLUMNS, rows)
    md = write_report(exp, tmp_path / "rep").read_text()
    sec = _section(md, "Critics against the soft-Q bound")
    assert _row(sec, "`alpha=0` | `a0-s0`")[2:6] == ["yes", "500", "6 / 10", "yes"]
    assert _row(sec, "`alpha=0` | `a0-s1`")[2] == "no"
    assert "`a0-s2`" not in sec  # no q_mean logged: not checked
    assert _row(sec, "`alpha=0` | 1 of 2")[1] == "1 of 2 (0.50 [0.01, 0.99])"
    assert _row(sec, "`alpha=0.2` | 0 of 1")[1:] == ["0 of 1 (0.00 [0.00, 0.97])", "p = 1.0000 vs `alpha=0`"]


# ------------------------------------------------------------------ other intrinsic rewards (issue 29)


def test_other_intrinsic_rewards_against_sac_and_sac_mc(tmp_path: Path) -> None:
    # 6 seeds each. RND is above every SAC seed and interleaved with SAC-MC; Disagreement is interleaved with SAC
    # and below every SAC-MC seed.
    arms = {"alpha=0": (0.0, "mc", [0.10, 0.15, 0.20, 0.25, 0.30, 0.35]),
            "alpha=0.2": (0.2, "mc", [0.60, 0.65, 0.70, 0.75, 0.80, 0.85]),
            "rnd": (0.2, "rnd", [0.62, 0.67, 0.72, 0.77, 0.82, 0.87]),
            "disagreement": (0.2, "disagreement", [0.11, 0.16, 0.21, 0.26, 0.31, 0.36])}
    exp, runs = tmp_path / "exp", []
    for key, (alpha, intrinsic, finals) in arms.items():
        for seed, s in enumerate(finals):
            name = f"{key}-s{seed}"
            # SAC-MC's config.json has no `intrinsic` key, as the reproduction's (written before it existed)
            _write_run(exp / "runs" / name, alpha, seed, (s, -50 * (1 - s)),
                       config={} if intrinsic == "mc" else {"intrinsic": intrinsic})
            runs.append({"name": name, "config_key": key, "seed": seed})
    (exp / "sweep.json").write_text(json.dumps({"preset": "fetchpush-test", "runs": runs}))
    assert [(g.key, g.intrinsic) for g in load_experiment(exp).configs] == [
        ("alpha=0", "mc"), ("alpha=0.2", "mc"), ("disagreement", "disagreement"), ("rnd", "rnd")]

    md = write_report(exp, tmp_path / "rep").read_text()
    sec = _section(md, "Other intrinsic rewards against SAC and SAC-MC")
    # vs SAC, one-sided, Holm over SAC's family: SAC-MC's claim and the two arms' (three claims). RND above all 6
    # SAC seeds, p = 1/924, as SAC-MC: adjusted x3; Disagreement lowered by the thesis' +0.23 is below SAC at ranks
    # 1-5 and 7 of 12: p = 2/924, adjusted x3
    rnd_sac = _row(sec, "`rnd` | `alpha=0`")
    assert rnd_sac[2:7] == ["6 / 6", "one-sided X > Y", "0.0011 (0.0032)", "1.0000 (1.0000)", "**better than SAC**"]
    assert rnd_sac[7].startswith("1.000 [")
    dis_sac = _row(sec, "`disagreement` | `alpha=0`")
    assert dis_sac[3] == "one-sided X > Y" and dis_sac[5:7] == ["0.0022 (0.0065)", "**short of SAC +0.23**"]
    # vs SAC-MC, two-sided: Disagreement below every seed, p = 2/924 (adjusted x2); RND interleaved
    dis_mc = _row(sec, "`disagreement` | `alpha=0.2`")
    assert dis_mc[3:7] == ["two-sided", "0.0022 (0.0043)", "-", "**worse than SAC-MC**"]
    rnd_mc = _row(sec, "`rnd` | `alpha=0.2`")
    assert rnd_mc[6] == "**not decidable with this many seeds**" and float(rnd_mc[4].split()[0]) > 0.3
    assert all(0.0 < float(_row(sec, r)[9].split()[0]) <= 1.0 for r in ("`rnd` | `alpha=0`", "`disagreement` | `alpha=0.2`"))
    # each at its family's first Holm level: SAC's 3 claims, SAC-MC's 2
    assert [_row(sec, r)[9].split()[1:] for r in ("`rnd` | `alpha=0`", "`rnd` | `alpha=0.2`")] == [
        ["at", "0.0167"], ["at", "0.025"]]
    # RND at mc_alpha 0.2 is not the thesis' SAC-MC: its claim and table see only the MC arm
    thesis = _section(md, "Comparison with the thesis (FetchPush)")
    assert "`rnd`" not in thesis and "`disagreement`" not in thesis and "X = `alpha=0.2`" in thesis
    # the effect-size table reads RND against SAC-MC by SAC-MC's name, not as "SAC"
    poi = _row(_section(md, "IQM and probability of improvement"), "`rnd` > `alpha=0.2`")
    assert poi[3].startswith("no clear difference")
    assert _row(_section(md, "IQM and probability of improvement"), "`rnd` > `alpha=0`")[3].startswith("better than SAC")
    assert _row(_section(md, "MC reward and raw KL during training"), "`rnd`")[2] == "rnd"

    # the same arms with too few seeds: no verdict, said so
    small = tmp_path / "small"
    sweep = [r for r in runs if int(r["name"].rsplit("-s", 1)[1]) < 2]
    for r in sweep:
        shutil.copytree(exp / "runs" / r["name"], small / "runs" / r["name"])
    (small / "sweep.json").write_text(json.dumps({"preset": "fetchpush-test", "runs": sweep}))
    sec = _section(write_report(small, tmp_path / "rep2").read_text(), "Other intrinsic rewards against SAC and SAC-MC")
    assert _row(sec, "`rnd` | `alpha=0`")[6].startswith("not decidable with this many seeds: too few seeds")
    rows = [ln for ln in sec.splitlines() if ln.startswith("| `")]
    assert len(rows) == 4 and not any("better" in r or "worse" in r or "short" in r for r in rows)


def test_a_scheduled_arm_is_compared_as_its_own_arm_not_as_its_starting_alpha(tmp_path: Path) -> None:
    # A `success` schedule from 0.4 starts at the alpha curve's 0.4 but moves: it is no point of the thesis'
    # fixed-alpha claims (issue 67), so it must not fill the curve's 0.4 row nor its 'about the same as SAC'
    # claim; it is an arm of its own, compared with SAC (one-sided) and SAC-MC (two-sided) like a bonus.
    arms = {"alpha=0": (0.0, {}, [0.10, 0.15, 0.20, 0.25, 0.30, 0.35]),
            "alpha=0.2": (0.2, {}, [0.60, 0.65, 0.70, 0.75, 0.80, 0.85]),
            "success": (0.4, {"intrinsic_schedule": "success"}, [0.61, 0.66, 0.71, 0.76, 0.81, 0.86])}
    md = write_report(_sweep(tmp_path / "exp", arms), tmp_path / "rep").read_text()
    curve = md[md.index("### The thesis' alpha curve"):md.index("**Caveats:**")]
    assert _row(curve, "0.4")[2] == "not in this report" and "`success`" not in curve
    assert "`success`" not in _section(md, "Comparison with the thesis (FetchPush)").split("### The thesis' alpha")[0]
    sec = _section(md, "Other intrinsic rewards and schedules against SAC and SAC-MC")
    # above all 6 SAC seeds: p = 1/924, Holm x2 over SAC's family (SAC-MC 0.2's claim and this one)
    assert _row(sec, "`success` | `alpha=0`")[2:7] == ["6 / 6", "one-sided X > Y", "0.0011 (0.0022)",
                                                      "1.0000 (1.0000)", "**better than SAC**"]
    assert _row(sec, "`success` | `alpha=0.2`")[3] == "two-sided"
    verdicts = _section(md, "Verdicts")
    assert "issue 67: a schedule's claim" in verdicts and "SAC-MC 0.4 about the same" not in verdicts


def test_arms_that_differ_only_in_the_reward_are_named_by_algorithm(tmp_path: Path) -> None:
    exp = _experiment(tmp_path / "exp", {0.0: FINALS["alpha=0"], 0.2: FINALS["alpha=0.2"]})
    arms, runs = tmp_path / "arms", []
    for intrinsic in ("rnd", "disagreement"):
        for seed, final in enumerate(FINALS["alpha=0.2"]):
            name = f"intrinsic={intrinsic}-s{seed}"
            _write_run(arms / "runs" / name, 0.2, seed, final, config={"intrinsic": intrinsic})
            runs.append({"name": name, "config_key": f"intrinsic={intrinsic}", "seed": seed})
    (arms / "sweep.json").write_text(json.dumps({"preset": "fetchpush-sacmc-0.2", "runs": runs}))
    # two sweeps: their keys no longer name the arms; the settings differ only in mc_alpha and intrinsic
    assert [g.key for g in load_experiment(arms, [exp]).configs] == [
        "SAC", "SAC+Disagreement 0.2", "SAC+RND 0.2", "SAC-MC 0.2"]
    assert [g.key for g in load_experiment(arms).configs] == ["intrinsic=disagreement", "intrinsic=rnd"]
    # a partial sweep (issue 29's after its first run): Disagreement has not started, so it has no config.json;
    # sweep.json's overrides over the RND runs' settings name it as the others are named
    partial = tmp_path / "partial"
    entries = [{**r, "overrides": {"intrinsic": r["name"].split("=")[1].split("-s")[0], "seed": r["seed"]}}
               for r in runs]
    for r in entries:
        if r["overrides"]["intrinsic"] == "rnd":
            shutil.copytree(arms / "runs" / r["name"], partial / "runs" / r["name"])
    (partial / "sweep.json").write_text(json.dumps({"preset": "fetchpush-sacmc-0.2", "runs": entries}))
    groups = load_experiment(partial, [exp]).configs
    n = len(FINALS["alpha=0.2"])
    assert [(g.key, len(g.runs), len(g.finished)) for g in groups] == [
        ("SAC", n, n), ("SAC+Disagreement 0.2", n, 0), ("SAC+RND 0.2", n, n), ("SAC-MC 0.2", n, n)]
    assert groups[1].intrinsic_alpha == 0.2 and groups[1].intrinsic == "disagreement" and groups[1].total_steps == TOTAL
    # its final-table row gives the configured budget and no mean, rather than "?" and "n/a n/a"
    row = _row(_section(write_report(partial, tmp_path / "rep", extra_runs=[exp]).read_text(),
                        "Final performance per configuration"), "`SAC+Disagreement 0.2`")
    assert row[2:5] == [f"0 / {n}", f"{TOTAL:,}", "n/a"] and row[6] == "n/a"


# ------------------------------------------------------------------ the thesis' alpha curve (issue 50), axes


def test_the_alpha_curve_beside_the_thesis(tmp_path: Path) -> None:
    sac = [0.30, 0.32, 0.34, 0.36, 0.38, 0.40]
    arms = {0.0: sac, 0.2: [s + 0.4 for s in sac], 0.4: [s + 0.01 for s in sac], 0.6: [s + 0.3 for s in sac],
            0.8: [0.0, 0.01, 0.02, 0.03, 0.04, 0.05], 1.0: sac}
    exp = _experiment(tmp_path / "exp", {a: [(round(s, 2), -50 * (1 - s)) for s in v] for a, v in arms.items()})
    md = write_report(exp, tmp_path / "rep").read_text()
    assert (tmp_path / "rep" / "alpha_curve.png").stat().st_size > 1000
    curve = md[md.index("### The thesis' alpha curve"):md.index("**Caveats:**")]
    # every alpha, the thesis' numbers where it gives them and its words where it does not
    row = _row(curve, "0.0")
    assert row[1] == "0.52" and row[2].startswith("0.350 [") and row[3] == "-31.3" and row[4].startswith("-32.50 [")
    assert row[5] == "6" and _row(curve, "0.2")[1:4:2] == ["0.75", "-23.0"]
    assert _row(curve, "0.4")[1] == "comparable to SAC ('becomes comparable')"
    assert _row(curve, "0.6")[3] == "about -29.0 ('a mean reward of 28.96')"
    assert _row(curve, "1.0")[1:4:2] == ["'relatively low'", "'decrease'"]
    # one verdict per thesis claim, decided in SAC's family of five (0.2 and the four of the curve): 6 vs 6 fully
    # separated gives p = 1/924, x5 after Holm; 0.6 is 0.3 above SAC: beyond the margin; 1.0 is SAC: not worse
    verdicts = {a: _row(curve, a)[7] for a in ("0.4", "0.6", "0.8", "1.0")}
    assert verdicts == {"0.4": "**reproduced** (about the same)", "0.6": "**not reproduced** (differs by more than 0.115)",
                        "0.8": "**reproduced** (worse)", "1.0": "**not reproduced** (not worse by 0.23)"}
    assert ("**Reproduced** (about the same): the thesis' claim that SAC-MC alpha=0.4 is about the same as SAC, X = "
            "`alpha=0.4`, Y = `alpha=0`, 6 vs 6 seeds: two one-sided exact rank-sum tests, X + 0.115 > Y: p = 0.0011 "
            "and X - 0.115 < Y: p = 0.0011, so equivalence p = 0.0011 (Holm-adjusted over the 5 claims against this "
            "baseline in this report: 0.0054)") in curve
    assert "Power of these seeds to show equivalence within 0.115 when there is no difference: " in curve
    assert "- 'against `alpha=0`' (this report): 5 claims, Holm over the 5 with enough seeds" in md
    # the MC reward and raw KL during training: every alpha that has them
    mc = _section(md, "MC reward and raw KL during training")
    assert [_row(mc, f"`alpha={a}`")[1] for a in ("0.2", "0.4", "0.6", "0.8", "1")] == [
        "0.20", "0.40", "0.60", "0.80", "1.00"]


def test_step_axes_read_in_thousands() -> None:
    from matplotlib.figure import Figure as MplFigure

    from mcrl.analysis.plots import plot_curves_with_band

    fig = MplFigure(figsize=(5, 3.2))
    ax = fig.add_subplot()
    steps = np.arange(0, 150_001, 2_500)
    plot_curves_with_band(ax, steps, {"arm": np.random.default_rng(0).random((3, steps.size))})
    fig.canvas.draw()
    labels = [t.get_text() for t in ax.get_xticklabels() if 0 <= t.get_position()[0] <= 150_000]
    assert labels[0] == "0" and "50k" in labels and "150k" in labels and len(labels) <= 7
    assert all(len(t) <= 5 for t in labels)  # not "100000120000140000" run together


def test_the_thesis_final_numbers_stand_at_the_end_of_curves_trained_for_its_budget(tmp_path: Path) -> None:
    """At the thesis' own budget (FetchPush: 150,000 steps) each row of its table is a star at that budget on the
    success and return curves, in the colour of the configuration held against it, and an arm of another intrinsic
    reward at 0.2 gets none (it is not the thesis' SAC-MC); at any other budget there are no stars. The critics'
    mean Q and entropy coefficient are drawn beside the bound's table wherever metrics.csv logs them."""
    from matplotlib.figure import Figure as MplFigure

    from mcrl.analysis.comparison import thesis_at_budget
    from mcrl.analysis.plots import arm_colors
    from mcrl.analysis.sections import _thesis_stars

    full = {"total_steps": THESIS_RESULTS["FetchPush"]["total_steps"]}
    exp = load_experiment(_sweep(tmp_path / "full", {"a0": (0.0, full, [0.2, 0.4, 0.6]),
                                                     "rnd": (0.2, {**full, "intrinsic": "rnd"}, [0.3, 0.5, 0.7])}))
    short = load_experiment(_sweep(tmp_path / "short", {"a0": (0.0, {}, [0.2, 0.4, 0.6])}))
    assert thesis_at_budget(short) is None
    name, t = thesis_at_budget(exp)
    assert name == "FetchPush"
    colors = arm_colors([g.key for g in exp.configs])
    for col, thesis in (("success_rate", 0.52), ("mean_return", -31.3)):
        ax = MplFigure().add_subplot()
        _thesis_stars(ax, exp, t, col, colors)
        assert [(tuple(ln.get_xydata()[0]), ln.get_color(), ln.get_label()) for ln in ax.lines] == [
            ((150_000.0, thesis), colors[exp.configs[0].key], "thesis: SAC")]  # SAC-MC's row: no arm of MC

    md = write_report(exp.dir, tmp_path / "rep").read_text()
    assert "Stars at 150,000 env steps: the thesis' final success rate" in _section(md, "Learning curves")
    assert "Stars at" not in write_report(short.dir, tmp_path / "rep-short").read_text()
    assert "](critics_entropy.png)" in _section(md, "Critics against the soft-Q bound")
    assert (tmp_path / "rep" / "critics_entropy.png").stat().st_size > 0
