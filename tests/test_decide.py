"""`mcrl decide`: group-sequential bounds against published tables, the look's statistic and decisions, error rates
by simulation on a bimodal tied outcome, the plan's file rules, and one end-to-end plan on FetchReach."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import scipy.stats

from mcrl.cli import main
from mcrl.decide import runner
from mcrl.decide.boundaries import exit_probabilities, lower_bounds, spent, upper_bounds
from mcrl.decide.look import REPRODUCED, information, rank_sum_z, take_look
from mcrl.decide.plan import load_plan
from mcrl.errors import MCRLError


# ------------------------------------------------------------------------------------------------ boundaries
@pytest.mark.parametrize("K, pocock, obf", [(2, 2.178, 1.977), (3, 2.289, 2.004), (4, 2.361, 2.024),
                                            (5, 2.413, 2.040)])
def test_published_constants_cross_with_the_level_they_were_built_for(K, pocock, obf):
    """Jennison and Turnbull (2000) Table 2.1 / 2.3: two-sided 0.05 with K equally spaced looks. Pocock: |Z_k| >= C;
    O'Brien-Fleming: |Z_k| >= C sqrt(K / k). The constants are printed to 3 decimals (about +-1e-4 in level)."""
    info = np.arange(1, K + 1, dtype=float)
    for bounds in (np.full(K, pocock), obf * np.sqrt(K / info)):
        up, down = exit_probabilities(info, bounds, -bounds)
        assert up.sum() + down.sum() == pytest.approx(0.05, abs=2.5e-4)
        assert up.sum() == pytest.approx(down.sum(), abs=1e-9)  # symmetric under the null


def test_lan_demets_bounds_match_the_published_ones():
    """One-sided 0.025, five equally spaced looks (DeMets and Lan 1994; gsDesign's sfLDOF / sfLDPocock)."""
    info = np.arange(1, 6, dtype=float)
    obf, cum = upper_bounds(info, 5.0, 0.025, "obrien-fleming")
    np.testing.assert_allclose(obf, [4.877, 3.357, 2.680, 2.290, 2.031], atol=2e-3)
    poc, _ = upper_bounds(info, 5.0, 0.025, "pocock")
    np.testing.assert_allclose(poc, [2.438, 2.427, 2.410, 2.397, 2.386], atol=2e-3)
    # the error each look spends is what the spending function says
    up, _ = exit_probabilities(info, obf)
    np.testing.assert_allclose(np.cumsum(up), cum, atol=1e-7)
    np.testing.assert_allclose(cum, spent("obrien-fleming", 0.025, info / 5))


def test_recursion_agrees_with_the_bivariate_normal_at_unequal_information():
    """Two looks at information 2 and 7 (correlation sqrt(2/7)) under a drift: the crossing probability from the
    recursion equals one minus the bivariate normal's mass below both bounds."""
    info, theta, b = np.array([2.0, 7.0]), 0.4, np.array([2.5, 2.1])
    up, _ = exit_probabilities(info, b, theta=theta)
    r = math.sqrt(2 / 7)
    mean = theta * np.sqrt(info)
    below = scipy.stats.multivariate_normal(mean, [[1, r], [r, 1]]).cdf(b)
    assert up.sum() == pytest.approx(1 - below, abs=1e-6)


def test_futility_bounds_spend_beta_under_the_planning_drift_and_meet_at_the_end():
    info = np.array([1.0, 2.0, 3.0, 4.0])
    upper, _ = upper_bounds(info, 4.0, 0.05, "pocock")
    theta = 1.2
    lower = lower_bounds(info, 4.0, upper, 0.2, theta, "pocock")
    assert lower[-1] == upper[-1] and np.all(lower[:-1] < upper[:-1])
    _, down = exit_probabilities(info, upper, lower, theta=theta)
    np.testing.assert_allclose(np.cumsum(down)[:-1], spent("pocock", 0.2, info / 4)[:-1], atol=1e-7)


# ------------------------------------------------------------------------------------------------ the statistic
def test_rank_sum_z_is_the_tie_corrected_normal_statistic():
    rng = np.random.default_rng(0)
    for _ in range(20):
        x, y = rng.integers(0, 6, 9) / 10, rng.integers(0, 6, 7) / 10  # many ties
        p = scipy.stats.mannwhitneyu(x, y, alternative="greater", method="asymptotic", use_continuity=False).pvalue
        assert rank_sum_z(x, y) == pytest.approx(scipy.stats.norm.isf(p), abs=1e-9)
    assert rank_sum_z([0.1, 0.1], [0.1, 0.1, 0.1]) == 0.0  # all tied: no evidence, not a division by zero


def _plan(tmp_path: Path, body: str, name: str = "plan.yaml") -> Path:
    d = tmp_path / name.replace(".yaml", "")
    d.mkdir(exist_ok=True)
    (d / "plan.yaml").write_text(body)
    return d / "plan.yaml"


PLAN = """preset: fetchreach-sac
set: {total_steps: 200, hidden_sizes: [32, 32], mc_hidden_sizes: [32, 32], batch_size: 32, eval_every: 200,
      eval_episodes: 2, log_every: 100, learning_starts: 100, checkpoint_every: 100}
arms:
  sac: {intrinsic_alpha: 0.0}
  mc: {intrinsic_alpha: 0.2}
  hi: {intrinsic_alpha: 1.0}
seeds: 1000..1011
batch: 4
level: 0.05
multiplicity: %s
claims:
  - {name: mc-better, primary: true, better: mc, than: sac, level: 0.04, spending: %s,
     futility: {beta: 0.15, effect: 0.75}}
  - {name: hi-worse, better: sac, than: hi, level: 0.01, spending: pocock, futility: {beta: 0.1, effect: 0.8}}
"""


def _bimodal(rng, p_learn: float, shape) -> np.ndarray:
    """A seed learns (final 0.30-0.90) or not (0.00-0.15), in steps of 0.01 as a 100-episode success rate."""
    learned = rng.integers(30, 91, shape) / 100
    not_learned = rng.integers(0, 16, shape) / 100
    return np.where(rng.random(shape) < p_learn, learned, not_learned)


def _run_plan(plan, draws: dict[str, np.ndarray]) -> list[dict]:
    history: list[dict] = []
    seeds = {a: 0 for a in plan.arms}
    while not (history and history[-1]["done"]):
        for a in (history[-1]["continue_arms"] if history else plan.arms):
            seeds[a] += plan.batch
        history.append(take_look(plan, {a: draws[a][:seeds[a]] for a in plan.arms}, history, describe=False))
    return history


@pytest.mark.parametrize("multiplicity, spending", [("holm", "pocock"), ("bonferroni", "obrien-fleming")])
def test_family_error_under_a_bimodal_tied_null_stays_at_the_level(tmp_path, multiplicity, spending):
    """Every arm from one bimodal distribution with ties, 3 looks: no claim may be reproduced more often than the
    family's 0.05 allows (3 Monte Carlo standard errors of slack at 1,500 experiments)."""
    plan = load_plan(_plan(tmp_path, PLAN % (multiplicity, spending)))
    rng = np.random.default_rng(1)
    E = 1500
    false = 0
    for _ in range(E):
        draws = {a: _bimodal(rng, 0.45, 12) for a in plan.arms}
        last = _run_plan(plan, draws)[-1]["claims"]
        false += any(c["decision"] == REPRODUCED for c in last.values())
    assert false / E <= 0.05 + 3 * math.sqrt(0.05 * 0.95 / E)


def test_a_true_difference_is_reproduced_and_stops_early(tmp_path):
    """Learning 0.3 against 0.9 of seeds (about +0.4 in mean): reproduced in most experiments, the hi arm stops once
    its claim is decided, and an experiment under this shift uses fewer seeds than the maximum on average."""
    plan = load_plan(_plan(tmp_path, PLAN % ("holm", "pocock")))
    rng = np.random.default_rng(2)
    E, hits, seeds = 300, 0, []
    for _ in range(E):
        draws = {"sac": _bimodal(rng, 0.3, 12), "mc": _bimodal(rng, 0.9, 12), "hi": rng.integers(0, 10, 12) / 100}
        hist = _run_plan(plan, draws)
        hits += hist[-1]["claims"]["mc-better"]["decision"] == REPRODUCED
        seeds.append(hist[-1]["seeds_per_arm"]["mc"])
    assert hits / E >= 0.7  # 0.78 here; the null gives at most 0.05
    assert np.mean(seeds) < 0.85 * plan.max_seeds


def test_holm_passes_a_confirmed_claims_level_on(tmp_path):
    """With the primary at 0.01 and the secondary at 0.04, the secondary is confirmed at look 1; the primary is then
    tested at the whole 0.05 and reproduced with a z between its own bound and the 0.05 one. Bonferroni keeps 0.01."""
    swapped = (PLAN % ("holm", "pocock")).replace("level: 0.04", "level: X").replace("level: 0.01", "level: 0.04")
    plan = load_plan(_plan(tmp_path, swapped.replace("level: X", "level: 0.01")))
    from mcrl.decide.look import claim_bounds
    infos = [information(4, 4)]
    u01, u05 = (claim_bounds(plan, plan.primary, infos, lv)[0][0] for lv in (0.01, 0.05))
    finals = {"sac": [0.30, 0.35, 0.10, 0.45], "hi": [0.00, 0.01, 0.02, 0.03], "mc": [0.5, 0.6, 0.7, 0.8]}
    assert u05 <= rank_sum_z(finals["mc"], finals["sac"]) < u01
    rec = take_look(plan, finals, [])
    assert rec["claims"]["hi-worse"]["decision"] == REPRODUCED
    assert rec["claims"]["mc-better"]["decision"] == REPRODUCED
    assert rec["claims"]["mc-better"]["level"] == pytest.approx(0.05)
    bonf = load_plan(_plan(tmp_path, swapped.replace("level: X", "level: 0.01").replace("holm", "bonferroni"),
                           "b.yaml"))
    assert take_look(bonf, finals, [])["claims"]["mc-better"]["decision"] == "continue"


# ------------------------------------------------------------------------------------------------ the runner
def _finish(plan_path: Path, arm: str, seed: int, success: float) -> None:
    rd = plan_path.parent / "runs" / f"{arm}-s{seed}"
    rd.mkdir(parents=True, exist_ok=True)
    (rd / "final_eval.json").write_text(json.dumps({"step": 200, "success_rate": success, "mean_return": -1.0,
                                                    "episodes": 100}))
    (rd / "done").write_text(json.dumps({"step": 200, "success_rate": success}))


def _finish_batch(path: Path, look: int, values: dict[str, list[float]]) -> None:
    plan = load_plan(path)
    for arm, vals in values.items():
        for seed, v in zip(plan.seeds[(look - 1) * plan.batch: look * plan.batch], vals):
            _finish(path, arm, seed, v)


def test_a_look_is_refused_while_its_batch_is_unfinished_and_appended_once_it_is(tmp_path, capsys):
    path = _plan(tmp_path, PLAN % ("holm", "pocock"))
    _finish_batch(path, 1, {"sac": [0.1, 0.2, 0.3, 0.4], "mc": [0.5, 0.6, 0.7, 0.8], "hi": [0.0, 0.0, 0.1]})
    assert main(["decide", str(path), "--look"]) == 2
    err = capsys.readouterr().err
    assert "hi-s1003" in err and "\n" == err[-1] and err.count("\n") == 1
    assert not (path.parent / "looks.jsonl").exists()
    _finish(path, "hi", 1003, 0.05)
    assert main(["decide", str(path), "--look"]) == 0
    (rec,) = [json.loads(x) for x in (path.parent / "looks.jsonl").read_text().splitlines()]
    for key in ("look", "seeds_per_arm", "finals", "z", "upper", "lower", "alpha_spent", "decision", "plan_hash"):
        assert key in rec
    assert rec["look"] == 1 and rec["seeds_per_arm"] == {"sac": 4, "mc": 4, "hi": 4}
    assert rec["finals"]["mc"] == [0.5, 0.6, 0.7, 0.8] and rec["z"] == pytest.approx(rank_sum_z(
        [0.5, 0.6, 0.7, 0.8], [0.1, 0.2, 0.3, 0.4]))
    assert main(["decide", str(path), "--look"]) == 2  # look 2's batch has not run
    assert len((path.parent / "looks.jsonl").read_text().splitlines()) == 1


def test_a_plan_changed_after_its_first_look_is_refused(tmp_path, capsys):
    path = _plan(tmp_path, PLAN % ("holm", "pocock"))
    _finish_batch(path, 1, {"sac": [0.1] * 4, "mc": [0.2] * 4, "hi": [0.0] * 4})
    assert main(["decide", str(path), "--look"]) == 0
    path.write_text(path.read_text().replace("beta: 0.15", "beta: 0.2"))
    for args in (["--look"], ["--dry-run"], []):
        assert main(["decide", str(path), *args]) == 2
        err = capsys.readouterr().err
        assert "changed after look 1" in err and err.count("\n") == 1


def test_a_decided_plan_starts_no_runs(tmp_path, capsys, monkeypatch):
    path = _plan(tmp_path, PLAN % ("holm", "pocock"))
    _finish_batch(path, 1, {"sac": [0.0, 0.01, 0.02, 0.03], "mc": [0.9, 0.8, 0.85, 0.95],
                            "hi": [0.5, 0.6, 0.7, 0.8]})
    assert main(["decide", str(path), "--look"]) == 0
    rec = json.loads((path.parent / "looks.jsonl").read_text())
    assert rec["claims"]["mc-better"]["decision"] == REPRODUCED  # z 2.31 over its 0.04 bound 2.12
    assert rec["claims"]["hi-worse"]["decision"] == "futile"  # z -2.31 under its futility bound
    assert rec["done"] and rec["continue_arms"] == []

    def no_sweep(*a, **k):
        raise AssertionError("a decided plan started a sweep")

    import mcrl.sweep
    monkeypatch.setattr(mcrl.sweep, "run_sweep", no_sweep)
    capsys.readouterr()
    assert main(["decide", str(path)]) == 0
    assert "decided at look 1" in capsys.readouterr().out
    assert main(["decide", str(path), "--dry-run"]) == 0
    assert "no run would start" in capsys.readouterr().out


def test_an_arm_whose_claims_are_decided_runs_no_more_seeds(tmp_path):
    path = _plan(tmp_path, PLAN % ("holm", "pocock"))
    _finish_batch(path, 1, {"sac": [0.3, 0.4, 0.5, 0.6], "mc": [0.3, 0.5, 0.4, 0.6], "hi": [0.7, 0.8, 0.9, 0.95]})
    plan = load_plan(path)
    rec = runner.look(plan, commit="x")
    assert rec["claims"]["hi-worse"]["decision"] == "futile" and rec["claims"]["mc-better"]["decision"] == "continue"
    st = runner.state(plan)
    assert st.next_batch() == {"sac": [1004, 1005, 1006, 1007], "mc": [1004, 1005, 1006, 1007]}
    names = [r.name for r in runner.batch_plan(st).runs]  # seed-major: arms share machines and times alike
    assert names[:4] == ["sac-s1000", "mc-s1000", "sac-s1001", "mc-s1001"] and len(names) == 16


def test_the_looks_table_shows_each_looks_repeated_interval_while_continuing(tmp_path):
    """The interval that stays valid whenever the experiment stops is shown at every look, not only at a decision:
    a continuing claim's row carries the test-inverted shift interval at its efficacy bound, with its coverage."""
    from mcrl.analysis.markdown import to_markdown
    from mcrl.decide.look import shift_interval
    from mcrl.decide.report import sequential_section
    path = _plan(tmp_path, PLAN % ("holm", "pocock"))
    mc, sac = [0.3, 0.5, 0.4, 0.6], [0.3, 0.4, 0.5, 0.6]
    _finish_batch(path, 1, {"sac": sac, "mc": mc, "hi": [0.7, 0.8, 0.9, 0.95]})
    c = runner.look(load_plan(path), commit="x")["claims"]["mc-better"]
    assert c["decision"] == "continue"
    lo, hi = shift_interval(mc, sac, c["upper"])
    assert lo < 0 < hi  # the same finals: no shift is excluded
    text = to_markdown(sequential_section(path.parent), tmp_path)
    (row,) = [line for line in text.splitlines() if line.startswith("| 1 | mc-better |")]
    assert f"[{lo:+.2f}, {hi:+.2f}] (92%)" in row and row.endswith("| continue |")
    assert "not decided yet" in text


def test_a_record_cut_short_by_a_crash_is_not_a_look(tmp_path):
    path = _plan(tmp_path, PLAN % ("holm", "pocock"))
    _finish_batch(path, 1, {"sac": [0.1, 0.3, 0.2, 0.4], "mc": [0.2, 0.25, 0.35, 0.15], "hi": [0.1, 0.2, 0.05, 0.3]})
    plan = load_plan(path)
    runner.look(plan, commit="x")
    looks = path.parent / "looks.jsonl"
    good = looks.read_text()
    looks.write_text(good + good[:40])  # a second record cut short
    assert len(runner.read_looks(plan)) == 1
    _finish_batch(path, 2, {"sac": [0.1, 0.3, 0.2, 0.4], "mc": [0.2, 0.25, 0.35, 0.15], "hi": [0.1, 0.2, 0.05, 0.3]})
    runner.look(plan, commit="x")
    assert [json.loads(x)["look"] for x in looks.read_text().splitlines()] == [1, 2]


@pytest.mark.parametrize("edit, words", [
    ("level: 0.04", "add up to"), ("seeds: 1000..1011", "whole number of batches"),
    ("effect: 0.75", "planning P(X > Y)"), ("spending: pocock", "choose one of"),
    ("multiplicity: holm", "choose holm"), ("set: {total_steps", "remove seed")])
def test_bad_plans_get_one_line_naming_the_fix(tmp_path, capsys, edit, words):
    bad = {"level: 0.04": "level: 0.045", "seeds: 1000..1011": "seeds: 1000..1010", "effect: 0.75": "effect: 1.5",
           "spending: pocock": "spending: linear", "multiplicity: holm": "multiplicity: sidak",
           "set: {total_steps": "set: {seed: 3, total_steps"}[edit]
    path = _plan(tmp_path, (PLAN % ("holm", "pocock")).replace(edit, bad, 1))
    assert main(["decide", str(path), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert words in err and err.count("\n") == 1
    assert sorted(p.name for p in path.parent.iterdir()) == ["plan.yaml"]


def test_a_pinned_commit_that_is_not_this_code_is_refused(tmp_path, capsys):
    path = _plan(tmp_path, (PLAN % ("holm", "pocock")) + "commit: deadbeefdeadbeefdeadbeefdeadbeefdeadbeef\n")
    _finish_batch(path, 1, {"sac": [0.1] * 4, "mc": [0.2] * 4, "hi": [0.0] * 4})
    assert main(["decide", str(path), "--look"]) == 2
    assert "pins commit deadbeefdead" in capsys.readouterr().err
    assert main(["decide", str(path), "--look", "--any-commit"]) == 0


# ------------------------------------------------------------------------------------------------ end to end
E2E = """preset: fetchreach-sac
set: {total_steps: 200, hidden_sizes: [32, 32], mc_hidden_sizes: [32, 32], batch_size: 32, eval_every: 200,
      eval_episodes: 2, log_every: 50, learning_starts: 100, checkpoint_every: 100}
arms:
  sac: {intrinsic_alpha: 0.0}
  mc: {intrinsic_alpha: 0.2}
seeds: [1000, 1001]
batch: 2
level: 0.05
claims:
  - {name: mc-better, primary: true, better: mc, than: sac, level: 0.05}
"""


def test_end_to_end_plan_on_fetchreach_survives_kill_9(tmp_path):
    """`mcrl decide` through the CLI and the local backend: killed with SIGKILL while its batch runs, started
    again, it finishes the batch without retraining finished runs and takes exactly one look, the maximum."""
    path = _plan(tmp_path, E2E)
    cmd = [sys.executable, "-c", "import sys; from mcrl.cli import main; sys.exit(main())", "decide", str(path),
           "--workers", "1", "--threads-per-run", "1", "--no-progress"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    runs = path.parent / "runs"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and not list(runs.glob("*/done")):
        time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    finished = {d.parent.name: d.stat().st_mtime_ns for d in runs.glob("*/done")}
    assert len(finished) == 1 and not (path.parent / "looks.jsonl").exists()
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=400)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "skip" in res.stdout and "decided at look 1" in res.stdout
    assert {n: (runs / n / "done").stat().st_mtime_ns for n in finished} == finished
    (rec,) = [json.loads(x) for x in (path.parent / "looks.jsonl").read_text().splitlines()]
    assert rec["decision"] == "not reproduced" and rec["seeds_per_arm"] == {"sac": 2, "mc": 2}
    assert len(rec["finals"]["sac"]) == 2 and rec["done"]
    sweep = json.loads((path.parent / "sweep.json").read_text())
    assert sorted(r["name"] for r in sweep["runs"]) == ["mc-s1000", "mc-s1001", "sac-s1000", "sac-s1001"]
    # the report leads with the verdict and shows only looked-at runs: a finished run no look has used stays out
    import shutil
    from mcrl.analysis.report import write_report
    shutil.copytree(runs / "sac-s1000", runs / "sac-s1002")
    sweep["runs"].append({**sweep["runs"][0], "name": "sac-s1002", "seed": 1002})
    (path.parent / "sweep.json").write_text(json.dumps(sweep))
    text = write_report(path.parent).read_text()
    assert text.index("Confirmatory verdict") < text.index("## ") + 40
    assert "**not reproduced** at look 1" in text and "sac-s1000" in text and "sac-s1002" not in text


def test_the_readme_leads_with_the_committed_plans_verdict():
    """README.md's confirmatory block is what `mcrl report docs/confirmatory/fetchpush --readme README.md` writes
    from the committed plan and looks: a look committed without regenerating the README fails here."""
    from mcrl.decide.report import answer_markdown, readme_answer
    root = Path(__file__).resolve().parents[1]
    assert readme_answer(root / "README.md") == answer_markdown(root / "docs" / "confirmatory" / "fetchpush")


def test_readme_answer_is_written_between_the_markers_only(tmp_path, capsys):
    path = _plan(tmp_path, PLAN % ("holm", "pocock"))
    _finish_batch(path, 1, {"sac": [0.0, 0.01, 0.02, 0.03], "mc": [0.9, 0.8, 0.85, 0.95], "hi": [0.5, 0.6, 0.7, 0.8]})
    assert main(["decide", str(path), "--look"]) == 0
    readme = tmp_path / "README.md"
    readme.write_text("# x\n\nbefore\n<!-- confirmatory:start -->\nold\n<!-- confirmatory:end -->\nafter\n")
    from mcrl.decide.report import answer_markdown, write_answer
    answer = answer_markdown(path.parent)
    assert "**reproduced** at look 1" in answer and "**futile** at look 1" in answer
    assert write_answer(path.parent, readme) and not write_answer(path.parent, readme)
    assert readme.read_text() == (f"# x\n\nbefore\n<!-- confirmatory:start -->\n{answer}\n"
                                  "<!-- confirmatory:end -->\nafter\n")
    readme.write_text("no markers\n")
    assert main(["report", str(path.parent), "--readme", str(readme)]) == 2
    assert "markers" in capsys.readouterr().err and readme.read_text() == "no markers\n"
    assert not (path.parent / "report").exists()
